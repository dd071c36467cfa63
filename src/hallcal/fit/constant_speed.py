"""Calibration from an open-loop constant-speed run (``[trajectory] kind = "constant-speed"``).

The paper (van Meer et al., "Self-Calibrating Position Measurements: Applied to Imperfect Hall
Sensors") identifies the flux model g_theta by simulation-error minimization of a closed loop,
the SEM problem. Many benches instead spin the rotor open loop at a constant speed. There the true
angle is known up to two numbers, ``y0_k = a + b k`` (k the sample index), and the SEM problem
becomes

    min_{theta, a, b}  sum_k || d_k - psi(a + b k) theta ||^2 ,

a separable nonlinear least-squares problem: linear in theta for fixed (a, b). It is solved by
variable projection (Golub & Pereyra, SIAM J. Numer. Anal. 10, 1973; Kaufman's Jacobian, BIT 15,
1975): theta is eliminated by linear least squares and Gauss-Newton runs on the nonlinear
parameters only. For a Fourier basis the set {g_theta(y0 + c)} equals {g_theta(y0)}, so
the cost does not depend on ``a`` at all: the only nonlinear parameter is the speed ``b``, and ``a``
is a gauge fixed afterwards (see :func:`calibrate_constant_speed`).

The module also estimates the electrical geometry of the three sensors from raw data
(:func:`estimate_sensor_geometry`), so that f_init (Clarke + atan2 + unwrap) can use the measured
sensor
spacing, gains and offsets instead of the nominal Clarke transform, and it locates the
constant-speed part of a recording (:func:`find_constant_speed`).

Units: angles in rad (mechanical unless stated), time in samples, d in the sensor's unit (V or raw
ADC counts: offsets are handled by the geometry and by the constant term of the basis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.limits import one_blas_thread
from hallcal.messages import Outcome
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sensor.reconstruction import f_init

__all__ = [
    "ConstantSpeedResult",
    "SensorGeometry",
    "SpeedSegment",
    "calibrate_constant_speed",
    "default_harmonics",
    "estimate_sensor_geometry",
    "find_constant_speed",
    "speed_deviation",
]


class GeometryStatus(Outcome):
    """How well the three signals determine the sensor geometry (:class:`SensorGeometry`)."""

    OK = "ok"
    PARTIAL_COVERAGE = "partial_coverage"  # not every electrical angle seen: extrapolated
    DEGENERATE = "degenerate"  # no ellipse: noise only, or no rotation


class SegmentStatus(Outcome):
    """Whether :func:`find_constant_speed` found a constant-speed part."""

    OK = "ok"
    NOT_FOUND = "not_found"


class ConstantSpeedStatus(Outcome):
    """Outcome of :func:`calibrate_constant_speed`."""

    OK = "ok"
    WARNING = "warning"  # see ConstantSpeedResult.warnings
    NOT_CONVERGED = "not_converged"  # the speed estimate did not meet its tolerance


# --------------------------------------------------------------------------------------------------
# Sensor geometry
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorGeometry:
    """Electrical geometry of three Hall sensors: ``d_h ~ o_h + A_h cos(psi - phi_h)``.

    psi is the electrical angle (``n_m y0`` up to a constant). The phases are relative to sensor 1
    (``phases[0] = 0``) and oriented so that the sensor order is the positive direction:
    ``0 < phases[1] < phases[2] < 2 pi``. For the nominal wiring of the paper (f_init with Clarke)
    the phases are 0, 120 and 240 degrees.

    Attributes
    ----------
    phases : ndarray, shape (3,)
        Electrical phase phi_h of each sensor [rad], in [0, 2 pi).
    amplitudes : ndarray, shape (3,)
        A_h, in the sensor's unit.
    offsets : ndarray, shape (3,)
        o_h, in the sensor's unit (the centre of the fitted ellipse).
    projection : ndarray, shape (2, 3)
        Least-squares left inverse of ``M = [A_h cos phi_h, A_h sin phi_h]`` scaled by the mean
        amplitude: ``projection @ (d - offsets)`` gives (alpha, beta) = A_mean (cos psi, sin psi).
        With equal amplitudes and nominal phases it equals the first two rows of the Clarke matrix.
    direction : int
        +1 if the electrical angle (with this orientation) increased over the data, -1 if it
        decreased, 0 if it did not move a full electrical cycle either way.
    electrical_cycles : float
        Net electrical cycles covered by the data (signed).
    revolutions : float or None
        ``electrical_cycles / pole_pairs`` when the pole pairs were given.
    fit_rms : float
        RMS of the residual of the three signals about the fitted ellipse, relative to the mean
        amplitude (harmonic distortion and noise; about 0.01-0.05 on real sensors).
    status : GeometryStatus
        ``"ok"``, ``"partial_coverage"`` (the data does not sweep all electrical angles, so the
        ellipse is extrapolated) or ``"degenerate"`` (the signals do not span a plane or do not
        trace an ellipse; the phases are then the nominal ones and meaningless).
    message : str
        Human-readable explanation of the status.
    """

    phases: NDArray[np.float64] = field(repr=False)
    amplitudes: NDArray[np.float64] = field(repr=False)
    offsets: NDArray[np.float64] = field(repr=False)
    projection: NDArray[np.float64] = field(repr=False)
    direction: int
    electrical_cycles: float
    revolutions: float | None
    fit_rms: float
    status: GeometryStatus
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.status is GeometryStatus.OK

    @property
    def phases_deg(self) -> NDArray[np.float64]:
        """phases in degrees."""
        return np.degrees(self.phases)

    @property
    def spacing_deg(self) -> NDArray[np.float64]:
        """Electrical spacing between neighbours 1->2, 2->3, 3->1 [deg]; sums to 360."""
        p = np.append(self.phases, TWO_PI)
        return np.degrees(np.diff(p))

    def f_init(self, d: ArrayLike, pole_pairs: int, *, y_initial: float = 0.0) -> NDArray:
        """f_init (Clarke + atan2 + unwrap, eq. (fimp)) with this geometry's projection and
        offsets.

        Parameters
        ----------
        d : array_like, shape (N, 3)
            Hall signals.
        pole_pairs : int
            n_m.
        y_initial : float, keyword-only
            f_init's estimate before the first sample [rad].

        Returns
        -------
        ndarray, shape (N,)
            y [rad, mechanical].
        """
        return f_init(
            d, pole_pairs, y_initial=y_initial, projection=self.projection, offset=self.offsets
        )

    def to_dict(self) -> dict:
        """JSON-ready description (for the calibration artifact)."""
        return {
            "phases": self.phases.tolist(),
            "phases_deg": self.phases_deg.tolist(),
            "amplitudes": self.amplitudes.tolist(),
            "offsets": self.offsets.tolist(),
            "projection": self.projection.tolist(),
            "direction": int(self.direction),
            "electrical_cycles": float(self.electrical_cycles),
            "revolutions": None if self.revolutions is None else float(self.revolutions),
            "fit_rms": float(self.fit_rms),
            "status": self.status,
            "message": self.message,
        }


def _projection_from(phases: NDArray, amplitudes: NDArray) -> NDArray[np.float64]:
    M = amplitudes[:, None] * np.column_stack([np.cos(phases), np.sin(phases)])
    return np.mean(amplitudes) * np.linalg.pinv(M)


def _fit_ellipse(z: NDArray[np.float64]) -> tuple[NDArray, NDArray] | None:
    """Direct least-squares ellipse fit (Fitzgibbon, Pilu & Fisher 1999; Halir & Flusser 1998).

    Returns the centre c (2,) and L (2, 2) with ``z - c = L [cos u, sin u]`` on the ellipse, or
    None if no ellipse fits.
    """
    s = np.std(z, axis=0)
    s[s == 0.0] = 1.0
    x, y = z[:, 0] / s[0], z[:, 1] / s[1]
    D1 = np.column_stack([x * x, x * y, y * y])
    D2 = np.column_stack([x, y, np.ones_like(x)])
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    try:
        T = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError:
        return None
    Mred = S1 + S2 @ T
    Mred = np.array([Mred[2] / 2.0, -Mred[1], Mred[0] / 2.0])
    w, V = np.linalg.eig(Mred)
    V = np.real(V)
    cond = 4.0 * V[0] * V[2] - V[1] ** 2
    good = np.flatnonzero(cond > 0)
    if good.size == 0:
        return None
    a1 = V[:, good[0]]
    A, B, C = a1
    Dl, E, F = T @ a1
    Q = np.array([[A, B / 2.0], [B / 2.0, C]])
    lin = np.array([Dl, E])
    try:
        c = -0.5 * np.linalg.solve(Q, lin)
    except np.linalg.LinAlgError:
        return None
    kappa = c @ Q @ c - F  # (z - c)^T Q (z - c) = kappa on the ellipse
    Qn = Q / kappa
    w, U = np.linalg.eigh(Qn)
    if np.any(w <= 0):
        return None
    L = U @ np.diag(1.0 / np.sqrt(w)) @ U.T  # (z-c) = L u, |u| = 1  <=>  (z-c)^T Qn (z-c) = 1
    Sd = np.diag(s)
    return Sd @ c, Sd @ L


def estimate_sensor_geometry(
    d: ArrayLike,
    pole_pairs: int | None = None,
    *,
    refine: int = 2,
    max_fit_rms: float = 0.3,
) -> SensorGeometry:
    """Electrical phases, amplitudes and offsets of three Hall sensors from raw data alone.

    Model: ``d_k - o = M [cos psi_k, sin psi_k]`` with ``M[h] = A_h [cos phi_h, sin phi_h]``, the
    first-harmonic part of the flux model of the paper (section "Model structure") seen in the
    electrical angle psi. The centred data spans (nearly) a plane in R^3; in that plane it traces an
    ellipse. Steps:

    1. principal plane by SVD of the centred data (PCA);
    2. direct least-squares ellipse fit in the plane (Fitzgibbon et al. 1999), giving the centre
       o and M up to a rotation/reflection of psi;
    3. ``refine`` rounds of alternation: psi_k = atan2 of the projected data, then o and M by
       linear least squares of d on [1, cos psi, sin psi] (the fundamental of each sensor);
    4. rotation fixing ``phi_1 = 0`` and reflection fixing the orientation
       ``0 < phi_2 < phi_3 < 2 pi`` (the sensor order is the positive direction, so that f_init
       increases when a standard-wired motor turns forward).

    Pure sinusoids (any spacing, gains, offsets) are recovered exactly up to noise. Harmonic
    distortion and per-pole variations average out in the fundamental; the calibration proper
    (:func:`calibrate_constant_speed`) corrects what remains.

    Parameters
    ----------
    d : array_like, shape (N, 3)
        Hall signals; best a constant-speed stretch sweeping whole electrical cycles.
    pole_pairs : int, optional
        n_m; only used to report the mechanical revolutions covered.
    refine : int, keyword-only
        Rounds of the alternating refinement after the ellipse fit (0 = pure ellipse fit).
    max_fit_rms : float, keyword-only
        Largest ``fit_rms`` (relative to the amplitude) accepted as an ellipse; above it the status
        is ``"degenerate"``. Real sensors give 0.01-0.1, pure noise about 0.6.

    Returns
    -------
    SensorGeometry
    """
    x = np.asarray(d, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError("d must have shape (N, 3)")
    if x.shape[0] < 8:
        raise ValueError("need at least 8 samples to fit the sensor geometry")
    if not np.all(np.isfinite(x)):
        raise ValueError("d contains non-finite values")
    try:
        o, M = _principal_plane_ellipse(x)  # steps 1-2
    except _NoEllipse as exc:
        return _degenerate_geometry(x, str(exc))
    o, M = _refine_fundamental(x, o, M, int(refine))  # step 3
    phi, amp = _oriented_phases(M)  # step 4
    P = _projection_from(phi, amp)
    psi, fit_rms = _ellipse_residual(x, o, phi, amp, P)
    un = np.unwrap(psi)
    cycles = float((un[-1] - un[0]) / TWO_PI)
    direction = int(np.sign(cycles)) if abs(cycles) >= 1.0 else 0
    status, message = _geometry_status(psi, fit_rms, max_fit_rms)
    revs = None if pole_pairs is None else cycles / int(pole_pairs)
    return SensorGeometry(phi, amp, o, P, direction, cycles, revs, fit_rms, status, message)


class _NoEllipse(Exception):
    """The data in their principal plane trace no ellipse (the message says why)."""


def _degenerate_geometry(x: NDArray, message: str) -> SensorGeometry:
    """Nominal phases, amplitudes from the spread, offsets from the mean: status "degenerate"."""
    ph = np.array([0.0, TWO_PI / 3.0, 2.0 * TWO_PI / 3.0])
    amp = np.maximum(np.std(x, axis=0) * math.sqrt(2.0), np.finfo(float).tiny)
    return SensorGeometry(
        ph, amp, x.mean(axis=0), _projection_from(ph, amp), 0, 0.0,
        None, float("nan"), GeometryStatus.DEGENERATE, message,
    )  # fmt: skip


def _principal_plane_ellipse(x: NDArray) -> tuple[NDArray, NDArray]:
    """Steps 1-2 of :func:`estimate_sensor_geometry`: centre o and M with ``d - o = M [cos u,
    sin u]``, from the principal plane (SVD of the centred data) and the direct least-squares
    ellipse fit in it (Fitzgibbon et al. 1999). Raises :class:`_NoEllipse`."""
    mean = x.mean(axis=0)
    xc = x - mean
    _, sv, Vt = np.linalg.svd(xc, full_matrices=False)
    if sv[1] <= 1e-9 * max(sv[0], np.finfo(float).tiny):
        raise _NoEllipse("the three signals do not span a plane (no rotation in the data?)")
    U2 = Vt[:2].T  # (3, 2)
    fit = _fit_ellipse(xc @ U2)
    if fit is None:
        raise _NoEllipse("no ellipse fits the data in its principal plane")
    c, L = fit
    return mean + U2 @ c, U2 @ L  # d - o = M [cos u, sin u]


def _refine_fundamental(x: NDArray, o: NDArray, M: NDArray, rounds: int) -> tuple[NDArray, NDArray]:
    """Step 3 of :func:`estimate_sensor_geometry`: alternate psi_k = atan2 of the projected data
    and (o, M) by linear least squares of d on [1, cos psi, sin psi] (each sensor's
    fundamental)."""
    for _ in range(rounds):
        psi = _psi_from(x, o, M)
        H = np.column_stack([np.ones_like(psi), np.cos(psi), np.sin(psi)])
        coef, *_ = np.linalg.lstsq(H, x, rcond=None)
        o, M = coef[0].copy(), coef[1:].T.copy()
    return o, M


def _oriented_phases(M: NDArray) -> tuple[NDArray, NDArray]:
    """Step 4 of :func:`estimate_sensor_geometry`: phases phi_h and amplitudes A_h of the rows of
    M, rotated so that ``phi_1 = 0`` and reflected so that ``0 < phi_2 < phi_3 < 2 pi``."""
    phi = np.arctan2(M[:, 1], M[:, 0])
    amp = np.hypot(M[:, 0], M[:, 1])
    phi = np.mod(phi - phi[0], TWO_PI)
    if phi[1] > phi[2]:
        phi = np.mod(-phi, TWO_PI)
    phi[0] = 0.0
    return phi, amp


def _ellipse_residual(
    x: NDArray, o: NDArray, phi: NDArray, amp: NDArray, P: NDArray
) -> tuple[NDArray, float]:
    """The electrical angle psi of every sample through the projection P, and the RMS residual
    of the data about the ellipse relative to the mean amplitude (``fit_rms``)."""
    ab = (x - o) @ P.T / np.mean(amp)
    psi = np.arctan2(ab[:, 1], ab[:, 0])
    Mfin = amp[:, None] * np.column_stack([np.cos(phi), np.sin(phi)])
    resid = x - o - np.column_stack([np.cos(psi), np.sin(psi)]) @ Mfin.T
    return psi, float(np.sqrt(np.mean(resid**2)) / np.mean(amp))


def _geometry_status(
    psi: NDArray, fit_rms: float, max_fit_rms: float
) -> tuple[GeometryStatus, str]:
    """Degenerate above ``max_fit_rms``; partial coverage when the data visit fewer than all 36
    electrical 10-degree sectors."""
    # coverage: fraction of 36 electrical sectors visited
    sectors = np.unique(np.floor(np.mod(psi, TWO_PI) / TWO_PI * 36).astype(int))
    if not fit_rms < max_fit_rms:
        return GeometryStatus.DEGENERATE, (
            f"the signals do not trace an ellipse (residual {fit_rms:.2f} of the amplitude): "
            "noise only, or no rotation?"
        )
    if sectors.size < 36:
        return GeometryStatus.PARTIAL_COVERAGE, (
            f"the data sweeps {sectors.size} of 36 electrical 10-degree sectors; the ellipse is "
            "extrapolated elsewhere"
        )
    return GeometryStatus.OK, ""


def _psi_from(x: NDArray, o: NDArray, M: NDArray) -> NDArray[np.float64]:
    u = (x - o) @ np.linalg.pinv(M).T
    return np.arctan2(u[:, 1], u[:, 0])


# --------------------------------------------------------------------------------------------------
# Constant-speed segment
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SpeedSegment:
    """The constant-speed part of a recording, found from f_init's speed.

    Attributes
    ----------
    start, stop : int
        Sample indices: the segment is ``start <= k < stop``.
    speed : float
        Mean f_init speed over the segment [rad (mechanical) per sample]; negative when turning
        backwards.
    samples_per_cycle : int
        Samples per electrical cycle at that speed (the smoothing window).
    revolutions : float
        Mechanical revolutions in the segment.
    status : SegmentStatus
        ``"ok"`` or ``"not_found"``.
    """

    start: int
    stop: int
    speed: float
    samples_per_cycle: int
    revolutions: float
    status: SegmentStatus

    @property
    def ok(self) -> bool:
        return self.status is SegmentStatus.OK

    def split(self, revolutions: float) -> tuple[int, int, int]:
        """Indices (start, mid, stop) with the first ``revolutions`` in start..mid."""
        mid = self.start + int(round(revolutions * TWO_PI / abs(self.speed)))
        return self.start, min(mid, self.stop), self.stop


def find_constant_speed(
    d: ArrayLike,
    pole_pairs: int,
    *,
    geometry: SensorGeometry | None = None,
    tolerance: float = 0.1,
    margin_cycles: float = 0.5,
) -> SpeedSegment:
    """Locate the longest stretch of nearly constant speed (e.g. the cruise of a trapezoidal move).

    f_init's angle (with the estimated geometry) is differentiated and averaged over a sliding
    window of exactly one electrical cycle, which removes f_init's errors that are periodic in
    the electrical angle (the bulk of them). The cruise speed is the median of that
    smoothed speed where it exceeds half its maximum magnitude. The segment is the longest run of
    samples all of whose one-cycle windows have a speed within ``tolerance`` (relative) of the
    cruise speed, shrunk by ``margin_cycles`` electrical cycles on each side.

    Parameters
    ----------
    d : array_like, shape (N, 3)
        Hall signals.
    pole_pairs : int
        n_m.
    geometry : SensorGeometry, optional
        Default: estimated from the whole recording.
    tolerance : float, keyword-only
        Allowed relative deviation of the smoothed speed from the cruise speed. Per-pole
        variations of real rings move f_init's cycle-averaged speed by a few percent.
    margin_cycles : float, keyword-only
        Extra electrical cycles dropped at each end.

    Returns
    -------
    SpeedSegment
    """
    x = np.asarray(d, dtype=np.float64)
    n = int(pole_pairs)
    geo = estimate_sensor_geometry(x, n) if geometry is None else geometry
    e = n * geo.f_init(x, n)  # electrical angle, unwrapped
    N = e.size
    v = np.diff(e)
    if N < 16 or not np.any(v):
        return SpeedSegment(0, 0, 0.0, 0, 0.0, SegmentStatus.NOT_FOUND)
    # first guess of the cruise speed: a high quantile of |v| (robust to the rest phases)
    vq = float(np.quantile(np.abs(v), 0.75))
    W = 0
    cruise = 0.0
    for _ in range(3):
        W_new = int(np.clip(round(TWO_PI / max(vq, 1e-12)), 2, max(2, N // 4)))
        if W_new == W:
            break
        W = W_new
        vs = (e[W:] - e[:-W]) / W  # mean speed over [k, k+W): centred at k + W/2
        big = np.abs(vs) >= 0.5 * np.max(np.abs(vs))
        cruise = float(np.median(vs[big]))
        vq = abs(cruise)
    ok = np.abs(vs - cruise) <= tolerance * abs(cruise)
    # longest run of True
    idx = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    starts, stops = idx[0::2], idx[1::2]
    if starts.size == 0:
        return SpeedSegment(0, 0, 0.0, W, 0.0, SegmentStatus.NOT_FOUND)
    j = int(np.argmax(stops - starts))
    # vs[i] is the mean speed over samples i..i+W-1 (W + 1 angle samples); keep the samples k all
    # of whose windows i in [k - W + 1, k] are within tolerance, then drop the margins
    margin = int(round(margin_cycles * W))
    start = int(starts[j]) + W - 1 + margin
    stop = min(int(stops[j]) - margin, N)
    if stop - start < 2 * W:
        return SpeedSegment(0, 0, 0.0, W, 0.0, SegmentStatus.NOT_FOUND)
    k = np.arange(start, stop, dtype=np.float64)
    slope = float(np.polyfit(k, e[start:stop], 1)[0]) / n
    revs = abs(slope) * (stop - start) / TWO_PI
    return SpeedSegment(start, stop, slope, W, revs, SegmentStatus.OK)


# --------------------------------------------------------------------------------------------------
# Harmonics
# --------------------------------------------------------------------------------------------------


def default_harmonics(
    pole_pairs: int,
    *,
    electrical: int = 3,
    sidebands: int | None = None,
) -> tuple[int, ...]:
    """Mechanical harmonics for a ring of ``pole_pairs`` pole pairs with per-pole variations.

    The flux of a ring of n_m identical pole pairs is periodic in the electrical angle n_m y0
    (mechanical harmonics j n_m); magnets that differ from each other modulate it, which
    puts energy in the sidebands ``j n_m +- s`` (an eccentric or tilted ring: s = 1; an arbitrary
    per-pole pattern of amplitudes and offsets: every s up to n_m / 2).

    With ``sidebands=None`` (default) every harmonic ``1 .. electrical * n_m`` is returned: the
    per-pole pattern of real rings is broadband, so all sidebands below the top electrical harmonic
    are kept. With an integer ``sidebands`` the set is
    ``{j n_m + s : j = 0..electrical, |s| <= sidebands} intersect [1, inf)``.

    The default (3 electrical harmonics, i.e. 1..75 for 25 pole pairs) was chosen by held-out error
    on the ring-jig recordings (``tests/test_real_ringjig.py``: calibrate on two revolutions, test
    on the remaining 2.35; f_star error in electrical degrees RMS, files 1/2/3, robust weights on):
    1..62: 1.03/0.80/0.83; 1..75: 0.82/0.40/0.44; 1..80: 0.82/0.40/0.41; 1..87: 1.05/0.42/0.42;
    1..100: 1.35/0.53/0.50 (without robust weights 1..75 gives 1.16/0.46/0.45). Multiples of 25
    with sidebands +-6 only: 3.6/4.5/4.2; multiples of 25 alone: 4.8/6.5/7.0 (f_init: 4.9/6.6/7.0):
    on that ring nearly all of f_init's error is per-magnet, and the sensor offsets vary at 1..24
    cycles per revolution.

    Parameters
    ----------
    pole_pairs : int
        n_m.
    electrical : int, keyword-only
        Highest electrical harmonic j.
    sidebands : int, keyword-only
        Sideband order s kept around each j n_m (also the low harmonics 1..s of j = 0); default
        all harmonics up to ``electrical * pole_pairs``.

    Returns
    -------
    tuple of int
        Sorted mechanical harmonics >= 1.
    """
    n = int(pole_pairs)
    if n < 1 or electrical < 1 or (sidebands is not None and sidebands < 0):
        raise ValueError("need pole_pairs >= 1, electrical >= 1 and sidebands >= 0")
    if sidebands is None:
        return tuple(range(1, int(electrical) * n + 1))
    sb = int(sidebands)
    out = {j * n + s for j in range(int(electrical) + 1) for s in range(-sb, sb + 1)}
    return tuple(sorted(h for h in out if h >= 1))


# --------------------------------------------------------------------------------------------------
# Constant-speed calibration
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ConstantSpeedResult:
    """Result of :func:`calibrate_constant_speed`.

    Attributes
    ----------
    model : FluxModel
        The identified g_theta (theta: ``model.theta``, shape (3, m)).
    a, b : float
        The true angle on the segment is ``y0_k = a + b k`` [rad, rad per sample], k the sample
        index of the whole recording, in f_init's frame (see the gauge in
        :func:`calibrate_constant_speed`). ``b < 0`` when the rotor turned against the sensor order.
    start, stop : int
        The segment used, ``start <= k < stop``.
    pole_pairs : int
        n_m.
    geometry : SensorGeometry
        The geometry of f_init (projection and offsets) used for the table.
    lut : LUT
        The table of f_star = f_init + eta built from the model with the geometry's
        projection/offset.
    cost : float
        Unweighted cost of the SEM problem at the solution: sum of squared residuals over the
        segment.
    residual_rms : ndarray, shape (3,)
        RMS residual per channel [sensor unit].
    noise_std : float
        White-noise estimate [sensor unit, per channel, assumed equal]: from the second differences
        of the residual component orthogonal to the model curve's tangent g'(y0). Angle errors of
        the rotor (which move d along the curve) do not enter it and smooth model errors hardly do.
    angle_noise_floor : float
        RMS angle error [rad, mechanical] that white noise of ``noise_std`` gives through f_init.
    motion_rms : float
        RMS of the residual's tangential component expressed as an angle [rad, mechanical]: how far
        the rotor (as seen through the model) strays from the straight line a + b k. Several times
        ``angle_noise_floor`` means the constant-speed assumption is violated (speed ripple,
        resonances, stepper microsteps).
    weights : ndarray, shape (stop - start,)
        Final robust sample weights in (0, 1] (all ones with ``robust=False``).
    revolutions : float
        Mechanical revolutions in the segment, ``|b| (stop - start) / 2 pi``.
    iterations : int
        Gauss-Newton iterations on b (summed over the robust reweighting rounds).
    converged : bool
        Whether the last Gauss-Newton run met ``tol``.
    status : ConstantSpeedStatus
        ``"ok"``, ``"warning"`` (see ``warnings``) or ``"not_converged"``.
    warnings : tuple of str
        E.g. fewer than one revolution, non-bijective table, geometry status.
    """

    model: FluxModel
    a: float
    b: float
    start: int
    stop: int
    pole_pairs: int
    geometry: SensorGeometry
    lut: LUT
    cost: float
    residual_rms: NDArray[np.float64] = field(repr=False)
    noise_std: float
    angle_noise_floor: float
    motion_rms: float
    weights: NDArray[np.float64] = field(repr=False)
    revolutions: float
    iterations: int
    converged: bool
    status: ConstantSpeedStatus
    warnings: tuple[str, ...] = ()

    @property
    def theta(self) -> NDArray[np.float64]:
        return self.model.theta

    @property
    def direction(self) -> int:
        """+1 if the rotor turned in the sensor order (f_init increasing), -1 otherwise."""
        return 1 if self.b > 0 else -1

    def y0(self, k: ArrayLike | None = None) -> NDArray[np.float64]:
        """The fitted straight line ``a + b k`` (default: the segment's samples) [rad]."""
        kk = (
            np.arange(self.start, self.stop, dtype=np.float64)
            if k is None
            else np.asarray(k, dtype=np.float64)
        )
        return self.a + self.b * kk

    def to_dict(self) -> dict:
        """JSON-ready summary (for the calibration artifact); theta and the table not included."""
        return {
            "trajectory": "constant-speed",
            "start": self.start,
            "stop": self.stop,
            "a": self.a,
            "b": self.b,
            "revolutions": self.revolutions,
            "cost": self.cost,
            "residual_rms": self.residual_rms.tolist(),
            "noise_std": self.noise_std,
            "angle_noise_floor": self.angle_noise_floor,
            "motion_rms": self.motion_rms,
            "downweighted_fraction": float(np.mean(self.weights < 1.0)),
            "iterations": self.iterations,
            "converged": self.converged,
            "status": self.status,
            "warnings": list(self.warnings),
            "geometry": self.geometry.to_dict(),
        }


class _WeightedLS:
    """Weighted linear least squares with the basis matrix B: the inner problem of VP.

    Normal equations with a Cholesky factor (the Fourier basis over whole revolutions is nearly
    orthogonal, so this is accurate and about 10x faster than QR); QR when the Gram matrix is
    ill-conditioned (e.g. less than a revolution of data).
    """

    def __init__(self, B: NDArray, sw: NDArray) -> None:
        self.B = B
        self.Bw = B * sw[:, None]
        self.sw = sw
        self._cho = None
        self._qr = None
        G = self.Bw.T @ self.Bw
        try:
            cho = scipy.linalg.cho_factor(G, lower=True, check_finite=False)
            dg = np.abs(np.diag(cho[0]))
            if dg.min() > 1e-6 * dg.max():
                self._cho = cho
        except np.linalg.LinAlgError:
            pass
        if self._cho is None:
            self._qr = np.linalg.qr(self.Bw)

    def coef(self, Xw: NDArray) -> NDArray:
        """C minimizing ||Xw - Bw C|| (Xw already weighted)."""
        if self._qr is not None:
            Q, R = self._qr
            return np.linalg.solve(R, Q.T @ Xw)
        return scipy.linalg.cho_solve(self._cho, self.Bw.T @ Xw, check_finite=False)

    def solve(self, D: NDArray) -> tuple[NDArray, NDArray]:
        """(theta^T, weighted residual) for data D (unweighted)."""
        Dw = D * self.sw[:, None]
        thT = self.coef(Dw)
        return thT, Dw - self.Bw @ thT

    def project_out(self, Xw: NDArray) -> NDArray:
        """Xw minus its projection on range(Bw)."""
        return Xw - self.Bw @ self.coef(Xw)


def _basis_derivative(B: NDArray, basis: FourierBasis) -> NDArray:
    """d beta / d y0 from beta itself (columns 1, sin h y, cos h y, ... of the Fourier basis)."""
    h = basis.harmonic_array
    out = np.zeros_like(B)
    out[:, 1::2] = h * B[:, 2::2]
    out[:, 2::2] = -h * B[:, 1::2]
    return out


def _gauss_newton_b(
    D: NDArray,
    basis: FourierBasis,
    t: NDArray,
    a_c: float,
    b: float,
    sw: NDArray,
    *,
    max_iterations: int,
    tol: float,
) -> tuple[float, int, bool]:
    """Variable-projection Gauss-Newton on the speed b (a is a gauge, held at a_c)."""
    h_max = float(np.max(basis.harmonic_array))
    tmax = float(np.max(np.abs(t)))
    ls = _WeightedLS(basis.evaluate(a_c + b * t), sw)
    thT, r = ls.solve(D)
    cost = float(np.sum(r * r))
    for it in range(1, int(max_iterations) + 1):
        Jc = (_basis_derivative(ls.B, basis) * (t * sw)[:, None]) @ thT  # d(sw model)/db
        Jp = ls.project_out(Jc)  # Kaufman: the part orthogonal to range(sw B)
        den = float(np.sum(Jp * Jp))
        if not den > 0.0:
            return b, it, False
        step = float(np.sum(Jp * r)) / den
        for _ in range(40):  # halve until the cost does not increase
            ls_n = _WeightedLS(basis.evaluate(a_c + (b + step) * t), sw)
            th_n, r_n = ls_n.solve(D)
            c_n = float(np.sum(r_n * r_n))
            if c_n <= cost * (1.0 + 1e-12):
                break
            step *= 0.5
        else:
            return b, it, abs(step) * h_max * tmax < tol
        b += step
        ls, thT, r, cost = ls_n, th_n, r_n, c_n
        if abs(step) * h_max * tmax < tol:
            return b, it, True
    return b, int(max_iterations), False


def calibrate_constant_speed(
    d: ArrayLike,
    pole_pairs: int,
    basis: FourierBasis,
    *,
    start: int,
    stop: int,
    geometry: SensorGeometry | None = None,
    max_iterations: int = 50,
    tol: float = 1e-9,
    robust: bool = True,
    robust_iterations: int = 4,
    robust_threshold: float = 2.0,
    lut_points: int = 4096,
) -> ConstantSpeedResult:
    """Identify g_theta from a constant-speed stretch: the SEM problem with ``y0_k = a + b k``.

    The cost ``J(theta, a, b) = sum_{k=start}^{stop-1} w_k ||d_k - psi(a + b k) theta||^2`` is
    separable (Golub & Pereyra 1973). For fixed (a, b), theta is the linear least-squares solution
    (QR of the basis matrix). The Fourier basis is shift-invariant, so after eliminating theta J
    does not depend on a; Gauss-Newton with Kaufman's variable-projection Jacobian
    ``dr/db = -(I - Q Q^T) (d beta / d y0 * k) theta`` runs on b alone, with step halving if
    the cost rises (3-5 iterations on real data). b starts from the slope of f_init's unwrapped
    output over the segment, well inside the basin: a slope error delta moves harmonic h by a phase
    of about h delta K over K samples, and f_init's error is periodic, so the line fit through it
    is accurate to a small fraction of a cycle.

    What pins b: the electrical period (harmonic n_m) and the per-magnet variations (harmonics
    other than multiples of n_m), which repeat once per revolution. With less than one revolution
    in the segment those harmonics cannot be told apart and part of the ring is never seen: the
    result then carries a warning, and the table extrapolates there.

    Gauge. Replacing a by a + c and theta by the correspondingly rotated theta gives the same fit,
    so a is fixed by convention. f_star = f_init + eta(f_init mod 2 pi) needs the
    model's angle to be f_init's own angle up to f_init's (small, periodic) error: f_init's frame
    starts at y = 0 before the first sample of the recording and counts electrical cycles from
    there, and the table's unwrapping (the bijectivity condition) assumes
    ``|y0 - y_hat| < pi / n_m``.
    We choose a such that the (unweighted) mean of ``f_init(d_k) - (a + b k)`` over the segment is
    zero: f_star agrees with f_init on average and removes only its periodic error (over whole
    revolutions the table's eta has zero mean). An absolute mechanical zero is not observable
    without an index. Hence the table applies to recordings whose f_init starts at the same pole
    pair as this one (same power-up position, or after homing), as in the paper.

    Robust weights (``robust=True``). A real open-loop rotor does not turn exactly at constant
    speed: a stepper-driven rig rings at its torsional resonance in bursts, which moves d *along*
    the model curve. The residual's tangential component ``(g' . r) / |g'|^2`` is such an angle
    error; its local RMS over one electrical cycle, ``s_k``, is compared with its median ``s_med``
    and samples get the weight ``w_k = min(1, (c s_med / s_k)^2)`` (c = ``robust_threshold``),
    iterated ``robust_iterations`` times (iteratively reweighted least squares). White noise alone
    leaves all weights at 1 (a 1-cycle local RMS rarely doubles), so nothing is lost on clean
    data; transients violating the constant-speed model stop dominating theta.

    Parameters
    ----------
    d : array_like, shape (N, 3)
        The whole recording (raw units allowed); f_init runs over it from sample 0.
    pole_pairs : int
        n_m.
    basis : FourierBasis
        Mechanical harmonics of the model; must contain n_m. See :func:`default_harmonics`.
    start, stop : int, keyword-only
        The constant-speed part, ``start <= k < stop`` (see :func:`find_constant_speed`).
    geometry : SensorGeometry, optional
        f_init's projection and offsets; default :func:`estimate_sensor_geometry` on the segment.
    max_iterations : int, keyword-only
        Gauss-Newton iterations on b per reweighting round.
    tol : float, keyword-only
        Convergence when a step in b moves the highest harmonic by less than ``tol`` rad of phase
        at the ends of the segment.
    robust : bool, keyword-only
        Down-weight transients that violate the constant-speed model (see above).
    robust_iterations : int, keyword-only
        Reweighting rounds.
    robust_threshold : float, keyword-only
        c in the weight formula (larger = milder).
    lut_points : int, keyword-only
        Grid points of the table.

    Returns
    -------
    ConstantSpeedResult

    Raises
    ------
    ValueError
        Bad shapes or indices, a basis without the harmonic n_m, a segment too short for the basis,
        a degenerate sensor geometry, or no rotation in the segment.
    """
    x = _checked_signals(d, pole_pairs, basis, start, stop)
    n = int(pole_pairs)
    geo, warnings = _usable_geometry(x[start:stop], n, geometry)
    fit = _line_and_flux(x, geo, n, basis, start, stop, max_iterations=max_iterations, tol=tol,
                         rounds=int(robust_iterations) if robust else 0,
                         threshold=robust_threshold)  # fmt: skip
    lut = build_lut(fit.model, n, points=lut_points, projection=geo.projection, offset=geo.offsets)
    warnings += _segment_warnings(fit.revolutions, fit.speed.b, n, lut)
    return _constant_speed_result(fit, geo, lut, warnings)


def _usable_geometry(
    segment: NDArray, n: int, geometry: SensorGeometry | None
) -> tuple[SensorGeometry, list[str]]:
    """f_init's geometry (given, or :func:`estimate_sensor_geometry` on the segment); a
    degenerate one is refused, any other status short of "ok" is a warning."""
    geo = estimate_sensor_geometry(segment, n) if geometry is None else geometry
    if geo.status is GeometryStatus.DEGENERATE:
        raise ValueError(f"cannot calibrate: sensor geometry: {geo.message}")
    warnings: list[str] = []
    if not geo.ok:
        warnings.append(f"sensor geometry: {geo.status}: {geo.message}")
    return geo, warnings


@dataclass(frozen=True)
class _LineFit:
    """The straight line ``y0_k = a + b k`` on the segment, the flux model at it, its residual."""

    model: FluxModel
    a: float
    speed: _SpeedFit
    residuals: _Residuals
    start: int
    stop: int
    pole_pairs: int

    @property
    def revolutions(self) -> float:
        return abs(self.speed.b) * (self.stop - self.start) / TWO_PI


def _line_and_flux(
    x: NDArray, geo: SensorGeometry, n: int, basis: FourierBasis, start: int, stop: int, *,
    max_iterations: int, tol: float, rounds: int, threshold: float,
) -> _LineFit:  # fmt: skip
    """The SEM problem with ``y0_k = a + b k`` (see :func:`calibrate_constant_speed`).

    b by variable-projection Gauss-Newton inside the robust reweighting (:func:`_fit_speed`),
    a by the gauge ``mean(f_init - y0) = 0`` over the segment, theta by weighted linear least
    squares at that line (Golub & Pereyra 1973).
    """
    y = geo.f_init(x, n)
    k = np.arange(start, stop, dtype=np.float64)
    D, ys = x[start:stop], y[start:stop]
    with one_blas_thread():
        speed = _fit_speed(D, ys, k, n, basis, max_iterations=max_iterations, tol=tol,
                           rounds=rounds, threshold=threshold)  # fmt: skip
        # gauge: mean(f_init - y0) = 0 over the segment, in absolute sample index
        a = float(np.mean(ys - speed.b * k))
        B = basis.evaluate(a + speed.b * k)
        thT, _ = _WeightedLS(B, np.sqrt(speed.weights)).solve(D)
    model = FluxModel(basis, thT.T)
    res = _residual_statistics(D, B, thT, basis, geo, n)
    return _LineFit(model, a, speed, res, int(start), int(stop), n)


def _constant_speed_result(
    fit: _LineFit, geo: SensorGeometry, lut: LUT, warnings: list[str]
) -> ConstantSpeedResult:
    """The result of :func:`calibrate_constant_speed`, with its status."""
    if not fit.speed.converged:
        status = ConstantSpeedStatus.NOT_CONVERGED
    elif warnings:
        status = ConstantSpeedStatus.WARNING
    else:
        status = ConstantSpeedStatus.OK
    res = fit.residuals
    return ConstantSpeedResult(
        model=fit.model,
        a=fit.a,
        b=fit.speed.b,
        start=fit.start,
        stop=fit.stop,
        pole_pairs=fit.pole_pairs,
        geometry=geo,
        lut=lut,
        cost=res.cost,
        residual_rms=res.rms,
        noise_std=res.noise,
        angle_noise_floor=res.angle_floor,
        motion_rms=res.motion,
        weights=fit.speed.weights,
        revolutions=fit.revolutions,
        iterations=fit.speed.iterations,
        converged=fit.speed.converged,
        status=status,
        warnings=tuple(warnings),
    )


def _checked_signals(
    d: ArrayLike, pole_pairs: int, basis: FourierBasis, start: int, stop: int
) -> NDArray[np.float64]:
    """d as an (N, 3) float64 array, after checking the segment and the basis."""
    x = np.asarray(d, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError("d must have shape (N, 3)")
    N = x.shape[0]
    if not (0 <= int(start) < int(stop) <= N):
        raise ValueError(f"need 0 <= start < stop <= {N}, got start={start}, stop={stop}")
    if int(pole_pairs) not in basis.harmonics:
        raise ValueError(f"the basis must contain the pole-pair harmonic {int(pole_pairs)}")
    K = int(stop) - int(start)
    if K < 2 * basis.size:
        raise ValueError(
            f"segment of {K} samples is too short for {basis.size} basis functions per channel"
        )
    if not np.all(np.isfinite(x)):
        raise ValueError("d contains non-finite values")
    return x


@dataclass(frozen=True)
class _SpeedFit:
    """The speed b of the straight line y0 = a + b k, with the robust weights it ended with."""

    b: float
    weights: NDArray[np.float64]
    iterations: int
    converged: bool


def _fit_speed(
    D: NDArray,
    ys: NDArray,
    k: NDArray,
    n: int,
    basis: FourierBasis,
    *,
    max_iterations: int,
    tol: float,
    rounds: int,
    threshold: float,
) -> _SpeedFit:
    """Variable-projection Gauss-Newton on b inside ``rounds`` IRLS reweighting rounds.

    b starts from the slope of f_init's output over the segment; between rounds the weights come
    from the local RMS of the tangential residual over one electrical cycle (see
    :func:`calibrate_constant_speed`), until they change by less than 1e-3.
    """
    K = ys.size
    t = k - float(np.mean(k))  # centred time for conditioning
    b = float(np.polyfit(t, ys, 1)[0])
    if not abs(b) * K * n >= TWO_PI:
        raise ValueError(
            "f_init moves less than one electrical cycle over the segment: no rotation to "
            "calibrate from"
        )
    a_c = float(np.mean(ys))  # any fixed value: the cost does not depend on it
    w = np.ones(K)
    iterations = 0
    converged = False
    window = int(np.clip(round(TWO_PI / (n * abs(b))), 1, K))
    for rnd in range(rounds + 1):
        b, its, converged = _gauss_newton_b(
            D, basis, t, a_c, b, np.sqrt(w), max_iterations=max_iterations, tol=tol
        )
        iterations += its
        if rnd == rounds:
            break
        thT, _ = _WeightedLS(basis.evaluate(a_c + b * t), np.sqrt(w)).solve(D)
        w_new = _robust_weights(D, basis, thT, a_c + b * t, window, threshold)
        done = float(np.max(np.abs(w_new - w))) < 1e-3
        w = w_new
        window = int(np.clip(round(TWO_PI / (n * abs(b))), 1, K))
        if done:
            b, its, converged = _gauss_newton_b(
                D, basis, t, a_c, b, np.sqrt(w), max_iterations=max_iterations, tol=tol
            )
            iterations += its
            break
    return _SpeedFit(b, w, iterations, converged)


@dataclass(frozen=True)
class _Residuals:
    cost: float
    rms: NDArray[np.float64]
    noise: float
    angle_floor: float
    motion: float


def _residual_statistics(
    D: NDArray, B: NDArray, thT: NDArray, basis: FourierBasis, geo: SensorGeometry, n: int
) -> _Residuals:
    """Cost, noise level, angle noise floor and rotor motion from the final residual.

    White noise: second differences of the residual component orthogonal to the model curve
    (variance 6 sigma^2 in each of the two orthogonal dimensions); smooth model errors and rotor
    motion hardly enter. Motion: the tangential component expressed as an angle.
    """
    r = D - B @ thT
    G = _basis_derivative(B, basis) @ thT
    g2 = np.maximum(np.sum(G * G, axis=1), np.finfo(float).tiny)
    tang = np.sum(r * G, axis=1) / g2  # angle error along the curve [rad]
    orth = r - tang[:, None] * G
    dd = np.diff(orth, 2, axis=0)
    K = D.shape[0]
    noise = float(np.sqrt(np.sum(dd * dd) / (12.0 * max(K - 2, 1))))
    Pn = geo.projection / float(np.mean(geo.amplitudes))  # unit-circle alpha/beta
    return _Residuals(
        cost=float(np.sum(r * r)),
        rms=np.sqrt(np.mean(r * r, axis=0)),
        noise=noise,
        angle_floor=float(noise * math.sqrt(0.5 * np.trace(Pn @ Pn.T)) / n),
        motion=float(np.sqrt(np.mean(tang * tang))),
    )


def _segment_warnings(revs: float, b: float, n: int, lut: LUT) -> list[str]:
    """Less than a revolution, too few samples per electrical cycle, a folded table."""
    out = []
    if revs < 1.0:
        out.append(
            f"the segment covers {revs:.2f} < 1 revolution: per-magnet harmonics are not "
            "identifiable and part of the ring is unseen; the table extrapolates there"
        )
    if TWO_PI / (n * abs(b)) < 3.5:
        out.append(
            f"only {TWO_PI / (n * abs(b)):.1f} samples per electrical cycle: spin slower or "
            "sample faster"
        )
    if not lut.bijective:
        out.append(
            f"the table is not bijective (min slope {lut.min_slope:.3g}): f_star is unavailable"
        )
    return out


def _robust_weights(
    D: NDArray, basis: FourierBasis, thT: NDArray, y0: NDArray, window: int, c: float
) -> NDArray[np.float64]:
    """IRLS weights from the local RMS of the tangential (angle-like) residual."""
    B = basis.evaluate(y0)
    r = D - B @ thT
    G = _basis_derivative(B, basis) @ thT
    g2 = np.maximum(np.sum(G * G, axis=1), np.finfo(float).tiny)
    tang = np.sum(r * G, axis=1) / g2
    ker = np.ones(window) / window
    local = np.sqrt(np.convolve(tang * tang, ker, mode="same"))
    med = float(np.median(local))
    if not med > 0.0:
        return np.ones_like(tang)
    return np.minimum(1.0, (c * med / np.maximum(local, np.finfo(float).tiny)) ** 2)


def speed_deviation(d: NDArray, pole_pairs: int) -> float:
    """Largest relative deviation of f_init's one-electrical-cycle mean speed from its median.

    Parameters
    ----------
    d : ndarray, shape (N, 3)
        Hall signals of the (supposedly) constant-speed segment.
    pole_pairs : int
        n_m.

    Returns
    -------
    float
        ``max |v - median v| / |median v|`` over the moving one-electrical-period means v of
        f_init's electrical angle (0 for fewer than 8 samples or no motion); dimensionless.
    """
    if d.shape[0] < 8:
        return 0.0
    geo = estimate_sensor_geometry(d, pole_pairs)
    e = pole_pairs * geo.f_init(d, pole_pairs)
    v = float(np.median(np.diff(e)))
    if v == 0.0:
        return 0.0
    W = int(np.clip(round(TWO_PI / abs(v)), 1, max(1, e.size // 2)))
    vs = (e[W:] - e[:-W]) / W
    med = float(np.median(vs))
    return float(np.max(np.abs(vs - med)) / abs(med)) if med != 0.0 else 0.0
