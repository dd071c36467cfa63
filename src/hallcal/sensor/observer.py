"""A model-based angle observer: the tracking maximum-likelihood angle from the three signals.

Where the lookup table of the paper (section "Designing a reconstruction function") inverts
f_init, a fixed combination of the three Hall signals, this observer uses the identified flux
model g_theta(y0) = psi(y0) theta (section "Model structure") directly: per sample it takes the
angle that best explains the three signals,

    y_obs = argmin_y  sum_i (d_i - m_i(y))^2 / sigma_i^2,   m_i(y) = a_i (g_i(y) - c_i) + b_i,

by one Gauss-Newton step per sample from the predicted angle (previous angle plus speed), with
g and dg/dy0 tabulated over one revolution (cubic Hermite interpolation of values and slopes) and
looked up once per sample, at the prediction: the chi-square after the step, the fits without
one channel and the adaptation's regressors all use the model linearized there (the step's own
error is second order in the prediction error, far below the noise once the speed is tracked).
The first sample is found by a search of table nodes within half a pole pitch of the start.
Work per sample is bounded and small (a Cortex-M4F: benchmarks/bench_observer_c.txt). ``c_i`` is
the model's constant term; the gain ``a_i`` and level ``b_i`` (initially 1 and c_i) are adapted
online. Only the three-signal curve g(y) must be injective (checked with a margin by
:func:`observer_model`), so a folding map (Clarke's angle not monotone, no table on f_init) is
tracked like any other.

Around it:

* **misfit monitor**: the chi-square of the residuals d - m(y_obs) against the calibrated noise
  over a sliding window of samples, per degree of freedom (about 1 when the model fits). The
  alarm threshold is the chi-square quantile of the window's degrees of freedom at a per-sample
  false-alarm probability (``false_alarm``, Wilson-Hilferty approximation of the quantile);
  each sample's contribution is capped (a spike moves the window by at most ``sample_cap``).
  Above the threshold for less than ``stale_travel`` electrical radians of travel the state is
  ``adapting``; longer, ``stale`` (the model no longer fits: remount, wiring, damage), and the
  adaptation freezes.
* **online adaptation**: per sensor, (a_i, b_i) by exponentially weighted least squares of d_i
  on [g_i(y_obs) - c_i, 1] (forgetting per electrical radian of travel, a weak prior on the
  calibrated values, bounded; the regressors projected off the angle's direction in the
  joint 6x6 information; one sample in each cycle of ``ADAPT_CYCLE`` samples without an
  unexplained outlier is measured, its update applied at the cycle's end, so that firmware
  spreads the 6x6 work over the cycle); this absorbs the temperature drift of NdFeB
  remanence (common gain), Hall sensitivity (per-sensor gain) and offsets.
* **one-sensor fallback**: a sample whose chi-square is an outlier and that one channel alone
  explains (the fit without it is within the noise) is reconstructed from the other two; a
  channel so blamed ``fault_count`` times within ``fault_window`` samples is excluded from the
  next sample on (so that firmware does not add the exclusion's work to the outlier sample's),
  a non-finite one at once: state ``degraded``, y_obs from the two others (the two-sensor ML
  angle, tracked on from the fit without the channel, never more than a bounded step per sample
  from the prediction), so it never slips a pole pitch. It is readmitted after
  ``readmit_travel`` electrical radians of consistent readings.

Units: angles in rad (mechanical), d and sigma in the sensor's unit.
"""

from __future__ import annotations

import enum
import math
import statistics
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.sensor.flux import FluxModel

__all__ = [
    "ADAPT_CYCLE",
    "Injectivity",
    "ObserverModel",
    "ObserverRun",
    "ObserverSettings",
    "ObserverState",
    "acquire_offsets",
    "chi_square_quantile",
    "observer_model",
    "run_observer",
]


class ObserverState(enum.StrEnum):
    """State of the observer at a sample (the ``state`` column of ``reconstruct --observer``).

    The order is that of the integer codes the kernel writes (0 .. 4).
    """

    #: the model fits (misfit within the false-alarm threshold), three channels in use
    OK = "ok"
    #: the misfit is above the threshold and the gain/offset adaptation is working on it
    ADAPTING = "adapting"
    #: the misfit stayed above the threshold for ``stale_travel``: the model no longer fits
    #: (remount, wiring, damage, an angle lost to garbage readings), also with a channel
    #: excluded; the adaptation is frozen
    STALE = "stale"
    #: one channel excluded (stuck, clipped, disconnected); the angle from the other two, which
    #: fit the model
    DEGRADED = "degraded"
    #: fewer than two usable channels, or the two left do not fit either
    FAULT = "fault"


STATE_ORDER: tuple[ObserverState, ...] = tuple(ObserverState)


