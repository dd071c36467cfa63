"""Calibrate a fleet of motors on Dask (``hallcal fleet``): end-of-line production.

One manifest lists the motors; each motor is calibrated by the same front-door calibration as
``hallcal calibrate`` (Algorithm 1 of van Meer et al.), in a Dask worker, independently of the
others: a bad file, a refused model or a crashed worker gives that motor's row a status and a
one-line reason, and the batch goes on.

Manifest
--------
A CSV (header row, UTF-8) or Parquet table, one row per motor:

``motor_id``
    Name of the motor; also the name of its output folder, so it may hold letters, digits,
    ``.``, ``_`` and ``-`` only (at most 128 characters, not starting with ``.``), and must be
    unique in the manifest.
``data``
    The calibration recording (any dataset format of :func:`hallcal.io.read_dataset`).
``setup``
    The setup file (TOML).
``bla_data`` (optional)
    A multisine experiment for the BLA, for setups without ``[plant]``.
``validation`` (optional)
    A second recording with ``y_ref`` (an encoder, or the virtual bench's truth) on which the
    RMS errors of f_init and f_star are measured. Validation only: never used to calibrate.

An empty cell means "none". Relative paths are relative to the manifest's folder. Other columns
are ignored, except a name that looks like a misspelling of one of these (an error).

Outputs
-------
``OUT/<motor_id>/calibration.json``
    The calibration artifact (``"hallcal-calibration/1"``), when the motor's status is ok or
    warning; with ``export_c`` also its C99 sources in ``OUT/<motor_id>/c/``.
``OUT/<motor_id>/fleet.json``
    The motor's record: its summary row, the fingerprint of its inputs and the SHA-256 of each
    output. A rerun skips a motor whose record is up to date (see below).
``OUT/summary.parquet``, ``OUT/summary.csv``
    One row per manifest row, in manifest order, columns :data:`SUMMARY_COLUMNS`.
``OUT/fleet.html``
    A self-contained page for a quality engineer: the distributions of the predicted error and
    of f_init versus f_star, the outliers and every motor that did not succeed.

Every file is written atomically (:func:`hallcal.io.atomic_write`); the workers return their
outputs to the client, which alone writes to ``OUT``, so the workers of an existing cluster need
to read the inputs (a shared file system, as usual with Dask) but not to write anywhere.

Up to date
----------
A motor's result is reused when its record exists and holds the same fingerprint, every output
it lists exists with the recorded SHA-256, and the result was not a transient failure (a crashed
worker or an unexpected error is always retried). The fingerprint is a SHA-256 over the
record format, the hallcal version, the options that change the outputs (``export_c``,
``adc_scale``) and, for each input role (data, setup, bla_data, validation), the file's
extension and the SHA-256 of its contents (or that it is absent or missing). Paths themselves do
not count: moving a batch keeps it up to date; editing, replacing or adding any input, or a new
hallcal version, does not. Inputs are hashed when the batch starts; a file replaced while the
batch runs is seen at the next run (its recorded hash is the old one).

Status
------
``ok``
    Artifact written, nothing to report.
``warning``
    Artifact written, with a caveat in the message (model adequacy warning, the validation run
    unusable or f_star worse than f_init on it, the C export refused (for instance an
    ``adc_scale`` too coarse for the signals), or an inadequate model written because the setup
    says ``[model] force = true``).
``refused``
    The calibration ran but its result must not be used (model inadequate, or the lookup table
    not bijective): no artifact.
``failed``
    No result: a bad input file (named in the message), a crashed worker or an unexpected error.

``hallcal fleet`` exits 0 when every motor is ok or warning and :data:`EXIT_INCOMPLETE` (4) when
at least one was refused or failed; 2 when the manifest itself is unusable.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import difflib
import enum
import hashlib
import json
import logging
import math
import os
import re
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pyarrow as pa

from hallcal.errors import HallcalInputError
from hallcal.io import atomic_write, read_json, write_json

__all__ = [
    "ARTIFACT_NAME",
    "C_DIR",
    "EXIT_INCOMPLETE",
    "MANIFEST_COLUMNS",
    "RECORD_NAME",
    "REPORT_NAME",
    "SUMMARY_COLUMNS",
    "FleetProgress",
    "MotorSpec",
    "MotorStatus",
    "all_succeeded",
    "fingerprint",
    "read_manifest",
    "run_fleet",
    "summary_counts",
]

#: Exit status of ``hallcal fleet`` when at least one motor was refused or failed.
EXIT_INCOMPLETE = 4

#: Manifest columns: required first, then optional.
MANIFEST_COLUMNS: tuple[str, ...] = ("motor_id", "data", "setup", "bla_data", "validation")
_REQUIRED_COLUMNS = ("motor_id", "data", "setup")
_INPUT_ROLES = ("data", "setup", "bla_data", "validation")

ARTIFACT_NAME = "calibration.json"
RECORD_NAME = "fleet.json"
C_DIR = "c"
REPORT_NAME = "fleet.html"
SUMMARY_CSV = "summary.csv"
SUMMARY_PARQUET = "summary.parquet"
RECORD_FORMAT = "hallcal-fleet-record/1"

#: How long to wait for an existing scheduler (``scheduler="tcp://..."``) to answer.
_CONNECT_TIMEOUT = "10s"

_MOTOR_ID = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}")

#: Summary columns with their Arrow types. Angles in rad, durations in s.
SUMMARY_SCHEMA = pa.schema(
    [
        pa.field("motor_id", pa.string(), nullable=False),
        pa.field("status", pa.string(), nullable=False),
        pa.field("message", pa.string(), nullable=False),
        pa.field("predicted_error", pa.float64(), metadata={"unit": "rad"}),
        pa.field("f_init_rms", pa.float64(), metadata={"unit": "rad"}),
        pa.field("f_star_rms", pa.float64(), metadata={"unit": "rad"}),
        pa.field("model", pa.string()),
        pa.field("seconds", pa.float64(), metadata={"unit": "s"}),
        pa.field("worker", pa.string()),
        pa.field("reused", pa.bool_(), nullable=False),
        pa.field("computed_at", pa.string()),
        pa.field("artifact", pa.string()),
    ]
)
SUMMARY_COLUMNS: tuple[str, ...] = tuple(SUMMARY_SCHEMA.names)

if TYPE_CHECKING:
    from hallcal.api import Calibration


class MotorStatus(enum.Enum):
    """Outcome of one motor (the ``status`` column).

    ``ok`` and ``warning`` wrote an artifact; ``refused`` and ``failed`` did not.
    """

    OK = "ok"
    WARNING = "warning"
    REFUSED = "refused"
    FAILED = "failed"

    @property
    def success(self) -> bool:
        """True when the motor has a usable artifact."""
        return self in (MotorStatus.OK, MotorStatus.WARNING)


# ------------------------------------------------------------------------------------------------
# Manifest
# ------------------------------------------------------------------------------------------------


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
        table = pq.read_table(p)
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
    p = Path(path)
    if not p.exists():
        raise HallcalInputError(f"{p}: file not found")
    if not p.is_file():
        raise HallcalInputError(f"{p}: not a regular file")
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


# ------------------------------------------------------------------------------------------------
# Fingerprints and records
# ------------------------------------------------------------------------------------------------


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _version() -> str:
    from hallcal._version import __version__

    return __version__


def fingerprint(spec: MotorSpec, options: Mapping[str, Any]) -> str:
    """SHA-256 of what a motor's result depends on (see "Up to date" in the module docs).

    Parameters
    ----------
    spec : MotorSpec
    options : mapping
        The run options that change the outputs (JSON-serializable).

    Returns
    -------
    str
        Hex digest.
    """
    h = hashlib.sha256()
    head = {"format": RECORD_FORMAT, "hallcal": _version(), "options": dict(options)}
    h.update(json.dumps(head, sort_keys=True).encode())
    for role in _INPUT_ROLES:
        path: Path | None = getattr(spec, role)
        if path is None:
            state = "none"
        else:
            try:
                state = f"{path.suffix.lower()}:{_sha256_file(path)}"
            except FileNotFoundError:
                state = "missing"
            except OSError as exc:
                state = f"unreadable:{exc.errno}"
        h.update(f"\0{role}={state}".encode())
    return h.hexdigest()


def _load_record(folder: Path) -> dict[str, Any] | None:
    path = folder / RECORD_NAME
    if not path.is_file():
        return None
    try:
        rec = read_json(path)
    except HallcalInputError:
        return None
    if not isinstance(rec, dict) or rec.get("format") != RECORD_FORMAT:
        return None
    return rec


def _record_is_current(folder: Path, record: Mapping[str, Any] | None, fp: str) -> bool:
    if record is None or record.get("fingerprint") != fp or record.get("retry", True):
        return False
    row = record.get("row")
    if not isinstance(row, dict) or set(row) != set(SUMMARY_COLUMNS) - {"reused"}:
        return False
    outputs = record.get("outputs")
    if not isinstance(outputs, dict):
        return False
    for rel, digest in outputs.items():
        p = folder / rel
        try:
            if not p.is_file() or _sha256_file(p) != digest:
                return False
        except OSError:
            return False
    return True


# ------------------------------------------------------------------------------------------------
# The work of one motor (runs in a worker)
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Task:
    """What a worker needs for one motor (sent through Dask; paths as strings)."""

    motor_id: str
    data: str
    setup: str
    bla_data: str | None
    validation: str | None
    export_c: bool
    adc_scale: float
    version: str


@dataclass
class _Result:
    """What a worker sends back: the summary row, the output files and whether to retry."""

    row: dict[str, Any]
    files: dict[str, bytes] = field(default_factory=dict)
    retry: bool = False
    detail: str | None = None


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _calibrate(data: str, setup: str, bla_data: str | None) -> Calibration:
    """The one call into the calibration: the front door, as ``hallcal calibrate`` uses it.

    Returns a :class:`hallcal.api.Calibration`; errors name the file at fault (the numeric
    layers say "setup:", replaced here by the setup file's path, as the CLI does).
    """
    from hallcal.api import calibrate

    try:
        return calibrate(data, setup, bla_data=bla_data)
    except HallcalInputError as exc:
        msg = str(exc)
        if msg.startswith("setup:"):
            raise HallcalInputError(setup + msg[len("setup") :]) from None
        raise


def _model_text(model: Mapping[str, Any]) -> str:
    basis = model.get("basis")
    if basis == "fourier":
        return "fourier " + _ranges(model.get("harmonics", []))
    if basis == "kernel":
        text = f"kernel m={model.get('points')}"
        ls = model.get("lengthscale")
        if isinstance(ls, int | float) and math.isfinite(ls):
            text += f" l={ls:.3g}"
        return text
    return str(basis or "")


def _ranges(values: Iterable[Any]) -> str:
    """[1, 2, 3, 5, 33] -> '1-3,5,33'."""
    v = sorted(int(x) for x in values)
    out, i = [], 0
    while i < len(v):
        j = i
        while j + 1 < len(v) and v[j + 1] == v[j] + 1:
            j += 1
        out.append(f"{v[i]}-{v[j]}" if j > i + 1 else ",".join(map(str, v[i : j + 1])))
        i = j + 1
    return ",".join(out)


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"local pid {os.getpid()}"


@contextlib.contextmanager
def _single_threaded() -> Iterator[None]:
    """BLAS (threadpoolctl) and numba at one thread, so n workers use n cores, not n^2."""
    from threadpoolctl import threadpool_limits

    try:
        import numba

        previous = numba.get_num_threads()
        numba.set_num_threads(1)
    except (ImportError, ValueError, RuntimeError):  # pragma: no cover - numba always present
        numba, previous = None, None
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        if numba is not None and previous is not None:
            numba.set_num_threads(previous)


def _empty_row(motor_id: str) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(SUMMARY_COLUMNS)
    row.update(motor_id=motor_id, message="", reused=False)
    return row


def _run_motor(task: _Task) -> _Result:
    """Calibrate one motor: never raises for a problem of the motor (it goes in the row)."""
    t0 = time.perf_counter()
    row = _empty_row(task.motor_id)
    row["worker"] = _worker_name()
    row["computed_at"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    result = _Result(row)
    try:
        if task.version != _version():
            raise HallcalInputError(
                f"worker {row['worker']} runs hallcal {_version()}, the client {task.version}: "
                "install the same version on every worker"
            )
        with _single_threaded():
            _calibrate_into(task, result)
    except HallcalInputError as exc:
        row.update(status=MotorStatus.FAILED.value, message=_one_line(str(exc)))
    except MemoryError:
        row.update(status=MotorStatus.FAILED.value, message="out of memory in the worker")
        result.retry = True
    except Exception as exc:  # a bug or an unforeseen input: report it, go on with the others
        row.update(
            status=MotorStatus.FAILED.value,
            message=_one_line(f"internal error: {type(exc).__name__}: {exc}"),
        )
        result.retry = True
        result.detail = traceback.format_exc()
        result.files.clear()
    row["seconds"] = time.perf_counter() - t0
    return result


def _calibrate_into(task: _Task, result: _Result) -> None:
    from hallcal.io import read_dataset
    from hallcal.pipeline.calibration import CalibrationStatus

    row = result.row
    cal = _calibrate(task.data, task.setup, task.bla_data)
    row["predicted_error"] = _finite(cal.predicted_error)
    row["model"] = _model_text(cal.model_info)
    force = bool(cal.setup.model.force)  # as `hallcal calibrate` honours [model] force = true
    notes = list(cal.messages)
    if cal.status is CalibrationStatus.NOT_BIJECTIVE or (cal.status.refused and not force):
        reason = cal.refusal or (notes[0] if notes else str(cal.status))
        row.update(status=MotorStatus.REFUSED.value, message=_one_line(reason))
        return
    status = MotorStatus.OK if cal.status is CalibrationStatus.OK else MotorStatus.WARNING
    if cal.status.refused:
        notes.insert(0, f"model inadequate, written because [model] force = true: {cal.refusal}")
    elif cal.status is CalibrationStatus.WARNING and not notes:
        notes.append("warning: see the artifact's diagnostics")
    with tempfile.TemporaryDirectory(prefix="hallcal-fleet-") as tmp:
        cal.save(Path(tmp) / ARTIFACT_NAME, force=force)
        result.files[ARTIFACT_NAME] = (Path(tmp) / ARTIFACT_NAME).read_bytes()
        if task.export_c:
            cdir = Path(tmp) / C_DIR
            try:
                res = cal.export_c(cdir, adc_scale=task.adc_scale)
            except HallcalInputError as exc:  # the artifact stands; its C sources do not
                status = MotorStatus.WARNING
                notes.insert(0, f"warning: no C export: {exc}")
            else:
                notes += [f"C export: {m}" for m in getattr(res, "messages", [])]
                for p in sorted(cdir.iterdir()):
                    result.files[f"{C_DIR}/{p.name}"] = p.read_bytes()
    if task.validation is not None:
        try:
            ds = read_dataset(task.validation, required=("d1", "d2", "d3", "y_ref"))
            v = cal.reconstruct(ds).validation
            row["f_init_rms"] = _finite(v.init.rms)
            row["f_star_rms"] = _finite(v.star.rms)
            if v.star.rms > v.init.rms:
                status = MotorStatus.WARNING
                notes.insert(
                    0,
                    f"warning: on the validation run f_star ({1e3 * v.star.rms:.3f} mrad RMS) is "
                    f"worse than f_init ({1e3 * v.init.rms:.3f} mrad)",
                )
        except HallcalInputError as exc:
            status = MotorStatus.WARNING
            notes.insert(0, f"warning: validation run unusable: {exc}")
    row["status"] = status.value
    row["artifact"] = f"{task.motor_id}/{ARTIFACT_NAME}"
    row["message"] = _one_line(notes[0]) if notes else ""


def _finite(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


# ------------------------------------------------------------------------------------------------
# Client side: scheduling, outputs, summary
# ------------------------------------------------------------------------------------------------


#: ``progress(row, done, total)``: once with ``row=None, done=0`` when the batch starts, then once
#: per motor as its row is known (reused and unrunnable rows first, then as workers finish).
FleetProgress = Callable[[Mapping[str, Any] | None, int, int], None]


def _failed_result(motor_id: str, message: str, *, retry: bool) -> _Result:
    row = _empty_row(motor_id)
    row.update(
        status=MotorStatus.FAILED.value,
        message=_one_line(message),
        computed_at=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    )
    return _Result(row, retry=retry)


def _store(out: Path, spec: MotorSpec, fp: str, result: _Result) -> None:
    """Write one motor's outputs then its record (the record last, so it vouches for them)."""
    folder = out / spec.motor_id
    folder.mkdir(parents=True, exist_ok=True)
    with contextlib.suppress(FileNotFoundError):
        (folder / RECORD_NAME).unlink()
    # outputs of an earlier run that this one does not produce (a motor now refused) must go
    stale = [folder / ARTIFACT_NAME] + sorted((folder / C_DIR).glob("*"))
    wanted = {folder / rel for rel in result.files}
    for p in stale:
        if p not in wanted and p.is_file():
            p.unlink()
    if (folder / C_DIR).is_dir() and not any((folder / C_DIR).iterdir()):
        (folder / C_DIR).rmdir()
    outputs: dict[str, str] = {}
    for rel, content in result.files.items():
        target = folder / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(target, "wb") as f:
            f.write(content)
        outputs[rel] = hashlib.sha256(content).hexdigest()
    record = {
        "format": RECORD_FORMAT,
        "fingerprint": fp,
        "retry": result.retry,
        "row": {k: v for k, v in result.row.items() if k != "reused"},
        "inputs": {
            role: None if getattr(spec, role) is None else str(getattr(spec, role))
            for role in _INPUT_ROLES
        },
        "outputs": outputs,
    }
    if result.detail:
        record["traceback"] = result.detail
    write_json(folder / RECORD_NAME, record)


def _local_cluster(workers: int | None) -> Any:
    import dask
    from distributed import LocalCluster

    n = workers if workers is not None else (os.cpu_count() or 1)
    settings = {
        # one retry of a task whose worker died (a transient crash), then it is reported failed
        "distributed.scheduler.allowed-failures": 1,
        # Dask sets MALLOC_TRIM_THRESHOLD_ in its workers to hand memory back to the system
        # early; it also turns off glibc's adaptive mmap threshold, so every large temporary of
        # a calibration is mapped and faulted in anew (twice the system time, measured)
        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    }
    with dask.config.set(settings):
        return LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address="127.0.0.1:0",  # a free port: no clash with other clusters
            silence_logs=logging.ERROR,
            env={
                "OMP_NUM_THREADS": "1",
                "OPENBLAS_NUM_THREADS": "1",
                "MKL_NUM_THREADS": "1",
                "NUMBA_NUM_THREADS": "1",
            },
        )


