"""The BLA's plant refined by the calibration run itself, within the BLA's own uncertainty.

With a plant from the BLA (section "Obtaining a Best Linear Approximation") the calibration knows
G(s) to a few per cent, and the paper refines only its gain c (eq. (c_hat)). What the gain does
not absorb still matters: on a constant-speed ramp the sensors' common angle and the loop's steady
lag are told apart only where the motion changes, so a plant a few per cent off moves the table's
offset by 0.4-1.1x the noise floor on the paper's study (DESIGN.md, "Numerical facts"), a bias no
covariance of theta shows.

The calibration run carries far more information about the loop than that: moving the BLA by one
standard deviation along a principal direction of its fit's covariance
(:attr:`hallcal.identify.parametric.ParametricBLA.deviations`) changes the SEM cost by tens to
hundreds of noise variances. So the plant is refined as a maximum a posteriori estimate with the
BLA as the prior (Pintelon & Schoukens 2012, sec. 9.11 for the prior's covariance; the SEM as the
likelihood, problem (problem) of the paper):

1. For each deviation ``G_i`` one Gauss-Newton step of the SEM from its optimum (theta, the gain c
   and the cogging re-estimated) gives the simulated signals ``d_sim,i``; their differences to the
   step with the plant as it is, ``rho_i = d_sim,i - d_sim,0``, are the profiled residual's
   derivatives in the deviations' coordinates alpha (alpha = e_i is one standard deviation).
2. ``A = R^T W R / sigma^2``, ``b = R^T W e_0 / sigma^2`` with ``e_0 = d - d_sim,0``; the posterior
   of alpha (prior N(0, I)) is ``N(P b, P)``, ``P = (A + I)^-1``.
3. The plant at alpha_hat (the model's coefficients are linear in the fit's parameters, so the
   deviations combine linearly), and the SEM solved again with it, warm.
4. What remains uncertain moves the table by ``Delta(y)^T P Delta(y)`` (RMS over the revolution,
   offset included), with ``Delta_i`` the table's move in step 1: added to the predicted error.

When ``alpha^T alpha`` exceeds the chi-square bound of p degrees of freedom, the run and the BLA
disagree beyond the BLA's uncertainty: something neither models moves the loop (a constant load
torque or friction sets the same steady lag as a velocity gain, DESIGN.md "Numerical facts"),
and moving the plant to absorb it would bias the table. The plant is then kept, the BLA's whole
uncertainty (P = I) is added to the predicted error and a warning names the disagreement.

Units: as the SEM (Hall signals in the data's unit, angles in rad).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from hallcal.fit.sem import SEMResult, solve_sem
from hallcal.io.setup import Setup
from hallcal.pipeline.checks import CheckStatus, check_loop
from hallcal.pipeline.plant import PlantModel, closed_loop
from hallcal.pipeline.sensors import SensorFindings
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sim.lti import ContinuousTF

__all__ = ["PlantRefinement", "refine_plant"]

TWO_PI = 2.0 * math.pi
#: Risk of calling a healthy BLA and run "in disagreement": alpha^T alpha above the chi-square
#: quantile of p degrees of freedom (under the prior, alpha_hat is about N(0, I - P)).
DISAGREEMENT_RISK = 1e-3
#: Angles at which table moves are compared (RMS over the revolution).
_GRID = TWO_PI * np.arange(4096) / 4096


@dataclass(frozen=True)
class PlantRefinement:
    """The BLA's plant refined by the calibration run (module doc).

    Attributes
    ----------
    shape : ContinuousTF
        The refined G(s) before the gain correction (the BLA's shape moved by alpha, its
        numerator's constant term kept at the BLA's).
    alpha : ndarray (p,)
        The move, in the BLA's standard deviations along its principal directions.
    posterior : ndarray (p, p)
        Covariance of alpha after the calibration run (``(A + I)^-1``).
    sem : SEMResult
        The SEM solved with the refined plant (its ``gain`` is relative to ``gain`` below).
    gain : float
        The gain the refined shape is scaled by in ``sem``'s loop (c before the SEM's factor).
    bias : float
        RMS move of the table that the remaining plant uncertainty allows [rad].
    refined : bool
        Whether the plant was refined; if not, ``shape``, ``gain`` and ``sem`` are the BLA's and
        the final SEM's as they came, and ``bias`` is the BLA's own uncertainty.
    distance, bound : float
        ``alpha^T alpha`` and the chi-square bound (p degrees of freedom, risk
        :data:`DISAGREEMENT_RISK`) above which the run and the BLA disagree.
    """

    shape: ContinuousTF
    alpha: NDArray[np.float64]
    posterior: NDArray[np.float64] = field(repr=False)
    sem: SEMResult = field(repr=False)
    gain: float
    bias: float
    refined: bool = True
    distance: float = 0.0
    bound: float = math.inf

    @property
    def note(self) -> str:
        """One line for the user (a warning when the run and the BLA disagree)."""
        moved = math.sqrt(self.distance)
        if self.refined:
            return (
                f"note: the BLA's plant was refined by the calibration run within the BLA's "
                f"uncertainty (moved {moved:.2g} standard deviations); what remains uncertain "
                f"may move the table by {1e3 * self.bias:.3g} mrad RMS, which the predicted "
                "error includes"
            )
        if self.distance > self.bound:
            return (
                f"warning: the calibration run disagrees with the BLA's plant ({moved:.2g} "
                f"standard deviations of the BLA, more than {math.sqrt(self.bound):.2g}): a load "
                "torque, friction or dynamics the BLA's model misses; the plant is kept as the "
                f"BLA says, and its uncertainty may move the table by {1e3 * self.bias:.3g} "
                "mrad RMS (in the predicted error): check the [bla] model order, or give [plant]"
            )
        return (
            f"note: the BLA's uncertainty may move the table by {1e3 * self.bias:.3g} mrad RMS, "
            "which the predicted error includes (the calibration run did not refine the plant)"
        )


def _shape(nominal: tuple, deviations: tuple, alpha: NDArray[np.float64]) -> ContinuousTF:
    """The BLA's model moved by ``sum alpha_i (deviation_i - nominal)`` (coefficients and delay
    are linear in the fit's parameters)."""
    num = np.asarray(nominal[0], dtype=np.float64).copy()
    den = np.asarray(nominal[1], dtype=np.float64).copy()
    delay = float(nominal[2])
    for a, (n_i, d_i, t_i) in zip(alpha, deviations, strict=True):
        num += a * (np.asarray(n_i) - nominal[0])
        den += a * (np.asarray(d_i) - nominal[1])
        delay += a * (float(t_i) - nominal[2])
    return ContinuousTF(tuple(num), tuple(den), max(delay, 0.0))


