"""Text tables: CSV and whitespace-separated ``.txt``/``.dat`` files, read and written.

Layout of a file
----------------
``.csv``
    A header row of column names, then one row of numbers per sample. The delimiter is a comma
    (a semicolon or a tab when the header holds no comma).
``.txt``, ``.dat``
    Columns separated by runs of spaces or tabs (or by commas or semicolons when the first line
    that is read holds one). The header row is optional: a file without one is read only when it
    has exactly three columns, which are then ``d1``, ``d2``, ``d3`` (the Hall signals of an
    open-loop recording, as in the recording guide's own data); with any other number of columns
    the names cannot be guessed and the file must start with a header line.

In both, blank lines and lines starting with ``#`` are skipped, except that a ``#`` line directly
followed by numbers is the header (``numpy.savetxt(..., header="d1,d2,d3")`` writes one; in a
``.txt`` file only when it names as many columns as the data have). Rows are counted from 1 at
the first data row; error messages also give the line number in the file.

Two readers, one result
-----------------------
Both readers find the layout (header, delimiter, names) with the same code, :func:`_layout`.

- :func:`_read_fast` hands the rows to pyarrow's CSV reader (C++, in the calling thread: Arrow's
  thread pool, still alive when the interpreter exits, sometimes aborts the process there with
  "terminate called without an active exception", apache/arrow#34314; on two cores the pool
  read 20 MB no faster), or to NumPy's ``loadtxt`` for columns aligned with runs of spaces. It
  accepts a file only when it is regular: every row complete and numeric, no comment lines
  among the rows, no trailing delimiters, no lone carriage returns. Anything else raises
  :class:`_NotRegular`.
- :func:`_read_careful` parses line by line in Python. It reads the irregular files the fast
  reader declines and writes the precise one-line error messages (row and line of a
  non-numeric or missing value, a ragged row, ...).

:func:`read_text_table` tries the first and falls back to the second;
``tests/test_text_tables.py`` checks that both give the same columns or the same message on a
collection of files, written and generated.
"""

from __future__ import annotations

import csv
import io
import re
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.io.files import _decode_text, _read_bytes, atomic_write

if TYPE_CHECKING:
    import pyarrow as pa

__all__ = ["TEXT_EXTENSIONS", "read_text_table", "write_text_table"]

#: Extensions of text tables (lower case); ``.csv`` needs a header, the others may omit it.
TEXT_EXTENSIONS: tuple[str, ...] = (".csv", ".txt", ".dat")

#: Column names of a headerless whitespace file, by its number of columns.
HEADERLESS_NAMES: dict[int, tuple[str, ...]] = {3: ("d1", "d2", "d3")}

_BOM = b"\xef\xbb\xbf"
_FIRST_FIELD_CSV = re.compile(r"[,;\t]")
_FIRST_FIELD_TXT = re.compile(r"[,;\s]")
_ROWS_PER_BATCH = 1 << 20


class _NotRegular(Exception):
    """The fast reader declines the file; the careful one reads it (or says what is wrong)."""


@dataclass(frozen=True)
class _Layout:
    """Where the rows of a text table start and what its columns are called.

    Attributes
    ----------
    names : tuple of str
        Column names (from the header, or :data:`HEADERLESS_NAMES`).
    delimiter : str or None
        Field delimiter; ``None`` for runs of spaces and tabs.
    body : int
        Index (from 0) of the first line after the header, or of the first data line when the
        file has no header.
    trailing_empty : bool
        The header ends with a delimiter (``d1,d2,d3,``); rows may too.
    headerless : bool
        No header line: the names come from the number of columns.
    """

    names: tuple[str, ...]
    delimiter: str | None
    body: int
    trailing_empty: bool = False
    headerless: bool = False


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return text.strip().lower() not in ("nan", "inf", "infinity", "-inf", "+inf")


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    return [field.strip() for field in next(csv.reader([line], delimiter=delimiter))]


def _csv_delimiter(line: str) -> str:
    if "," not in line:
        if "\t" in line:
            return "\t"
        if ";" in line:
            return ";"
    return ","


def _txt_delimiter(line: str) -> str | None:
    if "," in line:
        return ","
    if ";" in line:
        return ";"
    return None