@dataclass(frozen=True)
class ObserverSettings:
    """Tuning of :func:`run_observer` (defaults measured in ``benchmarks/bench_observer.py``).

    Attributes
    ----------
    acquire_points : int
        Table nodes searched (within half a pole pitch of the given angle) for the first sample;
        the next samples' Gauss-Newton steps refine the best.
    speed_gain, accel_gain : float
        Gains of the tracker that predicts the next angle (an alpha-beta-gamma tracker with
        alpha = 1, Bar-Shalom, Li & Kirubarajan, "Estimation with Applications to Tracking and
        Navigation", sec. 6.5): per sample a += accel_gain e, v += a + speed_gain e with
        e = y_obs - y_pred, y_pred = y_obs + v at the next sample [-]. A constant acceleration
        leaves no lag; the defaults (critically damped, accel_gain = speed_gain^2 / 4) keep the
        prediction within about 0.01 electrical rad of the rotor at 1e5 rad/s^2 (n_m 11,
        4 kHz), so that the misfit taken on the model linearized at the prediction stays that
        of the noise, and put the prediction's own noise at about 1.6 times the angle's, which
        only moves the point of linearization (benchmarks/bench_observer_unseen.txt).
    window : int
        Samples of the misfit window.
    false_alarm : float
        Probability, per sample, that the window's chi-square of a fitting model exceeds the
        alarm threshold (at 4 kHz, 1e-9 bounds the alarms by 0.015 per hour, union bound).
    sample_cap : float
        Largest contribution of one sample to the window's chi-square.
    outlier : float
        A sample's chi-square (3 channels, 2 degrees of freedom) above which the fits without
        one channel are tried.
    explained : float
        Chi-square (1 degree of freedom) below which the fit without a channel explains the
        sample (that channel is blamed).
    gross : float
        A channel is blamed for a sample only when its reading is off the fit of the two others
        by at least this fraction of its peak amplitude (and 8 noise sigmas): far beyond any
        drift the adaptation absorbs (1-2 %), well within what a stuck, clipped or disconnected
        channel shows.
    fault_window, fault_count : int
        A channel blamed ``fault_count`` times within the last ``fault_window`` samples is
        excluded.
    adapt_memory : float
        Memory of the gain/offset adaptation [electrical rad of travel].
    adapt_min_samples : float
        Its memory in samples at least: at speed, a memory of travel alone lasts a few cycles of
        the adaptation and its gains carry that few samples' noise (the ML angle 1.03-1.04x the
        floor and the misfit 1.3-1.5 at 0.2-1.1 electrical rad per sample on an exact model;
        1.00x with 2048 samples, 0.5 s at 4 kHz: temperature drifts take minutes).
    prior_samples : float
        Weight of the calibrated gain/offset as a prior, in samples of information.
    gain_bounds : (float, float)
        Bounds of the adapted gains a_i [-].
    offset_bound : float
        Bound of |b_i - c_i| relative to the channel's RMS amplitude [-].
    stale_travel : float
        Travel with the misfit above the threshold after which the state is ``stale``
        [electrical rad].
    readmit_travel : float
        Travel of consistent readings after which an excluded channel is readmitted
        [electrical rad].
    """

    acquire_points: int = 8
    speed_gain: float = 0.5
    accel_gain: float = 0.0625
    window: int = 256
    false_alarm: float = 1e-9
    sample_cap: float = 50.0
    outlier: float = 30.0
    explained: float = 12.0
    gross: float = 0.05
    fault_window: int = 64
    fault_count: int = 8
    adapt_memory: float = 8.0 * math.pi
    adapt_min_samples: float = 2048.0
    prior_samples: float = 100.0
    gain_bounds: tuple[float, float] = (0.7, 1.3)
    offset_bound: float = 0.2
    stale_travel: float = 6.0 * math.pi
    readmit_travel: float = 4.0 * math.pi

    def __post_init__(self) -> None:
        if not (self.acquire_points >= 2 and self.window >= 8 and 0 < self.false_alarm < 0.5):
            raise ValueError("acquire_points >= 2, window >= 8 and 0 < false_alarm < 0.5 required")
        if not (1 <= self.fault_count <= self.fault_window):
            raise ValueError("1 <= fault_count <= fault_window required")
        lo, hi = self.gain_bounds
        if not (0 < lo < 1 < hi):
            raise ValueError("gain_bounds must bracket 1 and be positive")


@dataclass(frozen=True)
class Injectivity:
    """Whether the three-signal curve g(y) can be inverted locally with a margin.

    Attributes
    ----------
    injective : bool
        ``separation >= margin`` and ``speed > 0`` everywhere.
    separation : float
        Smallest noise-weighted distance ||g(y) - g(y')||_W between two points of the curve a
        quarter to a half pole pitch apart (electrical pi/2 .. pi) [noise sigmas]: what keeps
        the tracking from jumping to another branch of the curve.
    margin : float
        Required separation [noise sigmas].
    worst_std : float
        Largest per-sample ML angle standard deviation 1 / ||dg/dy||_W over the revolution [rad].
    rms_std : float
        RMS over the revolution of that standard deviation [rad]: the observer's noise floor
        (Cramer-Rao bound of one sample).
    """

    injective: bool
    separation: float
    margin: float
    worst_std: float
    rms_std: float

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("injective", "separation", "margin", "worst_std",
                                               "rms_std")}  # fmt: skip


