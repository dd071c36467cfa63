"""Units of angle errors and the text helpers shared by the CLI, the report and the fleet page.

One place for how hallcal writes a number: an angle error in the user's units
(:class:`AngleUnit`), a number that may be missing (:func:`number`), integer ranges
(:func:`ranges`), a transfer function G(s) (:func:`tf_text`), a message in one line
(:func:`one_line`) and HTML escaping (:func:`esc`). Standard library only, so that every layer
(and the CLI's start-up) can import it.
"""

from __future__ import annotations

import enum
import html
import math
from collections.abc import Iterable, Sequence
from typing import Any

from hallcal.errors import HallcalInputError

__all__ = [
    "MISSING",
    "AngleUnit",
    "esc",
    "finite",
    "number",
    "one_line",
    "polynomial_text",
    "ranges",
    "tf_text",
]

#: How the HTML pages write a value that is missing or not finite (an en dash).
MISSING = "–"


class AngleUnit(enum.StrEnum):
    """Units of an angle error given in mechanical rad (``--units`` of the CLI).

    The value is the spelling the CLI, the API (``Calibration.report(units=...)``) and the
    report accept. An electrical angle is the mechanical one times the pole pairs n_m.
    """

    RAD = "rad"
    MRAD = "mrad"
    DEG = "deg"
    ELECTRICAL_DEG = "electrical-deg"

    @classmethod
    def parse(cls, value: str | AngleUnit) -> AngleUnit:
        """The unit named ``value``; an unknown name is an error naming the valid ones.

        Raises
        ------
        HallcalInputError
            ``value`` is not one of the members' values.
        """
        try:
            return cls(value)
        except ValueError:
            valid = ", ".join(repr(u.value) for u in cls)
            raise HallcalInputError(f"units: {value!r} is not one of {valid}") from None

    @property
    def label(self) -> str:
        """The unit after a number: ``mrad``, ``electrical deg``."""
        return _LABELS[self]

    @property
    def description(self) -> str:
        """The unit in a sentence: ``mechanical mrad``, ``electrical degrees``."""
        return _DESCRIPTIONS[self]

    def convert(self, x: Any, pole_pairs: int = 1) -> Any:
        """``x`` [rad, mechanical] in this unit.

        Parameters
        ----------
        x : float or ndarray
            Angle [rad, mechanical].
        pole_pairs : int
            n_m, for electrical degrees (electrical angle = n_m x mechanical angle).

        Returns
        -------
        float or ndarray
            ``x`` in this unit.
        """
        if self is AngleUnit.RAD:
            return x
        if self is AngleUnit.MRAD:
            return 1e3 * x
        deg = x * (180.0 / math.pi)
        return deg * pole_pairs if self is AngleUnit.ELECTRICAL_DEG else deg

    def text(self, x: float | None, pole_pairs: int = 1, *, page: bool = False) -> str:
        """``x`` [rad, mechanical] as text with the unit.

        Parameters
        ----------
        x : float or None
            Angle error [rad, mechanical].
        pole_pairs : int
            n_m, for electrical degrees.
        page : bool
            The HTML pages' style (``1.234 mrad``, :data:`MISSING` for a missing value) instead
            of the terminal's (``1.2345 mrad``, ``-``). rad get three more decimals.

        Returns
        -------
        str
            The number and the unit's :attr:`label`.
        """
        if x is None or not math.isfinite(x):
            return MISSING if page else "-"
        digits = (3 if page else 4) + (3 if self is AngleUnit.RAD else 0)
        return f"{self.convert(float(x), pole_pairs):.{digits}f} {self.label}"


_LABELS = {
    AngleUnit.RAD: "rad",
    AngleUnit.MRAD: "mrad",
    AngleUnit.DEG: "deg",
    AngleUnit.ELECTRICAL_DEG: "electrical deg",
}
_DESCRIPTIONS = {
    AngleUnit.RAD: "mechanical rad",
    AngleUnit.MRAD: "mechanical mrad",
    AngleUnit.DEG: "mechanical degrees",
    AngleUnit.ELECTRICAL_DEG: "electrical degrees",
}