def refine_plant(
    setup: Setup,
    pm: PlantModel,
    r: NDArray[np.float64],
    d: NDArray[np.float64],
    sem: SEMResult,
    found: SensorFindings,
) -> PlantRefinement | None:
    """Refine the BLA's plant with the calibration run (module doc, steps 1-4).

    Parameters
    ----------
    setup : Setup
        The controller, n_m, the sample time and ``[model]``.
    pm : PlantModel
        A plant from the BLA (``pm.bla`` and ``pm.gain`` set), before the SEM's gain factor.
    r : ndarray (N,)
        Reference [rad].
    d : ndarray (N, 3)
        The signals the final SEM saw.
    sem : SEMResult
        The final SEM (its ``gain`` relative to ``pm.plant``).
    found : SensorFindings
        Rails, weights and drift of the sensors (as the final SEM used them).

    Returns
    -------
    PlantRefinement or None
        None when the BLA has no deviations (a singular fit).
    """
    if pm.bla is None or pm.gain is None or not pm.bla.parametric.deviations:
        return None
    par = pm.bla.parametric
    nominal = (np.asarray(par.num, float), np.asarray(par.den, float), float(par.delay))
    deviations = par.deviations
    gain = pm.gain.c * sem.gain
    rails = found.censoring.rails

    def solve(shape: ContinuousTF, iterations: int, theta0: NDArray) -> SEMResult:
        loop = closed_loop(setup, shape.scaled(gain)).with_rails(*rails)
        return solve_sem(
            loop, r, d, sem.flux.basis, theta0=theta0, fit_gain=True, gain0=1.0,
            cogging=sem.cogging or (), weights=found.weights, fit_drift=found.drifting,
            drift0=sem.drift, max_iterations=iterations,
        )  # fmt: skip

    def table(fit: SEMResult) -> LUT:
        loop = closed_loop(setup, pm.plant)
        return build_lut(fit.flux, setup.pole_pairs, points=setup.model.lut_points,
                         projection=loop.projection, offset=loop.offset)  # fmt: skip

    base = solve(_shape(nominal, deviations, np.zeros(len(deviations))), 1, sem.flux.theta)
    steps = [solve(ContinuousTF(tuple(n), tuple(dd), max(float(t), 0.0)), 1, sem.flux.theta)
             for n, dd, t in deviations]  # fmt: skip
    sigma2 = base.noise_variance
    w = np.ones_like(d) if found.weights is None else np.broadcast_to(found.weights, d.shape)
    e0 = (d - base.d_sim) * w
    rho = np.stack([(st.d_sim - base.d_sim).ravel() for st in steps])
    info = (rho * w.ravel()) @ rho.T / sigma2
    posterior = np.asarray(np.linalg.inv(info + np.eye(len(steps))), dtype=np.float64)
    alpha = posterior @ (rho @ e0.ravel() / sigma2)
    lut0 = table(base)
    moves = []
    for st in steps:
        lut_i = table(st)
        moves.append(lut_i.correction(_GRID) - lut0.correction(_GRID) if lut_i.bijective
                     else np.full(_GRID.size, np.inf))  # fmt: skip
    delta = np.stack(moves)  # (p, G): the table's move per standard deviation of the BLA

    def bias(cov: NDArray) -> float:
        return float(np.sqrt(np.mean(np.einsum("ig,ij,jg->g", delta, cov, delta))))

    prior = np.eye(len(steps))
    distance = float(alpha @ alpha)  # squared, in the BLA's standard deviations
    bound = float(chi2.ppf(1.0 - DISAGREEMENT_RISK, len(steps)))
    kept = PlantRefinement(pm.bla.plant, alpha, prior, sem, pm.gain.c, bias(prior),
                           refined=False, distance=distance, bound=bound)  # fmt: skip
    if distance > bound:
        return kept  # the run and the BLA disagree: something neither models (module doc)
    shape = _shape(nominal, deviations, alpha)
    check = check_loop(setup.controller, shape.scaled(gain), setup.sample_time)
    if check.status is CheckStatus.FAILED:
        return kept
    final = solve(shape, setup.model.max_iterations, base.flux.theta)
    # the prior's cost in noise variances (alpha^T alpha) against the data's gain: a refinement
    # that does not pay for itself keeps the BLA as it is
    if final.cost / sigma2 + distance > sem.cost / sigma2:
        return kept
    # the shape keeps the BLA's static gain, so that c (the gain) says how far the loop's gain
    # moved, as with the paper's correction alone (the product is the same plant)
    k = float(nominal[0][-1] / shape.num[-1]) if shape.num[-1] != 0.0 else 1.0
    return PlantRefinement(shape.scaled(k), alpha, posterior, final, gain / k, bias(posterior),
                           refined=True, distance=distance, bound=bound)  # fmt: skip