def _layout(lines: Iterable[str], source: str, *, headerless_ok: bool) -> _Layout:
    """Find the header (or decide there is none), the delimiter and the column names.

    Reads `lines` only up to the first data line.

    Parameters
    ----------
    lines : iterable of str
        The file's lines, in order (line terminators may be left on).
    source : str
        File name for messages.
    headerless_ok : bool
        ``.txt``/``.dat`` rules (whitespace delimiters, headerless three-column files); else
        the ``.csv`` rules.

    Raises
    ------
    HallcalInputError
        Empty file, a header that is not one (a number, a name twice or missing), a headerless
        file whose column count does not say what the columns are.
    """
    last_comment: tuple[int, str] | None = None
    first_data: tuple[int, str] | None = None
    for i, line in enumerate(lines):
        text = line.strip()
        if not text:
            continue
        if text.startswith("#"):
            last_comment = (i, text[1:].strip())
            continue
        first_data = (i, text)
        break
    if first_data is None and last_comment is None:
        raise HallcalInputError(f"{source}: file is empty")

    header: tuple[int, str] | None
    if first_data is None:
        header = last_comment  # only comments: a header without rows
    else:
        splitter = _FIRST_FIELD_TXT if headerless_ok else _FIRST_FIELD_CSV
        first_field = splitter.split(first_data[1], maxsplit=1)[0].strip().strip('"')
        if not _looks_numeric(first_field):
            header = first_data
        elif not headerless_ok:
            # numpy.savetxt's "# d1,d2,d3" header, else the numbers themselves (refused below)
            header = last_comment if last_comment is not None else first_data
        else:
            header = None
            if last_comment is not None:
                delimiter = _txt_delimiter(first_data[1])
                names = _split(last_comment[1], delimiter)
                width = len(_split(first_data[1], delimiter))
                if len(names) == width and not any(map(_looks_numeric, names)):
                    header = last_comment

    if header is None:
        assert first_data is not None
        delimiter = _txt_delimiter(first_data[1])
        width = len(_split(first_data[1], delimiter))
        default_names = HEADERLESS_NAMES.get(width)
        if default_names is None:
            known = ", ".join(
                f"{n} columns ({' '.join(v)})" for n, v in sorted(HEADERLESS_NAMES.items())
            )
            raise HallcalInputError(
                f"{source}: no header line and {width} columns; a file without a header is read "
                f"only with {known}: add a first line naming the columns (for example "
                "'t d1 d2 d3')"
            )
        return _Layout(default_names, delimiter, first_data[0], headerless=True)

    index, line = header
    if line.startswith("#"):
        line = line[1:].strip()
    delimiter = _txt_delimiter(line) if headerless_ok else _csv_delimiter(line)
    names = _split(line, delimiter)
    trailing_empty = len(names) > 1 and names[-1] == ""
    if trailing_empty:
        names.pop()
    for j, name in enumerate(names):
        if not name:
            raise HallcalInputError(f"{source}: column {j + 1} of the header has no name")
        if names.index(name) != j:
            raise HallcalInputError(f"{source}: column '{name}' appears twice in the header")
        if _looks_numeric(name):
            raise HallcalInputError(
                f"{source}: the first line must be a header of column names, "
                f"found the number {name!r}"
            )
    return _Layout(tuple(names), delimiter, index + 1, trailing_empty=trailing_empty)


# ---- the careful reader ------------------------------------------------------------------------


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


def _records(body: list[str], layout: _Layout) -> Iterator[tuple[int, list[str]]]:
    """(line number from 1, fields) of every line after the header."""
    if layout.delimiter is None:
        for k, line in enumerate(body, start=layout.body + 1):
            yield k, line.split()
        return
    reader = csv.reader(body, delimiter=layout.delimiter)
    for record in reader:
        yield layout.body + reader.line_num, record


def _read_careful(
    p: Path, raw: bytes, *, headerless_ok: bool
) -> tuple[dict[str, np.ndarray], list[int]]:
    """Line-by-line reader: every irregular file, every precise message (see the module)."""
    source = str(p)
    lines = _decode_text(p, raw).splitlines()
    layout = _layout(lines, source, headerless_ok=headerless_ok)
    width = len(layout.names)
    values: list[list[str]] = [[] for _ in layout.names]
    row_lines: list[int] = []
    for line_no, record in _records(lines[layout.body :], layout):
        if not record or (len(record) == 1 and not record[0].strip()):
            continue
        if record[0].lstrip().startswith("#"):
            continue
        if layout.trailing_empty and len(record) == width + 1 and not record[-1].strip():
            record.pop()
        if len(record) != width:
            reference = "the first row" if layout.headerless else "the header"
            raise HallcalInputError(
                f"{source}: row {len(row_lines) + 1} (line {line_no}) has {len(record)} "
                f"fields, {reference} has {width}"
            )
        row_lines.append(line_no)
        for j, item in enumerate(record):
            values[j].append(item)
    if not row_lines:
        raise HallcalInputError(f"{source}: no data rows")
    cols = {
        name: _parse_numbers(name, vals, source, row_lines)
        for name, vals in zip(layout.names, values, strict=True)
    }
    return cols, row_lines


