"""Numeric design of the firmware's tables and arithmetic (no I/O; :mod:`hallcal.output.codegen`
writes the C, :mod:`hallcal.output.firmware` reads the artifact and assembles the design).

* The correction table (:class:`CorrectionTable`, :func:`fit_table`, :func:`choose_table`)
  replaces the artifact's M nodes ``(y_hat_i, eta_i)`` (piecewise-linear, eq. (f_final)) by a
  uniform piecewise quadratic ``eta(x) = T_i (1 - f) + T_(i+1) f + c_i f (1 - f)`` with
  ``x = 2 pi (i + f) / M``, ``T`` in int16 and ``c`` in int8, both in power-of-two fractions of a
  turn. The values are fitted by least squares to the artifact's own interpolant (what
  ``hallcal reconstruct`` computes), and the largest difference to it is computed exactly (both
  are piecewise polynomials: their difference is checked at every breakpoint and at every
  vertex). The size is M = n_m 2^k intervals (a power of two per electrical turn, so that the
  firmware finds the interval from f_init's turn and electrical angle with shifts).
* Single-precision arithmetic of the power-up decoder: linear minimax seeds of 1/x and
  1/sqrt(x) (Muller, *Elementary Functions*, 3rd ed., ch. 5), the Newton steps that take them
  below single precision, a polynomial of 2^-f, and the range of the decoder's tangent metric.

Units: angles in rad unless a name says turns (1 turn = 2 pi rad).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.sensor.absolute import PowerUpDecoder, gram_at, tangent_terms
from hallcal.sensor.lut import LUT

__all__ = [
    "F32_TARGET",
    "MAX_LINEAR_POINTS",
    "MAX_TABLE_POINTS",
    "TABLE_BYTES_TARGET",
    "TABLE_EVAL_CYCLES",
    "CorrectionTable",
    "choose_table",
    "exp2_poly",
    "fit_table",
    "newton_seed",
    "newton_steps",
    "table_error",
    "table_sizes",
    "tangent_range",
]

#: Largest table: M = n_m 2^k <= this many intervals.
MAX_TABLE_POINTS = 16384
#: Largest linear table the exporter chooses by itself (int16: 4 kB).
MAX_LINEAR_POINTS = 2048
_FIT_PER_INTERVAL = 8  # least-squares points per table interval (besides the artifact's nodes)
#: What the decoder's reciprocals and its 2^-x reach (relative): single precision.
F32_TARGET = 2.0**-25


@dataclass(frozen=True)
class CorrectionTable:
    """The uniform piecewise-quadratic correction table of the firmware.

    ``eta(x) = (T[i] (1 - f) + T[i+1] f + 2^k C[i] f (1 - f)) 2^-s`` turns, with
    ``x / (2 pi) = (i + f) / M`` turns, ``0 <= f < 1``, indices modulo M (wrap-around). A linear
    table has no curvatures (C = 0).

    Attributes
    ----------
    points : int
        M = n_m 2^k, intervals per revolution.
    quadratic : bool
        Whether the table has curvatures (piecewise quadratic) or not (piecewise linear).
    values : ndarray of int16, shape (M,)
        T, in units of 2^-s turn.
    curvature : ndarray of int8, shape (M,)
        C, in units of 2^(k - s) turn (zeros for a linear table).
    shift : int
        s: one unit of T is 2^-s turn.
    curvature_shift : int
        k: one unit of C is 2^k units of T.
    error : float
        Largest |eta_table - eta_artifact| over the revolution [rad], exact (in double).
    rms_error : float
        RMS of that difference over the revolution [rad].
    """

    points: int
    quadratic: bool
    values: NDArray[np.int16]
    curvature: NDArray[np.int8]
    shift: int
    curvature_shift: int
    error: float
    rms_error: float

    @property
    def nbytes(self) -> int:
        """Bytes of the table(s) in flash."""
        return 3 * self.points if self.quadratic else 2 * self.points

    @property
    def lsb_rad(self) -> float:
        """One unit of T [rad]."""
        return TWO_PI * 2.0**-self.shift

    def correction(self, y: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """eta of the table at mechanical angles ``y`` [rad] (double precision)."""
        pos = np.mod(np.asarray(y, dtype=np.float64), TWO_PI) * (self.points / TWO_PI)
        i = np.minimum(np.floor(pos).astype(np.int64), self.points - 1)
        f = pos - i
        t = self.values.astype(np.float64)
        c = self.curvature.astype(np.float64) * 2.0**self.curvature_shift
        j = (i + 1) % self.points
        return (t[i] * (1.0 - f) + t[j] * f + c[i] * f * (1.0 - f)) * self.lsb_rad


# --------------------------------------------------------------------------------------------
# The table
# --------------------------------------------------------------------------------------------


def _reference_breaks(lut: LUT) -> tuple[NDArray, NDArray]:
    """Breakpoints of the artifact's periodic interpolant on [0, 2 pi] and its values there."""
    x = np.sort(np.mod(lut.y_hat, TWO_PI))
    x = np.unique(np.concatenate([[0.0], x, [TWO_PI]]))
    return x, lut.correction(x)


