"""Numeric design of the generated firmware: the lean table, plausibility windows, error budget.

:mod:`hallcal.output.codegen` writes C; this module decides the numbers it writes, so that they
can be checked here without a C compiler:

* :func:`design_firmware` reads a calibration artifact (checked by the one validator,
  :func:`hallcal.io.validate_artifact`) and returns a :class:`FirmwareDesign`:
  the correction table resampled to a uniform grid over one mechanical revolution, the
  plausibility windows of the samples, the step limit and the error budget.
* The correction table (:class:`CorrectionTable`) replaces the artifact's M nodes
  ``(y_hat_i, eta_i)`` (piecewise-linear, eq. (f_final)) by a uniform piecewise quadratic:
  ``eta(x) = T_i (1 - f) + T_(i+1) f + c_i f (1 - f)`` with ``x = 2 pi (i + f) / M``, ``T`` in
  int16 and ``c`` in int8, both in power-of-two fractions of a turn. The values are fitted by
  least squares to the artifact's own interpolant (what ``hallcal reconstruct`` computes), and the
  largest difference to it is computed exactly (both are piecewise polynomials: their difference
  is checked at every breakpoint and at every vertex). The size is M = n_m 2^k intervals (a
  power of two per electrical turn, so that the firmware finds the interval from f_init's turn
  and electrical angle with shifts); the table is the cheapest whose difference is within the
  budget: a tenth of the calibration's noise floor (so the table
  adds at most 0.5 % to the RMS error in quadrature), and never more than 1e-5 rad.
* Plausibility (:class:`Plausibility`, :mod:`hallcal.output.plausibility`): the channel
  ranges, the alpha/beta radius window, the consistency window along the projection's null
  vector, and the step rule with its fault count.

Units: angles in rad unless a name says turns (1 turn = 2 pi rad); "electrical" angles are
n_m times the mechanical ones. Hall signals are in the artifact's unit.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from numpy.typing import NDArray

from hallcal.errors import HallcalInputError
from hallcal.io.artifact import ArtifactData, validate_artifact
from hallcal.output.plausibility import (
    DEFAULT_SPEED,
    Plausibility,
    _plausibility,
)
from hallcal.sensor.absolute import (
    GRID_CHOICES,
    IdentifiabilityReport,
    PowerUpDecoder,
)
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT

__all__ = [
    "DEFAULT_BUDGET",
    "DEFAULT_FAULT_AFTER",
    "DEFAULT_SPEED",
    "DEFAULT_TOLERANCE",
    "table_sizes",
    "MAX_TABLE_POINTS",
    "CorrectionTable",
    "FirmwareDesign",
    "Plausibility",
    "PowerUpCode",
    "PowerUpFirmware",
    "design_firmware",
    "design_powerup",
    "fit_table",
]

TWO_PI = 2.0 * math.pi
#: Largest table: M = n_m 2^k <= this many intervals.
MAX_TABLE_POINTS = 16384
#: Largest linear table the exporter chooses by itself (int16: 4 kB).
MAX_LINEAR_POINTS = 2048
#: Budget for the table's difference to the artifact's interpolant [rad] when the artifact
#: states no noise floor.
DEFAULT_BUDGET = 1e-6
#: Budget never above this [rad] (the acceptance bound of the firmware against Python).
MAX_BUDGET = 1e-5
#: Fraction of the noise floor the table may use.
BUDGET_FRACTION = 0.1
#: Relative widening of the calibrated amplitude windows (gain and magnet drift).
DEFAULT_TOLERANCE = 0.25
#: Consecutive rejected samples after which the state flags a fault.
DEFAULT_FAULT_AFTER = 8
_FIT_PER_INTERVAL = 8  # least-squares points per table interval (besides the artifact's nodes)


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


@dataclass(frozen=True)
class FirmwareDesign:
    """Everything the generated C needs, in double precision.

    Attributes
    ----------
    pole_pairs : int
    projection : ndarray, shape (2, 3)
    offset : ndarray, shape (3,)
    rejects_common_mode : bool
        Whether each row of the projection sums to zero (then the firmware rejects a common
        mode exactly).
    lut : LUT
        The artifact's table (the reference: ``hallcal reconstruct``).
    table : CorrectionTable
    plausibility : Plausibility
    noise_floor : float or None
        RMS angle error the Hall noise causes [rad], from the artifact.
    budget : float
        What the table may differ from the artifact's interpolant [rad].
    sample_time : float
        From the artifact's setup [s] (1.0: time in samples).
    sha256 : str
        Of the artifact's canonical JSON.
    messages : tuple of str
    flux : FluxModel or None
        The artifact's flux model (the power-up decoder's tables come from it).
    """

    pole_pairs: int
    projection: NDArray[np.float64]
    offset: NDArray[np.float64]
    rejects_common_mode: bool
    lut: LUT
    table: CorrectionTable
    plausibility: Plausibility
    noise_floor: float | None
    budget: float
    sample_time: float
    sha256: str
    messages: tuple[str, ...] = ()
    flux: FluxModel | None = None

    @property
    def step_rad_per_sample(self) -> float:
        """The step limit as a mechanical angle per sample [rad]."""
        return self.plausibility.step_limit * TWO_PI / self.pole_pairs


# --------------------------------------------------------------------------------------------
# Reading the artifact
# --------------------------------------------------------------------------------------------


def _bad(source: str, key: str, why: str) -> HallcalInputError:
    return HallcalInputError(f"{source}: key '{key}' {why}")


def _checked(artifact: Mapping | ArtifactData, source: str) -> ArtifactData:
    """The artifact as the one validator (:func:`hallcal.io.validate_artifact`) passed it."""
    if isinstance(artifact, ArtifactData):
        return artifact
    return validate_artifact(artifact, source)


def _lut(art: ArtifactData, source: str) -> LUT:
    """The artifact's table; the firmware keeps y_star within half a turn of f_init's
    revolution, so it takes corrections below pi/2 only (the validator allows up to pi)."""
    if np.max(np.abs(art.eta)) >= math.pi / 2:
        raise _bad(
            source, "lut.eta", "has corrections of pi/2 rad or more (the firmware takes less)"
        )
    return art.lut()


def _noise_floor(diag: Mapping[str, Any]) -> float | None:
    """The calibration's noise floor [rad] (closed loop, or the constant-speed estimate)."""
    value = diag.get("noise_floor")
    if value is None and isinstance(diag.get("constant_speed"), Mapping):
        value = diag["constant_speed"].get("angle_noise_floor")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    value = float(value)
    return value if math.isfinite(value) and 0.0 < value < 1.0 else None


