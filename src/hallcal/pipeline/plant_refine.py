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
torque or friction sets the same steady lag as a velocity gain, DESIGN.md "Numerical facts").
The refined plant still fits the run better (on a zoo motor with a load torque: 6.0x the floor
against 21x with the BLA's plant, ``benchmarks/bench_bla.txt``), but its posterior is not
credible: the BLA's whole uncertainty (P = I) is added to the predicted error and a warning
names the disagreement.

A frequent cause is a constant load torque (friction on a one-way ramp, gravity): the paper's
gain correction and its refinement with theta take up its steady lag (a zoo motor: c = 1.54 for a
BLA 4 % off), the cogging search then misses the real cogging, and the table is 21x the floor.
On a disagreement the BLA's own plant with the cogging search including the load torque is tried
as well (the same zoo motor: 1.03x with the BLA's plant, load and 60/rev cogging), refined the
same way, and kept when its MAP cost (data plus prior, in noise variances) is lower.

Units: as the SEM (Hall signals in the data's unit, angles in rad).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.fit.cogging_search import CoggingSelection, select_cogging
from hallcal.fit.sem import SEMResult, solve_sem
from hallcal.io.setup import Setup
from hallcal.messages import Message, MessageCode
from hallcal.pipeline.checks import CheckStatus, check_loop
from hallcal.pipeline.plant import PlantModel, closed_loop
from hallcal.pipeline.sensors import SensorFindings
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sim.lti import ContinuousTF

__all__ = ["PlantRefinement", "refine_plant"]

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
        the final SEM's as they came. ``bias`` is the BLA's own uncertainty when the plant was
        not refined or when the run disagrees with the BLA (``distance > bound``).
    distance, bound : float
        ``alpha^T alpha`` and the chi-square bound (p degrees of freedom, risk
        :data:`DISAGREEMENT_RISK`) above which the run and the BLA disagree.
    cogging : CoggingSelection or None
        A new cogging model (with a constant load torque) when the refinement found it instead
        of a gain (module doc); None: the final SEM's as it came.
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
    cogging: CoggingSelection | None = field(default=None, repr=False)

    @property
    def message(self) -> Message:
        """One line for the user (a warning when the run and the BLA disagree)."""
        moved = math.sqrt(self.distance)
        if self.refined and self.distance <= self.bound:
            return Message.note(
                MessageCode.PLANT_REFINED,
                f"the BLA's plant was refined by the calibration run within the BLA's "
                f"uncertainty (moved {moved:.2g} standard deviations); what remains uncertain "
                f"may move the table by {1e3 * self.bias:.3g} mrad RMS, which the predicted "
                "error includes",
            )
        if self.distance > self.bound:
            return Message.warning(
                MessageCode.PLANT_DISAGREES,
                f"the calibration run disagrees with the BLA's plant ({moved:.2g} standard "
                f"deviations of the BLA, more than {math.sqrt(self.bound):.2g}): a load torque, "
                "friction or dynamics the BLA's model misses; the BLA's whole uncertainty may "
                f"move the table by {1e3 * self.bias:.3g} mrad RMS (in the predicted error): "
                "check the [bla] model order, or give [plant]",
            )
        return Message.note(
            MessageCode.PLANT_REFINED,
            f"the BLA's uncertainty may move the table by {1e3 * self.bias:.3g} mrad RMS, which "
            "the predicted error includes (the calibration run did not refine the plant)",
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


@dataclass(frozen=True)
class _MapStep:
    """Steps 1-3 of the module doc around one start: the move, its covariances and the fit."""

    alpha: NDArray[np.float64]
    posterior: NDArray[np.float64]
    delta: NDArray[np.float64]  # (p, G): the table's move per standard deviation of the BLA
    shape: ContinuousTF
    final: SEMResult | None  # None when the refined loop is unstable

    @property
    def distance(self) -> float:
        """alpha^T alpha: squared, in the BLA's standard deviations."""
        return float(self.alpha @ self.alpha)

    def bias(self, cov: NDArray[np.float64]) -> float:
        """RMS over the revolution of the table's move with covariance ``cov`` of alpha [rad]."""
        d = self.delta
        return float(np.sqrt(np.mean(np.einsum("ig,ij,jg->g", d, cov, d))))


def _map_step(
    setup: Setup, nominal: tuple, deviations: tuple, gain: float, r: NDArray, d: NDArray,
    sem: SEMResult, found: SensorFindings, *, fit_gain: bool,
) -> _MapStep:  # fmt: skip
    """Steps 1-3 from ``sem`` (its loop: the BLA's ``nominal`` times ``gain``)."""
    rails = found.censoring.rails

    def solve(shape: ContinuousTF, iterations: int, theta0: NDArray) -> SEMResult:
        loop = closed_loop(setup, shape.scaled(gain)).with_rails(*rails)
        return solve_sem(
            loop, r, d, sem.flux.basis, theta0=theta0, fit_gain=fit_gain, gain0=1.0,
            cogging=sem.cogging or (), weights=found.weights, fit_drift=found.drifting,
            drift0=sem.drift, max_iterations=iterations,
        )  # fmt: skip

    nominal_shape = _shape(nominal, deviations, np.zeros(len(deviations)))
    f_init = closed_loop(setup, nominal_shape)  # f_init's projection and offset, for the tables

    def table(fit: SEMResult) -> LUT:
        return build_lut(fit.flux, setup.pole_pairs, points=setup.model.lut_points,
                         projection=f_init.projection, offset=f_init.offset)  # fmt: skip

    base = solve(nominal_shape, 1, sem.flux.theta)
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
    shape = _shape(nominal, deviations, alpha)
    check = check_loop(setup.controller, shape.scaled(gain), setup.sample_time)
    final = None
    if check.status is not CheckStatus.FAILED:
        final = solve(shape, setup.model.max_iterations, base.flux.theta)
    return _MapStep(alpha, posterior, np.stack(moves), shape, final)


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
    sigma2 = sem.noise_variance
    p = len(deviations)
    from scipy.stats import chi2  # a BLA plant only (the import costs 0.2 s)

    bound = float(chi2.ppf(1.0 - DISAGREEMENT_RISK, p))
    prior = np.eye(p)
    gain = pm.gain.c * sem.gain
    step = _map_step(setup, nominal, deviations, gain, r, d, sem, found, fit_gain=True)
    cogging = None
    if step.distance > bound and setup.model.cogging != "none":
        # the gain c (the paper's correction, refined with theta) may have taken up a load
        # torque's steady lag: the BLA's own plant with a load torque instead (module doc)
        alt = _with_load(setup, pm, r, d, sem, found)
        if alt.sem.cost < sem.cost:  # its loop: the BLA's plant with the BLA's gain (1)
            alt_step = _map_step(setup, nominal, deviations, 1.0, r, d, alt.sem, found,
                                 fit_gain=False)  # fmt: skip
            if _total(alt_step, sigma2) < _total(step, sigma2):
                step, gain, cogging = alt_step, 1.0, alt
    kept = PlantRefinement(pm.bla.plant, step.alpha, prior, sem, pm.gain.c, step.bias(prior),
                           refined=False, distance=step.distance, bound=bound)  # fmt: skip
    final = step.final
    # the prior's cost in noise variances (alpha^T alpha) against the data's gain: a refinement
    # that does not pay for itself keeps the BLA as it is
    if final is None or final.cost / sigma2 + step.distance > sem.cost / sigma2:
        return kept
    # when the run and the BLA disagree (something neither models, module doc) the posterior is
    # not credible: the refined plant fits the run better, but the BLA's whole uncertainty stays
    cov = prior if step.distance > bound else step.posterior
    # the shape keeps the BLA's static gain, so that c (the gain) says how far the loop's gain
    # moved, as with the paper's correction alone (the product is the same plant)
    shape = step.shape
    k = float(nominal[0][-1] / shape.num[-1]) if shape.num[-1] != 0.0 else 1.0
    if cogging is not None:  # the torque as the final fit refined it
        cogging = cogging.refitted(final)
    return PlantRefinement(shape.scaled(k), step.alpha, cov, final, gain / k, step.bias(cov),
                           refined=True, distance=step.distance, bound=bound,
                           cogging=cogging)  # fmt: skip


def _total(step: _MapStep, sigma2: float) -> float:
    """The MAP cost of a step's final fit in noise variances (data plus prior)."""
    return math.inf if step.final is None else step.final.cost / sigma2 + step.distance


def _with_load(
    setup: Setup, pm: PlantModel, r: NDArray, d: NDArray, sem: SEMResult, found: SensorFindings
) -> CoggingSelection:
    """The BLA's own plant (its gain, no correction) with the cogging search including a
    constant load torque (order 0), from ``sem``'s flux (``[model] cogging`` is not "none")."""
    assert pm.bla is not None
    loop = closed_loop(setup, pm.bla.plant).with_rails(*found.censoring.rails)
    start = solve_sem(loop, r, d, sem.flux.basis, theta0=sem.flux.theta,
                      max_iterations=setup.model.max_iterations)  # fmt: skip
    orders = setup.model.cogging
    sel = select_cogging(loop, r, d, start, orders=orders,
                         max_iterations=setup.model.max_iterations, load=True)  # fmt: skip
    if orders == "auto" and sel.sem.cost < start.cost:
        # the load's lag dominated the first search's residual: search again without it
        again = select_cogging(loop, r, d, sel.sem, orders="auto",
                               max_iterations=setup.model.max_iterations, load=True)  # fmt: skip
        if again.sem.cost < sel.sem.cost:
            sel = again
    return sel
