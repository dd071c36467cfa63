"""File input and output: datasets, the setup file, the calibration artifact, JSON sidecars.

Everything a user hands to hallcal goes through this module, and every mistake in it raises
:class:`hallcal.errors.HallcalInputError` with a one-line message that names the file and the
column or key at fault. Everything hallcal writes goes through :func:`atomic_write` (a temporary
file in the target directory, then :func:`os.replace`), so an interrupted or failed write never
leaves a half-written output behind. Nothing here unpickles anything.

The contracts implemented here are the ones of ``DESIGN.md`` ("Setup file", "Dataset files",
"Calibration artifact").

Datasets
--------
One table, one row per sample; the format is chosen by the file extension:

``.csv``
    UTF-8 text, a header row of column names, then one row of numbers per sample. The delimiter
    is a comma (a semicolon or a tab is accepted when the header holds no comma). Blank lines and
    lines starting with ``#`` are skipped, except that a ``#`` line directly followed by numbers
    is the header (``numpy.savetxt(..., header="d1,d2,d3")`` writes one). Rows are counted from
    1 at the first data row; error messages also give the line number in the file.
``.parquet``
    One Parquet table (pyarrow); integer, floating-point and boolean columns.
``.h5``, ``.hdf5``
    One 1-D dataset per column. The columns are the datasets of the group ``/data`` when the
    file has one, else the datasets at the root. MATLAB v7.3 files (which are HDF5) are read the
    same way.
``.mat``
    MATLAB file, one variable per column (row or column vectors).
``.npz``
    NumPy archive, one array per column, read with ``allow_pickle=False``.

In HDF5, MATLAB and NumPy files, members that are not numeric vectors (scalars, matrices,
strings, structs) and vectors whose length differs from the known columns' are not columns and
are ignored, unless their name is a known column (then they are an error). In CSV and Parquet
files every column is a column and is checked.

Every column is converted to a read-only float64 vector; all must be finite and of the same
length. The known columns are ``r``, ``y``, ``u``, ``d1``, ``d2``, ``d3``, ``t``, ``y_ref`` and
``realization`` (whole numbers, stored as float64); other columns are kept.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import difflib
import io
import json
import math
import os
import re
import tempfile
import tomllib
import zipfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal, NoReturn

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.sim.lti import ContinuousTF, DiscreteTF

__all__ = [
    "ARTIFACT_FORMAT",
    "DATASET_EXTENSIONS",
    "KNOWN_COLUMNS",
    "BLASpec",
    "BenchSpec",
    "ContinuousTF",
    "Dataset",
    "DiscreteTF",
    "MissingColumnError",
    "ModelSpec",
    "Setup",
    "TrajectorySpec",
    "atomic_path",
    "atomic_write",
    "default_setup",
    "read_artifact",
    "read_dataset",
    "read_json",
    "read_setup",
    "setup_from_dict",
    "setup_to_toml",
    "to_jsonable",
    "write_artifact",
    "write_dataset",
    "write_json",
    "write_setup",
]

#: Value of the ``"format"`` key of every calibration artifact this version writes and reads.
ARTIFACT_FORMAT = "hallcal-calibration/1"

#: Column names with a meaning to hallcal (``DESIGN.md``, "Dataset files").
KNOWN_COLUMNS: tuple[str, ...] = ("r", "y", "u", "d1", "d2", "d3", "t", "y_ref", "realization")

#: Dataset file extensions (lower case) understood by :func:`read_dataset`/:func:`write_dataset`.
DATASET_EXTENSIONS: tuple[str, ...] = (".csv", ".parquet", ".h5", ".hdf5", ".mat", ".npz")


# ================================================================================================
# Atomic writes
# ================================================================================================


def _umask() -> int:
    """Return the process umask without changing it (Linux), else by setting and restoring it."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success move it onto `path` atomically.

    For libraries that insist on a file name (h5py). The temporary file exists (empty) when the
    block starts. On any exception in the block the temporary file is removed and `path` is left
    untouched.

    Parameters
    ----------
    path : path-like
        Final destination. Its directory must exist.

    Yields
    ------
    pathlib.Path
        The temporary file to write, in the same directory as `path`.

    Raises
    ------
    HallcalInputError
        If the directory does not exist or the file cannot be created or replaced.
    """
    target = Path(path)
    directory = target.parent
    if not directory.is_dir():
        raise HallcalInputError(f"{target}: directory '{directory}' does not exist")
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise HallcalInputError(f"{target}: cannot write ({exc.strerror or exc})") from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        try:
            os.replace(tmp, target)
        except OSError as exc:
            raise HallcalInputError(f"{target}: cannot write ({exc.strerror or exc})") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike[str],
    mode: Literal["w", "wb", "w+b"] = "w",
    *,
    encoding: str = "utf-8",
) -> Iterator[IO[Any]]:
    """Open a temporary file next to `path` for writing; replace `path` with it on success.

    The data are flushed and synced before :func:`os.replace`, so `path` holds either its old
    content or the complete new one. On any exception in the block the temporary file is removed
    and the exception propagates. The new file gets the usual permissions (``0o666 & ~umask``).

    Parameters
    ----------
    path : path-like
        Final destination. Its directory must exist.
    mode : {"w", "wb", "w+b"}
        Text or binary (``"w+b"`` for writers that read back what they wrote).
    encoding : str
        Text encoding in text mode (newlines are written as ``"\\n"``).

    Yields
    ------
    file object
        Open on the temporary file.

    Raises
    ------
    HallcalInputError
        If the directory does not exist or the file cannot be created or replaced.

    Examples
    --------
    >>> with atomic_write("out.txt") as f:  # doctest: +SKIP
    ...     f.write("hello\\n")
    """
    if mode not in ("w", "wb", "w+b"):
        raise ValueError(f"atomic_write: mode must be 'w', 'wb' or 'w+b', got {mode!r}")
    with atomic_path(path) as tmp:
        if mode == "w":
            handle: IO[Any] = open(tmp, "w", encoding=encoding, newline="\n")
        else:
            handle = open(tmp, mode)
        with handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())


# ================================================================================================
# Small helpers shared by the readers
# ================================================================================================


def _closest(name: str, candidates: Iterable[str]) -> str | None:
    """Return the candidate `name` was most likely meant to be (difflib, then case), or None."""
    options = list(candidates)
    matches = difflib.get_close_matches(name, options, n=1, cutoff=0.6)
    if matches:
        return matches[0]
    lowered = {c.lower(): c for c in options}
    return lowered.get(name.lower())


def _suggest(name: str, candidates: Iterable[str]) -> str:
    """Return ``" (did you mean 'x'?)"`` for the closest candidate, or ``""``."""
    guess = _closest(name, candidates)
    return f" (did you mean '{guess}'?)" if guess is not None else ""


def _existing_file(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    if not p.exists():
        raise HallcalInputError(f"{p}: file not found")
    if not p.is_file():
        raise HallcalInputError(f"{p}: not a regular file")
    return p


def _read_bytes(p: Path) -> bytes:
    try:
        return p.read_bytes()
    except OSError as exc:
        raise HallcalInputError(f"{p}: cannot read ({exc.strerror or exc})") from None


def _decode_text(p: Path, raw: bytes) -> str:
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise HallcalInputError(f"{p}: not UTF-8 text (line {line})") from None


# ================================================================================================
# Datasets
# ================================================================================================


class MissingColumnError(HallcalInputError, KeyError):
    """A dataset column that is needed is absent.

    Both a :class:`HallcalInputError` (one-line message naming the file and the column) and a
    :class:`KeyError`, so ``dataset["y_ref"]`` behaves like a mapping lookup.
    """

    __str__ = BaseException.__str__


@dataclass(frozen=True, eq=False)
class Dataset:
    """One experiment: named sample-by-sample columns of equal length.

    Build it with :func:`read_dataset` or :meth:`Dataset.from_columns`, which check it.

    Attributes
    ----------
    columns : dict of str to numpy.ndarray
        Read-only float64 1-D arrays, all of length :attr:`n_samples`, in file order.
    path : pathlib.Path or None
        Where it was read from (``None`` for data built in memory); used in error messages.
    """

    columns: dict[str, np.ndarray]
    path: Path | None = None

    @classmethod
    def from_columns(
        cls,
        columns: Mapping[str, Any],
        *,
        path: str | os.PathLike[str] | None = None,
        required: Sequence[str] = (),
        min_samples: int = 1,
    ) -> Dataset:
        """Check in-memory columns and wrap them as a dataset (the arrays are copied).

        Parameters
        ----------
        columns : mapping of str to array_like
            Numeric 1-D arrays (or lists) of equal length.
        path : path-like, optional
            Recorded as :attr:`path` and used in error messages (default ``"<dataset>"``).
        required : sequence of str
            Columns that must be present.
        min_samples : int
            Minimum number of rows.

        Raises
        ------
        HallcalInputError
            For any of the problems :func:`read_dataset` reports.
        """
        source = str(path) if path is not None else "<dataset>"
        cols: dict[str, np.ndarray] = {}
        for name, values in columns.items():
            arr = np.asarray(values)
            if arr.dtype.kind not in "biuf":
                raise HallcalInputError(f"{source}: column '{name}' is not numeric")
            if arr.ndim != 1:
                raise HallcalInputError(
                    f"{source}: column '{name}' must be 1-D, got shape {arr.shape}"
                )
            cols[str(name)] = arr
        checked = _finish_columns(cols, source, required=required, min_samples=min_samples)
        return cls(checked, Path(path) if path is not None else None)

    @property
    def n_samples(self) -> int:
        """Number of rows (samples)."""
        return next(iter(self.columns.values())).shape[0] if self.columns else 0

    @property
    def names(self) -> tuple[str, ...]:
        """Column names in file order."""
        return tuple(self.columns)

    @property
    def source(self) -> str:
        """The file name for messages (``"<dataset>"`` when built in memory)."""
        return str(self.path) if self.path is not None else "<dataset>"

    @property
    def d(self) -> np.ndarray:
        """Hall signals ``d1``, ``d2``, ``d3`` as an ``(n_samples, 3)`` float64 array."""
        self.require("d1", "d2", "d3")
        return np.column_stack([self.columns["d1"], self.columns["d2"], self.columns["d3"]])

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.columns[name]
        except KeyError:
            raise MissingColumnError(self._missing_message(name)) from None

    def __contains__(self, name: object) -> bool:
        return name in self.columns

    def get(self, name: str, default: Any = None) -> Any:
        """Return column `name`, or `default` when the dataset has no such column."""
        return self.columns.get(name, default)

    def require(self, *names: str) -> None:
        """Raise :class:`MissingColumnError` naming the first of `names` that is absent."""
        for name in names:
            if name not in self.columns:
                raise MissingColumnError(self._missing_message(name))

    def _missing_message(self, name: str) -> str:
        return f"{self.source}: column '{name}' is missing{_suggest(name, self.columns)}"

    def __repr__(self) -> str:
        return (
            f"Dataset(path={self.source!r}, n_samples={self.n_samples}, "
            f"columns={list(self.columns)})"
        )


def _finish_columns(
    cols: dict[str, np.ndarray],
    source: str,
    *,
    required: Sequence[str],
    min_samples: int,
    row_lines: Sequence[int] | None = None,
) -> dict[str, np.ndarray]:
    """Check presence, length, finiteness and whole-number realizations; return float64 copies."""

    def where(i: int) -> str:
        line = f", line {row_lines[i]}" if row_lines is not None and i < len(row_lines) else ""
        return f"row {i + 1}{line}"

    if not cols:
        raise HallcalInputError(f"{source}: no columns")
    for name in required:
        if name not in cols:
            found = ", ".join(cols) if len(cols) <= 12 else ", ".join(list(cols)[:12]) + ", ..."
            raise MissingColumnError(
                f"{source}: column '{name}' is missing{_suggest(name, cols)} (found: {found})"
            )
    lengths = {name: arr.shape[0] for name, arr in cols.items()}
    if len(set(lengths.values())) > 1:
        first = next(iter(lengths))
        other = next(n for n in lengths if lengths[n] != lengths[first])
        raise HallcalInputError(
            f"{source}: columns have different lengths ('{first}': {lengths[first]} rows, "
            f"'{other}': {lengths[other]} rows)"
        )
    n = lengths[next(iter(lengths))]
    if n == 0:
        raise HallcalInputError(f"{source}: no data rows")
    if n < min_samples:
        raise HallcalInputError(f"{source}: {n} data rows, at least {min_samples} needed")
    out: dict[str, np.ndarray] = {}
    for name, arr in cols.items():
        values = np.array(arr, dtype=np.float64)
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.argmax(bad))
            raise HallcalInputError(f"{source}: column '{name}' contains NaN or inf ({where(i)})")
        if name == "realization":
            frac = values != np.round(values)
            if frac.any():
                i = int(np.argmax(frac))
                raise HallcalInputError(
                    f"{source}: column 'realization' must hold whole numbers "
                    f"({where(i)} has {float(values[i])!r})"
                )
        values.setflags(write=False)
        out[name] = values
    return out


def _check_extension(p: Path) -> str:
    ext = p.suffix.lower()
    if ext not in DATASET_EXTENSIONS:
        shown = f"'{p.suffix}'" if p.suffix else "(none)"
        raise HallcalInputError(
            f"{p}: unknown dataset extension {shown} (expected one of "
            f"{', '.join(DATASET_EXTENSIONS)})"
        )
    return ext


def read_dataset(
    path: str | os.PathLike[str],
    *,
    required: Sequence[str] = ("d1", "d2", "d3"),
    min_samples: int = 2,
) -> Dataset:
    """Read and check a dataset file (``DESIGN.md``, "Dataset files").

    Parameters
    ----------
    path : path-like
        ``.csv``, ``.parquet``, ``.h5``/``.hdf5``, ``.mat`` or ``.npz`` file (see the module
        documentation for the layout of each).
    required : sequence of str
        Columns that must be present.
    min_samples : int
        Minimum number of rows.

    Returns
    -------
    Dataset
        Read-only float64 columns of equal length, all finite.

    Raises
    ------
    HallcalInputError
        Missing or unreadable file, unknown extension, empty file or no rows, a missing required
        column (:class:`MissingColumnError`), a non-numeric value (with its row), NaN or inf
        (with its row), columns of different lengths, fewer than `min_samples` rows, an
        object (pickled) array in an ``.npz`` file.
    """
    p = _existing_file(path)
    ext = _check_extension(p)
    if p.stat().st_size == 0:
        raise HallcalInputError(f"{p}: file is empty")
    row_lines: list[int] | None = None
    if ext == ".csv":
        cols, row_lines = _read_csv(p)
    elif ext == ".parquet":
        cols = _read_parquet(p)
    elif ext in (".h5", ".hdf5"):
        cols = _read_hdf5(p)
    elif ext == ".mat":
        cols = _read_mat(p)
    else:
        cols = _read_npz(p)
    checked = _finish_columns(
        cols, str(p), required=required, min_samples=min_samples, row_lines=row_lines
    )
    return Dataset(checked, p)


# ---- CSV ---------------------------------------------------------------------------------------


def _parse_numbers(name: str, values: list[str], source: str, lines: Sequence[int]) -> np.ndarray:
    try:
        return np.array(values, dtype=np.float64)
    except ValueError:
        pass
    out = np.empty(len(values), dtype=np.float64)
    for i, text in enumerate(values):
        try:
            out[i] = float(text)
        except ValueError:
            stripped = text.strip()
            what = "a missing value" if not stripped else f"a non-numeric value {stripped[:30]!r}"
            raise HallcalInputError(
                f"{source}: column '{name}' has {what} in row {i + 1} (line {lines[i]})"
            ) from None
    return out


def _read_csv(p: Path) -> tuple[dict[str, np.ndarray], list[int]]:
    source = str(p)
    text = _decode_text(p, _read_bytes(p))
    lines = text.splitlines()
    header_index = _find_header(lines)
    if header_index is None:
        raise HallcalInputError(f"{source}: file is empty")
    header_line = lines[header_index].strip()
    if header_line.startswith("#"):
        header_line = header_line[1:].strip()
    delimiter = ","
    if "," not in header_line:
        if "\t" in header_line:
            delimiter = "\t"
        elif ";" in header_line:
            delimiter = ";"
    header = [name.strip() for name in next(csv.reader([header_line], delimiter=delimiter))]
    trailing_empty = len(header) > 1 and header[-1] == ""
    if trailing_empty:
        header.pop()
    for j, name in enumerate(header):
        if not name:
            raise HallcalInputError(f"{source}: column {j + 1} of the header has no name")
        if header.index(name) != j:
            raise HallcalInputError(f"{source}: column '{name}' appears twice in the header")
        if _looks_numeric(name):
            raise HallcalInputError(
                f"{source}: the first line must be a header of column names, "
                f"found the number {name!r}"
            )
    width = len(header)
    values: list[list[str]] = [[] for _ in header]
    row_lines: list[int] = []
    body = lines[header_index + 1 :]
    reader = csv.reader(body, delimiter=delimiter)
    for record in reader:
        line_no = header_index + 1 + reader.line_num
        if not record or (len(record) == 1 and not record[0].strip()):
            continue
        if record[0].lstrip().startswith("#"):
            continue
        if trailing_empty and len(record) == width + 1 and not record[-1].strip():
            record.pop()
        if len(record) != width:
            raise HallcalInputError(
                f"{source}: row {len(row_lines) + 1} (line {line_no}) has {len(record)} "
                f"fields, the header has {width}"
            )
        row_lines.append(line_no)
        for j, item in enumerate(record):
            values[j].append(item)
    if not row_lines:
        raise HallcalInputError(f"{source}: no data rows")
    cols = {
        name: _parse_numbers(name, vals, source, row_lines)
        for name, vals in zip(header, values, strict=True)
    }
    return cols, row_lines


def _find_header(lines: Sequence[str]) -> int | None:
    """Index of the header line: the first non-blank line that is not a ``#`` comment, unless
    that line holds numbers, in which case the last ``#`` line before it (``numpy.savetxt``)."""
    last_comment = None
    for i, line in enumerate(lines):
        text = line.strip()
        if not text:
            continue
        if text.startswith("#"):
            last_comment = i
            continue
        first_field = re.split(r"[,;\t]", text, maxsplit=1)[0].strip().strip('"')
        if _looks_numeric(first_field) and last_comment is not None:
            return last_comment
        return i
    return last_comment


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return text.strip().lower() not in ("nan", "inf", "infinity", "-inf", "+inf")


