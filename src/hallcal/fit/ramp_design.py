"""Experiment design of the closed-loop calibration run: how fast to ramp.

The Hall data alone, ``d(t) = g(y0(t))``, cannot tell the flux map g and the angle y0 from a
warped pair ``(g o w^-1, w(y0))``: both give the same d and the same f_init output y. The closed
loop tells them apart only through its dynamics. Linearised about the ramp, a warp
``delta(y0)`` of the model moves the simulated angle by ``T delta`` instead of ``delta``
(T the complementary sensitivity), so the data see ``S delta`` with ``S = 1 / (1 + C G)`` the
sensitivity at the warp's frequencies ``k v`` (harmonic k of the mechanical angle at ramp speed
v [rad/s]). A band-limited flux basis adds a second constraint (a warp moves flux energy beyond
the basis' band edge), but on a real rotor, whose magnets all differ in shape, the basis must hold
every sideband and the loop is left to do the work. On a fast loop a slow ramp puts the low
harmonics where ``|S| ~ (k v / w_c)^2`` is tiny, and the run determines the table poorly however
long it is; a faster ramp over the same revolutions (and fewer samples) fixes it.

This module predicts, before a run is recorded, the table error that a ramp at speed v over R
revolutions will give: the Fisher information ``J^T J / sigma^2`` of the SEM problem (problem),
evaluated on the noise-free closed loop of a flux model (e.g. a calibration of the same motor
type), propagated to the table by eq. (recon_biject) exactly as the calibration's own predicted
error (:func:`hallcal.fit.sem.predicted_angle_error`). See Ljung (1999), "System
Identification", ch. 13 (experiment design, informative experiments in closed loop) and
Pintelon & Schoukens (2012), sec. 2.7.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.fit.gauss_newton import ParameterLayout, gauss_newton_system, simulate_model
from hallcal.fit.sem import predicted_angle_error
from hallcal.messages import Outcome
from hallcal.sensor.flux import FluxModel
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "PlanStatus",
    "RampPlan",
    "RampPrediction",
    "angle_noise_floor",
    "plan_ramp",
    "predict_ramp_error",
    "speed_limits",
]

#: Samples per spatial period of the highest harmonic at the fastest speed considered: the
#: simulation holds the flux between samples, and 8 samples per period keep that well resolved.
SAMPLES_PER_PERIOD = 8
#: Fewest samples a planned run may have, per parameter (the covariance is a large-sample result).
SAMPLES_PER_PARAMETER = 20
#: Rows of J used for J^T J in a prediction (every stride-th sample, times stride): a prediction
#: need not be exact to the last percent, and this keeps one candidate below a second.
GRAM_SAMPLES = 40_000


class PlanStatus(Outcome):
    """How :func:`plan_ramp` ended."""

    #: A speed on the grid reaches the target; ``recommended`` is the slowest such speed.
    OK = "ok"
    #: No speed reaches the target; ``recommended`` is the one with the smallest prediction.
    TARGET_NOT_REACHED = "target_not_reached"
    #: The closed loop diverged (or the information was singular) at every speed.
    FAILED = "failed"


@dataclass(frozen=True)
class RampPrediction:
    """Predicted table error of one ramp.

    Attributes
    ----------
    speed : float
        Ramp speed v [rad/s, mechanical].
    revolutions : float
        Length of the ramp [mechanical revolutions].
    samples : int
        N = 2 pi R / (v Ts).
    predicted : float
        RMS angle error of f_star the run would give, ``sqrt(floor^2 + mean var eta)`` [rad];
        inf when the loop diverged or the information is singular.
    floor : float
        Noise floor of the angle for this flux model and noise [rad].
    """

    speed: float
    revolutions: float
    samples: int
    predicted: float
    floor: float

    @property
    def ratio(self) -> float:
        """predicted / floor."""
        return self.predicted / self.floor


@dataclass(frozen=True)
class RampPlan:
    """Predicted table error against ramp speed, and the speed to record at.

    Attributes
    ----------
    status : PlanStatus
        See :class:`PlanStatus`.
    predictions : tuple of RampPrediction
        One per candidate speed, slowest first.
    recommended : RampPrediction or None
        The slowest candidate within ``target`` x floor, else the best one (None when all failed).
    target : float
        The target ratio predicted / floor.
    message : str
        One line for a user.
    """

    status: PlanStatus
    predictions: tuple[RampPrediction, ...] = field(repr=False)
    recommended: RampPrediction | None
    target: float
    message: str


def angle_noise_floor(
    flux: FluxModel,
    pole_pairs: int,
    noise_variance: float,
    *,
    projection: ArrayLike,
    offset: ArrayLike,
    points: int = 512,
) -> float:
    """RMS over one revolution of the angle noise of one sample of f_init [rad].

    For white Hall noise of variance sigma^2 per channel, the electrical angle
    ``atan2(beta, alpha)`` of ``(alpha, beta) = P (d - o)`` has variance
    ``sigma^2 |P^T (-beta, alpha)|^2 / rho^4`` with ``rho^2 = alpha^2 + beta^2``; divided by n_m
    for the mechanical angle (for ideal amplitude-1 sensors about ``sigma sqrt(2/3) / n_m``).

    Parameters
    ----------
    flux : FluxModel
        g_theta.
    pole_pairs : int
        n_m.
    noise_variance : float
        sigma^2 per Hall channel [sensor unit^2].
    projection : array_like (2, 3), keyword-only
        f_init's projection P.
    offset : array_like (3,), keyword-only
        The offsets o f_init subtracts.
    points : int, keyword-only
        Grid size over one revolution.

    Returns
    -------
    float
        The floor [rad, mechanical].
    """
    y0 = TWO_PI * np.arange(points) / points
    P = np.asarray(projection, dtype=np.float64)
    ab = (flux(y0) - np.asarray(offset, dtype=np.float64)) @ P.T
    rho2 = ab[:, 0] ** 2 + ab[:, 1] ** 2
    a_perp = np.column_stack([-ab[:, 1], ab[:, 0]]) @ P
    var = noise_variance * np.einsum("ij,ij->i", a_perp, a_perp) / (pole_pairs**2 * rho2**2)
    return float(np.sqrt(np.mean(var)))


def _ramp(speed: float, revolutions: float, sample_time: float) -> NDArray[np.float64]:
    """r_k = v Ts k over R revolutions (the paper's calibration ramp from standstill)."""
    n = int(math.ceil(ramp_samples(speed, revolutions, sample_time)))
    return speed * sample_time * np.arange(n, dtype=np.float64)


def predict_ramp_error(
    loop: ClosedLoop,
    layout: ParameterLayout,
    x: ArrayLike,
    *,
    speed: float,
    revolutions: float,
    noise_variance: float,
) -> RampPrediction:
    """The table error a calibration ramp at ``speed`` would give, from the Fisher information.

    Simulates the noise-free closed loop (eq. state_eq) of the model x on the ramp, forms
    ``J^T J`` of problem (problem) there (:func:`~hallcal.fit.gauss_newton.gauss_newton_system`,
    from at most :data:`GRAM_SAMPLES` rows), takes ``cov = sigma^2 (J^T J)^-1`` (the gain and
    cogging parameters of the layout included, so their uncertainty counts) and propagates its
    theta block to the table (:func:`~hallcal.fit.sem.predicted_angle_error`).

    Parameters
    ----------
    loop : ClosedLoop
        Plant model, controller, n_m and f_init of the drive.
    layout : ParameterLayout
        What x holds (flux harmonics; gain and cogging parameters count as unknowns).
    x : array_like (p,)
        The model, e.g. a calibration of the same motor type.
    speed : float, keyword-only
        Ramp speed v [rad/s, mechanical], > 0.
    revolutions : float, keyword-only
        Ramp length R [revolutions], > 0.
    noise_variance : float, keyword-only
        sigma^2 per Hall channel [sensor unit^2].

    Returns
    -------
    RampPrediction
    """
    if not (speed > 0 and revolutions > 0 and noise_variance > 0):
        raise ValueError("speed, revolutions and noise_variance must be > 0")
    ts = loop.sample_time
    r = _ramp(speed, revolutions, ts)
    flux = FluxModel(layout.basis, layout.theta(x))
    floor = angle_noise_floor(flux, loop.pole_pairs, noise_variance,
                              projection=loop.projection, offset=loop.offset)  # fmt: skip
    sim = simulate_model(loop, layout, x, r)
    inf = RampPrediction(speed, revolutions, r.size, math.inf, floor)
    if not sim.status.success:
        return inf
    stride = max(1, r.size // GRAM_SAMPLES)
    system = gauss_newton_system(loop, layout, x, r, sim.d, stride=stride)
    if not system.status.success:
        return inf
    try:
        cov = noise_variance * np.linalg.inv(system.gram)
    except np.linalg.LinAlgError:
        return inf
    n_theta = layout.n_theta
    sd = predicted_angle_error(flux, cov[:n_theta, :n_theta], loop.pole_pairs,
                               projection=loop.projection, offset=loop.offset)  # fmt: skip
    mean_var = float(np.mean(sd**2))
    if not math.isfinite(mean_var):
        return inf
    return RampPrediction(speed, revolutions, r.size, math.sqrt(floor**2 + mean_var), floor)


#: The longest planned calibration run [samples]: 100 s at 10 kHz, 250 s at 4 kHz, several times
#: the runs of the paper (26-40 s). The plan's grid goes no slower than this.
PLAN_MAX_SAMPLES = 1_000_000


def speed_limits(
    loop: ClosedLoop, layout: ParameterLayout, revolutions: float
) -> tuple[float, float]:
    """The range of ramp speeds worth predicting [rad/s].

    Upper: the highest flux harmonic H keeps :data:`SAMPLES_PER_PERIOD` samples per spatial
    period, ``H v Ts <= 2 pi / 8``. Lower: not relevant for identifiability (slower is worse on
    any loop with integral action), so the grid starts a factor 100 below the upper limit; the
    run must also keep :data:`SAMPLES_PER_PARAMETER` samples per parameter, which caps the upper
    limit for short runs.

    Parameters
    ----------
    loop : ClosedLoop
        The drive's loop (its sample time).
    layout : ParameterLayout
        The model's parameters.
    revolutions : float
        Ramp length [revolutions].

    Returns
    -------
    tuple of float
        (v_min, v_max) [rad/s].
    """
    ts = loop.sample_time
    h_max = max(int(max(layout.basis.harmonics)), int(loop.pole_pairs))
    v_max = TWO_PI / (SAMPLES_PER_PERIOD * h_max * ts)
    n_min = SAMPLES_PER_PARAMETER * layout.size
    v_max = min(v_max, TWO_PI * revolutions / (n_min * ts))
    return v_max / 100.0, v_max


def candidate_speeds(
    loop: ClosedLoop, layout: ParameterLayout, revolutions: float, speeds: ArrayLike | None
) -> NDArray[np.float64]:
    """The speeds :func:`plan_ramp` predicts [rad/s], sorted: `speeds`, or by default 13 spaced
    by sqrt(2) up to the upper limit of :func:`speed_limits`."""
    if speeds is None:
        _, v_max = speed_limits(loop, layout, revolutions)
        return v_max * np.sqrt(0.5) ** np.arange(12, -1, -1)
    return np.sort(np.asarray(speeds, dtype=np.float64).reshape(-1))


def ramp_samples(speed: float, revolutions: float, ts: float) -> float:
    """Samples of a ramp over `revolutions` at `speed` [rad/s] with sample time `ts` [s]."""
    return TWO_PI * revolutions / (speed * ts)


def plan_ramp(
    loop: ClosedLoop,
    layout: ParameterLayout,
    x: ArrayLike,
    *,
    noise_variance: float,
    revolutions: float,
    speeds: ArrayLike | None = None,
    target: float = 1.1,
    stop_at_target: bool = False,
) -> RampPlan:
    """Predicted table error against ramp speed; the slowest speed within target x floor.

    Parameters
    ----------
    loop : ClosedLoop
        Plant model, controller, n_m and f_init of the drive.
    layout : ParameterLayout
        What x holds.
    x : array_like (p,)
        The model (a calibration of the same motor type, or a nominal one).
    noise_variance : float, keyword-only
        sigma^2 per Hall channel [sensor unit^2].
    revolutions : float, keyword-only
        Ramp length R [revolutions].
    speeds : array_like, optional, keyword-only
        Candidate speeds [rad/s]; default 13 speeds spaced by sqrt(2) up to the upper limit of
        :func:`speed_limits`.
    target : float, keyword-only
        Acceptable predicted / floor (default 1.1).
    stop_at_target : bool, keyword-only
        Stop at the first (slowest) speed within target: the slow candidates are the costly
        ones (most samples), so this costs little more than the answer.

    Returns
    -------
    RampPlan
    """
    default = speeds is None
    v = candidate_speeds(loop, layout, revolutions, speeds)

    def predict(speed: float) -> RampPrediction:
        return predict_ramp_error(loop, layout, x, speed=speed, revolutions=revolutions,
                                  noise_variance=noise_variance)  # fmt: skip

    preds: list[RampPrediction] = []
    for s in v:
        p = predict(float(s))
        preds.append(p)
        if stop_at_target and p.ratio <= target:
            break
    # the default grid's slowest speed within target: slower ones may be too, so the grid goes
    # on down (by sqrt 2) until one is not, or the run would exceed PLAN_MAX_SAMPLES
    capped = False
    while default and not stop_at_target and preds and preds[0].ratio <= target:
        slower = preds[0].speed * math.sqrt(0.5)
        if preds[0].samples * math.sqrt(2.0) > PLAN_MAX_SAMPLES:
            capped = True
            break
        preds.insert(0, predict(slower))
    finite = [p for p in preds if math.isfinite(p.predicted)]
    if not finite:
        return RampPlan(PlanStatus.FAILED, tuple(preds), None, target,
                        "the closed loop diverged at every candidate speed")  # fmt: skip
    good = [p for p in finite if p.ratio <= target]
    if good:
        best, status = good[0], PlanStatus.OK
        msg = (
            f"ramp at >= {best.speed:.3g} rad/s over {revolutions:g} revolutions "
            f"({best.samples} samples): predicted {best.ratio:.2f}x the noise floor"
        )
        if best is preds[0]:
            msg += f"; the slowest speed tried already meets {target:g}x" + (
                f" (slower runs would exceed {PLAN_MAX_SAMPLES} samples): the ramp speed "
                "does not limit this motor's table"
                if capped
                else ": slower speeds may too (give lower --speeds)"
            )
    else:
        best, status = min(finite, key=lambda p: p.ratio), PlanStatus.TARGET_NOT_REACHED
        msg = (
            f"no speed reaches {target:g}x the noise floor over {revolutions:g} revolutions; "
            f"the best is {best.speed:.3g} rad/s ({best.ratio:.2f}x): record more revolutions "
            "or use fewer harmonics"
        )
        if default:
            msg += (
                f" (the fastest speed tried, {v[-1]:.3g} rad/s, is the limit of "
                f"{SAMPLES_PER_PERIOD} samples per period of the highest flux harmonic)"
            )
    return RampPlan(status, tuple(preds), best, target, msg)