@dataclass(frozen=True)
class ObserverModel:
    """The flux model tabulated for the observer.

    Attributes
    ----------
    pole_pairs : int
        n_m.
    value, slope : ndarray, shape (M, 3)
        g(y_j) and dg/dy0(y_j) on y_j = 2 pi j / M [sensor unit, sensor unit / rad].
    center : ndarray, shape (3,)
        Constant term c_i of each channel (theta[:, 0]).
    amplitude : ndarray, shape (3,)
        RMS over the revolution of g_i - c_i.
    sigma : ndarray, shape (3,)
        Calibrated noise standard deviation per channel [sensor unit].
    injectivity : Injectivity
    """

    pole_pairs: int
    value: NDArray[np.float64] = field(repr=False)
    slope: NDArray[np.float64] = field(repr=False)
    center: NDArray[np.float64] = field(repr=False)
    amplitude: NDArray[np.float64] = field(repr=False)
    sigma: NDArray[np.float64] = field(repr=False)
    injectivity: Injectivity

    @property
    def points(self) -> int:
        """M, table points per revolution."""
        return int(self.value.shape[0])


def table_points(flux: FluxModel, pole_pairs: int) -> int:
    """Table points per revolution: at least 16 per period of the highest harmonic and 64 per
    pole pitch, a power of two (cubic Hermite error (h K)^4 / 384 of a harmonic's amplitude,
    below 1e-5 for 16 points per period)."""
    top = max(max(flux.basis.harmonics), 4 * int(pole_pairs))
    return int(2 ** math.ceil(math.log2(max(256, 16 * top))))


def observer_model(
    flux: FluxModel,
    pole_pairs: int,
    noise_variance: ArrayLike,
    *,
    points: int | None = None,
    margin: float = 8.0,
) -> ObserverModel:
    """Tabulate g and dg/dy0 and check that the three-signal curve is locally injective.

    Parameters
    ----------
    flux : FluxModel
        g_theta (section "Model structure").
    pole_pairs : int
        n_m.
    noise_variance : array_like, scalar or shape (3,)
        sigma_i^2 per channel [sensor unit^2] (the SEM's noise variance).
    points : int, keyword-only, optional
        Table points per revolution (default :func:`table_points`).
    margin : float, keyword-only
        Required separation of the curve from itself a quarter to a half pole pitch away, in
        noise sigmas: a noise vector of half that length has probability below 1e-6 in three
        channels.

    Returns
    -------
    ObserverModel
    """
    n = int(pole_pairs)
    M = int(points) if points is not None else table_points(flux, n)
    y = TWO_PI * np.arange(M) / M
    value, slope = flux.value_and_derivative(y)
    var = np.broadcast_to(np.asarray(noise_variance, dtype=np.float64), (3,)).copy()
    if not np.all(var > 0):
        raise ValueError("noise_variance must be > 0")
    sigma = np.sqrt(var)
    center = flux.theta[:, 0].copy()
    amplitude = np.sqrt(np.mean((value - center) ** 2, axis=0))
    inj = _injectivity(value / sigma, slope / sigma, n, margin)
    return ObserverModel(
        n,
        np.ascontiguousarray(value),
        np.ascontiguousarray(slope),
        center,
        amplitude,
        sigma,
        inj,
    )