# ---- Parquet -----------------------------------------------------------------------------------


def _read_parquet(p: Path) -> dict[str, np.ndarray]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    source = str(p)
    try:
        table = pq.read_table(p)
    except (pa.ArrowException, OSError, ValueError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise HallcalInputError(f"{source}: not a valid Parquet file ({first})") from None
    cols: dict[str, np.ndarray] = {}
    for j, name in enumerate(table.column_names):
        if not name:
            raise HallcalInputError(f"{source}: column {j + 1} has no name")
        if name in cols:
            raise HallcalInputError(f"{source}: column '{name}' appears twice")
        column = table.column(j)
        typ = column.type
        if pa.types.is_dictionary(typ):
            column = column.cast(typ.value_type)
            typ = column.type
        if not (pa.types.is_integer(typ) or pa.types.is_floating(typ) or pa.types.is_boolean(typ)):
            raise HallcalInputError(f"{source}: column '{name}' is not numeric (type {typ})")
        if column.null_count:
            nulls = column.is_null().to_numpy(zero_copy_only=False)
            i = int(np.argmax(nulls))
            raise HallcalInputError(f"{source}: column '{name}' has a missing value in row {i + 1}")
        cols[name] = np.asarray(column.to_numpy(), dtype=np.float64)
    if not cols:
        raise HallcalInputError(f"{source}: no columns")
    return cols


# ---- Containers: HDF5, MATLAB, NumPy -----------------------------------------------------------


def _container_columns(
    members: Iterable[tuple[str, np.ndarray | None, str]], source: str
) -> dict[str, np.ndarray]:
    """Pick the columns among named container members.

    `members` yields ``(name, array or None, description)``; ``None`` means "not a numeric
    array" and `description` says what it is. Known columns must be numeric vectors; other
    members are kept only when they are numeric vectors of the known columns' length.
    """
    known: dict[str, np.ndarray] = {}
    others: dict[str, np.ndarray] = {}
    order: list[str] = []
    for name, arr, description in members:
        vector = None
        if arr is not None and arr.dtype.kind in "biuf":
            if arr.size == 0:
                vector = arr.reshape(0)
            elif arr.ndim == 1:
                vector = arr
            elif arr.ndim >= 2 and sum(s != 1 for s in arr.shape) <= 1:
                vector = arr.reshape(-1)
            elif arr.ndim == 0:
                vector = arr.reshape(1) if name in KNOWN_COLUMNS else None
        if name in KNOWN_COLUMNS:
            if vector is None:
                what = f"shape {arr.shape}" if arr is not None else description
                raise HallcalInputError(
                    f"{source}: column '{name}' must be a numeric vector, got {what}"
                )
            known[name] = vector
        elif vector is not None and vector.shape[0] > 1:
            others[name] = vector
        else:
            continue
        order.append(name)
    lengths = {a.shape[0] for a in known.values()}
    if len(lengths) == 1:
        n = lengths.pop()
        others = {k: v for k, v in others.items() if v.shape[0] == n}
    elif lengths:
        others = {}  # known columns disagree: report them, not the others
    elif len({a.shape[0] for a in others.values()}) > 1:
        raise HallcalInputError(
            f"{source}: vectors of different lengths and no known column "
            f"({', '.join(KNOWN_COLUMNS)}) to tell which are columns"
        )
    cols = {**known, **others}
    return {name: cols[name] for name in order if name in cols}


def _read_hdf5(p: Path) -> dict[str, np.ndarray]:
    import h5py

    source = str(p)
    try:
        handle = h5py.File(p, "r")
    except OSError:
        raise HallcalInputError(f"{source}: not a valid HDF5 file") from None
    with handle:
        group = handle["data"] if isinstance(handle.get("data"), h5py.Group) else handle
        return _container_columns(_hdf5_members(group), source)


def _hdf5_members(group: Any) -> Iterator[tuple[str, np.ndarray | None, str]]:
    import h5py

    for name, item in group.items():
        if not isinstance(item, h5py.Dataset):
            yield name, None, "a group"
            continue
        if "MATLAB_empty" in item.attrs and bool(np.asarray(item.attrs["MATLAB_empty"]).any()):
            yield name, np.zeros(0), "an empty array"
            continue
        matlab_class = item.attrs.get("MATLAB_class")
        if isinstance(matlab_class, bytes):
            matlab_class = matlab_class.decode("ascii", "replace")
        if matlab_class in ("char", "cell", "struct") or item.dtype.kind not in "biuf":
            yield name, None, f"a non-numeric dataset ({item.dtype})"
            continue
        yield name, np.asarray(item[()]), "a dataset"


def _read_mat(p: Path) -> dict[str, np.ndarray]:
    import scipy.io

    source = str(p)
    try:
        contents = scipy.io.loadmat(p, squeeze_me=False, chars_as_strings=True)
    except NotImplementedError:
        # MATLAB v7.3 files are HDF5 files: variables are datasets at the root.
        return _read_hdf5(p)
    except (ValueError, TypeError, OSError, EOFError) as exc:
        import h5py

        if h5py.is_hdf5(p):  # an HDF5 file saved under .mat, read it like MATLAB v7.3
            return _read_hdf5(p)
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise HallcalInputError(f"{source}: not a valid MATLAB .mat file ({first})") from None

    def members() -> Iterator[tuple[str, np.ndarray | None, str]]:
        for name, value in contents.items():
            if name.startswith("__"):
                continue
            arr = np.asarray(value) if isinstance(value, np.ndarray) else None
            if arr is not None and arr.dtype.kind in "biuf":
                yield name, arr, "a variable"
            else:
                kind = "a string" if arr is not None and arr.dtype.kind == "U" else "not numeric"
                yield name, None, f"a variable that is {kind}"

    return _container_columns(members(), source)


def _read_npz(p: Path) -> dict[str, np.ndarray]:
    source = str(p)
    with open(p, "rb") as f:
        magic = f.read(6)
    if magic == b"\x93NUMPY":
        raise HallcalInputError(f"{source}: a single .npy array, not a .npz archive of columns")
    if not magic.startswith(b"PK"):
        raise HallcalInputError(f"{source}: not a valid .npz archive (not a zip file)")
    try:
        archive = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile):
        raise HallcalInputError(f"{source}: not a valid .npz archive") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise HallcalInputError(f"{source}: not a valid .npz archive")
    with archive:
        arrays: list[tuple[str, np.ndarray | None, str]] = []
        for name in archive.files:
            try:
                arr = archive[name]
            except ValueError as exc:
                if "pickle" in str(exc) or "Object arrays" in str(exc):
                    raise HallcalInputError(
                        f"{source}: array '{name}' holds Python objects (object dtype); hallcal "
                        "never unpickles data, save numeric arrays"
                    ) from None
                raise HallcalInputError(f"{source}: array '{name}' cannot be read") from None
            except (OSError, EOFError, zipfile.BadZipFile):
                raise HallcalInputError(f"{source}: array '{name}' cannot be read") from None
            if arr.dtype.kind in "biuf":
                arrays.append((name, arr, "an array"))
            else:
                arrays.append((name, None, f"an array of dtype {arr.dtype}"))
    return _container_columns(arrays, source)