# ---- the fast reader ---------------------------------------------------------------------------


def _lines_with_offsets(raw: bytes, starts: list[int]) -> Iterator[str]:
    """Decoded lines of `raw` split at ``\\n``; appends each line's byte offset to `starts`."""
    pos = 0
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        if end < 0:
            end = len(raw)
        line = raw[pos:end].decode("utf-8")
        if len(line.splitlines()) > 1:  # a separator str.splitlines knows and pyarrow does not
            raise _NotRegular
        starts.append(pos)
        yield line
        pos = end + 1
    starts.append(len(raw))


def _read_fast(p: Path, raw: bytes, *, headerless_ok: bool) -> dict[str, np.ndarray]:
    """pyarrow (or NumPy loadtxt) reader for regular files; :class:`_NotRegular` otherwise."""
    if raw.startswith(_BOM):
        raw = raw[len(_BOM) :]
    if not raw.isascii():
        try:
            raw.decode("utf-8")
        except UnicodeDecodeError:
            raise _NotRegular from None
    if b"\r" in raw and raw.count(b"\r") != raw.count(b"\r\n"):
        raise _NotRegular  # lone carriage returns: line numbers would differ
    starts: list[int] = []
    layout = _layout(_lines_with_offsets(raw, starts), str(p), headerless_ok=headerless_ok)
    if layout.body < len(starts):
        offset = starts[layout.body]
    else:  # the header is the last line read; rows start on the next one
        newline = raw.find(b"\n", starts[-1])
        offset = len(raw) if newline < 0 else newline + 1
    body = memoryview(raw)[offset:]  # no copy
    names = list(layout.names)
    try:
        cols = _pyarrow_csv(body, names, layout)
    except _NotRegular:
        if layout.delimiter is not None:
            raise
        # columns aligned with runs of spaces (MATLAB "save -ascii"): pyarrow splits at every
        # single space, NumPy's loadtxt at runs of whitespace
        cols = _loadtxt(body, names)
    if next(iter(cols.values())).shape[0] == 0:
        raise _NotRegular  # no rows: the careful reader says so
    return cols


def _pyarrow_csv(body: memoryview, names: list[str], layout: _Layout) -> dict[str, np.ndarray]:
    import pyarrow as pa
    import pyarrow.csv as pacsv

    spare = "\x00trailing" if layout.trailing_empty else None
    column_names = names + ([spare] if spare else [])
    try:
        table = pacsv.read_csv(
            pa.py_buffer(body),
            read_options=pacsv.ReadOptions(column_names=column_names, use_threads=False),
            parse_options=pacsv.ParseOptions(
                delimiter=layout.delimiter or " ",
                quote_char='"' if layout.delimiter else False,
                double_quote=True,
                newlines_in_values=False,
                ignore_empty_lines=True,
            ),
            convert_options=pacsv.ConvertOptions(
                column_types={name: pa.float64() for name in column_names},
                null_values=[""],
                strings_can_be_null=False,
            ),
        )
    except (pa.ArrowException, ValueError):
        raise _NotRegular from None
    if spare is not None:
        extra = table.column(spare)
        if extra.null_count != len(extra):
            raise _NotRegular
    cols: dict[str, np.ndarray] = {}
    for name in names:
        column = table.column(name)
        if column.null_count:
            raise _NotRegular  # a missing value: the careful reader gives its row and line
        # NumPy's own copy, so that the parser's buffers can go back to the system now
        cols[name] = np.array(column.to_numpy(), dtype=np.float64)
    del table
    pa.default_memory_pool().release_unused()
    return cols


def _loadtxt(body: memoryview, names: list[str]) -> dict[str, np.ndarray]:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # "input contained no data" among others
            data = np.loadtxt(
                io.StringIO(bytes(body).decode("utf-8")), dtype=np.float64, comments=None, ndmin=2
            )
    except (ValueError, UserWarning):
        raise _NotRegular from None
    if data.shape[1] != len(names):
        raise _NotRegular
    return {name: data[:, j] for j, name in enumerate(names)}