def table_error(table: CorrectionTable, lut: LUT) -> tuple[float, float]:
    """Exact max and RMS of |table - artifact interpolant| over the revolution [rad].

    On every piece between consecutive breakpoints of both, the difference is a quadratic: its
    largest magnitude is at an end or at its vertex, which are all evaluated.

    Parameters
    ----------
    table : CorrectionTable
        The firmware's table.
    lut : LUT
        The artifact's table (the reference).

    Returns
    -------
    (float, float)
        Largest and RMS difference [rad].
    """
    m = table.points
    xb, _ = _reference_breaks(lut)
    grid = TWO_PI * np.arange(m + 1) / m
    pts = np.unique(np.concatenate([xb, grid]))
    lo, hi = pts[:-1], pts[1:]
    mid = 0.5 * (lo + hi)
    # on (lo, hi): table quadratic of interval i, reference linear with slope s
    i = np.minimum(np.floor(mid * m / TWO_PI).astype(np.int64), m - 1)
    h = TWO_PI / m
    lsb = table.lsb_rad
    t0 = table.values[i].astype(np.float64) * lsb
    t1 = table.values[(i + 1) % m].astype(np.float64) * lsb
    c = table.curvature[i].astype(np.float64) * 2.0**table.curvature_shift * lsb
    ref_lo, ref_hi = lut.correction(lo), lut.correction(hi)
    slope = (ref_hi - ref_lo) / (hi - lo)
    # d(x) = t0 (1 - f) + t1 f + c f (1 - f) - ref(x); d'(x) = 0 at f = (1 + (t1 - t0 - s h)/c)/2
    with np.errstate(divide="ignore", invalid="ignore"):
        fv = 0.5 * (1.0 + (t1 - t0 - slope * h) / c)
    xv = grid[i] + fv * h
    inside = np.isfinite(fv) & (xv > lo) & (xv < hi)
    cand = np.concatenate([pts, xv[inside]])
    diff = table.correction(cand) - lut.correction(cand)
    dense = np.linspace(0.0, TWO_PI, 16 * max(m, lut.points), endpoint=False)
    d2 = table.correction(dense) - lut.correction(dense)
    return float(np.max(np.abs(diff))), float(np.sqrt(np.mean(d2**2)))


def fit_table(lut: LUT, points: int, *, quadratic: bool = True) -> CorrectionTable:
    """Fit the uniform table of ``points`` intervals to a LUT.

    Least squares (values, and curvatures when ``quadratic``) on the artifact's breakpoints and
    ``_FIT_PER_INTERVAL`` points per interval; then the values are rounded to int16 units of a
    power-of-two fraction of a turn, the curvatures refitted to the rounded values and rounded
    to int8. The returned error is exact for the rounded table.

    Parameters
    ----------
    lut : LUT
        The artifact's table (reference).
    points : int
        M, intervals per revolution, 64..65536.
    quadratic : bool, keyword-only
        Piecewise quadratic (values and curvatures) or piecewise linear (values only).

    Returns
    -------
    CorrectionTable
    """
    m = int(points)
    if not 64 <= m <= 65536:
        raise ValueError("points must be in 64..65536")
    h = TWO_PI / m
    xb, _ = _reference_breaks(lut)
    grid = h * np.arange(m * _FIT_PER_INTERVAL) / _FIT_PER_INTERVAL
    x = np.unique(np.concatenate([xb[:-1], grid]))
    ref = lut.correction(x)
    pos = x / h
    i = np.minimum(np.floor(pos).astype(np.int64), m - 1)
    f = pos - i
    g = f * (1.0 - f)
    rows = np.arange(x.size)
    cols = [i, (i + 1) % m] + ([m + i] if quadratic else [])
    vals = [1.0 - f, f] + ([g] if quadratic else [])
    A = sparse.csr_matrix(
        (np.concatenate(vals), (np.tile(rows, len(cols)), np.concatenate(cols))),
        shape=(x.size, (2 if quadratic else 1) * m),
    )
    sol = sparse_linalg.spsolve((A.T @ A).tocsc(), A.T @ ref)
    values = sol[:m] / TWO_PI  # turns
    # int16 values: the largest power-of-two unit 2^-s turn with |T| <= 32767
    vmax = float(np.max(np.abs(values))) or 2.0**-40
    shift = min(int(math.floor(math.log2(32767.0 / vmax))), 47)
    q = np.round(values * 2.0**shift)
    if np.max(np.abs(q)) > 32767:  # log2 rounding at an exact power of two
        shift -= 1
        q = np.round(values * 2.0**shift)
    cshift = 0
    cq = np.zeros(m)
    if quadratic:
        # curvatures refitted per interval to the rounded values: c_i = <g, r> / <g, g>
        resid = ref / TWO_PI * 2.0**shift - (q[i] * (1.0 - f) + q[(i + 1) % m] * f)
        num = np.bincount(i, weights=g * resid, minlength=m)
        den = np.bincount(i, weights=g * g, minlength=m)
        c = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
        cmax = float(np.max(np.abs(c)))
        cshift = max(0, int(math.ceil(math.log2(cmax / 127.0)))) if cmax > 127.0 else 0
        cq = np.clip(np.round(c / 2.0**cshift), -127, 127)
    table = CorrectionTable(
        m, quadratic, q.astype(np.int16), cq.astype(np.int8), shift, cshift, math.inf, math.inf
    )
    err, rms = table_error(table, lut)
    return CorrectionTable(m, quadratic, table.values, table.curvature, shift, cshift, err, rms)