# --------------------------------------------------------------------------------------------
# The table
# --------------------------------------------------------------------------------------------


def _reference_breaks(lut: LUT) -> tuple[NDArray, NDArray]:
    """Breakpoints of the artifact's periodic interpolant on [0, 2 pi] and its values there."""
    x = np.sort(np.mod(lut.y_hat, TWO_PI))
    x = np.unique(np.concatenate([[0.0], x, [TWO_PI]]))
    return x, lut.correction(x)


def _table_error(table: CorrectionTable, lut: LUT) -> tuple[float, float]:
    """Exact max and RMS of |table - artifact interpolant| over the revolution [rad].

    On every piece between consecutive breakpoints of both, the difference is a quadratic: its
    largest magnitude is at an end or at its vertex, which are all evaluated.
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
    err, rms = _table_error(table, lut)
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


def _choose_table(lut: LUT, budget: float) -> CorrectionTable:
    """The table within the budget and :data:`TABLE_BYTES_TARGET` whose evaluation costs the
    fewest estimated cycles (:data:`TABLE_EVAL_CYCLES`: linear, one load and a multiply-add
    less per sample, whenever one fits), the smaller one between equals; when none fits in the
    bytes, the smallest quadratic table within the budget (or the closest to it), each size
    ascending from 256."""
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
# The design
# --------------------------------------------------------------------------------------------


def _check_options(tolerance: float, fault_after: int, max_speed: float | None) -> None:
    if isinstance(tolerance, bool) or not (0.0 <= float(tolerance) <= 0.9):
        raise HallcalInputError(f"tolerance must be in [0, 0.9], got {tolerance!r}")
    if (
        isinstance(fault_after, bool)
        or not isinstance(fault_after, int)
        or not (4 <= fault_after <= 1000)
    ):
        raise HallcalInputError(f"fault_after must be an integer in 4..1000, got {fault_after!r}")
    if max_speed is not None and not (math.isfinite(max_speed) and max_speed > 0.0):
        raise HallcalInputError(f"max_speed must be a positive number, got {max_speed!r}")


def _table(lut: LUT, table_points: int | None, budget: float) -> tuple[CorrectionTable, list[str]]:
    """The table of ``table_points`` intervals, or the cheapest within the budget; and what to
    say about its size or its error."""
    n = lut.pole_pairs
    if table_points is not None:
        if (
            isinstance(table_points, bool)
            or not isinstance(table_points, int)
            or table_points not in table_sizes(n)
        ):
            raise HallcalInputError(
                f"table_points must be n_m 2^k in 64..{MAX_TABLE_POINTS} ({n} 2^k here), "
                f"got {table_points!r}"
            )
        table = fit_table(lut, table_points, quadratic=True)
        if table.error > budget:
            return table, [
                f"table of {table_points} points differs by {table.error:.2g} rad from the "
                f"calibration, more than the budget {budget:.2g} rad"
            ]
        return table, []
    table = _choose_table(lut, budget)
    if table.error > budget:
        return table, [
            f"even {table.points} points differ by {table.error:.2g} rad from the "
            f"calibration, more than the budget {budget:.2g} rad"
        ]
    if table.nbytes > 4096:
        return table, [
            f"the budget {budget:.2g} rad needs {table.points} points ({table.nbytes} bytes)"
        ]
    return table, []


def design_firmware(
    artifact: Mapping | ArtifactData,
    *,
    source: str = "<calibration artifact>",
    table_points: int | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
    max_speed: float | None = None,
    fault_after: int = DEFAULT_FAULT_AFTER,
    sha256: str = "",
) -> FirmwareDesign:
    """Decide the numbers of the generated firmware from a calibration artifact.

    Parameters
    ----------
    artifact : mapping or ArtifactData
        The artifact as read from JSON (``"format": "hallcal-calibration/1"``), checked here by
        :func:`hallcal.io.validate_artifact`, or its checked view.
    source : str, keyword-only
        Name of the artifact for error messages.
    table_points : int, keyword-only
        M = n_m 2^k (64..16384, a quadratic table); default the cheapest table within the
        budget.
    tolerance : float, keyword-only
        Relative widening of the calibrated amplitude windows, in [0, 0.9].
    max_speed : float, keyword-only
        Largest mechanical speed [rad/s] (with the setup's ``sample_time``); None: the default
        speed limit of 22.5 electrical degrees per sample.
    fault_after : int, keyword-only
        Consecutive rejected samples before the fault flag, 4..1000 (single glitches hold at
        most two samples; fewer when that count could alias, see :func:`alias_holds`).
    sha256 : str, keyword-only
        The artifact's hash, carried into the design.

    Returns
    -------
    FirmwareDesign

    Raises
    ------
    HallcalInputError
        An artifact the validator refuses (the key named), corrections the firmware cannot
        take, a sensor map without a usable amplitude window, or an option out of range.
    """
    art = _checked(artifact, source)
    _check_options(tolerance, fault_after, max_speed)
    n, P, o = art.pole_pairs, art.projection, art.offset
    lut = _lut(art, source)
    flux = art.flux()
    floor = _noise_floor(art.diagnostics)
    ts = art.setup.sample_time
    rows = np.abs(P.sum(axis=1))
    rejects = bool(np.all(rows <= 1e-9 * np.abs(P).sum(axis=1)))

    messages: list[str] = []
    budget = DEFAULT_BUDGET if floor is None else min(BUDGET_FRACTION * floor, MAX_BUDGET)
    if floor is None:
        messages.append(f"the artifact states no noise floor: table budget {DEFAULT_BUDGET:g} rad")
    table, table_messages = _table(lut, table_points, budget)
    messages += table_messages
    plaus = _plausibility(flux, n, P, o, floor, float(tolerance), max_speed, ts, fault_after,
                          source)  # fmt: skip
    if plaus.fault_after < fault_after != DEFAULT_FAULT_AFTER:  # the default: the banner says it
        messages.append(
            f"the fault flag latches after {plaus.fault_after} rejected samples in a row, not "
            f"{fault_after}: after a longer outage a rotor at up to twice the speed limit "
            "could be a pole pitch off"
        )
    return FirmwareDesign(
        pole_pairs=n,
        projection=P,
        offset=o,
        rejects_common_mode=rejects,
        lut=lut,
        table=table,
        plausibility=plaus,
        noise_floor=floor,
        budget=budget,
        sample_time=ts,
        sha256=sha256,
        messages=tuple(messages),
        flux=flux,
    )


# --------------------------------------------------------------------------------------------
# Anticogging feed-forward (artifact key "cogging")
# --------------------------------------------------------------------------------------------

#: Relative accuracy of the anticogging table against the Fourier map.
COGGING_RELATIVE_ERROR = 1e-6
#: Largest anticogging table (float values).
MAX_COGGING_POINTS = 65536


@dataclass(frozen=True)
class CoggingTable:
    """The anticogging feed-forward T_c(y0) as a uniform float table, cubic interpolation.

    ``T_c(y0) = sum_k a_k cos(k y0) + b_k sin(k y0)`` (artifact key ``"cogging"``, y0 the
    mechanical angle), tabulated at ``y0 = 2 pi i / N`` and interpolated by the cubic through the
    four nearest values (periodic).

    Attributes
    ----------
    orders, a, b : ndarray
        The map's harmonics and coefficients.
    unit : str
        As the artifact states it (``"plant input"``).
    values : ndarray of float32, shape (N,)
        The table.
    error : float
        Largest |table - map| over the revolution (dense evaluation with the table's float32
        values, in double), in the map's unit.
    scale : float
        Largest |T_c| over the revolution.
    """

    orders: NDArray[np.int64]
    a: NDArray[np.float64]
    b: NDArray[np.float64]
    unit: str
    values: NDArray[np.float32]
    error: float
    scale: float

    @property
    def points(self) -> int:
        return int(self.values.size)

    @property
    def slope(self) -> float:
        """Largest |d T_c / d y0| over the revolution (sum of k sqrt(a_k^2 + b_k^2))."""
        return float(np.sum(self.orders * np.hypot(self.a, self.b)))

    def torque(self, y0: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """The Fourier map T_c(y0) (double precision)."""
        return cogging_map(self.orders, self.a, self.b, y0)

    def interpolate(self, y0: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """The table's value at y0 as the firmware computes it (in double)."""
        return _cubic(self.values.astype(np.float64), y0)


def cogging_map(orders, a, b, y0) -> NDArray[np.float64]:
    """``sum_k a_k cos(k y0) + b_k sin(k y0)`` at mechanical angles y0 [rad]."""
    arg = np.multiply.outer(np.atleast_1d(np.asarray(y0, dtype=np.float64)), orders)
    return np.cos(arg) @ np.asarray(a, float) + np.sin(arg) @ np.asarray(b, float)


def _uniform(orders, a, b, n: int) -> NDArray[np.float64]:
    """The map on y0 = 2 pi i / n, i = 0 .. n - 1 (inverse real FFT; n > 2 max order)."""
    spec = np.zeros(n // 2 + 1, dtype=np.complex128)
    k = np.asarray(orders)
    scale = np.where(k == 0, float(n), n / 2.0)  # order 0 (a constant load torque): the DC bin
    np.add.at(spec, k, (np.asarray(a) - 1j * np.asarray(b)) * scale)
    return np.fft.irfft(spec, n)


def _cubic(values: NDArray[np.float64], y0) -> NDArray[np.float64]:
    n = values.size
    pos = np.mod(np.atleast_1d(np.asarray(y0, dtype=np.float64)), TWO_PI) * (n / TWO_PI)
    return _cubic_at(values, pos)


def _cubic_at(values: NDArray[np.float64], pos: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cubic through the 4 nearest of the periodic values, at positions in [0, N)."""
    n = values.size
    i = np.minimum(np.floor(pos).astype(np.int64), n - 1)
    t = pos - i
    p0, p1, p2, p3 = (values[(i + k) % n] for k in (-1, 0, 1, 2))
    return (
        -t * (t - 1) * (t - 2) / 6 * p0
        + (t + 1) * (t - 1) * (t - 2) / 2 * p1
        - (t + 1) * t * (t - 2) / 2 * p2
        + (t + 1) * t * (t - 1) / 6 * p3
    )


def cogging_table(
    cogging: Mapping[str, Any], *, source: str = "<calibration artifact>"
) -> CoggingTable:
    """Tabulate the artifact's cogging map (key ``"cogging"``) within 1e-6 relative.

    The table has the fewest points (a power of two, 64..65536, more than twice the largest
    order) whose cubic interpolation of the float32 values stays within half of
    :data:`COGGING_RELATIVE_ERROR` of the largest |T_c| (the other half is for the firmware's
    single-precision arithmetic) at 16 points per interval (dense enough
    for a cubic's error curve); the map on uniform grids comes from an inverse FFT.

    Parameters
    ----------
    cogging : mapping
        The artifact's ``"cogging"`` entry as :func:`hallcal.io.validate_artifact` checks it
        (distinct orders >= 0, one ``a`` and ``b`` per order).
    source : str, keyword-only
        Name of the artifact for error messages.

    Raises
    ------
    HallcalInputError
        No orders, coefficients single precision cannot hold, or no table up to 65536 points
        reaches the accuracy.
    """
    k = np.array([int(v) for v in cogging["orders"]], dtype=np.int64)
    if k.size == 0:
        raise _bad(source, "cogging.orders", "is empty: no map to tabulate")
    a = np.array(cogging["a"], dtype=np.float64)
    b = np.array(cogging["b"], dtype=np.float64)
    if float(np.max(np.abs(np.concatenate([a, b])))) > 1e30:
        raise _bad(source, "cogging.a", "has an implausible scale")
    unit = cogging.get("unit", "")
    unit = unit if isinstance(unit, str) else ""
    scale = 0.0
    m = 64
    while True:
        if 2 * int(k.max()) < m:
            sub = 16  # 16 points per interval: dense enough for a cubic's error curve
            ref = _uniform(k, a, b, sub * m)
            scale = max(scale, float(np.max(np.abs(ref))))
            vals = ref[::sub].astype(np.float32)
            pos = np.arange(sub * m) / sub
            err = float(np.max(np.abs(_cubic_at(vals.astype(np.float64), pos) - ref)))
            if err <= 0.5 * COGGING_RELATIVE_ERROR * scale:  # half for float32 arithmetic
                break
        if m >= MAX_COGGING_POINTS:
            raise _bad(source, "cogging.orders", "needs more than 65536 table points for 1e-6")
        m *= 2
    if not scale > 0.0:
        raise _bad(source, "cogging", "is zero everywhere")
    return CoggingTable(k, a, b, unit, vals, err, scale)


# --------------------------------------------------------------------------------------------
# Power-up identification of the pole pair (artifact key "identifiability")
# --------------------------------------------------------------------------------------------

#: Largest decoder table the exporter writes (points of each of R and Z).
MAX_POWERUP_TABLE = 65536
#: What the decoder's reciprocals and its 2^-x reach (relative): single precision.
_F32_TARGET = 2.0**-25
#: The exponent of 2^-x is built from its bits for x < this; beyond, the term is dropped
#: (it is below 2^-126, against a lock threshold of at least 2^-40).
EXP2_CUT = 126


class PowerUpCode(enum.StrEnum):
    """Whether the exported float variant identifies the pole pair at power-up."""

    EMITTED = "emitted"  # the decoder is in the float variant
    NO_ANALYSIS = "no_analysis"  # the artifact has no "identifiability" entry
    NOT_IDENTIFIABLE = "not_identifiable"  # the analysis says the magnets are too alike
    UNSUPPORTED = "unsupported"  # a grid the C cannot index with shifts, or a huge table
    SINGLE_POLE_PAIR = "single_pole_pair"  # nothing to identify: f_init's frame is absolute
    DISABLED = "disabled"  # left out on request (export_c(powerup=False), --no-powerup)

    @property
    def success(self) -> bool:
        return self is PowerUpCode.EMITTED


@dataclass(frozen=True)
class PowerUpFirmware:
    """The numbers of the power-up decoder in the float variant (module doc of
    :mod:`hallcal.sensor.absolute`, "Decoder specification").

    Costs are in noise-sigma units: every length (rho, zeta, R, Z) is divided by ``sigma``, the
    Gram terms multiplied by ``sigma^2``, so the numbers of the C are of order 1 to 10^5 and a
    sample's cost is the Python reference's exactly (in exact arithmetic).

    Attributes
    ----------
    status : PowerUpCode
    message : str
        One line: the verdict, or why no decoder is written.
    report : IdentifiabilityReport or None
        The artifact's analysis.
    decoder : PowerUpDecoder or None
        The Python decoder it was built from (``reconstruct --absolute`` rebuilds the same).
    sigma : float
        Noise sigma the costs are normalized by (artifact unit).
    radius, zero : ndarray of float32, shape (M + 1,)
        R[q] / sigma and Z[q] / sigma, the last entry repeating the first (wrap-around).
    null : ndarray, shape (3,)
        nv / sigma; ``zeta = null . d - null_offset`` in sigmas.
    null_offset : float
        nv . o / sigma.
    gram_a, gram_b, gram_c :
        A sigma^2 (2 x 2), B sigma^2 (2), C sigma^2.
    rsqrt_seed : tuple of float
        ``c0 - c1 r2`` approximates 1/sqrt(r2) on the amplitude window ``rsqrt_window``.
    rsqrt_steps : int
        Newton steps ``y (3/2 - r2 y^2 / 2)`` after the seed.
    rsqrt_error : float
        Relative error after them (before rounding).
    tangent_window : tuple of float
        Range of tt = t' S t over all table positions (sigmas^2 per electrical rad^2), widened.
    tangent_seed, tangent_steps, tangent_error :
        Seed ``c0 - c1 tt`` of 1/tt, Newton steps ``r (2 - tt r)``, relative error after them.
    slope : float
        L / (2 pi): table intervals per electrical rad.
    cost_cap, threshold : float
        The censoring level c and the lock threshold alpha / (1 - alpha).
    exp2 : ndarray
        Polynomial of 2^-f on [0, 1] (ascending powers).
    exp2_error : float
        Its largest relative error.
    """

    status: PowerUpCode
    message: str
    report: IdentifiabilityReport | None = None
    decoder: PowerUpDecoder | None = field(default=None, repr=False)
    sigma: float = 0.0
    radius: NDArray[np.float32] = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)
    zero: NDArray[np.float32] = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)
    null: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3), repr=False)
    null_offset: float = 0.0
    gram_a: NDArray[np.float64] = field(default_factory=lambda: np.zeros((2, 2)), repr=False)
    gram_b: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2), repr=False)
    gram_c: float = 0.0
    rsqrt_seed: tuple[float, float] = (0.0, 0.0)
    rsqrt_window: tuple[float, float] = (0.0, 0.0)
    rsqrt_steps: int = 0
    rsqrt_error: float = 0.0
    tangent_window: tuple[float, float] = (0.0, 0.0)
    tangent_seed: tuple[float, float] = (0.0, 0.0)
    tangent_steps: int = 0
    tangent_error: float = 0.0
    slope: float = 0.0
    cost_cap: float = 0.0
    threshold: float = 0.0
    exp2: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False)
    exp2_error: float = 0.0

    @property
    def emitted(self) -> bool:
        return self.status.success

    @property
    def pole_pairs(self) -> int:
        return 0 if self.decoder is None else self.decoder.pole_pairs

    @property
    def grid(self) -> int:
        """L, table points per electrical period."""
        return 0 if self.decoder is None else self.decoder.grid

    @property
    def table_bytes(self) -> int:
        """Flash of the two float tables (M + 1 points each)."""
        return 8 * int(self.radius.size)


def _reciprocal_seed(lo: float, hi: float) -> tuple[float, float, float]:
    """Linear minimax seed ``c0 - c1 x`` of 1/x on [lo, hi] (relative error) and that error."""
    c1 = 8.0 / (4.0 * lo * hi + (lo + hi) ** 2)
    c0 = c1 * (lo + hi)
    return c0, c1, abs(1.0 - c1 * lo * hi)


def _rsqrt_seed(lo: float, hi: float) -> tuple[float, float, float]:
    """Linear minimax seed ``c0 - c1 x`` of 1/sqrt(x) on [lo, hi] (relative error) and that
    error. The error ``sqrt(x) (c0 - c1 x) - 1`` equioscillates at lo, hi and its maximum
    ``x* = c0 / (3 c1)``: equal values at the ends give ``c0 / c1 = lo + sqrt(lo hi) + hi``,
    opposite ones at an end and at x* fix c1."""
    ratio = lo + math.sqrt(lo * hi) + hi
    xs = ratio / 3.0
    c1 = 2.0 / (math.sqrt(lo) * (ratio - lo) + 2.0 * xs**1.5)
    return c1 * ratio, c1, c1 * 2.0 * xs**1.5 - 1.0


def _exp2_poly(target: float = 2.0**-24) -> tuple[NDArray[np.float64], float]:
    """Polynomial of 2^-f on [0, 1] (ascending powers) with the fewest terms whose relative error
    is within ``target``: Chebyshev interpolation (within a factor 2 of minimax), the error
    measured on a dense grid."""
    from numpy.polynomial import Chebyshev

    x = np.linspace(0.0, 1.0, 100_001)
    y = 2.0**-x
    for deg in range(4, 10):
        poly = Chebyshev.interpolate(lambda t: 2.0**-t, deg, domain=[0.0, 1.0])
        coef = poly.convert(kind=np.polynomial.Polynomial).coef
        err = float(np.max(np.abs(np.polynomial.polynomial.polyval(x, coef) / y - 1.0)))
        if err <= target:
            break
    return coef, err


def _newton_steps(e0: float, square: float, limit: int = 6) -> tuple[int, float]:
    """Newton steps from a relative error e0 until below single precision; each step takes e to
    ``square e^2`` (plus the cube term for the reciprocal square root, covered by ``square``)."""
    steps, e = 0, e0
    while e > _F32_TARGET and steps < limit:
        e = square * e * e
        steps += 1
    return steps, e


def _tangent_range(dec: PowerUpDecoder, sigma: float, A, B, C) -> tuple[float, float]:
    """Smallest and largest tt = t' S t (sigma units) over all table positions: 16 points per
    interval and both ends (tt is smooth within an interval: a quadratic in the fraction times
    trigonometric terms of the angle, which moves by 2 pi / L over it)."""
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
    c, s = np.cos(psi), np.sin(psi)
    guu = A[0, 0] * c * c + 2 * A[0, 1] * c * s + A[1, 1] * s * s
    gvv = A[0, 0] * s * s - 2 * A[0, 1] * c * s + A[1, 1] * c * c
    guv = (A[1, 1] - A[0, 0]) * c * s + A[0, 1] * (c * c - s * s)
    gun = B[0] * c + B[1] * s
    gvn = B[1] * c - B[0] * s
    tt = (
        dR * dR * guu
        + Rj * Rj * gvv
        + dZ * dZ * C
        + 2.0 * dR * Rj * guv
        + 2.0 * dR * dZ * gun
        + 2.0 * Rj * dZ * gvn
    )
    return float(np.min(tt)), float(np.max(tt))


def design_powerup(
    artifact: Mapping | ArtifactData,
    design: FirmwareDesign,
    *,
    source: str = "<calibration artifact>",
) -> PowerUpFirmware:
    """Decide whether the float variant identifies the pole pair at power-up, and its numbers.

    No decoder (and the homing API) when the artifact has no ``"identifiability"`` entry, when
    its verdict is "not identifiable", or when its grid is not a power of two or its tables
    would pass :data:`MAX_POWERUP_TABLE` points; none either for one pole pair, where f_init
    from y = 0 already gives the calibration's frame (modulo one revolution). The decoder is
    the one ``hallcal reconstruct --absolute`` rebuilds from the same artifact
    (:meth:`IdentifiabilityReport.decoder`), so its tables are bit-identical to Python's before
    the conversion to single precision.

    Parameters
    ----------
    artifact : mapping or ArtifactData
        The parsed calibration artifact (checked by :func:`hallcal.io.validate_artifact`), or
        its checked view.
    design : FirmwareDesign
        The correction table's design (pole pairs, projection, flux model).
    source : str, keyword-only
        Name of the artifact in error messages.

    Returns
    -------
    PowerUpFirmware
        The verdict (a :class:`PowerUpCode`) and, when a decoder is written, its constants and
        tables in noise-sigma units.

    Raises
    ------
    HallcalInputError
        The artifact is refused by :func:`hallcal.io.validate_artifact`, or its
        ``"identifiability"`` entry is malformed (named).
    """
    entry = _checked(artifact, source).data.get("identifiability")
    if entry is None:
        return PowerUpFirmware(
            PowerUpCode.NO_ANALYSIS,
            "the artifact has no identifiability analysis (made before power-up identification "
            "existed; calibrate again)",
        )
    try:
        report = IdentifiabilityReport.from_dict(entry)
    except ValueError as exc:
        raise HallcalInputError(f"{source}: {exc}") from None
    no_decoder = _without_decoder(report, design)
    if no_decoder is not None:
        return no_decoder
    if not (math.isfinite(report.noise_std) and report.noise_std > 0.0):
        raise _bad(source, "identifiability.noise_std", "must be a positive number")
    if design.flux is None:  # pragma: no cover - design_firmware always sets it
        raise ValueError("the design has no flux model")
    try:
        dec = report.decoder(design.flux, design.lut)
    except ValueError as exc:
        raise HallcalInputError(f"{source}: identifiability: {exc}") from None
    return _decoder_numbers(report, dec, design.plausibility, source)


def _without_decoder(
    report: IdentifiabilityReport, design: FirmwareDesign
) -> PowerUpFirmware | None:
    """Why the float variant gets no decoder (one pole pair, the verdict, a grid or tables the
    C cannot take), or None."""
    if design.pole_pairs == 1:
        return PowerUpFirmware(
            PowerUpCode.SINGLE_POLE_PAIR,
            "one pole pair: f_init from y = 0 is in the frame of the calibration after any "
            "power-up (init with revolutions 0 and angle 0)",
            report,
        )
    if not report.status.success:
        return PowerUpFirmware(PowerUpCode.NOT_IDENTIFIABLE, report.message, report)
    L = report.grid
    if L not in GRID_CHOICES and not (4 <= L <= 65536 and L & (L - 1) == 0):
        return PowerUpFirmware(
            PowerUpCode.UNSUPPORTED,
            f"the decoder's grid ({L} points per electrical period) is not a power of two",
            report,
        )
    if design.pole_pairs * L + 1 > MAX_POWERUP_TABLE:
        return PowerUpFirmware(
            PowerUpCode.UNSUPPORTED,
            f"the decoder's tables would have {design.pole_pairs * L} points, more than "
            f"{MAX_POWERUP_TABLE}",
            report,
        )
    return None


def _decoder_numbers(
    report: IdentifiabilityReport, dec: PowerUpDecoder, pl: Plausibility, source: str
) -> PowerUpFirmware:
    """The decoder's tables and metric in noise-sigma units, and the seeds and Newton steps of
    its reciprocals over the windows they see."""
    sigma = dec.noise_std
    s2 = sigma * sigma
    A, B, C = dec.gram_a * s2, dec.gram_b * s2, float(dec.gram_c * s2)
    radius = np.append(dec.radius, dec.radius[0]) / sigma
    zero = np.append(dec.zero, dec.zero[0]) / sigma
    if (
        not (np.all(np.isfinite(radius)) and np.all(np.isfinite(zero)))
        or float(np.max(np.abs(np.concatenate([radius, zero])))) > 1e30
    ):
        raise _bad(source, "identifiability.noise_std", "is implausible for the signals")
    # 1/sqrt(r2) on the amplitude window the lean code admits
    w_lo, w_hi = pl.radius_lo**2, pl.radius_hi**2
    c0, c1, e0 = _rsqrt_seed(w_lo, w_hi)
    rs_steps, rs_err = _newton_steps(e0, 1.5 + e0)
    # 1/tt on the range of tt over the table, widened by 10 % both ways
    t_lo, t_hi = _tangent_range(dec, sigma, A, B, C)
    t_lo, t_hi = 0.9 * t_lo, 1.1 * t_hi
    r0, r1, re0 = _reciprocal_seed(t_lo, t_hi)
    tt_steps, tt_err = _newton_steps(re0, 1.0)
    poly, p_err = _exp2_poly()
    return PowerUpFirmware(
        status=PowerUpCode.EMITTED,
        message=report.message,
        report=report,
        decoder=dec,
        sigma=sigma,
        radius=radius.astype(np.float32),
        zero=zero.astype(np.float32),
        null=dec.null / sigma,
        null_offset=float(dec.null @ dec.offset) / sigma,
        gram_a=A,
        gram_b=B,
        gram_c=C,
        rsqrt_seed=(c0, c1),
        rsqrt_window=(w_lo, w_hi),
        rsqrt_steps=rs_steps,
        rsqrt_error=rs_err,
        tangent_window=(t_lo, t_hi),
        tangent_seed=(r0, r1),
        tangent_steps=tt_steps,
        tangent_error=tt_err,
        slope=dec.grid / TWO_PI,
        cost_cap=float(dec.cost_cap),
        threshold=float(dec.lock_threshold),
        exp2=poly,
        exp2_error=p_err,
    )
