"""Text that reaches the C files: sanitized comments, literals that read back exactly, banners.

Every number the generated C holds goes through :func:`_cf` (a float literal that reads back as
the same single-precision number, refused when single precision cannot hold it) or :func:`_cu`
(an unsigned 32-bit literal); every comment text through :func:`comment_text`.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence

import numpy as np

from hallcal.errors import HallcalInputError

_U32 = 1 << 32
_COMMENT_SAFE = re.compile(r"[^A-Za-z0-9 ._+=,:()\[\]-]")


def comment_text(text: str, *, limit: int = 80) -> str:
    """Text safe inside a C block comment on one line.

    Only ``A-Za-z0-9``, space and ``._+=,:()[]-`` survive; anything else (``*``, ``/``, ``\\``,
    ``?``, quotes, control characters, non-ASCII) becomes ``_``. So the result cannot end the
    comment (``*/``), splice a line (backslash-newline), form a trigraph (``??/``) or open a
    nested comment, and has no newline. Truncated to ``limit`` characters.

    Parameters
    ----------
    text : str
        Any text (a file name, a message).
    limit : int, keyword-only
        Maximum length of the result [characters], ``...`` included.

    Returns
    -------
    str
        The sanitized, possibly truncated text.
    """
    out = _COMMENT_SAFE.sub("_", str(text))
    return out if len(out) <= limit else out[: limit - 3] + "..."


def _source_name(source: str | os.PathLike[str] | None) -> str:
    """The base name of the artifact's path, sanitized (never an absolute path)."""
    if source is None:
        return "(in memory)"
    name = os.path.basename(os.fspath(source).replace("\\", "/").rstrip("/")) or "(unnamed)"
    return comment_text(name, limit=60)


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
    body = [comment_text(t, limit=100) for t in lines]
    return (
        "/*\n" + "\n".join((" * " + t).rstrip() for t in [comment_text(fname)] + body) + "\n */\n"
    )


def _version() -> str:
    from hallcal._version import __version__

    return comment_text(__version__, limit=20)


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
