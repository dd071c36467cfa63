"""The identified model's closed loop replayed on its recording, with cov(theta) from one pass.

A calibration read back from its artifact has the flux model, the plant, the controller and
the cogging torque but not the solver's internals. :func:`replay_closed_loop` re-simulates the
loop of the paper's SEM problem (Fig. cl_scheme: plant, controller, f_init, g_theta) at the
stored parameters to give the model's Hall signals d_sim and angle y0_sim, and for a Fourier
model one structured Gauss-Newton pass (:func:`~hallcal.fit.gauss_newton.gauss_newton_system`,
with the cogging coefficients as parameters, as in the calibration) gives
cov(theta) = sigma^2 (J^T J)^-1 over theta's block (Ljung 1999, sec. 9.3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.fit.gauss_newton import ParameterLayout, PassStatus, gauss_newton_system
from hallcal.fit.sem import _covariance
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import ClosedLoop
from hallcal.sim.lti import ContinuousTF, DiscreteTF

__all__ = ["LoopReplay", "replay_closed_loop"]


@dataclass(frozen=True)
class LoopReplay:
    """The closed loop of an identified model on its recording.

    Attributes
    ----------
    status : PassStatus
        ``ok``, or how the simulation failed (then the arrays are None).
    sse : float
        The simulation-error cost J(theta) = sum ||d - d_sim||^2 on the recording.
    d_sim : ndarray (N, 3) or None
        The model's Hall signals g_theta(y0_sim).
    y0_sim : ndarray (N,) or None
        The simulated mechanical angle [rad].
    covariance : ndarray (3 m, 3 m) or None
        cov(theta), flattened sensor-major (Fourier models; None otherwise or when J^T J is
        singular).
    noise_variance : float
        sigma^2 per Hall channel used for the covariance: the given one, else
        J / (3 N - p).
    """

    status: PassStatus
    sse: float
    d_sim: NDArray[np.float64] | None = field(default=None, repr=False)
    y0_sim: NDArray[np.float64] | None = field(default=None, repr=False)
    covariance: NDArray[np.float64] | None = field(default=None, repr=False)
    noise_variance: float = math.nan


def replay_closed_loop(
    flux: FluxModel,
    lut: LUT,
    plant: ContinuousTF,
    controller: DiscreteTF,
    sample_time: float,
    r: ArrayLike,
    d: ArrayLike,
    *,
    cogging: CoggingTorque | None = None,
    noise_variance: float = math.nan,
    covariance: bool = True,
) -> LoopReplay:
    """Re-simulate the calibration's closed loop with the identified model (paper sec. SEM).

    Parameters
    ----------
    flux : FluxModel
        g_theta* (Fourier form).
    lut : LUT
        The table; its f_init (projection, offsets, n_m) closes the loop.
    plant : ContinuousTF
        G(s) used in SEM (gain correction applied).
    controller : DiscreteTF
        C(q).
    sample_time : float
        [s].
    r : array_like (N,)
        The reference [rad].
    d : array_like (N, 3)
        The recorded Hall signals.
    cogging : CoggingTorque, keyword-only, optional
        The cogging torque identified with the flux (in the loop, and parameters of the pass).
    noise_variance : float, keyword-only
        sigma^2 per channel for the covariance; NaN: J / (3 N - p) from this pass.
    covariance : bool, keyword-only
        Compute cov(theta) (needs J^T J: one sensitivity recursion).

    Returns
    -------
    LoopReplay
    """
    loop = ClosedLoop.from_transfer_functions(
        plant, controller, sample_time, lut.pole_pairs, projection=lut.projection,
        offset=lut.offset,
    )  # fmt: skip
    r = np.ascontiguousarray(r, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    orders = () if cogging is None else cogging.orders
    layout = ParameterLayout(flux.basis, cogging_orders=orders)
    x = layout.pack(flux.theta, 0.0, cogging)
    gn = gauss_newton_system(loop, layout, x, r, d, gram=covariance)
    if not gn.status.success:
        return LoopReplay(status=gn.status, sse=float(gn.sse), noise_variance=noise_variance)
    cov = None
    s2 = noise_variance
    if covariance:
        if not math.isfinite(s2):
            s2 = gn.sse / max(3 * d.shape[0] - layout.size, 1)
        p = flux.theta.size
        full = _covariance(gn, np.zeros(layout.size), s2)
        cov = full[:p, :p] if np.all(np.isfinite(full)) else None
    return LoopReplay(
        status=gn.status, sse=float(gn.sse), d_sim=gn.d, y0_sim=gn.y0, covariance=cov,
        noise_variance=s2,
    )  # fmt: skip