# ---- Writing -----------------------------------------------------------------------------------

_MATLAB_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,62}")


def _columns_for_writing(p: Path, columns: Mapping[str, Any]) -> dict[str, np.ndarray]:
    if not columns:
        raise ValueError(f"{p}: no columns to write")
    out: dict[str, np.ndarray] = {}
    n = None
    for name, values in columns.items():
        if not isinstance(name, str) or not name or any(c in name for c in "\r\n"):
            raise ValueError(f"{p}: invalid column name {name!r}")
        arr = np.asarray(values)
        if arr.ndim != 1 or arr.dtype.kind not in "biuf":
            raise ValueError(f"{p}: column '{name}' must be a numeric 1-D array")
        if arr.dtype.kind == "f":
            arr = arr.astype(np.float64, copy=False)
            if not np.isfinite(arr).all():
                raise ValueError(f"{p}: column '{name}' contains NaN or inf")
        else:
            arr = arr.astype(np.int64, copy=False)
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise ValueError(f"{p}: columns have different lengths ('{name}': {arr.shape[0]})")
        out[name] = arr
    return out


def write_dataset(path: str | os.PathLike[str], columns: Mapping[str, Any]) -> None:
    """Write columns to a dataset file, the format chosen by the extension (atomically).

    Floating-point columns are written as float64 (CSV: shortest text that reads back to the
    same value), integer and boolean columns as int64 (CSV: integers). HDF5 files get one
    dataset per column at the root; MATLAB files one column-vector variable per column;
    ``.npz`` archives one array per column (never pickled).

    Parameters
    ----------
    path : path-like
        Destination with one of the :data:`DATASET_EXTENSIONS`.
    columns : mapping of str to array_like
        Numeric 1-D arrays of equal length, finite.

    Raises
    ------
    HallcalInputError
        Unknown extension, missing directory, or a column name the format cannot store.
    ValueError
        Columns that are not numeric 1-D arrays of equal length, or contain NaN or inf.
    """
    p = Path(path)
    ext = _check_extension(p)
    cols = _columns_for_writing(p, columns)
    if ext == ".csv":
        texts = [
            list(map(repr, a.tolist())) if a.dtype.kind == "f" else list(map(str, a.tolist()))
            for a in cols.values()
        ]
        header = io.StringIO()
        csv.writer(header, lineterminator="\n").writerow(list(cols))
        with atomic_write(p, "w") as f:
            f.write(header.getvalue())
            f.writelines(",".join(row) + "\n" for row in zip(*texts, strict=True))
    elif ext == ".parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.table({name: pa.array(arr) for name, arr in cols.items()})
        with atomic_write(p, "wb") as f:
            pq.write_table(table, f)
    elif ext in (".h5", ".hdf5"):
        import h5py

        for name in cols:
            if "/" in name or name in (".", ".."):
                raise HallcalInputError(f"{p}: column name '{name}' cannot be an HDF5 dataset")
        with atomic_path(p) as tmp, h5py.File(tmp, "w", track_order=True) as h5:
            for name, arr in cols.items():
                h5.create_dataset(name, data=arr)
    elif ext == ".mat":
        import scipy.io

        for name in cols:
            if not _MATLAB_NAME.fullmatch(name):
                raise HallcalInputError(
                    f"{p}: column name '{name}' is not a valid MATLAB variable name"
                )
        with atomic_write(p, "wb") as f:
            scipy.io.savemat(f, cols, oned_as="column", do_compression=False)
    else:
        with atomic_write(p, "wb") as f, zipfile.ZipFile(f, "w", zipfile.ZIP_STORED) as zf:
            for name, arr in cols.items():
                with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, arr, allow_pickle=False)


