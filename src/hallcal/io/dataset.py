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
from typing import Any

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.io.files import _existing_file, _suggest, atomic_path, atomic_write
from hallcal.io.text import TEXT_EXTENSIONS, read_text_table, write_text_table

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
    p = _existing_file(path)
    ext = _check_extension(p)
    if p.stat().st_size == 0:
        raise HallcalInputError(f"{p}: file is empty")
    row_lines: Sequence[int] | None = None
    if ext in TEXT_EXTENSIONS:
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
    mapped = _map_stored_members(p)
    with archive:
        arrays: list[tuple[str, np.ndarray | None, str]] = []
        for name in archive.files:
            try:
                arr = mapped[name] if name in mapped else archive[name]
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
        version = np.lib.format.read_magic(head)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(head)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(head)
        else:
            return None
    except ValueError:
        return None
    if dtype.hasobject:
        return None
    count = math.prod(shape)
    offset = start + head.tell()
    if offset + count * dtype.itemsize > end:
        return None
    arr = np.frombuffer(mm, dtype=dtype, count=count, offset=offset)
    return arr.reshape(shape, order="F" if fortran else "C")


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
                    member.write(memoryview(np.ascontiguousarray(arr)).cast("B"))
