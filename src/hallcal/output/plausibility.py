"""Plausibility of the firmware's samples: channel ranges, windows and the step rule.

:func:`_plausibility` decides, from the calibrated flux model, what a plausible sample looks
like (:class:`Plausibility`); :mod:`hallcal.output.firmware` puts it into the
:class:`~hallcal.output.firmware.FirmwareDesign` and :mod:`hallcal.output.codegen` into C.

Each Hall channel must lie in its calibrated range, and the alpha/beta radius in its calibrated
window, both widened by a relative ``tolerance`` (drift of gain and magnet with temperature) and
six noise sigmas. The step rule: with w the largest speed [electrical turns per sample], s the
largest slope of f_init's electrical angle against the true one (the sensors' distortion:
f_init's steps at speed w are up to ``ws = s w``) and m six sigmas of the step noise, a sample
is accepted when f_init's electrical step from the last accepted sample is within ``A_h = (h +
1) ws + m`` after h samples held (what f_init can have moved meanwhile at the speed limit:
:func:`step_window`). ``held`` counts the rejected samples and those accepted right after a
rejection (unconfirmed), less one for each sample accepted right after an accepted one; when it
reaches ``fault_after`` the fault flag latches and the angle is re-acquired (any step is then
accepted, the fault latched). ``fault_after`` is the requested count or fewer: at most ``H +
1``, H the largest hold count at which no step of a rotor at up to twice the speed limit can
alias, ``(h + 1) 2 ws + A_h + m < 1`` (:func:`alias_holds`: f_init's motion since the last
accepted sample and the window together stay below one electrical turn). So, without a fault: no
accepted step exceeds what the speed limit allows after the samples held, a rotor at up to 2 w
never slips (its samples are held above ``ws + m`` and the fault latches), and no accepted step
is an alias. Measured on top (``benchmarks/bench_slip.txt``): no slip without the fault flag
over 100 000 adversarial trials per class (overspeed to 2 w, a bad first sample, bursts of 2-5
bad samples, stuck and clipped channels); what the rule cannot tell from motion is a run of bad
samples that itself looks like a trajectory (each within the window of the last).

Units: angles in rad unless a name says turns; "electrical" angles are n_m times the
mechanical ones. Hall signals are in the artifact's unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.sensor.absolute import null_vector
from hallcal.sensor.flux import FluxModel

#: Speed limit without a maximum speed [electrical turns per sample]: 22.5 electrical degrees.
DEFAULT_SPEED = 0.0625
#: Noise sigmas added to every window.
NOISE_SIGMAS = 6.0
_MODEL_GRID = 4096  # points per revolution to evaluate the flux model for the windows


@dataclass(frozen=True)
class Plausibility:
    """What a plausible sample looks like, from the calibration.

    Attributes
    ----------
    tolerance : float
        Relative widening of the calibrated ranges (gain and magnet drift).
    channel_lo, channel_hi : ndarray, shape (3,)
        Range of each Hall channel (artifact unit).
    radius_lo, radius_hi : float
        Window of the alpha/beta radius |P (d - o)| (artifact unit).
    radius_model : tuple of float
        Smallest and largest radius of the calibrated model over the revolution.
    null : ndarray, shape (3,)
        Unit null vector of the projection (``P @ null = 0``, components summing to >= 0).
    null_lo, null_hi : float
        Window of ``null . (d - o)`` (artifact unit): the model's range widened by
        ``tolerance`` times the largest radius and six noise sigmas. A stuck, clipped or
        disconnected channel leaves it long before the angle is far off.
    noise_sigma : float
        Hall noise per channel used for the margins (artifact unit; 0 if unknown).
    step_limit : float
        Largest electrical step of f_init from the last accepted sample with no sample held,
        ``slope w + m`` [turns per sample].
    step_growth : float
        What the window grows by for each sample held after the first, ``slope w`` [electrical
        turns] (:func:`step_window`).
    step_first : float
        The window after one sample held [electrical turns] (:func:`step_window`).
    slope : float
        Largest ratio of f_init's electrical angle to the true one over a small step (the
        model's d f_init / d y0, at least 1): f_init's steps at speed w are up to slope w.
    step_noise : float
        Six sigmas of the step's noise [electrical turns], m.
    max_speed : float or None
        The maximum speed the step limit was derived from [rad/s mechanical], or None for the
        default limit.
    speed : float
        w: the largest true speed [electrical turns per sample] tracked without rejections (up
        to it no input of one glitch sample makes the angle slip).
    glitch_safe_step : float
        The speed below which nothing slips [electrical turns per sample]: w.
    alias_holds : int
        H: the largest count of samples held in a row at which no accepted step can be an alias
        for a rotor at up to 2 w (``(h + 1) 2 w + A_h + m < 1``).
    fault_after : int
        Consecutive rejected samples after which the state flags a fault (latched) and
        re-acquires: the requested count, or ``alias_holds + 1`` when that is fewer.
    requested_fault_after : int
        The count asked for.
    """

    tolerance: float
    channel_lo: NDArray[np.float64]
    channel_hi: NDArray[np.float64]
    radius_lo: float
    radius_hi: float
    radius_model: tuple[float, float]
    null: NDArray[np.float64]
    null_lo: float
    null_hi: float
    noise_sigma: float
    step_limit: float
    step_growth: float
    step_first: float
    slope: float
    step_noise: float
    max_speed: float | None
    speed: float
    glitch_safe_step: float
    alias_holds: int
    fault_after: int
    requested_fault_after: int


def _plausibility(
    flux: FluxModel,
    n: int,
    P: NDArray,
    o: NDArray,
    noise_floor: float | None,
    tolerance: float,
    max_speed: float | None,
    sample_time: float,
    fault_after: int,
    source: str,
) -> Plausibility:
    y0 = TWO_PI * np.arange(_MODEL_GRID) / _MODEL_GRID
    g = flux(y0)
    ab = (g - o) @ P.T
    r = np.hypot(ab[:, 0], ab[:, 1])
    r_min, r_max = float(np.min(r)), float(np.max(r))
    if not r_min > 0.0:
        raise HallcalInputError(
            f"{source}: key 'model' gives a zero alpha/beta vector: no angle there"
        )
    # Hall noise per channel from the noise floor: floor = sigma |P|_F / (sqrt(2) r n)
    sigma = 0.0
    if noise_floor is not None:
        sigma = noise_floor * math.sqrt(2.0) * float(np.mean(r)) * n / float(np.linalg.norm(P))
    sigma_r = sigma * float(np.max(np.linalg.norm(P, axis=1)))
    gmin, gmax = np.min(g, axis=0), np.max(g, axis=0)
    centre, half = 0.5 * (gmax + gmin), 0.5 * (gmax - gmin)
    widen = (1.0 + tolerance) * half + NOISE_SIGMAS * sigma
    radius_lo = (1.0 - tolerance) * r_min - NOISE_SIGMAS * sigma_r
    radius_hi = (1.0 + tolerance) * r_max + NOISE_SIGMAS * sigma_r
    # the component along P's null vector (a common mode for symmetric sensors): its model
    # range widened as the radius window is; a stuck or clipped channel moves it by about 0.6
    # of its error, far out of the window before the angle is off by a twentieth of a turn
    nv = null_vector(P)
    nv = nv if float(np.sum(nv)) >= 0.0 else -nv
    zeta = (g - o) @ nv
    null_lo = float(np.min(zeta)) - tolerance * r_max - NOISE_SIGMAS * sigma
    null_hi = float(np.max(zeta)) + tolerance * r_max + NOISE_SIGMAS * sigma
    if not radius_lo > 0.05 * r_min:
        raise HallcalInputError(
            f"{source}: the amplitude window would reach zero (tolerance {tolerance:g} and the "
            "noise are too large for this sensor map)"
        )
    # step: noise of the electrical angle between two samples, in turns
    sigma_el = sigma_r / r_min  # rad, per sample
    step_noise = NOISE_SIGMAS * math.sqrt(2.0) * sigma_el / TWO_PI
    w = DEFAULT_SPEED if max_speed is None else max_speed * sample_time * n / TWO_PI
    # f_init's electrical angle moves up to `slope` times as fast as the true one (the sensors'
    # distortion): its steps at the speed limit are up to slope w
    el = np.unwrap(np.arctan2(ab[:, 1], ab[:, 0]))
    slope = max(1.0, float(np.max(np.diff(el) / np.diff(n * y0))))
    ws = slope * w
    holds = alias_holds(ws, step_noise)
    if holds < 0:
        given = "the default speed limit" if max_speed is None else f"max_speed {max_speed:g} rad/s"
        raise HallcalInputError(
            f"{given} is {ws:.3g} electrical turns per sample of f_init (the sensor map's "
            f"distortion speeds f_init up to {slope:.3g}x): f_init cannot follow a third of a "
            "turn per sample or more; give a lower --max-speed"
        )
    return Plausibility(
        tolerance=tolerance,
        channel_lo=centre - widen,
        channel_hi=centre + widen,
        radius_lo=radius_lo,
        radius_hi=radius_hi,
        radius_model=(r_min, r_max),
        null=nv,
        null_lo=null_lo,
        null_hi=null_hi,
        noise_sigma=sigma,
        step_limit=ws + step_noise,
        step_growth=ws,
        step_first=step_window(1, ws, step_noise),
        slope=slope,
        step_noise=step_noise,
        max_speed=max_speed,
        speed=w,
        glitch_safe_step=w,
        alias_holds=holds,
        fault_after=min(fault_after, holds + 1),
        requested_fault_after=fault_after,
    )


def step_window(h: int, w: float, m: float) -> float:
    """The step window after h samples held [electrical turns]: ``w + m`` for none; after the
    first, also room for the last accepted sample having been a glitch (another ``w + m``), so
    that the true angle is back within it after one held sample even at the speed limit the
    other way; then ``w`` more per sample held (the most f_init moves per sample).

    Parameters
    ----------
    h : int
        Samples held since the last accepted one.
    w : float
        f_init's largest step at the speed limit [electrical turns per sample].
    m : float
        Noise margin of a step [electrical turns].
    """
    return (h + 1) * w + m


def alias_holds(w: float, m: float, *, cap: int = 1000) -> int:
    """The largest count h of samples held after which an accepted step cannot be an alias
    for a rotor at up to twice the speed limit: ``(h + 1) 2 w + A_h + m < 1``, the motion since
    the last accepted sample and the window ``A_h`` (:func:`step_window`) together below one
    electrical turn.

    Parameters
    ----------
    w : float
        f_init's largest step at the speed limit [electrical turns per sample].
    m : float
        Noise margin of a step [electrical turns].
    cap : int, keyword-only
        Largest count returned (the largest ``fault_after``).

    Returns
    -------
    int
        H (-1 when even the first sample's window can alias: ``3 w + 2 m >= 1``).
    """
    if 3.0 * w + 2.0 * m >= 1.0:
        return -1
    h = 0
    while h < cap and (h + 2) * 2.0 * w + step_window(h + 1, w, m) + m < 1.0:
        h += 1
    return h