def table_sizes(pole_pairs: int) -> list[int]:
    """Candidate table sizes M = n_m 2^k (64 <= M <= :data:`MAX_TABLE_POINTS`), ascending.

    Parameters
    ----------
    pole_pairs : int
        n_m.

    Returns
    -------
    list of int
        The sizes M [table points per revolution] (empty when n_m exceeds the maximum).
    """
    out = []
    m = int(pole_pairs)
    while m <= MAX_TABLE_POINTS:
        if m >= 64:
            out.append(m)
        m *= 2
    return out


#: Table bytes the exporter aims at (flash of a small MCU's budget for the table).
TABLE_BYTES_TARGET = 4096
#: Estimated Cortex-M4 cycles of eta from the table in the float variant's sample path (measured
#: with GCC 12 -O2: two int16 loads, a multiply-add and one conversion; a quadratic table adds
#: the int8 load, f (1 - f) and its multiply-add).
TABLE_EVAL_CYCLES = {False: 9, True: 16}


def choose_table(lut: LUT, budget: float) -> CorrectionTable:
    """The table within the budget and :data:`TABLE_BYTES_TARGET` whose evaluation costs the
    fewest estimated cycles (:data:`TABLE_EVAL_CYCLES`: linear, one load and a multiply-add
    less per sample, whenever one fits), the smaller one between equals; when none fits in the
    bytes, the smallest quadratic table within the budget (or the closest to it), each size
    ascending from 256.

    Parameters
    ----------
    lut : LUT
        The artifact's table (the reference).
    budget : float
        Largest difference to it the table may have [rad].

    Returns
    -------
    CorrectionTable
    """
    sizes = [m for m in table_sizes(lut.pole_pairs) if m >= min(256, MAX_TABLE_POINTS)]
    fitting: list[CorrectionTable] = []
    for quadratic in (False, True):
        for m in sizes:
            nbytes = (3 if quadratic else 2) * m
            if nbytes > TABLE_BYTES_TARGET or (not quadratic and m > MAX_LINEAR_POINTS):
                break
            table = fit_table(lut, m, quadratic=quadratic)
            if table.error <= budget:
                fitting.append(table)
                break  # the smallest of this kind
    if fitting:
        return min(fitting, key=lambda t: (TABLE_EVAL_CYCLES[t.quadratic], t.nbytes))
    best = None
    for m in sizes:
        table = fit_table(lut, m, quadratic=True)
        if table.error <= budget:
            return table
        if best is None or table.error < best.error:
            best = table
    assert best is not None
    return best


# --------------------------------------------------------------------------------------------
# Single-precision arithmetic of the power-up decoder
# --------------------------------------------------------------------------------------------


