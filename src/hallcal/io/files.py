"""Files: atomic writes, JSON, and the small checks every reader shares.

Everything hallcal writes goes through :func:`atomic_write` (a temporary file in the target
directory, then :func:`os.replace`), so an interrupted or failed write never leaves a half-written
output behind. Every mistake in an input raises :class:`hallcal.errors.HallcalInputError` with a
one-line message that names the file. Nothing here unpickles anything.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import json
import math
import os
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any, Literal, NoReturn

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.limits import MAX_JSON_BYTES, MAX_JSON_DEPTH

__all__ = ["atomic_path", "atomic_write", "read_json", "to_jsonable", "write_json"]


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


# ------------------------------------------------------------------------------------------------
# Small helpers shared by the readers


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


def _size_text(nbytes: float) -> str:
    """``"3.2 MB"``: a byte count for messages."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{int(nbytes)} bytes"


def _check_size(p: Path, limit: int | None, what: str) -> None:
    """Refuse a file larger than `limit` bytes before reading it."""
    if limit is None:
        return
    try:
        size = p.stat().st_size
    except OSError as exc:
        raise HallcalInputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if size > limit:
        raise HallcalInputError(
            f"{p}: {_size_text(size)}, above the limit of {_size_text(limit)} for {what}"
        )


def _read_bytes(p: Path, *, limit: int | None = None, what: str = "this file") -> bytes:
    """The file's content, refusing files above `limit` bytes (checked before reading)."""
    _check_size(p, limit, what)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise HallcalInputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if limit is not None and len(raw) > limit:  # the file grew while we looked at it
        raise HallcalInputError(
            f"{p}: {_size_text(len(raw))}, above the limit of {_size_text(limit)} for {what}"
        )
    return raw


def _decode_text(p: Path, raw: bytes) -> str:
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise HallcalInputError(f"{p}: not UTF-8 text (line {line})") from None


def _check_parsed(p: str | os.PathLike[str], data: Any) -> None:
    """Nesting at most MAX_JSON_DEPTH levels, every float finite, every integer within 64 bits.

    For parsed JSON or TOML; iterative (the data may be deep). The message names the key path of
    the first offender.
    """
    stack: list[tuple[Any, str, int]] = [(data, "", 0)]
    while stack:
        value, where, depth = stack.pop()
        if isinstance(value, bool) or value is None or isinstance(value, str):
            continue
        if isinstance(value, float):
            if not math.isfinite(value):
                raise HallcalInputError(
                    f"{p}: key '{where or '(top level)'}' holds a number out of the range of "
                    "a 64-bit float (1e999 and the like are infinite)"
                )
            continue
        if isinstance(value, int):
            if not -(2**63) <= value < 2**63:
                raise HallcalInputError(
                    f"{p}: key '{where or '(top level)'}' holds an integer out of the 64-bit range"
                )
            continue
        if isinstance(value, dict | list):
            if depth >= MAX_JSON_DEPTH:
                raise HallcalInputError(
                    f"{p}: key '{where or '(top level)'}' is nested more than {MAX_JSON_DEPTH} "
                    "levels deep (the limit)"
                )
            items = value.items() if isinstance(value, dict) else enumerate(value)
            for key, item in items:
                if isinstance(value, dict):
                    path = f"{where}.{key}" if where else str(key)
                else:
                    path = f"{where}[{key}]"
                stack.append((item, path, depth + 1))


def _nested_too_deeply(p: str | os.PathLike[str]) -> HallcalInputError:
    """The parsers recurse once per level; Python stops them at about a thousand."""
    return HallcalInputError(f"{p}: nested far more than {MAX_JSON_DEPTH} levels deep (the limit)")


# ------------------------------------------------------------------------------------------------
# JSON


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

    Returns
    -------
    object
        Nested dicts (str keys), lists, str, int, finite float, bool and None.

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

    Parameters
    ----------
    path : path-like
        Destination file; its directory must exist.
    obj : object
        Anything :func:`to_jsonable` converts.

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

    The size is checked before reading (at most :data:`~hallcal.limits.MAX_JSON_BYTES`); after
    parsing, the nesting depth (at most :data:`~hallcal.limits.MAX_JSON_DEPTH`), and that every
    number is finite (``1e999`` parses to infinity) and every integer fits in 64 bits.

    Parameters
    ----------
    path : path-like
        The JSON file.

    Returns
    -------
    object
        The parsed data (dicts, lists, str, int, float, bool, None).

    Raises
    ------
    HallcalInputError
        Missing file, invalid UTF-8, invalid JSON (with its line and column), a file above the
        size or depth limit, or a number out of range (with its key path).
    """
    p = _existing_file(path)
    text = _decode_text(p, _read_bytes(p, limit=MAX_JSON_BYTES, what="a JSON file"))
    try:
        data = json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise HallcalInputError(
            f"{p}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    except ValueError as exc:  # NaN/Infinity, integers of more than 4300 digits
        raise HallcalInputError(f"{p}: invalid JSON: {' '.join(str(exc).split())}") from None
    except RecursionError:
        raise _nested_too_deeply(p) from None
    _check_parsed(p, data)
    return data
