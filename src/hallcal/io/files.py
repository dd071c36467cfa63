"""Files: atomic writes, JSON, and the small checks every reader shares.

Everything hallcal writes goes through :func:`atomic_write` (a temporary file in the target
directory, then :func:`os.replace`), so an interrupted or failed write never leaves a half-written
output behind; inside :func:`output_set` the files of one command appear together or not at all,
and a write error is one line naming the file and the cause (:func:`write_error`).
:func:`check_outputs` refuses, before any work, an output that is an input or another output.
Every mistake in an input raises :class:`hallcal.errors.HallcalInputError` with a one-line
message that names the file. Nothing here unpickles anything.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import difflib
import errno
import json
import math
import os
import secrets
import signal
import threading
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any, Literal, NoReturn

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.formatting import one_line
from hallcal.limits import MAX_JSON_BYTES, MAX_JSON_CONTAINERS, MAX_JSON_DEPTH

__all__ = [
    "atomic_path",
    "atomic_write",
    "check_outputs",
    "existing_file",
    "make_folder",
    "output_set",
    "read_json",
    "to_jsonable",
    "write_error",
    "write_json",
]


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


#: Errors of a write that name a cause the user can act on (a full disk, a file-size limit, a
#: name too long, no permission, a read-only file system, a folder where a file should go).
WRITE_ERRNOS = frozenset(
    {
        errno.ENOSPC,
        errno.EFBIG,
        errno.ENAMETOOLONG,
        errno.EACCES,
        errno.EPERM,
        errno.EROFS,
        errno.EISDIR,
        errno.ENOTDIR,
        errno.EDQUOT,
        errno.EEXIST,
        errno.ENOENT,
        errno.EIO,
        errno.EMLINK,
        errno.EXDEV,
    }
)


def write_error(path: str | os.PathLike[str], exc: OSError) -> HallcalInputError:
    """The one-line error of a failed write: ``PATH: cannot write (CAUSE)``.

    Parameters
    ----------
    path : path-like
        The file the user asked for (not the temporary name).
    exc : OSError
        What the system said (ENOSPC "No space left on device", EFBIG "File too large", ...).

    Returns
    -------
    HallcalInputError
        Exit status 2.
    """
    why = exc.strerror or one_line(exc) or type(exc).__name__
    return HallcalInputError(f"{os.fspath(path)}: cannot write ({why})")


def _name_max(directory: Path) -> int:
    try:
        return int(os.pathconf(directory, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def _temporary_name(target: Path) -> str:
    """A fresh hidden name beside `target`: ``.NAME.XXXXXX.tmp``, NAME cut so that the whole is
    no longer than the file system's limit (a legal 255-character target works)."""
    room = _name_max(target.parent) - 12  # "." + "." + 6 random + ".tmp"
    return f".{target.name[: max(room, 1)]}.{secrets.token_hex(3)}.tmp"


def _create_temporary(target: Path) -> Path:
    for _ in range(100):
        tmp = target.parent / _temporary_name(target)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(errno.EEXIST, "no free temporary name")


@dataclasses.dataclass
class _Staged:
    """The files of one output set, written to temporary names, moved in place together."""

    files: dict[Path, Path] = dataclasses.field(default_factory=dict)  # target -> temporary
    folders: list[Path] = dataclasses.field(default_factory=list)  # created for this set

    def add(self, target: Path, tmp: Path) -> None:
        old = self.files.pop(target, None)
        if old is not None:
            with contextlib.suppress(OSError):
                old.unlink()
        self.files[target] = tmp

    def discard(self) -> None:
        for tmp in self.files.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
        self.files.clear()
        for folder in reversed(self.folders):  # innermost last created
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if empty: a folder that holds anything else stays

    def commit(self) -> None:
        for target in self.files:  # what would make a rename fail, before the first rename
            if target.is_dir() and not target.is_symlink():
                raise write_error(target, IsADirectoryError(errno.EISDIR, "Is a directory"))
        mask = _block_interrupts()
        try:
            for target, tmp in self.files.items():
                try:
                    os.replace(tmp, target)
                except OSError as exc:
                    raise write_error(target, exc) from None
        finally:
            _restore_interrupts(mask)
        self.files.clear()


_STAGING: contextvars.ContextVar[_Staged | None] = contextvars.ContextVar(
    "hallcal_output_set", default=None
)