def _injectivity(gw: NDArray, dgw: NDArray, n: int, margin: float) -> Injectivity:
    """Separation of the whitened curve from itself electrical pi/2 .. pi away, and its speed."""
    M = gw.shape[0]
    lo = max(1, int(math.ceil(M / (4 * n))))  # a quarter pole pitch, in table steps
    hi = max(lo, int(M // (2 * n)))  # half a pole pitch
    best = math.inf
    for s in range(lo, hi + 1):
        diff = gw - np.roll(gw, -s, axis=0)
        best = min(best, float(np.sqrt(np.min(np.einsum("ij,ij->i", diff, diff)))))
    speed2 = np.einsum("ij,ij->i", dgw, dgw)
    std = 1.0 / np.sqrt(np.maximum(speed2, 1e-300))
    return Injectivity(
        injective=bool(best >= margin and np.min(speed2) > 0),
        separation=best,
        margin=float(margin),
        worst_std=float(np.max(std)),
        rms_std=float(np.sqrt(np.mean(std**2))),
    )


@dataclass(frozen=True)
class ObserverRun:
    """The observer over a recording.

    Attributes
    ----------
    y_obs : ndarray (N,)
        Tracking ML angle [rad, mechanical].
    misfit : ndarray (N,)
        Windowed chi-square per degree of freedom [-] (about 1 when the model fits).
    state_code : ndarray (N,) of int8
        Index into :data:`STATE_ORDER`.
    gain, offset : ndarray (3,)
        Adapted a_i and b_i - c_i at the end [-, sensor unit].
    excluded : int
        The channel (0, 1, 2) excluded at the end, or -1.
    first_exclusion : int
        Sample at which a channel was first excluded, or -1.
    threshold : float
        The misfit alarm threshold of a full window of three channels [-].
    """

    y_obs: NDArray[np.float64] = field(repr=False)
    misfit: NDArray[np.float64] = field(repr=False)
    state_code: NDArray[np.int8] = field(repr=False)
    gain: NDArray[np.float64]
    offset: NDArray[np.float64]
    excluded: int
    first_exclusion: int
    threshold: float

    @property
    def state(self) -> NDArray[np.str_]:
        """The state per sample as text (ok | adapting | stale | degraded | fault)."""
        names = np.array([s.value for s in STATE_ORDER])
        return names[self.state_code]

    def __len__(self) -> int:
        return int(self.y_obs.size)


def acquire_offsets(points: int, pole_pairs: int, count: int) -> NDArray[np.int64]:
    """Table-node offsets searched at the start: ``count`` nodes evenly spread over one pole
    pitch centred on the start (within half a pole pitch), in table steps (M / n_m per pitch).
    The C export takes the same offsets.

    Parameters
    ----------
    points : int
        M, table points per revolution.
    pole_pairs : int
        n_m.
    count : int
        Nodes searched.

    Returns
    -------
    ndarray of int64, shape (count,)
        Offsets in table steps.
    """
    per_pitch = points / pole_pairs
    return np.array([round((q / count - 0.5) * per_pitch) for q in range(count)], dtype=np.int64)


def run_observer(
    model: ObserverModel,
    d: ArrayLike,
    *,
    y_initial: float = 0.0,
    settings: ObserverSettings | None = None,
) -> ObserverRun:
    """Run the observer over a recording, sample by sample as firmware would.

    Parameters
    ----------
    model : ObserverModel
    d : array_like, shape (N, 3)
        Hall signals (non-finite values mark a disconnected channel).
    y_initial : float, keyword-only
        Angle before the first sample [rad]; the first sample is acquired by a search within
        half a pole pitch of it (the calibration's frame when the run starts where the
        calibration run started).
    settings : ObserverSettings, keyword-only, optional

    Returns
    -------
    ObserverRun
    """
    s = ObserverSettings() if settings is None else settings
    x = np.require(np.asarray(d, dtype=np.float64), requirements=("C", "W"))
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError("d must have shape (N, 3)")
    N = x.shape[0]
    y_obs = np.empty(N)
    misfit = np.empty(N)
    code = np.empty(N, dtype=np.int8)
    gain = np.ones(3)
    level = model.center.copy()
    info = np.zeros(5)  # excluded, first exclusion
    z = -statistics.NormalDist().inv_cdf(s.false_alarm)
    cfg = np.array(
        [
            s.accel_gain, s.speed_gain, s.window, z, s.sample_cap, s.outlier, s.explained,
            s.fault_window, s.fault_count, s.adapt_memory, s.prior_samples, s.gain_bounds[0],
            s.gain_bounds[1], s.offset_bound, s.stale_travel, s.readmit_travel, s.gross,
            model.pole_pairs, s.adapt_min_samples,
        ],
        dtype=np.float64,
    )  # fmt: skip
    _track(
        x,
        np.require(model.value, requirements=("C", "W")),
        np.require(model.slope, requirements=("C", "W")),
        model.center.copy(),
        model.amplitude.copy(),
        1.0 / model.sigma**2,
        float(model.pole_pairs),
        float(y_initial),
        cfg,
        acquire_offsets(model.points, model.pole_pairs, s.acquire_points),
        gain,
        level,
        y_obs,
        misfit,
        code,
        info,
    )
    k = 2 * s.window
    threshold = chi_square_quantile(float(k), z) / k
    return ObserverRun(
        y_obs,
        misfit,
        code,
        gain,
        level - model.center,
        int(info[0]),
        int(info[1]),
        float(threshold),
    )


# ----------------------------------------------------------------------------- numeric kernel


@nb.njit(cache=True, inline="always")
def chi_square_quantile(k, z):
    """Wilson-Hilferty approximation of the chi-square quantile (Johnson, Kotz & Balakrishnan,
    "Continuous Univariate Distributions", vol. 1, sec. 18.8): the misfit alarm threshold.

    Parameters
    ----------
    k : float
        Degrees of freedom (> 0).
    z : float
        Standard normal quantile of the upper tail probability (e.g. 6.0 for 1e-9).

    Returns
    -------
    float
        k (1 - 2/(9k) + z sqrt(2/(9k)))^3; never below the exact quantile for k >= 1 and tail
        probabilities 1e-12 .. 1e-3, within 1 % of it for k >= 64 (tests/test_observer.py).
    """
    c = 2.0 / (9.0 * k)
    return k * (1.0 - c + z * math.sqrt(c)) ** 3


@nb.njit(cache=True, inline="always")
def _table(G, dG, h, y, g, dg):
    """Cubic Hermite interpolation of the tabulated g and dg/dy0 at y (wrap-around)."""
    M = G.shape[0]
    u = y / h
    fu = math.floor(u)
    t = u - fu
    j = int(fu - M * math.floor(fu / M))
    if j >= M:
        j -= M
    j1 = j + 1
    if j1 == M:
        j1 = 0
    t2 = t * t
    t3 = t2 * t
    h00 = 2.0 * t3 - 3.0 * t2 + 1.0
    h10 = (t3 - 2.0 * t2 + t) * h
    h01 = -2.0 * t3 + 3.0 * t2
    h11 = (t3 - t2) * h
    d00 = (6.0 * t2 - 6.0 * t) / h
    d10 = 3.0 * t2 - 4.0 * t + 1.0
    d11 = 3.0 * t2 - 2.0 * t
    for i in range(3):
        g[i] = h00 * G[j, i] + h10 * dG[j, i] + h01 * G[j1, i] + h11 * dG[j1, i]
        dg[i] = d00 * (G[j, i] - G[j1, i]) + d10 * dG[j, i] + d11 * dG[j1, i]


@nb.njit(cache=True)
def _linearize(G, dG, h, dk, c, a, b, w, yp, f, dg, r):
    """The model at the predicted angle yp (one table look-up per sample): field parts
    f_i = g_i(yp) - c_i, slopes dg_i/dy0 and residuals r_i = d_i - a_i f_i - b_i of all three
    channels, and the weighted sums over the channels in use: (sum w r^2, sum w J r, sum w J^2)
    with J_i = a_i dg_i/dy0."""
    _table(G, dG, h, yp, f, dg)
    srr = 0.0
    num = 0.0
    den = 0.0
    for i in range(3):
        f[i] -= c[i]
        r[i] = dk[i] - a[i] * f[i] - b[i]
        if w[i] > 0.0:
            J = a[i] * dg[i]
            srr += w[i] * r[i] * r[i]
            num += w[i] * J * r[i]
            den += w[i] * J * J
    return srr, num, den


@nb.njit(cache=True, inline="always")
def _step(srr, num, den, max_step):
    """One Gauss-Newton step of the angle on the model linearized at the prediction, bounded by
    max_step, and the chi-square of the linearized model after it: (step, chi2)."""
    if den <= 0.0:
        return 0.0, srr
    if abs(num) > max_step * den:  # bounded, tested before the division (as the C: none then)
        step = max_step if num > 0.0 else -max_step
    else:
        step = num / den
    chi = srr - step * (2.0 * num - step * den)
    return step, chi if chi > 0.0 else 0.0


@nb.njit(cache=True)
def _robust(f, dg, r, a, w, srr, num, den, chi, max_step, explained, gross):
    """An outlier sample (three channels, chi2 above ``outlier``), on the linearized model: is it
    explained by a common gain s of the field parts (remanence, air gap; the (y, s) least
    squares)? If not, the fits without each channel (chosen by their chi2 unbounded, closed form
    from the sums; the chosen one's step then bounded by max_step, so that firmware needs no
    bound per fit). Returns (step, chi2, blamed channel or -1,
    mark: blamed, 3 unexplained outlier, -1; outlier: True when no common gain explains it)."""
    A01 = 0.0
    A11 = 0.0
    r1 = 0.0
    for i in range(3):
        Js = a[i] * f[i]
        A01 += w[i] * (a[i] * dg[i]) * Js
        A11 += w[i] * Js * Js
        r1 += w[i] * Js * r[i]
    det = den * A11 - A01 * A01
    if det > 0.0:
        chi_s = srr - (A11 * num * num - 2.0 * A01 * num * r1 + den * r1 * r1) / det
        if chi_s <= explained:
            return _step(srr, num, den, max_step)[0], chi, -1, -1, False
    best = math.inf
    best_step = 0.0
    blamed = -1
    for q in range(3):  # the fits without q, unbounded: chi2 = srr_q - num_q^2 / den_q
        Jq = a[q] * dg[q]
        nq = num - w[q] * Jq * r[q]
        eq = den - w[q] * Jq * Jq
        sq = nq / eq if eq > 0.0 else 0.0
        cq = (srr - w[q] * r[q] * r[q]) - sq * nq
        if cq < best:
            best = cq
            best_step = sq
            blamed = q
    best_step = min(max(best_step, -max_step), max_step)  # the chosen fit's step, bounded
    step = _step(srr, num, den, max_step)[0]
    if not (best < explained and best < 0.1 * chi):
        return step, chi, -1, 3, True
    e = r[blamed] - a[blamed] * dg[blamed] * best_step
    if abs(e) < gross[blamed]:
        return step, chi, -1, -1, True  # small enough to be drift, not a channel fault
    return best_step, chi, blamed, blamed, True


@nb.njit(cache=True)
def _acquire(G, dk, c, a, b, w, yp, h, offsets):
    """The start: the best of the table nodes ``offsets`` (within half a pole pitch) around the
    node nearest yp, by chi2 at the nodes themselves (no interpolation): its angle [rad]."""
    M = G.shape[0]
    j0 = int(math.floor(yp / h + 0.5))
    e = np.empty(3)
    for i in range(3):
        e[i] = dk[i] - b[i] + a[i] * c[i]
    best = math.inf
    bj = j0
    for q in range(offsets.size):
        j = j0 + offsets[q]
        jm = j % M
        chi = 0.0
        for i in range(3):
            if w[i] > 0.0:
                rr = e[i] - a[i] * G[jm, i]
                chi += w[i] * rr * rr
        if chi < best:
            best = chi
            bj = j
    return bj * h


#: The adaptation runs in cycles of this many samples: the first sample's information and
#: gradient (weighted by the cycle's length) enter the 6x6 information matrix, the solve and the
#: update follow on the cycle's last sample (firmware spreads the factorization over the samples
#: in between, so that no sample carries the whole 6x6 update).
ADAPT_CYCLE = 16


@nb.njit(cache=True)
def _adapt_measure(f, dg, r, step, den, amp, w, w0, a, H, gr, lam, prior, weight):
    """The information and gradient of one sample for the gains a_i and levels b_i, at the
    fitted angle y = yp + step (the model linearized at yp), weighted by ``weight`` samples.

    Model m_i = a_i (g_i(y) - c_i) + b_i; the regressors J_p (d m_i / d a_i = g_i - c_i,
    d m_i / d b_i = 1) are projected off the angle's direction J_y (d m_i / d y = a_i g_i'),
    since y is re-fitted at every sample: H <- lam H + weight (J_p^T W J_p - q q^T / s)
    + (1 - lam) Q (q = J_p^T W J_y, s = J_y^T W J_y), gr = weight J_p^T W r (the residual r is
    W-orthogonal to J_y at the fitted angle). lam = exp(-travel / memory) (its Taylor
    polynomial, passed in); the prior Q keeps H positive definite. Returns False when nothing
    is measured (no slope)."""
    if den <= 0.0:
        return False
    for p in range(6):
        for q in range(6):
            H[p, q] *= lam
    qv = np.zeros(6)
    for i in range(3):
        H[2 * i, 2 * i] += (1.0 - lam) * prior * w0[i] * amp[i] * amp[i]
        H[2 * i + 1, 2 * i + 1] += (1.0 - lam) * prior * w0[i]
        gr[2 * i] = 0.0
        gr[2 * i + 1] = 0.0
        if w[i] > 0.0:
            fy = f[i] + dg[i] * step
            Jy = a[i] * dg[i]
            ry = r[i] - Jy * step
            u = weight * w[i]
            H[2 * i, 2 * i] += u * fy * fy
            H[2 * i, 2 * i + 1] += u * fy
            H[2 * i + 1, 2 * i] += u * fy
            H[2 * i + 1, 2 * i + 1] += u
            qv[2 * i] = w[i] * fy * Jy
            qv[2 * i + 1] = w[i] * Jy
            gr[2 * i] = u * fy * ry
            gr[2 * i + 1] = u * ry
    t = weight / den
    for p in range(6):
        for q in range(6):
            H[p, q] -= t * qv[p] * qv[q]
    return True


@nb.njit(cache=True)
def _adapt_solve(H, gr, wm, amp, a, b, p0, a_lo, a_hi, b_bound, L, P):
    """Solve H x = gr (L D L^T: H is symmetric positive definite, prior + projected Gram) and
    update the gains and levels of the channels measured (``wm``), bounded: a_i in
    [a_lo, a_hi], |b_i - b_i^0| <= b_bound * amplitude_i."""
    for j in range(6):
        t = H[j, j]
        for k in range(j):
            t -= L[j, k] * L[j, k] * P[k]
        if not t > 0.0:
            return
        P[j] = t
        for i in range(j + 1, 6):
            t = H[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k] * P[k]
            L[i, j] = t / P[j]
    z = np.empty(6)
    for i in range(6):  # L z = gr
        t = gr[i]
        for k in range(i):
            t -= L[i, k] * z[k]
        z[i] = t
    for i in range(5, -1, -1):  # D L^T x = z
        t = z[i] / P[i]
        for k in range(i + 1, 6):
            t -= L[k, i] * z[k]
        z[i] = t
    for i in range(3):
        if wm[i] > 0.0:
            a[i] = min(max(a[i] + z[2 * i], a_lo), a_hi)
            lim = b_bound * amp[i]
            b[i] = min(max(b[i] + z[2 * i + 1], p0[i, 1] - lim), p0[i, 1] + lim)


@nb.njit(cache=True)
def _adapt_cycle(phase, pending, eligible, stale, travel, f, dg, r, step, den, amp, w, w0, a, b,
                 p0, H, gr, wm, L, P, cfg):  # fmt: skip
    """One sample of the adaptation's cycle of ``ADAPT_CYCLE`` samples: on its first (an
    eligible sample: fitted, not stale, no channel blamed) the measurement, on its last the
    solve and the update (not while stale). Returns (pending, next phase)."""
    if phase == 0:
        if eligible:
            x = min(ADAPT_CYCLE * travel / cfg[9], ADAPT_CYCLE / cfg[18])  # the cycle's forgetting
            lam = 1.0 - x + 0.5 * x * x - x * x * x / 6.0  # exp(-x), 1.6e-4 up to x = 1/4
            pending = _adapt_measure(f, dg, r, step, den, amp, w, w0, a, H, gr, lam, cfg[10],
                                     float(ADAPT_CYCLE))  # fmt: skip
            wm[:] = w
            return pending, 1
        return pending, 0
    if phase == ADAPT_CYCLE - 1 and pending:
        if not stale:
            _adapt_solve(H, gr, wm, amp, a, b, p0, cfg[11], cfg[12], cfg[13], L, P)
        pending = False
    return pending, (phase + 1) % ADAPT_CYCLE


#: Indices of the tracker's float state: angle, speed [rad/sample], the misfit window's sums,
#: the consistent travel of an excluded channel, the travel with the misfit above threshold and
#: the acceleration [rad/sample^2].
_Y, _V, _SUM_CHI, _SUM_DOF, _CLEAN, _BAD, _A = 0, 1, 2, 3, 4, 5, 6
#: Indices of its integer state: excluded channel (-1 none), first exclusion (sample, -1),
#: exclusion from the residual (not a non-finite reading), exclusions suppressed, acquire,
#: the channel whose exclusion takes effect at the next sample (-1 none).
_EXCL, _FIRST, _BLAMED_OUT, _SUPPRESS, _ACQUIRE, _NEXT = 0, 1, 2, 3, 4, 5


@nb.njit(cache=True)
def _read(d, k, dk, w, w0, S, I):
    """The sample's readings and weights; a non-finite channel is excluded at once."""
    for i in range(3):
        dk[i] = d[k, i]
        if not math.isfinite(dk[i]):
            dk[i] = 0.0
            if I[_EXCL] < 0:  # a disconnected channel
                I[_EXCL] = i
                I[_BLAMED_OUT] = 0
                if I[_FIRST] < 0:
                    I[_FIRST] = k
                S[_CLEAN] = 0.0
    active = 0
    for i in range(3):
        w[i] = 0.0 if (i == I[_EXCL] or not math.isfinite(d[k, i])) else w0[i]
        if w[i] > 0.0:
            active += 1
    return active


@nb.njit(cache=True)
def _isolate(k, blamed, mark, ring, blame, FC, I):
    """Fault isolation: True when channel ``blamed`` has been blamed ``FC`` times within the
    ring's window and (nearly) alone (a model that no longer fits, e.g. a remount, puts
    outliers on every channel and many that no channel explains)."""
    FW = ring.size
    old = ring[k % FW]
    if old >= 0:
        blame[old] -= 1
    ring[k % FW] = mark
    if mark >= 0:
        blame[mark] += 1
    if blamed < 0 or I[_EXCL] >= 0 or I[_SUPPRESS] != 0:
        return False
    others = 0
    for q in range(4):
        if q != blamed:
            others += blame[q]
    return blame[blamed] >= FC and 4 * others <= blame[blamed]


@nb.njit(cache=True)
def _window(k, chi, dof, blamed, ring_chi, ring_dof, cap, z, S):
    """The misfit window: (chi-square per degree of freedom, above the alarm threshold)."""
    c_max = cap * max(dof, 1.0)
    cc = chi if chi < c_max else c_max
    if blamed >= 0 and cc > cap:
        cc = cap
    j = k % ring_chi.size
    S[_SUM_CHI] += cc - ring_chi[j]
    S[_SUM_DOF] += dof - ring_dof[j]
    ring_chi[j] = cc
    ring_dof[j] = dof
    if S[_SUM_DOF] <= 0.5:
        return 0.0, False
    return S[_SUM_CHI] / S[_SUM_DOF], S[_SUM_CHI] > chi_square_quantile(S[_SUM_DOF], z)


@nb.njit(cache=True)
def _follow(S, step, accel_gain, speed_gain, v_max):
    """The tracker (alpha-beta-gamma with alpha = 1; :class:`ObserverSettings`): the
    acceleration, then the speed from the innovation ``step``; the speed bounded by ``v_max``,
    and then no acceleration (no wind-up)."""
    S[_A] += accel_gain * step
    S[_V] = S[_V] + S[_A] + speed_gain * step
    if abs(S[_V]) > v_max:
        S[_V] = v_max if S[_V] > 0.0 else -v_max
        S[_A] = 0.0


@nb.njit(cache=True)
def _readmit(d, k, r, a, dg, step, w0, travel, readmit_travel, S, I):
    """Readmit an excluded channel after ``readmit_travel`` of readings within 4 sigma of the
    model at the fitted angle (linearized at the prediction)."""
    x = I[_EXCL]
    if x < 0:
        return
    if not math.isfinite(d[k, x]):
        S[_CLEAN] = 0.0
        return
    e = r[x] - a[x] * dg[x] * step
    S[_CLEAN] = S[_CLEAN] + travel if w0[x] * e * e < 16.0 else 0.0
    if S[_CLEAN] >= readmit_travel:
        I[_EXCL] = -1
        S[_CLEAN] = 0.0


@nb.njit(cache=True)
def _track(d, G, dG, c, amp, w0, n_m, y_initial, cfg, offsets, a, b, y_out, misfit, code, info):
    """The observer over a recording: per sample read, one look-up of the model at the
    predicted angle, one Gauss-Newton step (robustly: the fits without each channel on an
    outlier), isolate faults, update the misfit window, adapt gain and level, readmit, and write
    y_obs, misfit and state. The first sample (and only it) is
    acquired by a search of the table nodes ``offsets`` within half a pole pitch."""
    h = TWO_PI / G.shape[0]
    pitch = TWO_PI / n_m
    max_step = pitch / 8.0
    v_max = 0.4 * pitch  # the tracker's speed bound: 0.8 of Nyquist (half a pitch per sample)
    gross = np.maximum(cfg[16] * math.sqrt(2.0) * amp, 8.0 / np.sqrt(w0))
    f, dg, r, dk, w = np.empty(3), np.empty(3), np.empty(3), np.empty(3), w0.copy()
    ring_chi, ring_dof = np.zeros(int(cfg[2])), np.zeros(int(cfg[2]))
    ring_blame = -np.ones(int(cfg[7]), dtype=np.int64)
    blame = np.zeros(4, dtype=np.int64)
    # adaptation: information matrix of (a_0, b_0, a_1, b_1, a_2, b_2), starting at the prior
    p0, H, L = np.empty((3, 2)), np.zeros((6, 6)), np.zeros((6, 6))
    gr, P, wm = np.zeros(6), np.zeros(6), np.zeros(3)
    for i in range(3):
        p0[i, 0] = a[i]
        p0[i, 1] = b[i]
        H[2 * i, 2 * i] = cfg[10] * w0[i] * amp[i] * amp[i]
        H[2 * i + 1, 2 * i + 1] = cfg[10] * w0[i]
    pending, phase, hold = False, 0, False
    S = np.zeros(7)
    S[_Y] = y_initial
    I = np.array([-1, -1, 0, 0, 1, -1], dtype=np.int64)
    for k in range(d.shape[0]):
        if I[_NEXT] >= 0:  # the exclusion decided on the previous sample (hold: see below)
            hold, I[_EXCL], I[_BLAMED_OUT], I[_NEXT] = True, I[_NEXT], 1, -1
            I[_FIRST] = k if I[_FIRST] < 0 else I[_FIRST]
            S[_CLEAN] = 0.0
            ring_blame[:], blame[:] = -1, 0
            ring_chi[:], ring_dof[:] = 0.0, 0.0  # the window starts again on two channels
            S[_SUM_CHI], S[_SUM_DOF] = 0.0, 0.0
        active = _read(d, k, dk, w, w0, S, I)
        yp = S[_Y] + S[_V]
        blamed, mark, chi, step, y_new, outlier = -1, -1, 0.0, 0.0, yp, False
        acquired = active >= 2 and I[_ACQUIRE] != 0
        fitted = active >= 2 and not acquired
        if acquired:
            y_new = _acquire(G, dk, c, a, b, w, yp, h, offsets)
            I[_ACQUIRE] = 0
        elif fitted:
            srr, num, den = _linearize(G, dG, h, dk, c, a, b, w, yp, f, dg, r)
            step, chi = _step(srr, num, den, max_step)
            if active == 3 and chi > cfg[5]:
                step, chi, blamed, mark, outlier = _robust(f, dg, r, a, w, srr, num, den, chi,
                                                           max_step, cfg[6], gross)  # fmt: skip
            y_new = yp + step
        if _isolate(k, blamed, mark, ring_blame, blame, int(cfg[8]), I):
            I[_NEXT] = blamed  # excluded from the next sample on (firmware: not on this one's time)
        if blamed < 0 and fitted:  # speed held on samples explained without a channel
            _follow(S, step, cfg[0], cfg[1], v_max)
        S[_Y] = y_new
        travel = n_m * abs(S[_V])
        dof = float(active - 1) if fitted else 0.0
        mf, above = _window(k, chi, dof, blamed, ring_chi, ring_dof, cfg[4], cfg[3], S)
        S[_BAD] = S[_BAD] + travel if above else 0.0
        stale = above and S[_BAD] >= cfg[14]
        if not above:
            I[_SUPPRESS] = 0
        elif I[_EXCL] >= 0 and I[_BLAMED_OUT] != 0 and math.isfinite(d[k, I[_EXCL]]):
            # the two channels left do not fit either: not a channel fault but a model that no
            # longer fits (remount): readmit the channel and let the misfit monitor speak
            I[_EXCL], I[_SUPPRESS] = -1, 1
        # the adaptation's cycle advances on samples without the fits of _robust, but for the
        # first such sample after an exclusion (hold; firmware: the exclusion's work does not
        # share its sample's time with a part of the adaptation)
        if not (outlier or hold):
            # settled: the step (the innovation) within 5 sigma of the angle's own noise 1/den,
            # so the gains and levels never learn a prediction still catching up (a rotor
            # already spinning at the first sample, an acquisition off by a transient)
            eligible = fitted and not stale and blamed < 0 and step * step * den < 25.0
            pending, phase = _adapt_cycle(
                phase, pending, eligible, stale, travel, f, dg, r, step, den, amp, w, w0, a, b,
                p0, H, gr, wm, L, P, cfg,
            )  # fmt: skip
        hold = hold and outlier
        if fitted:
            _readmit(d, k, r, a, dg, step, w0, travel, cfg[15], S, I)
        y_out[k], misfit[k] = S[_Y], mf
        # a model that no longer fits outranks a channel out: the two left must fit to be trusted
        code[k] = 4 if active < 2 else 2 if stale else 3 if I[_EXCL] >= 0 else 1 if above else 0
    info[0], info[1] = I[_EXCL], I[_FIRST]