def _crash_message(exc: BaseException) -> tuple[str, bool]:
    name = type(exc).__name__
    if name == "KilledWorker":
        return (
            "worker crashed while calibrating this motor (the task killed its worker; retried once)"
        ), True
    if name in ("CancelledError", "FutureCancelledError"):
        return "the task was cancelled (scheduler or worker lost)", True
    return f"worker error: {name}: {exc}", True


def run_fleet(
    manifest_or_rows: str | os.PathLike[str] | Iterable[Mapping[str, Any] | MotorSpec],
    out: str | os.PathLike[str],
    *,
    scheduler: Any = None,
    workers: int | None = None,
    export_c: bool = False,
    adc_scale: float = 1.0,
    recompute: bool = False,
    report: bool = True,
    base: str | os.PathLike[str] | None = None,
    progress: FleetProgress | None = None,
    _task: Callable[[_Task], _Result] | None = None,
) -> pa.Table:
    """Calibrate every motor of a manifest on Dask; write the artifacts and the summary.

    Parameters
    ----------
    manifest_or_rows : path-like or iterable of mapping or MotorSpec
        A manifest file (CSV or Parquet), or rows with the manifest's keys (``motor_id``,
        ``data``, ``setup``, optional ``bla_data`` and ``validation``).
    out : path-like
        Output folder (created if missing).
    scheduler : str or distributed.Client, optional
        None: a local cluster in this machine, one single-threaded worker process per core
        (``workers`` to change), closed at the end. A string: the address of an existing Dask
        scheduler (``"tcp://host:8786"``); its workers need hallcal (same version) and read access
        to the inputs. A ``distributed.Client``: used as it is. ``"sequential"``: no Dask, the
        motors one after the other in this process (debugging, the benchmarks' baseline).
    workers : int, optional
        Number of workers of the local cluster (default: ``os.cpu_count()``).
    export_c : bool
        Also write each artifact's C99 sources (:func:`hallcal.output.codegen.export_c`) to
        ``OUT/<motor_id>/c/``.
    adc_scale : float
        ADC counts per Hall signal unit for the fixed-point C export.
    recompute : bool
        Ignore the records of earlier runs and calibrate every motor again.
    report : bool
        Write ``OUT/fleet.html``.
    base : path-like, optional
        Folder that relative paths in `manifest_or_rows` rows are relative to (default: the
        current directory; a manifest file's own folder for a manifest).
    progress : callable, optional
        ``progress(row, done, total)``: once with ``row=None`` at the start, then after each
        motor (see :data:`FleetProgress`).

    Returns
    -------
    pyarrow.Table
        The summary (:data:`SUMMARY_COLUMNS`, one row per manifest row, in manifest order), as
        written to ``OUT/summary.parquet`` and ``OUT/summary.csv``. ``table.to_pylist()`` gives
        the rows as dicts; :func:`summary_counts` the number per status. Angles in rad.

    Raises
    ------
    HallcalInputError
        The manifest is unusable (missing file or column, no motors), the output folder cannot
        be created, or the scheduler cannot be reached. Problems of single motors do not raise:
        they are in their rows.
    Notes
    -----
    The default local cluster spawns worker processes, which import the calling script's main
    module: a script (not a notebook) that calls this needs the usual
    ``if __name__ == "__main__":`` guard, as with any Dask process cluster.

    Examples
    --------
    >>> table = run_fleet("manifest.csv", "batch")  # doctest: +SKIP
    >>> [r["motor_id"] for r in table.to_pylist() if r["status"] == "failed"]  # doctest: +SKIP
    """
    specs, source = _specs(manifest_or_rows, base)
    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise HallcalInputError(f"{out_dir}: exists and is not a folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HallcalInputError(f"{out_dir}: cannot create the folder ({exc.strerror})") from None
    if not (isinstance(adc_scale, int | float) and math.isfinite(adc_scale) and adc_scale > 0):
        raise HallcalInputError(f"adc_scale must be a positive number, got {adc_scale!r}")
    options = {"export_c": bool(export_c), "adc_scale": float(adc_scale) if export_c else None}
    version = _version()
    total = len(specs)
    rows: list[dict[str, Any] | None] = [None] * total
    done = 0
    if progress is not None:
        progress(None, 0, total)

    def finish(i: int, row: dict[str, Any]) -> None:
        nonlocal done
        rows[i] = row
        done += 1
        if progress is not None:
            progress(row, done, total)

    pending: list[tuple[int, MotorSpec, str]] = []
    for i, spec in enumerate(specs):
        if spec.problem is not None:
            finish(i, _failed_result(spec.motor_id, spec.problem, retry=False).row)
            continue
        fp = fingerprint(spec, options)
        folder = out_dir / spec.motor_id
        record = None if recompute else _load_record(folder)
        if _record_is_current(folder, record, fp):
            assert record is not None
            finish(i, {**record["row"], "reused": True})
        else:
            pending.append((i, spec, fp))

    def task_of(spec: MotorSpec) -> _Task:
        return _Task(
            motor_id=spec.motor_id,
            data=str(spec.data),
            setup=str(spec.setup),
            bla_data=None if spec.bla_data is None else str(spec.bla_data),
            validation=None if spec.validation is None else str(spec.validation),
            export_c=bool(export_c),
            adc_scale=float(adc_scale),
            version=version,
        )

    def accept(i: int, spec: MotorSpec, fp: str, result: _Result) -> None:
        _store(out_dir, spec, fp, result)
        finish(i, result.row)

    work = _task or _run_motor
    if pending:
        if isinstance(scheduler, str) and scheduler == "sequential":
            for i, spec, fp in pending:
                accept(i, spec, fp, work(task_of(spec)))
        else:
            with _client(scheduler, workers) as client:
                _run_on_dask(client, pending, task_of, accept, work)

    table = pa.Table.from_pylist([r for r in rows if r is not None], schema=SUMMARY_SCHEMA)
    _write_summary(out_dir, table)
    if report:
        from hallcal.output.fleet_report import write_fleet_report

        write_fleet_report(table, out_dir / REPORT_NAME, source=source)
    return table


@contextlib.contextmanager
def _client(scheduler: Any, workers: int | None) -> Iterator[Any]:
    from distributed import Client

    if scheduler is None:
        cluster = _local_cluster(workers)
        try:
            with Client(cluster, set_as_default=False) as client:
                yield client
        finally:
            cluster.close()
    elif isinstance(scheduler, str):
        try:
            client = Client(scheduler, timeout=_CONNECT_TIMEOUT, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            why = _one_line(str(exc)) or type(exc).__name__
            raise HallcalInputError(f"scheduler {scheduler}: cannot connect ({why})") from None
        with client:
            yield client
    else:
        yield scheduler  # a Client the caller owns


def _run_on_dask(
    client: Any,
    pending: Sequence[tuple[int, MotorSpec, str]],
    task_of: Callable[[MotorSpec], _Task],
    accept: Callable[[int, MotorSpec, str, _Result], None],
    work: Callable[[_Task], _Result],
) -> None:
    from distributed import as_completed

    futures = {}
    for i, spec, fp in pending:
        fut = client.submit(
            work,
            task_of(spec),
            key=f"hallcal-fleet-{spec.motor_id}-{fp[:16]}",
            pure=False,
            retries=0,
        )
        futures[fut] = (i, spec, fp)
    try:
        for fut in as_completed(list(futures), loop=client.loop):
            i, spec, fp = futures.pop(fut)
            try:
                result = fut.result()
            except Exception as exc:  # the worker died, or the task was lost with it
                message, retry = _crash_message(exc)
                result = _failed_result(spec.motor_id, message, retry=retry)
            accept(i, spec, fp, result)
            fut.release()
    finally:
        for fut in futures:
            fut.cancel()


def _write_summary(out: Path, table: pa.Table) -> None:
    import csv
    import io

    import pyarrow.parquet as pq

    with atomic_write(out / SUMMARY_PARQUET, "wb") as f:
        pq.write_table(table, f)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(table.column_names)
    for row in table.to_pylist():
        w.writerow([_csv_cell(row[k]) for k in table.column_names])
    with atomic_write(out / SUMMARY_CSV, "w") as f:
        f.write(buf.getvalue())


def _csv_cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def summary_counts(table: pa.Table) -> dict[str, int]:
    """Number of motors per status (every status present, zeros included).

    Parameters
    ----------
    table : pyarrow.Table
        The fleet summary (its ``status`` column).

    Returns
    -------
    dict of str to int
        Status value (``"ok"``, ``"warning"``, ``"refused"``, ``"failed"``) -> motors.
    """
    counts = dict.fromkeys((s.value for s in MotorStatus), 0)
    for s in table.column("status").to_pylist():
        counts[s] = counts.get(s, 0) + 1
    return counts


def all_succeeded(table: pa.Table) -> bool:
    """True when every motor is ok or warning (``hallcal fleet`` then exits 0).

    Parameters
    ----------
    table : pyarrow.Table
        The fleet summary (its ``status`` column).

    Returns
    -------
    bool
    """
    return all(MotorStatus(s).success for s in table.column("status").to_pylist())
