"""Text that reaches the C files: sanitized comments, literals that read back exactly, banners.

Every number the generated C holds goes through :func:`_cf` (a float literal that reads back as
the same single-precision number, refused when single precision cannot hold it) or :func:`_cu`
(an unsigned 32-bit literal); every comment text through :func:`comment_text`.
"""

from __future__ import annotations

import math
import os
import re
import textwrap
from collections.abc import Sequence

import numpy as np

from hallcal.errors import HallcalInputError

_U32 = 1 << 32
_NAME_SAFE = re.compile(r"[^A-Za-z0-9 ._+=,:()\[\]-]")
_NOT_PRINTABLE = re.compile(r"[^\x20-\x7e]")
_COMMENT_BREAKERS = (("*/", "* /"), ("/*", "/ *"), ("??", "? ?"), ("//", "/ /"))


def comment_text(text: str, *, limit: int = 80) -> str:
    """Text safe inside a C block comment on one line, its punctuation kept.

    Characters outside printable ASCII (control characters, newlines, non-ASCII) and the
    backslash become ``_``; the sequences that could end or open a comment (``*/``, ``/*``,
    ``//``) or form a trigraph (``??``) get a space in between, until none is left. So the
    result cannot end the comment, splice a line (backslash-newline), form a trigraph or open
    a nested comment, and has no newline, while "the calibration's table", "956.9 rad/s" and
    "|error| <= 3.6e-06" read as written. Truncated to ``limit`` characters (the cut cannot
    create a sequence: it only removes characters from the end).

    Parameters
    ----------
    text : str
        Any text (a message, a file name).
    limit : int, keyword-only
        Maximum length of the result [characters], ``...`` included.

    Returns
    -------
    str
        The sanitized, possibly truncated text.
    """
    out = _NOT_PRINTABLE.sub("_", str(text)).replace("\\", "_")
    while any(bad in out for bad, _ in _COMMENT_BREAKERS):
        for bad, good in _COMMENT_BREAKERS:
            out = out.replace(bad, good)
    if len(out) > limit:
        out = out[: limit - 3].rstrip("/*?") + "..."
    return out


def name_text(text: str, *, limit: int = 60) -> str:
    """What comes from outside and names something (a file name, a prefix): only
    ``A-Za-z0-9``, space and ``._+=,:()[]-`` survive, anything else becomes ``_``; truncated
    to ``limit`` characters."""
    out = _NAME_SAFE.sub("_", str(text))
    return out if len(out) <= limit else out[: limit - 3] + "..."


def _source_name(source: str | os.PathLike[str] | None) -> str:
    """The base name of the artifact's path, sanitized (never an absolute path)."""
    if source is None:
        return "(in memory)"
    name = os.path.basename(os.fspath(source).replace("\\", "/").rstrip("/")) or "(unnamed)"
    return name_text(name, limit=60)


def _f32(value: float, what: str) -> float:
    """``value`` as single precision; refuse what float cannot hold (the C would be wrong)."""
    v = float(np.float32(value))
    if not math.isfinite(v) or (v != 0.0 and abs(v) < 1e-30) or abs(v) > 1e30:
        raise HallcalInputError(
            f"the calibration's numbers do not fit single precision ({what} = {value:.3g})"
        )
    return v


def _cf(value: float, what: str = "constant") -> str:
    """A float literal that reads back as the same single-precision number."""
    v = _f32(value, what)
    s = f"{v:.9g}"
    if not any(ch in s for ch in ".e"):
        s += ".0"
    return s + "f"


def _cu(value: int) -> str:
    v = int(value)
    if not 0 <= v < _U32:
        raise ValueError(v)
    return f"{v}u"


def _c_list(values: Sequence[str], per_line: int, indent: str = "    ") -> str:
    return "\n".join(
        indent + ", ".join(values[i : i + per_line]) + "," for i in range(0, len(values), per_line)
    )


def _banner(fname: str, lines: Sequence[str]) -> str:
    body = [
        part
        for t in lines
        for part in (
            textwrap.wrap(
                comment_text(t, limit=600),
                96,
                subsequent_indent="    ",
                break_on_hyphens=False,
                break_long_words=False,
            )
            or [""]
        )
    ]
    return "/*\n" + "\n".join((" * " + t).rstrip() for t in [name_text(fname)] + body) + "\n */\n"


def _version() -> str:
    from hallcal._version import __version__

    return name_text(__version__, limit=20)


def _speed_text(speed: float, sample_time: float) -> str:
    """`` (= X rad/s)`` when the sample time is known (the artifact's setup), else empty."""
    return f" (= {speed / sample_time:.4g} rad/s)" if sample_time != 1.0 else ""


def _int_sub(var: str, value: int) -> str:
    """``var - value`` for 0 < value <= 2^31 without a literal outside int32."""
    if value >= 2**31:
        return f"({var} - 2147483647) - 1"
    return f"{var} - {value}"


def _int_add(var: str, value: int) -> str:
    if value >= 2**31:
        return f"({var} + 2147483647) + 1"
    return f"{var} + {value}"


def _f32_down(v: float) -> np.float32:
    x = np.float32(v)
    return x if float(x) <= v else np.nextafter(x, np.float32(-np.inf))


def _f32_up(v: float) -> np.float32:
    x = np.float32(v)
    return x if float(x) >= v else np.nextafter(x, np.float32(np.inf))


def _bits(x: np.float32) -> int:
    return int(np.array(x, dtype=np.float32).view(np.uint32))
