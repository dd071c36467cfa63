"""How fast to ramp the next calibration run, from a calibration of the same motor type.

The numeric part is :mod:`hallcal.fit.ramp_design` (Fisher information of the SEM problem against
ramp speed); this module builds its loop and model from a :class:`Calibration` (or an artifact)
and is what ``hallcal plan`` and the calibrate warning call.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import ArrayLike

from hallcal.errors import HallcalInputError
from hallcal.fit.gauss_newton import ParameterLayout
from hallcal.fit.ramp_design import RampPlan, candidate_speeds, plan_ramp, ramp_samples
from hallcal.limits import MAX_PLAN_SAMPLES, MAX_PLAN_SPEEDS
from hallcal.pipeline.calibration import Calibration
from hallcal.pipeline.plant import closed_loop

__all__ = ["plan_next_ramp"]


def plan_next_ramp(
    cal: Calibration,
    *,
    revolutions: float,
    speeds: ArrayLike | None = None,
    target: float = 1.1,
    noise_variance: float | None = None,
) -> RampPlan:
    """Predicted table error against ramp speed for the drive and motor type of ``cal``.

    The loop is the calibration's (its controller, its plant with the gain correction, its
    f_init projection and offsets); the model is its flux map and cogging torque, whose
    coefficients count as unknowns of the next run; the noise is the calibration's estimate.

    Parameters
    ----------
    cal : Calibration
        A closed-loop calibration of the same motor type (from ``hallcal.calibrate`` or
        ``hallcal.load``).
    revolutions : float, keyword-only
        Length of the planned ramp [mechanical revolutions].
    speeds : array_like, optional, keyword-only
        Candidate speeds [rad/s] (default: see :func:`hallcal.fit.ramp_design.plan_ramp`).
    target : float, keyword-only
        Acceptable predicted / noise floor.
    noise_variance : float, optional, keyword-only
        sigma^2 per Hall channel [sensor unit^2] (default: the calibration's estimate).

    Returns
    -------
    RampPlan

    Raises
    ------
    HallcalInputError
        The calibration has no closed loop (constant-speed), no Fourier flux model or no noise
        estimate, or an argument is out of range.
    """
    if cal.plant is None or cal.setup.controller is None:
        raise HallcalInputError(
            "plan: the calibration has no closed loop (plant and controller); a ramp plan is "
            "for closed-loop runs"
        )
    if not (math.isfinite(revolutions) and revolutions > 0):
        raise HallcalInputError("plan: revolutions must be a number > 0")
    if not (math.isfinite(target) and target >= 1.0):
        raise HallcalInputError("plan: target must be a number >= 1 (predicted / noise floor)")
    sigma2 = noise_variance
    if sigma2 is None:
        sigma2 = _noise_variance(cal)
    loop = closed_loop(cal.setup, cal.plant)
    loop = dataclasses.replace(loop, projection=cal.lut.projection, offset=cal.lut.offset)
    orders = tuple(cal.cogging.orders) if cal.cogging is not None else ()
    layout = ParameterLayout(cal.flux.basis, cogging_orders=orders)
    x = layout.pack(cal.flux.theta, 0.0, cal.cogging)
    if speeds is not None:
        speeds = np.asarray(speeds, dtype=np.float64).reshape(-1)
        if speeds.size == 0 or not np.all(np.isfinite(speeds) & (speeds > 0)):
            raise HallcalInputError("plan: speeds must be numbers > 0 [rad/s]")
        if speeds.size > MAX_PLAN_SPEEDS:
            raise HallcalInputError(
                f"plan: {speeds.size} speeds, above the limit of {MAX_PLAN_SPEEDS}"
            )
    grid = candidate_speeds(loop, layout, revolutions, speeds)
    ts = loop.sample_time
    total = sum(ramp_samples(float(v), revolutions, ts) for v in grid)
    if not total <= MAX_PLAN_SAMPLES:
        raise HallcalInputError(
            f"plan: {revolutions:g} revolutions at {grid.size} speeds from {grid[0]:.3g} rad/s "
            f"would simulate {total:.3g} samples, above the limit of {MAX_PLAN_SAMPLES:.3g}: "
            "fewer revolutions, fewer or faster speeds"
        )
    # the default grid is passed as None: plan_ramp extends it downwards (within its own
    # sample cap, PLAN_MAX_SAMPLES) while its slowest speed meets the target
    return plan_ramp(loop, layout, x, noise_variance=sigma2, revolutions=revolutions,
                     speeds=speeds, target=target)  # fmt: skip


def _noise_variance(cal: Calibration) -> float:
    """sigma^2 of the calibration run (its SEM's: the artifact's diagnostics)."""
    value = cal.diagnostics.get("noise_variance", math.nan)
    try:
        value = float(value)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise HallcalInputError(
            "plan: the calibration holds no noise estimate (diagnostics.noise_variance); pass "
            "the Hall noise variance"
        )
    return value