def one_line(text: object) -> str:
    """A message (or an exception's text) in one line: runs of white space become one space.

    Parameters
    ----------
    text : object
        The message or exception.

    Returns
    -------
    str
        Its text in one line.
    """
    return " ".join(str(text).split())


def esc(x: Any) -> str:
    """``x`` as HTML text, quotes escaped too.

    Parameters
    ----------
    x : object
        Anything; its ``str``.

    Returns
    -------
    str
        The escaped text.
    """
    return html.escape(str(x), quote=True)


def finite(x: Any) -> float | None:
    """``float(x)``, or None for None, a non-number or a non-finite value.

    Parameters
    ----------
    x : object
        A value read from a result or a summary row.

    Returns
    -------
    float or None
        The finite number, or None.
    """
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def number(x: Any, fmt: str = ".4g", *, missing: str = MISSING) -> str:
    """``format(x, fmt)``, or ``missing`` for None, a non-number or a non-finite value.

    Parameters
    ----------
    x : object
        The value.
    fmt : str
        A format specification (``".4g"``).
    missing : str, keyword-only
        The text of a missing value.

    Returns
    -------
    str
        The text.
    """
    v = finite(x)
    return missing if v is None else format(v, fmt)


def ranges(values: Iterable[Any], *, to: str = "..", sep: str = ", ") -> str:
    """[1, 2, 3, 5, 33] -> '1..3, 5, 33' (three or more consecutive integers as a range).

    Parameters
    ----------
    values : iterable of int
        The integers (harmonic orders), in any order.
    to : str, keyword-only
        Between the ends of a range.
    sep : str, keyword-only
        Between the items.

    Returns
    -------
    str
        The sorted integers, runs of three or more as ranges.
    """
    v = sorted(int(x) for x in values)
    out, i = [], 0
    while i < len(v):
        j = i
        while j + 1 < len(v) and v[j + 1] == v[j] + 1:
            j += 1
        out.append(f"{v[i]}{to}{v[j]}" if j > i + 1 else sep.join(map(str, v[i : j + 1])))
        i = j + 1
    return sep.join(out)


def polynomial_text(coefficients: Sequence[float], var: str = "s") -> str:
    """A polynomial in descending powers as people write it: ``s^3 + 632.6 s^2 + 2702 s``.

    Parameters
    ----------
    coefficients : sequence of float
        Coefficients in descending powers of ``var`` (4 significant digits are shown).
    var : str
        The variable's name (``"s"`` or ``"q"``).

    Returns
    -------
    str
        The text; zero terms left out, a unit coefficient not written, "0" for none.
    """
    n = len(coefficients) - 1
    terms = []
    for i, a in enumerate(coefficients):
        if a == 0.0:
            continue
        p = n - i
        power = "" if p == 0 else (var if p == 1 else f"{var}^{p}")
        coef = f"{a:.4g}"
        terms.append(coef if not power else (power if coef == "1" else f"{coef} {power}"))
    return " + ".join(terms).replace("+ -", "- ") or "0"


def tf_text(num: Sequence[float], den: Sequence[float], delay: float, *, page: bool = False) -> str:
    """A continuous transfer function G(s) = num / den with input delay [s] as text.

    Parameters
    ----------
    num, den : sequence of float
        Coefficients of the numerator and denominator in descending powers of s.
    delay : float
        Input delay [s].
    page : bool, keyword-only
        The report page's form instead of the terminal's.

    Returns
    -------
    str
        The terminal writes ``G(s) = N / (D), input delay 0.5 ms``; the report's page
        (``page=True``) writes ``(N) / (D) · exp(-0.0005 s)``.
    """
    n, d = polynomial_text(num), polynomial_text(den)
    if page:
        return f"({n}) / ({d})" + (f" · exp(-{delay:.4g} s)" if delay else "")
    return f"G(s) = {n} / ({d})" + (f", input delay {1e3 * delay:.4g} ms" if delay > 0 else "")
