"""Datasets: one table, one row per sample (``docs/design.md``, "Dataset files").

Datasets
--------
One table, one row per sample; the format is chosen by the file extension:

``.csv``
    UTF-8 text, a header row of column names, then one row of numbers per sample. The delimiter
    is a comma (a semicolon or a tab is accepted when the header holds no comma). Blank lines and
    lines starting with ``#`` are skipped, except that a ``#`` line directly followed by numbers
    is the header (``numpy.savetxt(..., header="d1,d2,d3")`` writes one). Rows are counted from
    1 at the first data row; error messages also give the line number in the file.
``.txt``, ``.dat``
    UTF-8 text, columns separated by runs of spaces or tabs (or commas or semicolons), with the
    same header, comment and blank-line rules as CSV, except that the header may be left out
    when the file has exactly three columns: they are then ``d1``, ``d2``, ``d3`` (an open-loop
    recording of the Hall signals, like ``shared/data/real/ring-jig/*.txt``). With any other
    number of columns a headerless file is refused, since the names cannot be guessed.
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
import difflib
import io
import math
import mmap
import os
import re
import struct
import zipfile
import zlib
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, NoReturn

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.formatting import one_line
from hallcal.io.files import _suggest, atomic_path, atomic_write, existing_file
from hallcal.io.text import TEXT_EXTENSIONS, read_text_table, write_text_table
from hallcal.limits import (
    MAX_ABS_VALUE,
    MAX_COLUMNS,
    MAX_DATASET_VALUES,
    MAX_SAMPLES,
    MIN_HALL_MAGNITUDE,
    SPIKE_RATIO,
)

__all__ = [
    "DATASET_EXTENSIONS",
    "KNOWN_COLUMNS",
    "Dataset",
    "MissingColumnError",
    "read_dataset",
    "write_dataset",
]

#: Column names with a meaning to hallcal (``docs/design.md``, "Dataset files").
KNOWN_COLUMNS: tuple[str, ...] = ("r", "y", "u", "d1", "d2", "d3", "t", "y_ref", "realization")

#: Dataset file extensions (lower case) understood by :func:`read_dataset`/:func:`write_dataset`.
DATASET_EXTENSIONS: tuple[str, ...] = (
    ".csv",
    ".txt",
    ".dat",
    ".parquet",
    ".h5",
    ".hdf5",
    ".mat",
    ".npz",
)


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
        """Return column `name`, or `default` when the dataset has no such column.

        Parameters
        ----------
        name : str
            Column name (``"r"``, ``"y"``, ``"u"``, ``"d1"``..``"d3"``, ``"t"``, ``"y_ref"``...).
        default : object
            Returned when the column is absent.

        Returns
        -------
        ndarray or object
            The read-only float64 column, or `default`.
        """
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
    copy: bool = True,
) -> dict[str, np.ndarray]:
    """Check presence, length, finiteness and whole-number realizations; return float64 arrays.

    With ``copy=False`` (for arrays a reader has just made, which nobody else holds) a
    contiguous float64 column is kept as it is, only marked read-only; otherwise it is copied.
    """

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
    _check_unknown_names(cols, source)
    lengths = {name: arr.shape[0] for name, arr in cols.items()}
    if len(set(lengths.values())) > 1:
        first = next(iter(lengths))
        other = next(n for n in lengths if lengths[n] != lengths[first])
        raise HallcalInputError(
            f"{source}: columns have different lengths ('{first}': {lengths[first]} rows, "
            f"'{other}': {lengths[other]} rows)"
        )
    n = lengths[next(iter(lengths))]
    _check_table_size(source, n, len(cols))
    if n == 0:
        raise HallcalInputError(f"{source}: no data rows")
    if n < min_samples:
        raise HallcalInputError(f"{source}: {n} data rows, at least {min_samples} needed")
    out: dict[str, np.ndarray] = {}
    for name, arr in cols.items():
        if copy:
            values = np.array(arr, dtype=np.float64)
        else:
            values = np.ascontiguousarray(arr, dtype=np.float64)
        finite = np.isfinite(values)
        if not finite.all():
            i = int(np.argmin(finite))
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
    _check_plausible(out, source, where)
    return out


#: Names that mean the encoder column but are not its name (misspellings of ``y_ref`` itself are
#: found by similarity).
_ENCODER_NAMES = frozenset({"enc", "encoder", "y_enc", "yenc", "y_encoder", "theta_enc"})


def _check_unknown_names(cols: Mapping[str, np.ndarray], source: str) -> None:
    """Refuse a column that is a misspelling of a known column the file lacks.

    Columns hallcal does not read are ignored, but one named like a missing known column
    (``yref``, ``y_enc``, ``Realization``) is a typo: ignoring it would make the validation
    against the encoder (or the BLA's realizations) vanish without a word, so it is an error
    naming the column and the name it was meant to have, like a misspelled setup key. Single
    letters (r, y, u, t) are not guessed at: too many names are near them, and a near name must
    be close (``i_ref``, a current reference, is not taken for ``y_ref``).
    """
    missing = [k for k in KNOWN_COLUMNS if k not in cols and len(k) > 1]
    if not missing:
        return

    def norm(text: str) -> str:
        return re.sub(r"[\s_\-]", "", text.lower())

    for name in cols:
        if name in KNOWN_COLUMNS:
            continue
        guess = "y_ref" if "y_ref" in missing and name.lower() in _ENCODER_NAMES else None
        for known in missing:
            ratio = difflib.SequenceMatcher(None, name.lower(), known).ratio()
            if guess is None and (norm(name) == norm(known) or ratio >= 0.85):
                guess = known
        if guess is not None:
            raise HallcalInputError(
                f"{source}: column '{name}' is not a column hallcal reads: did you mean "
                f"'{guess}'? (rename it; the known columns are {', '.join(KNOWN_COLUMNS)})",
                key=name,
            )


#: The Hall signal columns: their values have a physical scale.
_HALL_COLUMNS = ("d1", "d2", "d3")


def _check_plausible(cols: Mapping[str, np.ndarray], source: str, where: Any) -> None:
    """Refuse values no recording holds (see :mod:`hallcal.limits`): a corrupt file, not data.

    Binary formats carry no checksum over their data (HDF5, MATLAB, uncompressed Parquet), so
    damaged bytes read as float64 give values of random exponent. Refused, in the known
    columns: any value above MAX_ABS_VALUE in magnitude; in the Hall columns, nonzero values
    below MIN_HALL_MAGNITUDE and values more than SPIKE_RATIO times the column's typical
    magnitude.
    """

    def fail(name: str, i: int, value: float, why: str) -> NoReturn:
        raise HallcalInputError(
            f"{source}: column '{name}' {where(i)}: the value {value:.4g} is implausible "
            f"({why}): the file is corrupt, or the column is in a wrong unit"
        )

    for name, values in cols.items():
        if values.size == 0 or name not in KNOWN_COLUMNS:
            continue  # other columns are the user's, with units hallcal does not know
        mag = np.abs(values)
        i = int(np.argmax(mag))
        if mag[i] > MAX_ABS_VALUE:
            fail(name, i, float(values[i]), f"above {MAX_ABS_VALUE:g} in magnitude")
        if name not in _HALL_COLUMNS:
            continue
        tiny = (mag < MIN_HALL_MAGNITUDE) & (mag > 0.0)
        if tiny.any():
            j = int(np.argmax(tiny))
            fail(name, j, float(values[j]), f"nonzero but below {MIN_HALL_MAGNITUDE:g}")
        # the typical magnitude from at most 2^16 evenly spaced samples (a median of 10 M
        # samples costs 0.1 s per column and tells nothing more)
        typical = float(np.median(mag[:: max(1, mag.size // 65536)]))
        if typical > 0.0 and mag[i] > SPIKE_RATIO * typical:
            fail(
                name,
                i,
                float(values[i]),
                f"{mag[i] / typical:.3g} times the column's typical magnitude {typical:.3g}",
            )


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
    """Read and check a dataset file (``docs/design.md``, "Dataset files").

    Parameters
    ----------
    path : path-like
        ``.csv``, ``.txt``/``.dat``, ``.parquet``, ``.h5``/``.hdf5``, ``.mat`` or ``.npz`` file
        (see the module documentation for the layout of each).
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
    p = existing_file(path)
    ext = _check_extension(p)
    if p.stat().st_size == 0:
        raise HallcalInputError(f"{p}: file is empty")
    row_lines: Sequence[int] | None = None
    if ext in TEXT_EXTENSIONS:
        # what the text readers' libraries raise themselves (the csv module's field-size limit,
        # pyarrow's parser) is one line too
        with _library_errors(p, "CSV file" if ext == ".csv" else "text table", recognized=False):
            cols, row_lines = read_text_table(p, headerless_ok=ext != ".csv")
    elif ext == ".parquet":
        cols = _read_parquet(p)
    elif ext in (".h5", ".hdf5"):
        cols = _read_hdf5(p)
    elif ext == ".mat":
        cols = _read_mat(p)
    else:
        cols = _read_npz(p)
    checked = _finish_columns(
        cols, str(p), required=required, min_samples=min_samples, row_lines=row_lines, copy=False
    )
    return Dataset(checked, p)


# ---- Binary formats: the library boundary -----------------------------------------------------


@contextlib.contextmanager
def _library_errors(p: Path, what: str, *, recognized: bool = True) -> Iterator[None]:
    """Turn whatever a file-format library raises on a corrupt or truncated file into one line.

    h5py, scipy.io, zipfile, numpy's .npy format and pyarrow raise anything from OSError to
    IndexError, KeyError or their own classes on damaged input; each reader wraps its library
    calls (and only those) in this block. Errors hallcal raised on purpose pass through.

    Parameters
    ----------
    p : Path
    what : str
        The format, e.g. ``"HDF5 file"``.
    recognized : bool
        Whether the file starts like one of `what` (its signature): then it is "corrupt or
        truncated", else "not a valid" one.
    """
    try:
        yield
    except HallcalInputError:
        raise
    except MemoryError:
        raise HallcalInputError(
            f"{p}: corrupt {what}: it declares more data than fits in memory"
        ) from None
    except Exception as exc:  # every library exception of a damaged file, see above
        state = "corrupt or truncated" if recognized else "not a valid"
        raise HallcalInputError(f"{p}: {state} {what} ({_why(exc)})") from None


def _head(p: Path, n: int) -> bytes:
    """The first `n` bytes of the file."""
    try:
        with open(p, "rb") as f:
            return f.read(n)
    except OSError as exc:
        raise HallcalInputError(f"{p}: cannot read ({exc.strerror or exc})") from None


def _why(exc: BaseException) -> str:
    """``"OSError: first line of the message"``, at most 150 characters."""
    text = one_line(exc)
    text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return text if len(text) <= 150 else text[:147] + "..."


def _check_table_size(source: str, rows: int, columns: int) -> None:
    """Rows, columns and values of a table against :mod:`hallcal.limits`, before reading it."""
    if rows > MAX_SAMPLES:
        raise HallcalInputError(
            f"{source}: {rows} rows, above the limit of {MAX_SAMPLES} samples of one dataset"
        )
    if columns > MAX_COLUMNS:
        raise HallcalInputError(
            f"{source}: {columns} columns, above the limit of {MAX_COLUMNS} columns of one dataset"
        )
    if rows * columns > MAX_DATASET_VALUES:
        raise HallcalInputError(
            f"{source}: {rows} rows x {columns} columns, above the limit of "
            f"{MAX_DATASET_VALUES} values of one dataset"
        )


# ---- Parquet -----------------------------------------------------------------------------------


def _read_parquet(p: Path) -> dict[str, np.ndarray]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    source = str(p)
    if _head(p, 4) != b"PAR1":
        raise HallcalInputError(f"{source}: not a valid Parquet file (no PAR1 signature)")
    cols: dict[str, np.ndarray] = {}
    with _library_errors(p, "Parquet file"):
        pf = pq.ParquetFile(p, pre_buffer=False)  # no Arrow I/O thread (see text.py)
        meta = pf.metadata
        _check_table_size(source, int(meta.num_rows), int(meta.num_columns))
        table = pf.read(use_threads=False)
        if table.num_rows != meta.num_rows:
            raise HallcalInputError(
                f"{source}: corrupt Parquet file ({table.num_rows} rows read, "
                f"{meta.num_rows} declared)"
            )
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
            if not (
                pa.types.is_integer(typ) or pa.types.is_floating(typ) or pa.types.is_boolean(typ)
            ):
                raise HallcalInputError(f"{source}: column '{name}' is not numeric (type {typ})")
            if column.null_count:
                nulls = column.is_null().to_numpy(zero_copy_only=False)
                i = int(np.argmax(nulls))
                raise HallcalInputError(
                    f"{source}: column '{name}' has a missing value in row {i + 1}"
                )
            cols[name] = np.asarray(column.to_numpy(), dtype=np.float64)
    if not cols:
        raise HallcalInputError(f"{source}: no columns")
    return cols


# ---- Containers: HDF5, MATLAB, NumPy -----------------------------------------------------------

#: Members of one container file looked at: far more than any dataset's columns (MAX_COLUMNS),
#: few enough that listing them is instant.
_MAX_MEMBERS = 16 * MAX_COLUMNS


@dataclass(frozen=True)
class _Member:
    """One named member of a container file, described before its data are read.

    Attributes
    ----------
    name : str
    shape : tuple of int or None
        Shape of a numeric array; None when the member is not one (then `description` says what).
    description : str
        What the member is, for messages.
    """

    name: str
    shape: tuple[int, ...] | None
    description: str


def _vector_length(member: _Member) -> int | None:
    """Length of a numeric vector member (row, column or 1-D), None for anything else."""
    shape = member.shape
    if shape is None:
        return None
    size = math.prod(shape)
    if size == 0:
        return 0
    if len(shape) == 1:
        return shape[0]
    if len(shape) >= 2 and sum(s != 1 for s in shape) <= 1:
        return size
    if len(shape) == 0 and member.name in KNOWN_COLUMNS:
        return 1
    return None


def _select_columns(members: Iterable[_Member], source: str) -> dict[str, int]:
    """Pick the columns among a container's members from their shapes, before reading any.

    Known columns must be numeric vectors; other members are kept only when they are numeric
    vectors of the known columns' length. Returns ``{name: length}`` in file order; the sizes
    are checked against :mod:`hallcal.limits`.
    """
    known: dict[str, int] = {}
    others: dict[str, int] = {}
    order: list[str] = []
    count = 0
    for member in members:
        count += 1
        if count > _MAX_MEMBERS:
            raise HallcalInputError(
                f"{source}: more than {_MAX_MEMBERS} members, above the limit for a dataset file"
            )
        name = member.name
        length = _vector_length(member)
        if name in KNOWN_COLUMNS:
            if length is None:
                what = f"shape {member.shape}" if member.shape is not None else member.description
                raise HallcalInputError(
                    f"{source}: column '{name}' must be a numeric vector, got {what}"
                )
            if length > MAX_SAMPLES:
                raise HallcalInputError(
                    f"{source}: column '{name}' has {length} rows, above the limit of "
                    f"{MAX_SAMPLES} samples of one dataset"
                )
            known[name] = length
        elif length is not None and 1 < length <= MAX_SAMPLES:
            others[name] = length
        else:
            continue
        order.append(name)
    lengths = set(known.values())
    if len(lengths) == 1:
        n = lengths.pop()
        others = {k: v for k, v in others.items() if v == n}
    elif lengths:
        others = {}  # known columns disagree: report them, not the others
    elif len(set(others.values())) > 1:
        raise HallcalInputError(
            f"{source}: vectors of different lengths and no known column "
            f"({', '.join(KNOWN_COLUMNS)}) to tell which are columns"
        )
    chosen = {**known, **others}
    out = {name: chosen[name] for name in order if name in chosen}
    if out:
        _check_table_size(source, max(out.values()), len(out))
    return out


def _as_vector(arr: Any, name: str, length: int, source: str, what: str) -> np.ndarray:
    """A member's data as the vector its header declared; anything else is a corrupt file."""
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "biuf" or arr.size != length:
        got = f"{arr.size} values" if isinstance(arr, np.ndarray) else type(arr).__name__
        raise HallcalInputError(
            f"{source}: corrupt {what}: column '{name}' declares {length} values, holds {got}"
        )
    return arr.reshape(-1)


def _read_hdf5(p: Path) -> dict[str, np.ndarray]:
    import h5py

    source = str(p)
    with _library_errors(p, "HDF5 file", recognized=False):
        recognized = h5py.is_hdf5(p)
    if not recognized:
        raise HallcalInputError(f"{source}: not a valid HDF5 file (no HDF5 signature)")
    with _library_errors(p, "HDF5 file"):
        with h5py.File(p, "r") as handle:
            group = handle
            if isinstance(handle.get("data", getlink=True), h5py.HardLink) and isinstance(
                handle["data"], h5py.Group
            ):
                group = handle["data"]
            chosen = _select_columns(_hdf5_members(group), source)
            return {
                name: _as_vector(np.asarray(group[name][()]), name, n, source, "HDF5 file")
                for name, n in chosen.items()
            }


def _hdf5_members(group: Any) -> Iterator[_Member]:
    """The members of an HDF5 group, described from their headers (no data read).

    Only datasets stored in this file are numeric members: links (soft or to other files),
    virtual datasets and datasets with external storage could make the reader open any file on
    the machine, so they are not columns.
    """
    import h5py

    for name in group:
        if not isinstance(group.get(name, getlink=True), h5py.HardLink):
            yield _Member(name, None, "a link to another object or file")
            continue
        item = group[name]
        if not isinstance(item, h5py.Dataset):
            yield _Member(name, None, "a group")
            continue
        if item.is_virtual or item.external:
            yield _Member(name, None, "a dataset stored in other files")
            continue
        if "MATLAB_empty" in item.attrs and bool(np.asarray(item.attrs["MATLAB_empty"]).any()):
            yield _Member(name, (0,), "an empty array")
            continue
        matlab_class = item.attrs.get("MATLAB_class")
        if isinstance(matlab_class, bytes):
            matlab_class = matlab_class.decode("ascii", "replace")
        if (
            matlab_class in ("char", "cell", "struct")
            or item.dtype.kind not in "biuf"
            or item.shape is None
        ):
            yield _Member(name, None, f"a non-numeric dataset ({item.dtype})")
            continue
        yield _Member(name, tuple(int(s) for s in item.shape), "a dataset")


#: MATLAB classes that hold numbers (whosmat's third field).
_MATLAB_NUMERIC = frozenset(
    ["double", "single", "logical", "int8", "uint8", "int16", "uint16", "int32", "uint32"]
    + ["int64", "uint64"]
)


def _read_mat(p: Path) -> dict[str, np.ndarray]:
    import h5py
    import scipy.io

    source = str(p)
    head = _head(p, 128)
    # MATLAB 5 and 7.3 files: a text header "MATLAB 5.0 MAT-file..." and the endian indicator
    # "IM" or "MI" at bytes 126-127 (MATLAB 4 files have no signature)
    recognized = head[126:128] in (b"IM", b"MI") or (
        len(head) < 128 and b"MATLAB".startswith(head[:6])
    )
    try:
        with _library_errors(p, "MATLAB .mat file", recognized=recognized):
            try:
                listing = scipy.io.whosmat(p)
            except NotImplementedError:
                listing = None
    except HallcalInputError:
        if h5py.is_hdf5(p):  # an HDF5 file saved under .mat, read it like MATLAB v7.3
            return _read_hdf5(p)
        raise
    if listing is None:  # MATLAB v7.3 files are HDF5 files: variables are datasets at the root
        return _read_hdf5(p)

    def members() -> Iterator[_Member]:
        for name, shape, cls in listing:
            if name.startswith("__"):
                continue
            if cls in _MATLAB_NUMERIC:
                yield _Member(name, tuple(int(s) for s in shape), "a variable")
            else:
                kind = "a string" if cls == "char" else f"of class {cls}"
                yield _Member(name, None, f"a variable that is {kind}")

    chosen = _select_columns(members(), source)
    if not chosen:
        return {}
    with _library_errors(p, "MATLAB .mat file", recognized=recognized):
        contents = scipy.io.loadmat(
            p, squeeze_me=False, chars_as_strings=True, variable_names=list(chosen)
        )
    return {
        name: _as_vector(contents.get(name), name, n, source, "MATLAB .mat file")
        for name, n in chosen.items()
    }


def _npy_header(f: IO[bytes], name: str, source: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Shape, Fortran order and dtype of a .npy member from its header, refusing object
    (pickled) arrays and unknown versions (a HallcalInputError, a ValueError as a malformed
    header's)."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
    else:
        raise HallcalInputError(f"{source}: array '{name}' has an unsupported .npy version")
    if dtype.hasobject:
        raise HallcalInputError(
            f"{source}: array '{name}' holds Python objects (object dtype); hallcal never "
            "unpickles data, save numeric arrays"
        )
    return tuple(int(s) for s in shape), bool(fortran), dtype


def _read_npz(p: Path) -> dict[str, np.ndarray]:
    source = str(p)
    magic = _head(p, 6)
    if magic == b"\x93NUMPY":
        raise HallcalInputError(f"{source}: a single .npy array, not a .npz archive of columns")
    if not magic.startswith(b"PK"):
        raise HallcalInputError(f"{source}: not a valid .npz archive (not a zip file)")
    with _library_errors(p, ".npz archive"), zipfile.ZipFile(p) as archive:
        infos = archive.infolist()
        if len(infos) > _MAX_MEMBERS:
            raise HallcalInputError(
                f"{source}: {len(infos)} members, above the limit of {_MAX_MEMBERS} for a "
                "dataset file"
            )
        by_name: dict[str, zipfile.ZipInfo] = {}
        members: list[_Member] = []
        for info in infos:
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if name in by_name:
                raise HallcalInputError(f"{source}: array '{name}' appears twice")
            by_name[name] = info
            with archive.open(info) as f:
                try:
                    shape, _, dtype = _npy_header(f, name, source)
                except ValueError:
                    if not info.filename.endswith(".npy"):
                        members.append(_Member(name, None, "not a .npy array"))
                        continue
                    raise
            if dtype.kind not in "biuf":
                members.append(_Member(name, None, f"an array of dtype {dtype}"))
                continue
            if math.prod(shape) * dtype.itemsize > info.file_size:
                raise HallcalInputError(
                    f"{source}: corrupt .npz archive: array '{name}' declares "
                    f"{math.prod(shape)} values of {dtype}, the archive holds "
                    f"{info.file_size} bytes"
                )
            members.append(_Member(name, shape, "an array"))
        chosen = _select_columns(members, source)
        # stored members are mapped from the file (their CRC checked), the others read
        mapped = _map_stored_members(p) if chosen else {}
        out: dict[str, np.ndarray] = {}
        for name, n in chosen.items():
            arr = mapped.get(name)
            if arr is None:
                with archive.open(by_name[name]) as f:
                    arr = np.lib.format.read_array(f, allow_pickle=False)
                    f.read()  # to the end of the member: the zip's CRC-32 is checked there
            out[name] = _as_vector(arr, name, n, source, ".npz archive")
    return out


def _map_stored_members(p: Path) -> dict[str, np.ndarray]:
    """Arrays of the uncompressed members of an ``.npz`` file, mapped from the file, not read.

    ``numpy.savez`` and :func:`write_dataset` store members uncompressed, so each array's bytes
    lie in the file as they are: mapping them costs nothing until they are used, and memory is
    the page cache's, not a private copy (``numpy.load`` of a 10 million-row archive copies the
    data through 256 KiB reads). Each member's CRC is checked as ``zipfile`` would. Members that
    are compressed, encrypted, hold objects or are not plain ``.npy`` data are left out; the
    caller reads those with ``numpy.load``.
    """
    out: dict[str, np.ndarray] = {}
    try:
        with open(p, "rb") as f, zipfile.ZipFile(f) as zf:
            infos = zf.infolist()
            mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError, zipfile.BadZipFile):
        return out
    for info in infos:
        name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
        arr = _mapped_npy(mm, info)
        if arr is not None:
            out[name] = arr
    return out


def _mapped_npy(mm: mmap.mmap, info: zipfile.ZipInfo) -> np.ndarray | None:
    if info.compress_type != zipfile.ZIP_STORED or info.flag_bits & 0x1:
        return None
    at = info.header_offset
    local = mm[at : at + 30]
    if len(local) != 30 or local[:4] != b"PK\x03\x04":
        return None
    name_length, extra_length = struct.unpack("<HH", local[26:30])
    start = at + 30 + name_length + extra_length
    end = start + info.file_size
    if end > len(mm) or zlib.crc32(memoryview(mm)[start:end]) != info.CRC:
        return None
    head = io.BytesIO(mm[start : min(end, start + (1 << 20))])
    try:
        shape, fortran, dtype = _npy_header(head, info.filename, "")
    except ValueError:  # an unknown version, a malformed header or object (pickled) values
        return None
    count = math.prod(shape)
    offset = start + head.tell()
    if offset + count * dtype.itemsize > end:
        return None
    arr = np.frombuffer(mm, dtype=dtype, count=count, offset=offset)
    return arr.reshape(shape, order="F" if fortran else "C")


# ---- Writing -----------------------------------------------------------------------------------

_MATLAB_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,62}")


#: Values of a text column that :func:`write_dataset` accepts: a lowercase word.
_WORD = re.compile(r"[a-z]+")


def _columns_for_writing(p: Path, columns: Mapping[str, Any]) -> dict[str, np.ndarray]:
    if not columns:
        raise ValueError(f"{p}: no columns to write")
    out: dict[str, np.ndarray] = {}
    n = None
    for name, values in columns.items():
        if not isinstance(name, str) or not name or any(c in name for c in "\r\n"):
            raise ValueError(f"{p}: invalid column name {name!r}")
        arr = np.asarray(values)
        if arr.ndim == 1 and arr.dtype.kind == "U" and all(map(_WORD.fullmatch, set(arr))):
            # a column of lowercase words (the observer's state): text as it is, HDF5 as bytes
            out[name] = arr.astype("S") if p.suffix.lower() in (".h5", ".hdf5") else arr
            n = arr.shape[0] if n is None else n
            if arr.shape[0] != n:
                raise ValueError(f"{p}: columns have different lengths ('{name}': {arr.shape[0]})")
            continue
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

    Floating-point columns are written as float64 (text: the shortest digits that read back to
    the same value, with ``.0`` on whole numbers), integer and boolean columns as int64 (text:
    integers). CSV files are comma-separated with a header row; ``.txt``/``.dat`` files are
    separated by one space, with a header row (names with spaces are refused). HDF5 files get one
    dataset per column at the root; MATLAB files one column-vector variable per column;
    ``.npz`` archives one array per column (never pickled).

    Parameters
    ----------
    path : path-like
        Destination with one of the :data:`DATASET_EXTENSIONS`.
    columns : mapping of str to array_like
        Numeric 1-D arrays of equal length, finite, or text arrays of lowercase words (the
        observer's ``state``; bytes in HDF5).

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
    if ext in TEXT_EXTENSIONS:
        write_text_table(p, cols, delimiter="," if ext == ".csv" else " ")
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
                    # the bytes numpy.lib.format.write_array writes, without its 16 MiB copies
                    header = np.lib.format.header_data_from_array_1_0(arr)
                    np.lib.format.write_array_header_1_0(member, header)
                    member.write(np.ascontiguousarray(arr).data.cast("B"))