class _LinesOnDemand(Sequence[int]):
    """Line numbers of the rows, found by the careful reader when a message first needs one.

    The fast reader does not track lines (blank lines are skipped); the numbers matter only for
    an error message (a NaN, a fractional realization), so they are worked out then.
    """

    def __init__(self, p: Path, raw: bytes, *, headerless_ok: bool, n_rows: int) -> None:
        self._args = (p, raw, headerless_ok)
        self._n = n_rows
        self._lines: list[int] | None = None

    def _load(self) -> list[int]:
        if self._lines is None:
            p, raw, headerless_ok = self._args
            self._lines = _read_careful(p, raw, headerless_ok=headerless_ok)[1]
        return self._lines

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        return self._load()[i]


def read_text_table(p: Path, *, headerless_ok: bool) -> tuple[dict[str, np.ndarray], Sequence[int]]:
    """Read a CSV or whitespace-separated text table (see the module for the layout).

    Parameters
    ----------
    p : pathlib.Path
        An existing, non-empty file.
    headerless_ok : bool
        ``True`` for ``.txt``/``.dat`` (whitespace or delimiters, header optional for three
        columns); ``False`` for ``.csv``.

    Returns
    -------
    columns : dict of str to numpy.ndarray
        float64 columns in file order (not yet checked for NaN, length or required names).
    row_lines : sequence of int
        Line number (from 1) of each row, for messages.

    Raises
    ------
    HallcalInputError
        Not UTF-8, empty, no header (a ``.csv``, or a ``.txt`` whose columns cannot be named),
        no data rows, a ragged row, a non-numeric or missing value (with row and line).
    """
    raw = _read_bytes(p)
    try:
        cols = _read_fast(p, raw, headerless_ok=headerless_ok)
    except _NotRegular:
        return _read_careful(p, raw, headerless_ok=headerless_ok)
    n = next(iter(cols.values())).shape[0]
    return cols, _LinesOnDemand(p, raw, headerless_ok=headerless_ok, n_rows=n)


# ---- writing -----------------------------------------------------------------------------------


def _as_text(values: np.ndarray) -> pa.Array:
    """Shortest text that reads back to the same float64 (integers as integers).

    pyarrow prints floats with the shortest round-trip digits; a float that prints as an integer
    gets ``.0`` so that the column still reads as floating point in other tools.
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    text = pc.cast(pa.array(values), pa.string())
    if values.dtype.kind != "f":
        return text
    integral = values == np.trunc(values)
    if integral.any():
        whole = text.filter(pa.array(integral))
        fixed = pc.if_else(
            pc.match_substring(whole, "e"), whole, pc.binary_join_element_wise(whole, ".0", "")
        )
        text = pc.replace_with_mask(text, pa.array(integral), fixed)
    return text


def write_text_table(p: Path, cols: Mapping[str, np.ndarray], *, delimiter: str) -> None:
    """Write checked columns (float64 or int64, equal length) as a text table, atomically.

    Parameters
    ----------
    p : pathlib.Path
        Destination.
    cols : mapping of str to numpy.ndarray
        Finite float64 or int64 1-D arrays of equal length.
    delimiter : {",", " "}
        Comma (CSV: the header is quoted where needed) or one space (``.txt``/``.dat``).

    Raises
    ------
    HallcalInputError
        A column name a whitespace-separated file cannot hold (empty, with a space or tab,
        starting with ``#``), or the file cannot be written.
    """
    import pyarrow as pa
    import pyarrow.csv as pacsv

    names = list(cols)
    if delimiter == ",":
        header = io.StringIO()
        csv.writer(header, lineterminator="\n").writerow(names)
        header_text = header.getvalue()
    else:
        for name in names:
            if not name or name.startswith("#") or any(c.isspace() for c in name):
                raise HallcalInputError(
                    f"{p}: column name {name!r} cannot be stored in a whitespace-separated file"
                )
        header_text = delimiter.join(names) + "\n"
    n = len(next(iter(cols.values()))) if cols else 0
    schema = pa.schema([(name, pa.string()) for name in names])
    options = pacsv.WriteOptions(include_header=False, quoting_style="none", delimiter=delimiter)
    with atomic_write(p, "wb") as f:
        f.write(header_text.encode("utf-8"))
        with pacsv.CSVWriter(f, schema, write_options=options) as writer:
            for start in range(0, n, _ROWS_PER_BATCH):
                stop = min(start + _ROWS_PER_BATCH, n)
                arrays = [_as_text(cols[name][start:stop]) for name in names]
                writer.write_batch(pa.RecordBatch.from_arrays(arrays, schema=schema))