# ================================================================================================
# Setup
# ================================================================================================


def _tuple_of_floats(values: Iterable[Any]) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


@dataclass(frozen=True)
class ModelSpec:
    """Flux model and solver options (``[model]``; paper, section on the flux model g_theta).

    Attributes
    ----------
    basis : {"fourier", "kernel"}
        Fourier series in the mechanical angle, or the periodic kernel basis.
    harmonics : tuple of int or "auto"
        Fourier basis: mechanical harmonics (the constant term is always included); ``"auto"``
        leaves the choice to the calibration.
    points : int
        Kernel basis: number of kernel centres on [0, 2 pi).
    lengthscale : float or "auto"
        Kernel basis: length scale l of the kernel.
    lut_points : int
        Number M of grid points of the lookup table.
    max_iterations : int
        Iteration limit of the simulation-error minimization.
    force : bool
        Write the artifact even when the adequacy check fails.
    """

    basis: Literal["fourier", "kernel"] = "fourier"
    harmonics: tuple[int, ...] | Literal["auto"] = "auto"
    points: int = 400
    lengthscale: float | Literal["auto"] = "auto"
    lut_points: int = 4096
    max_iterations: int = 50
    force: bool = False

    def __post_init__(self) -> None:
        if self.harmonics != "auto":
            object.__setattr__(self, "harmonics", tuple(int(h) for h in self.harmonics))


@dataclass(frozen=True)
class TrajectorySpec:
    """How the true angle moved during the calibration run (``[trajectory]``).

    Attributes
    ----------
    kind : {"closed-loop", "constant-speed"}
        Closed-loop ramp tracking (the paper), or an open-loop spin at constant speed.
    start, stop : int, int or None
        Constant speed: sample indices of the constant-speed part, ``stop`` exclusive
        (``None``: end of the data).
    """

    kind: Literal["closed-loop", "constant-speed"] = "closed-loop"
    start: int = 0
    stop: int | None = None


@dataclass(frozen=True)
class BLASpec:
    """Multisine experiment for the Best Linear Approximation (``[bla]``; Pintelon & Schoukens).

    Attributes
    ----------
    period_samples : int
        Samples per multisine period (>= 8).
    periods : int
        Periods per realization, including the transient ones (>= 2).
    transient_periods : int
        Leading periods discarded in each realization (< periods).
    realizations : int
        Number of random-phase realizations.
    band : tuple of float
        ``(f_lo, f_hi)`` excited frequency band in Hz.
    rms : float
        RMS of the multisine in rad.
    lines : {"full", "odd", "random-odd"}
        Which frequency lines in the band are excited.
    drift : float
        Speed in rad/s of the slow ramp the multisine rides on.
    numerator_order, denominator_order : int
        Orders of the parametric model fitted to the BLA; the denominator order excludes the
        integrator pole (the paper's G(s) is numerator 0, denominator 2, integrator).
    integrator : bool
        Whether the parametric model has a pole at s = 0.
    fit_delay : bool
        Whether the parametric model has an input delay estimated from the data.
    """

    period_samples: int
    periods: int
    transient_periods: int = 1
    realizations: int = 8
    band: tuple[float, float] = (1.0, 400.0)
    rms: float = 0.05
    lines: Literal["full", "odd", "random-odd"] = "random-odd"
    drift: float = 1.0
    numerator_order: int = 0
    denominator_order: int = 2
    integrator: bool = True
    fit_delay: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "band", _tuple_of_floats(self.band))