def _block_interrupts() -> Any:
    """Block SIGINT/SIGTERM during the renames of a set (main thread only; a no-op elsewhere)."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(
        signal, "pthread_sigmask"
    ):
        return None
    return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})


def _restore_interrupts(mask: Any) -> None:
    if mask is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


@contextlib.contextmanager
def output_set() -> Iterator[None]:
    """Make every write in the block part of one set: all files appear together, or none.

    Inside the block, :func:`atomic_write` and :func:`atomic_path` (and so every writer of
    hallcal) write to temporary names beside their targets; when the block ends normally the
    temporary files are renamed onto their targets one after the other, with interrupts held
    back, after checking that nothing is in the way. On any exception (a full disk, a file-size
    limit, Ctrl-C) every temporary file is removed, the folders made by :func:`make_folder` in
    the block are removed again when empty, and the previous outputs stay as they were,
    complete. A nested block joins the outer set.

    Yields
    ------
    None
        The block runs with the set collecting its writes.

    Examples
    --------
    >>> with output_set():  # doctest: +SKIP
    ...     write_json("b.json", bla)
    ...     with atomic_write("b.png", "wb") as f:
    ...         fig.savefig(f)
    """
    if _STAGING.get() is not None:
        yield
        return
    staged = _Staged()
    token = _STAGING.set(staged)
    try:
        yield
    except BaseException:
        staged.discard()
        raise
    finally:
        _STAGING.reset(token)
    try:
        staged.commit()
    except BaseException:
        staged.discard()
        raise


def make_folder(path: str | os.PathLike[str]) -> Path:
    """Create a folder (and its parents) for outputs; inside :func:`output_set`, a failed set
    removes the folders it created.

    Parameters
    ----------
    path : path-like
        The folder.

    Returns
    -------
    pathlib.Path
        The folder.

    Raises
    ------
    HallcalInputError
        A file is in the way, or the folder cannot be created.
    """
    p = Path(path)
    missing: list[Path] = []
    q = p
    while not q.exists() and q != q.parent:
        missing.append(q)
        q = q.parent
    if p.exists() and not p.is_dir():
        raise HallcalInputError(f"{p}: exists and is not a folder")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HallcalInputError(f"{p}: cannot create the folder ({exc.strerror or exc})") from None
    staged = _STAGING.get()
    if staged is not None:
        staged.folders.extend(reversed(missing))  # outermost first
    return p


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success move it onto `path` atomically.

    For libraries that insist on a file name (h5py). The temporary file exists (empty) when the
    block starts; its name is no longer than the file system allows (``NAME_MAX``). On any
    exception in the block the temporary file is removed and `path` is left untouched. Inside
    :func:`output_set` the move waits for the end of the set.

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
        If the directory does not exist or the file cannot be created, written or replaced
        (a full disk, a file-size limit, no permission: :func:`write_error`).
    """
    target = Path(path)
    directory = target.parent
    if not directory.is_dir():
        raise HallcalInputError(f"{target}: directory '{directory}' does not exist")
    try:
        tmp = _create_temporary(target)
    except OSError as exc:
        raise write_error(target, exc) from None
    try:
        try:
            yield tmp
            os.chmod(tmp, 0o666 & ~_umask())
        except OSError as exc:
            if exc.errno not in WRITE_ERRNOS:
                raise
            raise write_error(target, exc) from None
        staged = _STAGING.get()
        if staged is not None:
            staged.add(target, tmp)
            return
        try:
            os.replace(tmp, target)
        except OSError as exc:
            raise write_error(target, exc) from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _identity(p: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(p)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


def _real(p: Path) -> Path:
    """The path with symlinks and ``..`` resolved (a missing tail kept as written)."""
    try:
        return Path(os.path.realpath(p))
    except (OSError, ValueError):
        return Path(os.path.abspath(p))


def check_outputs(
    outputs: Iterable[str | os.PathLike[str]],
    inputs: Iterable[str | os.PathLike[str] | None] = (),
    *,
    folders: Iterable[str | os.PathLike[str]] = (),
) -> None:
    """Refuse, before any work, outputs that would destroy an input or each other.

    An output is refused when it is an input (the same file: the same inode, also through a
    symbolic or hard link, ``..`` or another spelling of the path), when two outputs are the
    same file (``bla --out b.png`` would write its Bode plot over its JSON), when a folder is
    where it goes, when one of its names is longer than the file system allows, or when an
    input lies inside an output `folder` that the command fills.

    Parameters
    ----------
    outputs : iterable of path-like
        The files the command will write.
    inputs : iterable of path-like or None
        The files it reads (None entries are skipped).
    folders : iterable of path-like
        Folders the command writes into (an input inside one is refused).

    Raises
    ------
    HallcalInputError
        One line naming the output and the input (or other output) it would overwrite.
    """
    ins = [Path(p) for p in inputs if p is not None]
    in_ids = {i: _identity(i) for i in ins}
    in_real = {i: _real(i) for i in ins}
    outs, dirs = [Path(p) for p in outputs], [Path(p) for p in folders]
    for out in outs + dirs:
        for part in out.parts:
            limit = _name_max(_nearest_folder(out))
            if len(os.fsencode(part)) > limit:
                raise HallcalInputError(
                    f"{out}: cannot write (the name '{part[:40]}...' has "
                    f"{len(os.fsencode(part))} bytes, above the limit of {limit})"
                )
    seen: dict[Path, Path] = {}
    for out in outs:
        if out.is_dir() and not out.is_symlink():
            raise HallcalInputError(f"{out}: cannot write (Is a directory)")
        ident, real = _identity(out), _real(out)
        for i in ins:
            if (ident is not None and ident == in_ids[i]) or real == in_real[i]:
                raise HallcalInputError(
                    f"{out}: is the input {i}: choose another output name (the input would "
                    "be overwritten)"
                )
        if real in seen:
            raise HallcalInputError(
                f"{out}: two outputs of this command would be this same file ({seen[real]} and "
                f"{out}): choose another output name"
            )
        seen[real] = out
    inside: dict[Path, Path] = {}  # every folder that holds an input (or is one) -> the input
    for i in ins:
        for q in (in_real[i], *in_real[i].parents):
            inside.setdefault(q, i)
    for folder in dirs:
        held = inside.get(_real(folder))
        if held is not None:
            raise HallcalInputError(
                f"{folder}: holds the input {held}, which the output could overwrite: choose "
                "another output folder"
            )


def _nearest_folder(p: Path) -> Path:
    q = p.parent
    while True:
        try:
            if q.is_dir():
                return q
        except OSError:
            pass
        if q == q.parent:
            return q
        q = q.parent


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


def existing_file(path: str | os.PathLike[str]) -> Path:
    """An input file that must exist (the readers' first check).

    Parameters
    ----------
    path : path-like
        The file.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    HallcalInputError
        It does not exist, or is not a regular file (the message names it).
    """
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
        if isinstance(value, str):
            _check_text(p, value, where)
            continue
        if isinstance(value, bool) or value is None:
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
            if isinstance(value, dict):
                for key, item in value.items():
                    _check_text(p, key, where)
                    stack.append((item, f"{where}.{key}" if where else str(key), depth + 1))
            else:
                for i, item in enumerate(value):
                    stack.append((item, f"{where}[{i}]", depth + 1))


def _check_text(p: str | os.PathLike[str], text: str, where: str) -> None:
    """Refuse a string UTF-8 cannot hold: JSON's ``"\\ud800"`` parses to a lone surrogate,
    which no output (HTML, C comments, the terminal) can write."""
    if text.isascii():
        return
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise HallcalInputError(
            f"{p}: key '{where or '(top level)'}' holds a lone UTF-16 surrogate (\\ud800 to "
            "\\udfff without its pair), not a character"
        ) from None


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
        if all(type(v) is float for v in obj) and all(map(math.isfinite, obj)):
            return list(obj)  # a table's worth of plain finite floats: nothing to convert
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
    return _read_json_raw(path)[0]


def _read_json_raw(path: str | os.PathLike[str]) -> tuple[Any, bytes]:
    """:func:`read_json`, also returning the bytes it parsed (for their SHA-256)."""
    p = existing_file(path)
    raw = _read_bytes(p, limit=MAX_JSON_BYTES, what="a JSON file")
    containers = raw.count(b"{") + raw.count(b"[")  # at least as many as the parser would make
    if containers > MAX_JSON_CONTAINERS:
        raise HallcalInputError(
            f"{p}: {containers} JSON objects and arrays, above the limit of "
            f"{MAX_JSON_CONTAINERS} (parsing them would take about {containers * 1e-7:.2g} GB)"
        )
    text = _decode_text(p, raw)
    try:
        data = json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise HallcalInputError(
            f"{p}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    except ValueError as exc:  # NaN/Infinity, integers of more than 4300 digits
        raise HallcalInputError(f"{p}: invalid JSON: {one_line(exc)}") from None
    except RecursionError:
        raise _nested_too_deeply(p) from None
    _check_parsed(p, data)
    return data, raw
