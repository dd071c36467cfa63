"""The fleet manifest: one row per motor (``motor_id``, ``data``, ``setup``, optional ``bla_data``
and ``validation``), CSV or Parquet, or rows given in memory."""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

from hallcal.errors import HallcalInputError
from hallcal.io.files import existing_file

#: Manifest columns: required first, then optional.
MANIFEST_COLUMNS: tuple[str, ...] = ("motor_id", "data", "setup", "bla_data", "validation")
_REQUIRED_COLUMNS = ("motor_id", "data", "setup")
_INPUT_ROLES = ("data", "setup", "bla_data", "validation")


_MOTOR_ID = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}")


@dataclass(frozen=True)
class MotorSpec:
    """One manifest row, paths resolved.

    Attributes
    ----------
    motor_id : str
        As written in the manifest.
    data, setup : pathlib.Path or None
        Calibration recording and setup file (None when the cell was empty).
    bla_data, validation : pathlib.Path or None
        Optional multisine experiment and validation recording.
    row : int
        1-based row number in the manifest (data rows; the header is row 0), for messages.
    problem : str or None
        Why this row cannot be run at all (invalid or duplicate motor_id, empty required cell);
        such a row becomes a failed row without reaching a worker.
    """

    motor_id: str
    data: Path | None
    setup: Path | None
    bla_data: Path | None = None
    validation: Path | None = None
    row: int = 0
    problem: str | None = None


def _manifest_rows_csv(p: Path) -> tuple[list[str], list[dict[str, str]]]:
    import csv
    import io

    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise HallcalInputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise HallcalInputError(f"{p}: not UTF-8 text (line {line})") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise HallcalInputError(f"{p}: the manifest is empty (expected a header row)")
    reader = csv.reader(io.StringIO("\n".join(lines)))
    try:
        table = list(reader)
    except csv.Error as exc:
        raise HallcalInputError(f"{p}: invalid CSV ({exc})") from None
    header = [h.strip() for h in table[0]]
    rows = []
    for i, cells in enumerate(table[1:], start=1):
        if len(cells) > len(header) and any(c.strip() for c in cells[len(header) :]):
            raise HallcalInputError(
                f"{p}: row {i} has {len(cells)} cells but the header has {len(header)}"
            )
        rows.append({h: (cells[j].strip() if j < len(cells) else "") for j, h in enumerate(header)})
    return header, rows


def _manifest_rows_parquet(p: Path) -> tuple[list[str], list[dict[str, str]]]:
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(p, use_threads=False, pre_buffer=False)
    except (OSError, pa.ArrowException) as exc:
        raise HallcalInputError(f"{p}: cannot read the Parquet manifest ({exc})") from None
    header = list(table.column_names)
    rows = [
        {k: "" if v is None else str(v).strip() for k, v in row.items()}
        for row in table.to_pylist()
    ]
    return header, rows


def _resolve(cell: str, base: Path) -> Path | None:
    if not cell:
        return None
    path = Path(cell).expanduser()
    return path if path.is_absolute() else base / path


def _check_header(header: Sequence[str], source: str) -> None:
    seen: set[str] = set()
    for name in header:
        if name in seen and name in MANIFEST_COLUMNS:
            raise HallcalInputError(f"{source}: column '{name}' appears twice")
        seen.add(name)
    for name in _REQUIRED_COLUMNS:
        if name not in seen:
            near = [h for h in header if h not in MANIFEST_COLUMNS]
            guess = difflib.get_close_matches(name, near, n=1, cutoff=0.7)
            hint = f" (is '{guess[0]}' meant to be '{name}'?)" if guess else ""
            shown = ", ".join(header) if header else "none"
            raise HallcalInputError(f"{source}: column '{name}' is missing{hint}; columns: {shown}")
    for name in header:
        if name in MANIFEST_COLUMNS:
            continue
        guess = difflib.get_close_matches(name, MANIFEST_COLUMNS, n=1, cutoff=0.75)
        if guess or name.lower() in MANIFEST_COLUMNS:
            meant = guess[0] if guess else name.lower()
            raise HallcalInputError(f"{source}: unknown column '{name}' (did you mean '{meant}'?)")