@dataclass(frozen=True)
class BenchSpec:
    """Virtual bench used by ``hallcal simulate`` (``[bench]``); defaults are the paper's.

    Attributes
    ----------
    experiment : {"ramp", "multisine"}
        Calibration ramp, or the BLA multisine experiment of ``[bla]``.
    seed : int
        Seed of the random generator (noise, flux variations, multisine phases).
    noise_variance : float
        Variance of the white noise on each Hall channel.
    ramp_end : float
        Final value of the ramp reference in rad.
    duration : float
        Duration of the ramp experiment in s.
    amplitude : float
        Amplitude A of the Hall signals.
    magnet_variation : float
        Relative size of the per-magnet flux variations (mechanical harmonics
        1 .. pole_pairs - 1).
    pole_modulation : float
        Relative size of per-pole amplitude differences (amplitude modulation by mechanical
        harmonics 1..3: sidebands k pole_pairs +- j).
    misalignment_deg : tuple of 3 float
        Electrical degrees added to each sensor's nominal 0/120/240 degrees.
    gain_mismatch : tuple of 3 float
        Relative gain error of each sensor (gain ``1 + g``).
    offset : tuple of 3 float
        Offset of each sensor.
    electrical_harmonics : tuple of (int, float)
        ``(harmonic >= 2, relative amplitude)`` pairs of electrical harmonics of the flux.
    torque_disturbance : float
        Standard deviation of a random low-frequency torque at the plant input.
    cogging : float
        Amplitude of a cogging torque at the plant input.
    cogging_periods : int
        Cogging periods per revolution; 0 means ``6 * pole_pairs`` (see
        :meth:`cogging_periods_per_revolution`).
    """

    experiment: Literal["ramp", "multisine"] = "ramp"
    seed: int = 0
    noise_variance: float = 7.5e-6
    ramp_end: float = 13.0
    duration: float = 26.0
    amplitude: float = 1.0
    magnet_variation: float = 0.04
    pole_modulation: float = 0.0
    misalignment_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gain_mismatch: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    electrical_harmonics: tuple[tuple[int, float], ...] = ()
    torque_disturbance: float = 0.0
    cogging: float = 0.0
    cogging_periods: int = 0

    def __post_init__(self) -> None:
        for name in ("misalignment_deg", "gain_mismatch", "offset"):
            object.__setattr__(self, name, _tuple_of_floats(getattr(self, name)))
        pairs = tuple((int(h), float(a)) for h, a in self.electrical_harmonics)
        object.__setattr__(self, "electrical_harmonics", pairs)

    def cogging_periods_per_revolution(self, pole_pairs: int) -> int:
        """Cogging periods per revolution: :attr:`cogging_periods`, or ``6 * pole_pairs`` if 0."""
        return self.cogging_periods if self.cogging_periods > 0 else 6 * pole_pairs


@dataclass(frozen=True)
class Setup:
    """Everything the setup file says (``DESIGN.md``, "Setup file").

    Build it with :func:`read_setup` or :func:`setup_from_dict`, which check it; constructing it
    directly checks nothing (``setup_from_dict(s.to_dict())`` does).

    Attributes
    ----------
    pole_pairs : int
        Number of pole pairs n_m.
    sample_time : float
        Sample time Ts in s (1.0 means "time in samples").
    controller : DiscreteTF or None
        The known feedback controller C(q); ``None`` only for constant-speed trajectories.
    plant : ContinuousTF or None
        The plant G(s) when known; ``None`` when a BLA experiment replaces it.
    model : ModelSpec
    trajectory : TrajectorySpec
    bla : BLASpec or None
    bench : BenchSpec
    """

    pole_pairs: int
    sample_time: float
    controller: DiscreteTF | None
    plant: ContinuousTF | None = None
    model: ModelSpec = field(default_factory=ModelSpec)
    trajectory: TrajectorySpec = field(default_factory=TrajectorySpec)
    bla: BLASpec | None = None
    bench: BenchSpec = field(default_factory=BenchSpec)

    def to_dict(self) -> dict[str, Any]:
        """Return the setup as plain JSON-serializable data (the layout of the TOML file).

        Every option is written explicitly (defaults included); options that do not apply
        (kernel options of a Fourier model, ``start``/``stop`` of a closed-loop trajectory) and
        absent tables are left out, so ``setup_from_dict(s.to_dict()) == s``.
        """
        out: dict[str, Any] = {"pole_pairs": self.pole_pairs, "sample_time": self.sample_time}
        if self.controller is not None:
            out["controller"] = {"num": list(self.controller.num), "den": list(self.controller.den)}
        if self.plant is not None:
            out["plant"] = {
                "num": list(self.plant.num),
                "den": list(self.plant.den),
                "delay": self.plant.delay,
            }
        m = self.model
        model: dict[str, Any] = {"basis": m.basis}
        if m.basis == "fourier":
            model["harmonics"] = m.harmonics if m.harmonics == "auto" else list(m.harmonics)
        else:
            model["points"] = m.points
            model["lengthscale"] = m.lengthscale
        model.update(lut_points=m.lut_points, max_iterations=m.max_iterations, force=m.force)
        out["model"] = model
        t = self.trajectory
        trajectory: dict[str, Any] = {"kind": t.kind}
        if t.kind == "constant-speed":
            trajectory["start"] = t.start
            if t.stop is not None:
                trajectory["stop"] = t.stop
        out["trajectory"] = trajectory
        if self.bla is not None:
            bla = dataclasses.asdict(self.bla)
            bla["band"] = list(self.bla.band)
            out["bla"] = bla
        b = self.bench
        bench = dataclasses.asdict(b)
        for name in ("misalignment_deg", "gain_mismatch", "offset"):
            bench[name] = list(getattr(b, name))
        bench["electrical_harmonics"] = [[h, a] for h, a in b.electrical_harmonics]
        out["bench"] = bench
        return out


def default_setup() -> Setup:
    """Return the setup of the paper's simulation study (section "Simulation results").

    11 pole pairs, Ts = 1/4000 s, the paper's C(q) and G(s) (input delay 1.2e-4 s), a Fourier
    flux model with mechanical harmonics 1..11, a BLA experiment of 4 periods of 4000 samples
    (1 transient) and the default virtual bench (ramp 0 -> 13 rad in 26 s, noise variance
    7.5e-6). Equal to parsing the example setup file of ``DESIGN.md``.
    """
    return Setup(
        pole_pairs=11,
        sample_time=2.5e-4,
        controller=DiscreteTF((2.94, -3.29, -2.10, 2.45), (1.0, -3.45, 4.52, -2.68, 0.61)),
        plant=ContinuousTF((1.663e5,), (1.0, 632.6, 2702.0, 0.0), delay=1.2e-4),
        model=ModelSpec(basis="fourier", harmonics=tuple(range(1, 12))),
        trajectory=TrajectorySpec(),
        bla=BLASpec(period_samples=4000, periods=4, transient_periods=1),
        bench=BenchSpec(),
    )


# ---- Setup parsing -----------------------------------------------------------------------------

_SETUP_KEYS: dict[str, tuple[str, ...]] = {
    "": ("pole_pairs", "sample_time", "controller", "plant", "model", "trajectory", "bla", "bench"),
    "controller": ("num", "den"),
    "plant": ("num", "den", "delay"),
    "model": (
        "basis",
        "harmonics",
        "points",
        "lengthscale",
        "lut_points",
        "max_iterations",
        "force",
    ),
    "trajectory": ("kind", "start", "stop"),
    "bla": tuple(f.name for f in dataclasses.fields(BLASpec)),
    "bench": tuple(f.name for f in dataclasses.fields(BenchSpec)),
}
_ALL_SETUP_KEYS: tuple[str, ...] = tuple(
    f"{table}.{key}" if table else key for table, keys in _SETUP_KEYS.items() for key in keys
)

_REQUIRED: Any = object()