def newton_seed(lo: float, hi: float, *, root: bool = False) -> tuple[float, float, float]:
    """Linear minimax seed ``c0 - c1 x`` of 1/x (or of 1/sqrt(x) with ``root``) on [lo, hi]
    (relative error) and that error. For 1/sqrt(x) the error ``sqrt(x) (c0 - c1 x) - 1``
    equioscillates at lo, hi and its maximum ``x* = c0 / (3 c1)``: equal values at the ends give
    ``c0 / c1 = lo + sqrt(lo hi) + hi``, opposite ones at an end and at x* fix c1.

    Parameters
    ----------
    lo, hi : float
        The window of x, 0 < lo < hi.
    root : bool, keyword-only
        Seed 1/sqrt(x) instead of 1/x.

    Returns
    -------
    (float, float, float)
        c0, c1 and the largest relative error.
    """
    if not root:
        c1 = 8.0 / (4.0 * lo * hi + (lo + hi) ** 2)
        c0 = c1 * (lo + hi)
        return c0, c1, abs(1.0 - c1 * lo * hi)
    ratio = lo + math.sqrt(lo * hi) + hi
    xs = ratio / 3.0
    c1 = 2.0 / (math.sqrt(lo) * (ratio - lo) + 2.0 * xs**1.5)
    return c1 * ratio, c1, c1 * 2.0 * xs**1.5 - 1.0


def exp2_poly(target: float = 2.0**-24) -> tuple[NDArray[np.float64], float]:
    """Polynomial of 2^-f on [0, 1] (ascending powers) with the fewest terms whose relative error
    is within ``target``: Chebyshev interpolation (within a factor 2 of minimax), the error
    measured on a dense grid.

    Parameters
    ----------
    target : float
        Largest relative error allowed (default single precision, 2^-24).

    Returns
    -------
    (ndarray, float)
        Coefficients in ascending powers of f, and the measured largest relative error.
    """
    from numpy.polynomial import Chebyshev

    x = np.linspace(0.0, 1.0, 100_001)
    y = 2.0**-x
    for deg in range(4, 10):
        poly = Chebyshev.interpolate(lambda t: 2.0**-t, deg, domain=[0.0, 1.0])
        coef = np.asarray(poly.convert(kind=np.polynomial.Polynomial).coef, dtype=np.float64)
        err = float(np.max(np.abs(np.polynomial.polynomial.polyval(x, coef) / y - 1.0)))
        if err <= target:
            break
    return coef, err


def newton_steps(e0: float, square: float, limit: int = 6) -> tuple[int, float]:
    """Newton steps from a relative error e0 until below single precision; each step takes e to
    ``square e^2`` (plus the cube term for the reciprocal square root, covered by ``square``).

    Parameters
    ----------
    e0 : float
        Relative error of the seed.
    square : float
        Factor of e^2 per step (1 for 1/x, 1.5 + e0 for 1/sqrt(x)).
    limit : int
        Most steps.

    Returns
    -------
    (int, float)
        Steps and the relative error after them.
    """
    steps, e = 0, e0
    while e > F32_TARGET and steps < limit:
        e = square * e * e
        steps += 1
    return steps, e


def tangent_range(dec: PowerUpDecoder, sigma: float, A, B, C) -> tuple[float, float]:
    """Smallest and largest tt = t' S t (sigma units) over all table positions: 16 points per
    interval and both ends (tt is smooth within an interval: a quadratic in the fraction times
    trigonometric terms of the angle, which moves by 2 pi / L over it).

    Parameters
    ----------
    dec : PowerUpDecoder
        The decoder (tables R, Z on its grid).
    sigma : float
        Noise sigma the lengths are divided by (artifact unit).
    A, B, C :
        The metric's Gram terms in sigma units (2 x 2, 2, scalar).

    Returns
    -------
    (float, float)
        Smallest and largest tt.
    """
    L, M = dec.grid, dec.table_size
    R = dec.radius / sigma
    Z = dec.zero / sigma
    sub = 16
    pos = np.arange(M * sub + 1) / sub
    i = np.minimum(np.floor(pos).astype(np.int64), M - 1)
    f = pos - i
    i1 = np.where(i == M - 1, 0, i + 1)
    k = L / TWO_PI
    Rj = R[i] + f * (R[i1] - R[i])
    dR = (R[i1] - R[i]) * k
    dZ = (Z[i1] - Z[i]) * k
    psi = TWO_PI * pos / L
    g = gram_at(A, B, np.cos(psi), np.sin(psi))
    _, _, tt = tangent_terms(dR, Rj, dZ, (g["guu"], g["gvv"], g["guv"], g["gun"], g["gvn"], C))
    return float(np.min(tt)), float(np.max(tt))