def _specs_from_rows(rows: Sequence[Mapping[str, Any]], base: Path, source: str) -> list[MotorSpec]:
    specs: list[MotorSpec] = []
    first_row: dict[str, int] = {}
    for i, row in enumerate(rows, start=1):
        cell = {k: "" if row.get(k) is None else str(row[k]).strip() for k in MANIFEST_COLUMNS}
        if not any(cell.values()):
            continue
        motor_id = cell["motor_id"]
        problem = None
        if not motor_id:
            problem = f"{source}: row {i}: motor_id is empty"
        elif not _MOTOR_ID.fullmatch(motor_id):
            problem = (
                f"{source}: row {i}: motor_id '{motor_id}' is not usable as a folder name "
                "(letters, digits, '.', '_' and '-' only, at most 128, not starting with '.')"
            )
        elif motor_id in first_row:
            problem = (
                f"{source}: row {i}: motor_id '{motor_id}' already used on row "
                f"{first_row[motor_id]}"
            )
        else:
            first_row[motor_id] = i
        for key in ("data", "setup"):
            if problem is None and not cell[key]:
                problem = f"{source}: row {i} (motor '{motor_id}'): '{key}' is empty"
        specs.append(
            MotorSpec(
                motor_id=motor_id,
                data=_resolve(cell["data"], base),
                setup=_resolve(cell["setup"], base),
                bla_data=_resolve(cell["bla_data"], base),
                validation=_resolve(cell["validation"], base),
                row=i,
                problem=problem,
            )
        )
    if not specs:
        raise HallcalInputError(f"{source}: the manifest has no motors")
    return specs


def read_manifest(path: str | os.PathLike[str]) -> list[MotorSpec]:
    """Read a fleet manifest (CSV or Parquet, see the module documentation).

    Parameters
    ----------
    path : path-like
        ``.csv`` or ``.parquet`` file. Relative paths in it are taken relative to its folder.

    Returns
    -------
    list of MotorSpec
        In manifest order; rows whose motor_id is unusable or duplicated, or whose ``data`` or
        ``setup`` cell is empty, carry a :attr:`MotorSpec.problem` (they become failed rows).

    Raises
    ------
    HallcalInputError
        Missing or unreadable file, unknown extension, a required column missing, a misspelled
        column, or no motor at all; the message names the file and the column.
    """
    p = existing_file(path)
    ext = p.suffix.lower()
    if ext == ".csv":
        header, rows = _manifest_rows_csv(p)
    elif ext == ".parquet":
        header, rows = _manifest_rows_parquet(p)
    else:
        shown = f"'{p.suffix}'" if p.suffix else "(none)"
        raise HallcalInputError(
            f"{p}: unknown manifest extension {shown} (expected .csv or .parquet)"
        )
    _check_header(header, str(p))
    return _specs_from_rows(rows, p.resolve().parent, str(p))


def _specs(
    manifest_or_rows: str | os.PathLike[str] | Iterable[Mapping[str, Any] | MotorSpec],
    base: str | os.PathLike[str] | None,
) -> tuple[list[MotorSpec], str]:
    if isinstance(manifest_or_rows, str | os.PathLike):
        return read_manifest(manifest_or_rows), str(manifest_or_rows)
    root = Path.cwd() if base is None else Path(base)
    rows: list[Mapping[str, Any]] = []
    given: list[MotorSpec] = []
    for item in manifest_or_rows:
        if isinstance(item, MotorSpec):
            given.append(item)
        elif isinstance(item, Mapping):
            rows.append(item)
        else:
            raise TypeError(f"run_fleet: a row must be a mapping or a MotorSpec, not {item!r}")
    if given and rows:
        raise TypeError("run_fleet: give either MotorSpec rows or mappings, not both")
    if given:
        return given, "<rows>"
    names = {str(k) for r in rows for k in r}
    known = [n for n in MANIFEST_COLUMNS if n in names]
    _check_header(known + sorted(names - set(MANIFEST_COLUMNS)), "<rows>")
    return _specs_from_rows(rows, root, "<rows>"), "<rows>"