def _show(value: Any) -> str:
    """Render a setup value the way it looks in TOML, shortened."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, Mapping):
        text = "a table"
    elif isinstance(value, str | list | tuple):
        try:
            text = json.dumps(value, default=str)
        except (TypeError, ValueError):
            text = repr(value)
    else:
        text = repr(value) if isinstance(value, float) else str(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_int(value: Any) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def _is_number(value: Any) -> bool:
    return _is_int(value) or (isinstance(value, float | np.floating))


class _Table:
    """One table of the setup, with typed getters whose errors name the key."""

    def __init__(self, data: Mapping[str, Any], source: str, table: str, prefix: str) -> None:
        self.data = data
        self.source = source
        self.table = table  # schema name: "", "model", ...
        self.prefix = prefix  # shown before key names: "", "setup.", ...

    def key(self, name: str) -> str:
        return f"{self.prefix}{self.table}.{name}" if self.table else f"{self.prefix}{name}"

    def error(self, message: str) -> NoReturn:
        raise HallcalInputError(f"{self.source}: {message}")

    def fail(self, name: str, what: str, hint: str = "") -> NoReturn:
        self.error(f"key '{self.key(name)}' must be {what}, got {_show(self.data[name])}{hint}")

    def check_keys(self) -> None:
        allowed = _SETUP_KEYS[self.table]
        for name in self.data:
            if name in allowed:
                continue
            guess = _closest(str(name), allowed)
            hint = ""
            if guess is not None:
                hint = f" (did you mean '{self.key(guess)}'?)"
            else:
                elsewhere = [k for k in _ALL_SETUP_KEYS if k.rsplit(".", 1)[-1] == name]
                if elsewhere:
                    hint = f" (did you mean '{self.prefix}{elsewhere[0]}'?)"
            self.error(f"unknown key '{self.key(str(name))}'{hint}")

    def has(self, name: str) -> bool:
        return name in self.data

    def _get(self, name: str, default: Any, what: str) -> Any:
        if name in self.data:
            return self.data[name]
        if default is _REQUIRED:
            self.error(f"key '{self.key(name)}' is missing (it must be {what})")
        return default

    def integer(self, name: str, *, default: Any = _REQUIRED, minimum: int | None = None) -> Any:
        what = "an integer" + (f" >= {minimum}" if minimum is not None else "")
        value = self._get(name, default, what)
        if value is default and name not in self.data:
            return value
        if not _is_int(value) or (minimum is not None and value < minimum):
            self.fail(name, what)
        return int(value)

    def number(
        self,
        name: str,
        *,
        default: Any = _REQUIRED,
        minimum: float | None = None,
        positive: bool = False,
    ) -> Any:
        what = "a number"
        if positive:
            what += " > 0"
        elif minimum is not None:
            what += f" >= {minimum:g}"
        value = self._get(name, default, what)
        if value is default and name not in self.data:
            return value
        if not _is_number(value) or not math.isfinite(value):
            self.fail(name, "a finite number" if _is_number(value) else what)
        if (positive and value <= 0) or (minimum is not None and value < minimum):
            self.fail(name, what)
        return float(value)

    def boolean(self, name: str, *, default: Any = _REQUIRED) -> Any:
        value = self._get(name, default, "true or false")
        if not isinstance(value, bool):
            self.fail(name, "true or false")
        return value

    def choice(self, name: str, options: Sequence[str], *, default: Any = _REQUIRED) -> Any:
        what = "one of " + ", ".join(f'"{o}"' for o in options)
        value = self._get(name, default, what)
        if not isinstance(value, str) or value not in options:
            self.fail(name, what, _suggest(value, options) if isinstance(value, str) else "")
        return value

    def numbers(self, name: str, *, default: Any = _REQUIRED, length: int | None = None) -> Any:
        what = (
            f"a list of {length} numbers" if length is not None else "a non-empty list of numbers"
        )
        value = self._get(name, default, what)
        if value is default and name not in self.data:
            return value
        if (
            not isinstance(value, list | tuple)
            or not value
            or (length is not None and len(value) != length)
            or not all(_is_number(v) for v in value)
        ):
            self.fail(name, what)
        if not all(math.isfinite(v) for v in value):
            self.fail(name, "a list of finite numbers")
        return tuple(float(v) for v in value)

    def table_at(self, name: str) -> _Table | None:
        if name not in self.data:
            return None
        value = self.data[name]
        if not isinstance(value, Mapping):
            self.fail(name, "a table")
        return _Table(value, self.source, name, self.prefix)


def _parse_tf(t: _Table, *, continuous: bool) -> tuple[tuple[float, ...], tuple[float, ...]]:
    num = t.numbers("num")
    den = t.numbers("den")
    if den[0] == 0.0:
        t.error(f"key '{t.key('den')}' must have a nonzero leading coefficient, got {_show(den)}")
    stripped = num
    while len(stripped) > 1 and stripped[0] == 0.0:
        stripped = stripped[1:]
    if len(stripped) > len(den):
        what = "proper" if continuous else "causal"
        t.error(
            f"key '{t.key('num')}' has more coefficients than '{t.key('den')}' (the transfer "
            f"function must be {what})"
        )
    if all(v == 0.0 for v in num):
        t.error(f"key '{t.key('num')}' must not be all zero")
    return num, den


def _only_for(t: _Table, names: Sequence[str], condition: str) -> None:
    for name in names:
        if t.has(name):
            t.error(f"key '{t.key(name)}' applies only to {condition}")


def _parse_model(t: _Table | None) -> ModelSpec:
    if t is None:
        return ModelSpec()
    t.check_keys()
    basis = t.choice("basis", ("fourier", "kernel"), default="fourier")
    harmonics: tuple[int, ...] | str = "auto"
    points = 400
    lengthscale: float | str = "auto"
    if basis == "fourier":
        _only_for(t, ("points", "lengthscale"), 'basis = "kernel"')
        value = t.data.get("harmonics", "auto")
        what = 'a list of distinct integers >= 1 or "auto"'
        if not (isinstance(value, str) and value == "auto"):
            if (
                not isinstance(value, list | tuple)
                or not value
                or not all(_is_int(h) and h >= 1 for h in value)
            ):
                t.fail("harmonics", what)
            if len(set(value)) != len(value):
                t.error(f"key '{t.key('harmonics')}' lists a harmonic twice: {_show(value)}")
            harmonics = tuple(int(h) for h in value)
    else:
        _only_for(t, ("harmonics",), 'basis = "fourier"')
        points = t.integer("points", default=400, minimum=8)
        value = t.data.get("lengthscale", "auto")
        if not (isinstance(value, str) and value == "auto"):
            if not _is_number(value) or not math.isfinite(value) or value <= 0:
                t.fail("lengthscale", 'a number > 0 or "auto"')
            lengthscale = float(value)
    return ModelSpec(
        basis=basis,
        harmonics=harmonics,  # type: ignore[arg-type]
        points=points,
        lengthscale=lengthscale,  # type: ignore[arg-type]
        lut_points=t.integer("lut_points", default=4096, minimum=16),
        max_iterations=t.integer("max_iterations", default=50, minimum=1),
        force=t.boolean("force", default=False),
    )


def _parse_trajectory(t: _Table | None) -> TrajectorySpec:
    if t is None:
        return TrajectorySpec()
    t.check_keys()
    kind = t.choice("kind", ("closed-loop", "constant-speed"), default="closed-loop")
    if kind == "closed-loop":
        _only_for(t, ("start", "stop"), 'kind = "constant-speed"')
        return TrajectorySpec(kind=kind)
    start = t.integer("start", default=0, minimum=0)
    stop = t.integer("stop", default=None, minimum=1)
    if stop is not None and stop <= start:
        t.error(
            f"key '{t.key('stop')}' must be greater than '{t.key('start')}' ({start}), got {stop}"
        )
    return TrajectorySpec(kind=kind, start=start, stop=stop)


def _parse_bla(t: _Table | None, sample_time: float) -> BLASpec | None:
    if t is None:
        return None
    t.check_keys()
    period_samples = t.integer("period_samples", minimum=8)
    periods = t.integer("periods", minimum=2)
    transient = t.integer("transient_periods", default=1, minimum=0)
    if transient >= periods:
        t.error(
            f"key '{t.key('transient_periods')}' must be less than '{t.key('periods')}' "
            f"({periods}), got {transient}"
        )
    band = t.numbers("band", default=(1.0, 400.0), length=2)
    nyquist = 0.5 / sample_time
    if not 0.0 <= band[0] < band[1]:
        t.fail("band", "[f_lo, f_hi] with 0 <= f_lo < f_hi")
    if band[1] > nyquist:
        t.error(
            f"key '{t.key('band')}' must stay below the Nyquist frequency {nyquist:g} Hz, "
            f"got {_show(list(band))}"
        )
    f0 = 1.0 / (period_samples * sample_time)
    first = max(1, math.ceil(band[0] / f0 - 1e-9))
    if first * f0 > band[1] * (1 + 1e-12):
        t.error(
            f"key '{t.key('band')}' holds no frequency line (lines are multiples of "
            f"1/(period_samples*sample_time) = {f0:g} Hz), got {_show(list(band))}"
        )
    numerator_order = t.integer("numerator_order", default=0, minimum=0)
    denominator_order = t.integer("denominator_order", default=2, minimum=0)
    if numerator_order > denominator_order:
        t.error(
            f"key '{t.key('numerator_order')}' must not exceed "
            f"'{t.key('denominator_order')}' ({denominator_order}), got {numerator_order}"
        )
    return BLASpec(
        period_samples=period_samples,
        periods=periods,
        transient_periods=transient,
        realizations=t.integer("realizations", default=8, minimum=1),
        band=band,  # type: ignore[arg-type]
        rms=t.number("rms", default=0.05, positive=True),
        lines=t.choice("lines", ("full", "odd", "random-odd"), default="random-odd"),
        drift=t.number("drift", default=1.0),
        numerator_order=numerator_order,
        denominator_order=denominator_order,
        integrator=t.boolean("integrator", default=True),
        fit_delay=t.boolean("fit_delay", default=True),
    )


def _parse_bench(t: _Table | None) -> BenchSpec:
    if t is None:
        return BenchSpec()
    t.check_keys()
    gain = t.numbers("gain_mismatch", default=(0.0, 0.0, 0.0), length=3)
    if any(g <= -1.0 for g in gain):
        t.fail("gain_mismatch", "a list of 3 numbers > -1")
    pairs: list[tuple[int, float]] = []
    value = t.data.get("electrical_harmonics", [])
    what = "a list of [harmonic >= 2, relative amplitude] pairs"
    if not isinstance(value, list | tuple):
        t.fail("electrical_harmonics", what)
    for pair in value:
        if (
            not isinstance(pair, list | tuple)
            or len(pair) != 2
            or not _is_int(pair[0])
            or pair[0] < 2
            or not _is_number(pair[1])
            or not math.isfinite(pair[1])
        ):
            t.fail("electrical_harmonics", what)
        pairs.append((int(pair[0]), float(pair[1])))
    if len({h for h, _ in pairs}) != len(pairs):
        t.error(f"key '{t.key('electrical_harmonics')}' lists a harmonic twice: {_show(value)}")
    return BenchSpec(
        experiment=t.choice("experiment", ("ramp", "multisine"), default="ramp"),
        seed=t.integer("seed", default=0, minimum=0),
        noise_variance=t.number("noise_variance", default=7.5e-6, minimum=0.0),
        ramp_end=t.number("ramp_end", default=13.0),
        duration=t.number("duration", default=26.0, positive=True),
        amplitude=t.number("amplitude", default=1.0, positive=True),
        magnet_variation=t.number("magnet_variation", default=0.04, minimum=0.0),
        pole_modulation=t.number("pole_modulation", default=0.0, minimum=0.0),
        misalignment_deg=t.numbers("misalignment_deg", default=(0.0, 0.0, 0.0), length=3),
        gain_mismatch=gain,
        offset=t.numbers("offset", default=(0.0, 0.0, 0.0), length=3),
        electrical_harmonics=tuple(pairs),
        torque_disturbance=t.number("torque_disturbance", default=0.0, minimum=0.0),
        cogging=t.number("cogging", default=0.0, minimum=0.0),
        cogging_periods=t.integer("cogging_periods", default=0, minimum=0),
    )


def _parse_setup(data: Mapping[str, Any], source: str, prefix: str = "") -> Setup:
    if not isinstance(data, Mapping):
        what = f"key '{prefix.rstrip('.')}'" if prefix else "the setup"
        raise HallcalInputError(f"{source}: {what} must be a table")
    top = _Table(data, source, "", prefix)
    top.check_keys()
    pole_pairs = top.integer("pole_pairs", minimum=1)
    sample_time = top.number("sample_time", positive=True)
    controller_t = top.table_at("controller")
    plant_t = top.table_at("plant")
    model_t = top.table_at("model")
    trajectory_t = top.table_at("trajectory")
    bla_t = top.table_at("bla")
    bench_t = top.table_at("bench")
    for sub in (controller_t, plant_t, model_t, trajectory_t, bla_t, bench_t):
        if sub is not None:
            sub.check_keys()  # a misspelled key is reported before anything it might cause

    trajectory = _parse_trajectory(trajectory_t)
    controller = None
    if controller_t is not None:
        controller_t.check_keys()
        controller = DiscreteTF(*_parse_tf(controller_t, continuous=False))
    elif trajectory.kind == "closed-loop":
        top.error(
            f"key '{prefix}controller' is missing (a [controller] table with num and den is "
            'needed unless trajectory.kind = "constant-speed")'
        )
    plant = None
    if plant_t is not None:
        plant_t.check_keys()
        num, den = _parse_tf(plant_t, continuous=True)
        plant = ContinuousTF(num, den, plant_t.number("delay", default=0.0, minimum=0.0))
    bla = _parse_bla(bla_t, sample_time)
    bench = _parse_bench(bench_t)
    if bench.experiment == "multisine" and bla is None:
        top.error(f"key '{prefix}bench.experiment' is \"multisine\" but there is no [bla] table")
    return Setup(
        pole_pairs=pole_pairs,
        sample_time=sample_time,
        controller=controller,
        plant=plant,
        model=_parse_model(model_t),
        trajectory=trajectory,
        bla=bla,
        bench=bench,
    )


def setup_from_dict(d: Mapping[str, Any], *, source: str = "<setup>") -> Setup:
    """Check a setup given as nested dictionaries (the layout of the TOML file).

    Parameters
    ----------
    d : mapping
        As parsed from the TOML file, or as returned by :meth:`Setup.to_dict`.
    source : str
        Name used in error messages (normally the file name).

    Returns
    -------
    Setup

    Raises
    ------
    HallcalInputError
        Unknown key (with a did-you-mean suggestion), missing required key, wrong type or
        value out of range; the message names `source` and the dotted key.
    """
    return _parse_setup(d, source)


def read_setup(path: str | os.PathLike[str]) -> Setup:
    """Read and check a setup file (TOML, ``DESIGN.md`` "Setup file").

    Parameters
    ----------
    path : path-like
        The ``.toml`` file.

    Returns
    -------
    Setup

    Raises
    ------
    HallcalInputError
        Missing file, invalid UTF-8, malformed TOML (with its line), or any problem
        :func:`setup_from_dict` reports.
    """
    p = _existing_file(path)
    text = _decode_text(p, _read_bytes(p))
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        message = " ".join(str(exc).split())
        raise HallcalInputError(f"{p}: invalid TOML: {message}") from None
    return _parse_setup(data, str(p))


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def setup_to_toml(setup: Setup) -> str:
    """Return the text of a setup file that :func:`read_setup` reads back as `setup`."""
    data = setup.to_dict()
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for name, table in data.items():
        if isinstance(table, dict):
            lines.append("")
            lines.append(f"[{name}]")
            lines.extend(f"{k} = {_toml_value(v)}" for k, v in table.items())
    return "\n".join(lines) + "\n"


def write_setup(path: str | os.PathLike[str], setup: Setup) -> None:
    """Write `setup` as a TOML setup file (atomically); see :func:`setup_to_toml`."""
    text = setup_to_toml(setup)
    with atomic_write(path, "w") as f:
        f.write(text)


# ================================================================================================
# JSON: generic files and the calibration artifact
# ================================================================================================


def to_jsonable(obj: Any, *, where: str = "") -> Any:
    """Convert `obj` to plain JSON data, refusing NaN and inf.

    NumPy arrays become (nested) lists, NumPy scalars Python numbers, tuples lists, paths
    strings, objects with a ``to_dict()`` method (such as :class:`Setup`) and dataclasses
    dictionaries.

    Parameters
    ----------
    obj : object
        The data.
    where : str
        Key path of `obj` used in error messages.

    Raises
    ------
    ValueError
        NaN or inf anywhere (the message names the key path, e.g. ``lut.eta[3]``).
    TypeError
        Values JSON cannot hold (complex numbers, arbitrary objects), or non-string keys.
    """
    label = where or "(top level)"
    if obj is None or isinstance(obj, bool | str):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        value = float(obj)
        if not math.isfinite(value):
            raise ValueError(f"{value} at key '{label}' cannot be written to JSON")
        return value
    if isinstance(obj, complex | np.complexfloating):
        raise TypeError(f"complex value at key '{label}': store real and imaginary parts")
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "c":
            raise TypeError(f"complex array at key '{label}': store real and imaginary parts")
        if obj.dtype.kind not in "biuf":
            raise TypeError(f"array of dtype {obj.dtype} at key '{label}' is not JSON data")
        if obj.dtype.kind == "f" and not np.isfinite(obj).all():
            index = np.unravel_index(int(np.argmax(~np.isfinite(obj))), obj.shape)
            pos = "".join(f"[{i}]" for i in index)
            raise ValueError(f"NaN or inf at key '{where}{pos}' cannot be written to JSON")
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, Mapping):
        out: dict[str, Any] = {}
        for key, value in obj.items():
            if not isinstance(key, str):
                raise TypeError(f"key {key!r} under '{label}' is not a string")
            out[key] = to_jsonable(value, where=f"{where}.{key}" if where else key)
        return out
    if isinstance(obj, list | tuple):
        return [to_jsonable(v, where=f"{where}[{i}]") for i, v in enumerate(obj)]
    to_dict = getattr(obj, "to_dict", None)
    if callable(to_dict):
        return to_jsonable(to_dict(), where=where)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(
            {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}, where=where
        )
    raise TypeError(f"value of type {type(obj).__name__} at key '{label}' is not JSON data")


def _dump_json(p: Path, obj: Any) -> str:
    try:
        data = to_jsonable(obj)
    except (ValueError, TypeError) as exc:
        raise type(exc)(f"{p}: {exc}") from None
    return json.dumps(data, indent=1, allow_nan=False, ensure_ascii=False) + "\n"


def write_json(path: str | os.PathLike[str], obj: Any) -> None:
    """Write `obj` as JSON (atomically, indent 1), converting NumPy data (see :func:`to_jsonable`).

    Raises
    ------
    ValueError
        NaN or inf anywhere in `obj` (nothing is written).
    TypeError
        Data JSON cannot hold.
    HallcalInputError
        The directory does not exist or the file cannot be written.
    """
    p = Path(path)
    text = _dump_json(p, obj)
    with atomic_write(p, "w") as f:
        f.write(text)


def _reject_constant(name: str) -> NoReturn:
    raise ValueError(f"{name} is not valid JSON")


def read_json(path: str | os.PathLike[str]) -> Any:
    """Read a JSON file (NaN and Infinity are refused, as JSON says).

    Raises
    ------
    HallcalInputError
        Missing file, invalid UTF-8 or invalid JSON (with its line and column).
    """
    p = _existing_file(path)
    text = _decode_text(p, _read_bytes(p))
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise HallcalInputError(
            f"{p}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    except ValueError as exc:
        raise HallcalInputError(f"{p}: invalid JSON: {exc}") from None


def _hallcal_version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("hallcal")
    except (ImportError, PackageNotFoundError):
        return "unknown"


def _validate_artifact(data: Any, source: str) -> None:
    def bad(message: str) -> NoReturn:
        raise HallcalInputError(f"{source}: {message}")

    if not isinstance(data, Mapping):
        bad("not a hallcal calibration artifact (not a JSON object)")
    if "format" not in data:
        bad("not a hallcal calibration artifact (format key missing)")
    if data["format"] != ARTIFACT_FORMAT:
        bad(f"unsupported format {_show(data['format'])} (this hallcal reads '{ARTIFACT_FORMAT}')")
    for key in ("pole_pairs", "reconstruction", "lut", "model", "setup", "diagnostics"):
        if key not in data:
            bad(f"key '{key}' is missing")
    if "hallcal_version" not in data:
        bad("key 'hallcal_version' is missing")
    if not isinstance(data["hallcal_version"], str):
        bad("key 'hallcal_version' must be a string")
    if not _is_int(data["pole_pairs"]) or data["pole_pairs"] < 1:
        bad(f"key 'pole_pairs' must be an integer >= 1, got {_show(data['pole_pairs'])}")
    for key in ("reconstruction", "lut", "model", "diagnostics"):
        if not isinstance(data[key], Mapping):
            bad(f"key '{key}' must be an object")

    def vector(value: Any, length: int | None = None) -> bool:
        return (
            isinstance(value, list)
            and (length is None or len(value) == length)
            and all(_is_number(v) for v in value)
        )

    rec = data["reconstruction"]
    for key in ("projection", "offset"):
        if key not in rec:
            bad(f"key 'reconstruction.{key}' is missing")
    projection = rec["projection"]
    if not (isinstance(projection, list) and len(projection) == 2):
        bad("key 'reconstruction.projection' must be a 2x3 array of numbers")
    if not all(vector(row, 3) for row in projection):
        bad("key 'reconstruction.projection' must be a 2x3 array of numbers")
    if not vector(rec["offset"], 3):
        bad("key 'reconstruction.offset' must be a list of 3 numbers")
    lut = data["lut"]
    for key in ("y_hat", "eta"):
        if key not in lut:
            bad(f"key 'lut.{key}' is missing")
    for key in ("y_hat", "eta"):
        if not vector(lut[key]) or len(lut[key]) < 16:
            bad(f"key 'lut.{key}' must be a list of at least 16 numbers")
    n_hat, n_eta = len(lut["y_hat"]), len(lut["eta"])
    if n_hat != n_eta:
        bad(f"keys 'lut.y_hat' and 'lut.eta' have different lengths ({n_hat} and {n_eta})")
    setup = _parse_setup(data["setup"], source, prefix="setup.")
    if setup.pole_pairs != data["pole_pairs"]:
        bad(
            f"key 'pole_pairs' ({data['pole_pairs']}) differs from 'setup.pole_pairs' "
            f"({setup.pole_pairs})"
        )


def write_artifact(path: str | os.PathLike[str], artifact: Mapping[str, Any]) -> None:
    """Write a calibration artifact (JSON, ``DESIGN.md`` "Calibration artifact"), atomically.

    ``"format"`` (:data:`ARTIFACT_FORMAT`) and ``"hallcal_version"`` are filled in when absent;
    a :class:`Setup` under ``"setup"`` is converted with :meth:`Setup.to_dict`; NumPy data are
    converted to lists and numbers. The result is checked like :func:`read_artifact` checks it
    before anything is written.

    Raises
    ------
    ValueError
        NaN or inf anywhere (the message names the key); nothing is written.
    HallcalInputError
        The artifact does not have the structure :func:`read_artifact` requires, or the file
        cannot be written.
    """
    p = Path(path)
    data = dict(artifact)
    data.setdefault("format", ARTIFACT_FORMAT)
    data.setdefault("hallcal_version", _hallcal_version())
    ordered = {"format": data.pop("format"), **data}
    text = _dump_json(p, ordered)
    _validate_artifact(json.loads(text), str(p))
    with atomic_write(p, "w") as f:
        f.write(text)


def read_artifact(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read and check a calibration artifact.

    Checks: valid JSON; ``"format" == ARTIFACT_FORMAT``; ``pole_pairs`` (integer >= 1, equal to
    ``setup.pole_pairs``); ``reconstruction.projection`` (2x3) and ``reconstruction.offset``
    (3); ``lut.y_hat`` and ``lut.eta`` (lists of numbers of equal length >= 16); ``model`` and
    ``diagnostics`` (objects); ``setup`` (a valid setup, see :func:`setup_from_dict`);
    ``hallcal_version`` (string).

    Returns
    -------
    dict
        The artifact as parsed JSON (lists, not arrays). ``setup_from_dict(a["setup"])`` gives
        the :class:`Setup`.

    Raises
    ------
    HallcalInputError
        Missing file, invalid JSON, not an artifact, unsupported format, or a missing or
        malformed key (named in the message).
    """
    data = read_json(path)
    _validate_artifact(data, str(Path(path)))
    return data
