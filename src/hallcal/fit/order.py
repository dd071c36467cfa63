"""Automatic choice of the Fourier model: ``[model] harmonics = "auto"``.

The paper (section "Model structure") notes that "the order m can be chosen by analyzing the
harmonic content of data d". On a rotor whose magnets all differ, that content is everywhere
(every mechanical harmonic up to a few n_m, every sideband ``k n_m +- j``), and a model wider
than the flux's own band costs more than variance: a slow warp of the angle, which the closed loop
reveals only weakly, is then free, and the table carries it. Measured on the rich-shape bench
(``benchmarks/bench_rich.txt``: 11 pole pairs, per-magnet shape variation over harmonics 1..55):
the Fourier model with the truth's harmonics 1..55 reaches 1.04-1.07x the noise floor; with
1..56 3.7x, with 1..88 5-35x, although every one of these fits the data to the noise level.

:func:`select_harmonics` therefore chooses in five steps, each with its own honest criterion:

1. **The band** (:func:`hallcal.fit.warp.band_edge`): the smallest 1..E into which f_init's
   view of the flux can be un-warped, leaving only noise above E (chi-square test on the
   content above E; no loop simulation, so no motion error enters). A narrower band leaves
   flux content out (bias); a wider one leaves low-order warps undetermined (unbounded
   variance of the table). The un-warped flux is also the SEM start (1.02-1.07x the floor
   already on the rich-shape bench).
2. **The harmonics within the band** (:func:`hallcal.fit.evidence.harmonic_relevance`):
   harmonics whose coefficients the evidence of the data's shape (normal-plane part, free of
   motion errors) does not support are dropped, e.g. 40 of 55 for a trapezoidal flux with
   identical magnets (MacKay 1992; Tipping & Faul 2003). A short gap between kept harmonics
   is filled (:func:`fill_gaps`): a magnet's shape puts flux at every harmonic of its band, and
   a hole there bent the angle (zoo seed 41: 1..35 without 16 and 20, 3.98x the floor; 1..35,
   1.004x). After step 5, a band left with longer holes that the adequacy test does not pass is
   fitted whole, 1..E, and kept when the BIC prefers it (:func:`_contiguous`).
3. **SEM and the adequacy test** (:func:`hallcal.fit.sem.solve_sem`,
   :func:`hallcal.fit.adequacy.assess`): the chosen harmonics are fitted through the closed loop;
   flux harmonics that remain in the shape residual (model validation by residual analysis,
   Ljung 1999, sec. 16.6) are added and the fit repeated while the budget allows. Residual
   harmonics that only the motion leaves (cogging, disturbances) are never added.
4. **Widening the band** (:func:`_widen`): the band test of step 1 can pass a band that is too
   narrow when the flux's top harmonics are weak, because the warp's many degrees of freedom
   absorb their content (each warp harmonic j moves content of a strong harmonic h to h +- j).
   The table then carries a large wrong warp that no covariance shows. Measured on a random
   motor (11 pole pairs, flux band 1..77, 25 000 samples): the band test chose 1..61, the SEM fit
   left a shape ratio of 1.07 (14 standard deviations above 1) and f_star was 21x the noise
   floor (f_init 9x); 1..77 gave 4x. So while the shape ratio stays significantly above 1
   (more than 3 standard deviations), the band is widened to the next multiple of n_m (the
   next electrical harmonic with its sidebands) and the wider fit kept when it is clearly better
   (:func:`_better`).
5. **Narrowing to what the run determines** (:func:`nested_bands`, :func:`_narrow`): steps 1
   and 4 can end with a band wider than the flux's when f_init's view is not clean to the
   noise level (low noise, long runs: the un-warped view's content above the true edge stayed
   at 1.7-2.8 times its noise model on a 10-pole-pair drive, so step 1 ran to its bound 8 n_m)
   or the widening's criterion passes a band the loop cannot pin. A band the run cannot
   determine fits the data as well as the flux's own: the coefficients beyond the flux's band
   are within their covariance of zero, and the Wald test of the dropped block says so without
   any simulation. The narrowest nested band 1..E (E a multiple of n_m, or the static edge)
   that passes it is fitted from its linearized coefficients and kept unless its cost is
   clearly worse. Measured (``benchmarks/bench_choice.txt``): on the rich-shape motor with a
   clean sensor (noise variance 2e-7; truth 1..55) step 1 ran to 88 and the fit gave 4.2x the
   noise floor, narrowed to 1..55 1.05x; on two 10-pole-pair drives 8.1x -> 1.7x (the truth's
   own harmonics: 1.6x) and 3.1x -> 1.05x; the paper's bench and the other rich-shape benches
   keep their model.

Every step is bounded in work, never in wall time (the same input gives the same model at any
load and thread count): at most ``max_fits`` SEM solves of at most ``max_iterations``
Gauss-Newton iterations each, and at most ``work_budget`` (:data:`WORK_BUDGET`) iterations times
N p^2 over all of them, each solve from a warm start (the current fit, or the un-warped view
when that simulates closer to the data). A search stopped by a budget says so in its status
(FIT_BUDGET, WORK_BUDGET or MAX_ROUNDS: :attr:`SelectionStatus.budget_hit`), in a calibration
warning and in the artifact's ``diagnostics.model_selection``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from hallcal.fit.adequacy import (
    AdequacyReport,
    NoiseEstimate,
    _f,
    assess,
    chi2_isf_even,
    default_max_harmonic,
    estimate_noise_variance,
)
from hallcal.fit.evidence import HarmonicRelevance, harmonic_relevance
from hallcal.fit.gauss_newton import ParameterLayout, simulate_model
from hallcal.fit.sem import SEMResult, SEMStatus, least_squares_start, solve_sem
from hallcal.fit.warp import BandEdge, band_edge, unwarp
from hallcal.limits import one_blas_thread
from hallcal.messages import Message, MessageCode, Outcome
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "Candidate",
    "fill_gaps",
    "HarmonicSelection",
    "NestedBand",
    "WORK_BUDGET",
    "SelectionStatus",
    "restrict_theta",
    "nested_bands",
    "select_harmonics",
    "shape_off",
]

#: Largest fraction of 1..top missing for which :func:`fill_gaps` fills the short gaps: the
#: zoo's shape motors whose holes cost accuracy missed 2 of 32, 2 of 35 and 1 of 18 (6 %); the
#: sparse sets whose holes were right missed 36-55 % (``benchmarks/bench_zoo.py``).
DENSE_HOLES = 0.15

_RANK = {"adequate": 0, "warning": 1, "inadequate": 2}

#: Default work budget of :func:`select_harmonics`: Gauss-Newton iterations times N p^2 summed
#: over its SEM fits (N samples, p = 3 (2 harmonics + 1) parameters). Measured on the 2-core
#: machines: 5.1e11 took 12 s of CPU (a 10-pole-pair drive, 200 000 samples, a first fit on
#: 79 harmonics in 9 iterations and a narrowed one on 60), so 6e11 keeps the search under
#: about 15 s of CPU and a calibrate of 200 000 samples under 30 s.
WORK_BUDGET = 6e11


class SelectionStatus(Outcome):
    """How :func:`select_harmonics` ended."""

    #: the adequacy test asks for no further flux harmonics
    CONVERGED = "converged"
    #: stopped with harmonics still suggested: the extension rounds ran out
    MAX_ROUNDS = "max_rounds"
    #: adding the suggested harmonics did not improve the fit
    NO_IMPROVEMENT = "no_improvement"
    #: the SEM fit failed (the loop diverged)
    FAILED = "failed"
    #: stopped with the shape still off the data: the budget of SEM solves ran out
    FIT_BUDGET = "fit_budget"
    #: the budget of Gauss-Newton work (iterations x N p^2) ran out before a fit or within one
    WORK_BUDGET = "work_budget"

    @property
    def budget_hit(self) -> bool:
        """The search stopped on a budget (SEM solves, Gauss-Newton work or rounds)."""
        return self in (
            SelectionStatus.FIT_BUDGET,
            SelectionStatus.MAX_ROUNDS,
            SelectionStatus.WORK_BUDGET,
        )


@dataclass(frozen=True)
class Candidate:
    """One model tried by :func:`select_harmonics`.

    Attributes
    ----------
    harmonics : tuple of int
    stage : str
        "static" (the un-warped band, no loop), "sem" (the first SEM fit), "extended"
        (harmonics added from the residual), "widened" (the band widened to the next
        multiple of n_m), "narrowed" (the narrowest nested band the Wald test allows) or
        "contiguous" (a band with holes tried whole, :func:`_contiguous`).
    cost, ratio, shape_ratio : float
        SEM cost and the ratios of :class:`hallcal.fit.adequacy.AdequacyReport` (static stage:
        NaN, and the band's residual above E over its degrees of freedom as ``shape_ratio``).
    verdict : str
        Verdict of the adequacy test ("" for the static stage).
    sem_status : str
        SEM status ("static" for the static stage).
    iterations : int
        SEM iterations (band trials for the static stage).
    solve_time : float
        Wall time of the step [s] (a diagnostic only: nothing is decided on it).
    accepted : bool
        Whether the candidate became the current model.
    """

    harmonics: tuple[int, ...]
    stage: str
    cost: float
    ratio: float
    shape_ratio: float
    verdict: str
    sem_status: str
    iterations: int
    solve_time: float
    accepted: bool

    def to_dict(self, *, timings: bool = True) -> dict:
        """The candidate as a plain dict; ``timings=False`` leaves out the wall time."""
        out = {
            "harmonics": list(self.harmonics),
            "stage": self.stage,
            "cost": _f(self.cost),
            "ratio": _f(self.ratio),
            "shape_ratio": _f(self.shape_ratio),
            "verdict": self.verdict,
            "sem_status": self.sem_status,
            "iterations": self.iterations,
            "solve_time": _f(self.solve_time),
            "accepted": self.accepted,
        }
        if not timings:
            del out["solve_time"]
        return out


@dataclass(frozen=True)
class HarmonicSelection:
    """Outcome of :func:`select_harmonics`.

    Attributes
    ----------
    harmonics : tuple of int
        The chosen mechanical harmonics (the constant term is always in the basis).
    sem : SEMResult
        The fit with these harmonics.
    report : AdequacyReport
        Its adequacy assessment.
    edge : BandEdge
        The band 1..E found from f_init's view (step 1).
    relevance : HarmonicRelevance
        The evidence within the band (step 2).
    noise : NoiseEstimate
    candidates : tuple of Candidate
        Every model fitted, in order.
    status : SelectionStatus
    elapsed : float
        Wall time [s] (a diagnostic only: nothing is decided on it).
    max_fits : int
        The work budget: SEM solves allowed.
    nested : tuple of NestedBand
        The Wald tests of the nested bands of the last wide fit (step 5).
    """

    harmonics: tuple[int, ...]
    sem: SEMResult = field(repr=False)
    report: AdequacyReport = field(repr=False)
    edge: BandEdge = field(repr=False)
    relevance: HarmonicRelevance = field(repr=False)
    noise: NoiseEstimate = field(repr=False)
    candidates: tuple[Candidate, ...] = field(repr=False)
    status: SelectionStatus
    elapsed: float
    max_fits: int = 0
    nested: tuple[NestedBand, ...] = field(default=(), repr=False)

    @property
    def fits(self) -> int:
        """SEM solves done."""
        return sum(1 for c in self.candidates if c.stage != "static")

    @property
    def budget_message(self) -> Message | None:
        """One line when the work budget stopped the search, else None."""
        if not self.status.budget_hit:
            return None
        what = {
            SelectionStatus.FIT_BUDGET: f"its budget of {self.max_fits} SEM fits",
            SelectionStatus.MAX_ROUNDS: "its extension rounds",
            SelectionStatus.WORK_BUDGET: "its budget of Gauss-Newton work",
        }[self.status]
        return Message.warning(
            MessageCode.SEARCH_BUDGET,
            f"the harmonic search used up {what} before it was done "
            f"(status {self.status}); harmonics up to {max(self.harmonics)} kept",
        )

    @property
    def verdict(self) -> str:
        return self.report.verdict

    @property
    def adequacy(self) -> AdequacyReport:
        """Alias of ``report``."""
        return self.report

    def to_dict(self, *, timings: bool = True) -> dict:
        """The selection as a plain dict; ``timings=False`` leaves out every wall time (the
        rest depends only on the input: the artifact's ``diagnostics.model_selection``)."""
        out = {
            "harmonics": list(self.harmonics),
            "band_edge": self.edge.edge,
            "band_status": str(self.edge.status),
            "band_trials": [
                {
                    "edge": t.edge,
                    "residual": _f(t.residual),
                    "dof": t.dof,
                    "threshold": _f(t.threshold),
                }
                for t in self.edge.trials
            ],  # fmt: skip
            "dropped_in_band": [
                h for h in self.relevance.harmonics if h not in self.relevance.active
            ],
            "status": str(self.status),
            "budget_hit": self.status.budget_hit,
            "fits": self.fits,
            "max_fits": self.max_fits,
            "elapsed": _f(self.elapsed),
            "candidates": [c.to_dict(timings=timings) for c in self.candidates],
            "nested_bands": [t.to_dict() for t in self.nested],
            "report": self.report.to_dict(),
        }
        if not timings:
            del out["elapsed"]
        return out


def restrict_theta(flux: FluxModel, basis: FourierBasis) -> NDArray[np.float64]:
    """theta on another basis: shared harmonics copied, the others zero.

    Parameters
    ----------
    flux : FluxModel
        The model whose theta is copied.
    basis : FourierBasis
        The target basis.

    Returns
    -------
    ndarray, shape (3, basis.size)
        theta on ``basis``: the constant and the harmonics both bases share, zero elsewhere.
    """
    theta = np.zeros((3, basis.size))
    theta[:, 0] = flux.theta[:, 0]
    for h in basis.harmonics:
        if h in flux.basis.harmonics:
            js, jc = flux.basis.index(h)
            ks, kc = basis.index(h)
            theta[:, ks] = flux.theta[:, js]
            theta[:, kc] = flux.theta[:, jc]
    return theta


def _expand_theta(
    flux: FluxModel, basis: FourierBasis, residual: NDArray, y0: NDArray
) -> NDArray[np.float64]:
    """theta for a wider basis: old coefficients kept, new harmonics from the residual at y0."""
    theta = restrict_theta(flux, basis)
    new = tuple(h for h in basis.harmonics if h not in flux.basis.harmonics)
    if new:
        coef = least_squares_start(FourierBasis(new), residual, y0)
        for j, h in enumerate(new):
            ks, kc = basis.index(h)
            theta[:, [ks, kc]] = coef[:, [1 + 2 * j, 2 + 2 * j]]
    return theta


@dataclass
class _Search:
    """State of :func:`select_harmonics` shared by its steps."""

    loop: ClosedLoop
    r: NDArray[np.float64]
    d: NDArray[np.float64]
    n: int
    noise: NoiseEstimate
    max_harmonic: int
    max_iterations: int
    tol: float
    assess_options: dict
    significance: float = 1e-3
    max_fits: int = 6
    work_budget: float = math.inf
    work_used: float = 0.0
    truncated: bool = False
    candidates: list[Candidate] = field(default_factory=list)

    def fits_left(self) -> int:
        return self.max_fits - sum(1 for c in self.candidates if c.stage != "static")

    def iteration_work(self, harmonics: tuple[int, ...]) -> float:
        """Work of one Gauss-Newton iteration: N p^2 (the rank-one products dominate)."""
        return float(self.r.size) * float(3 * (2 * len(harmonics) + 1)) ** 2

    def out_of_budget(self, harmonics: tuple[int, ...]) -> SelectionStatus | None:
        """FIT_BUDGET or WORK_BUDGET when a fit with these harmonics may not start, else None."""
        if self.fits_left() <= 0:
            return SelectionStatus.FIT_BUDGET
        if self.work_used + 2.0 * self.iteration_work(harmonics) > self.work_budget:
            return SelectionStatus.WORK_BUDGET
        return None

    def cost(self, basis: FourierBasis, theta: NDArray) -> float:
        """J(theta) from one plain simulation (inf when the loop diverges)."""
        sim = simulate_model(self.loop, ParameterLayout(basis), theta.ravel(), self.r)
        if not sim.status.success:
            return math.inf
        e = self.d - sim.d
        return float(np.vdot(e, e))

    def fit(
        self, harmonics: tuple[int, ...], theta0: NDArray, stage: str,
        max_iterations: int | None = None,
    ) -> tuple[SEMResult, AdequacyReport]:  # fmt: skip
        """SEM with these harmonics from theta0, judged by the adequacy test.

        The iterations are capped by the work left (at least one: the first fit always runs);
        the work of a fit is counted as its iterations plus one (the exact system for the
        covariance) times N p^2.
        """
        its = self.max_iterations if max_iterations is None else int(max_iterations)
        unit = self.iteration_work(harmonics)
        allowed = max(1, int((self.work_budget - self.work_used) // unit) - 1)
        capped = allowed < its
        its = min(its, allowed)
        sem = solve_sem(self.loop, self.r, self.d, FourierBasis(harmonics), theta0=theta0,
                        max_iterations=its, tol=self.tol)  # fmt: skip
        self.work_used += (sem.iterations + 1) * unit
        if capped and sem.status is SEMStatus.MAX_ITERATIONS:
            self.truncated = True  # the work budget, not max_iterations, stopped this fit
        hmax = max(self.max_harmonic, default_max_harmonic(self.n, harmonics))
        rep = assess(sem, self.d, pole_pairs=self.n, noise=self.noise,
                     projection=self.loop.projection, offset=self.loop.offset,
                     max_harmonic=hmax, **self.assess_options)  # fmt: skip
        self.candidates.append(
            Candidate(
                harmonics,
                stage,
                sem.cost,
                rep.ratio,
                rep.shape_ratio,
                rep.verdict,
                str(sem.status),
                sem.iterations,
                sem.solve_time,
                False,
            )  # fmt: skip
        )
        return sem, rep

    def accept(self) -> None:
        self.candidates[-1] = replace(self.candidates[-1], accepted=True)


def _band_step(s: _Search, y: NDArray) -> tuple[BandEdge, HarmonicRelevance]:
    """Steps 1 and 2: the band from f_init's view, the evidence within it."""
    t0 = time.perf_counter()
    edge = band_edge(y, s.d, pole_pairs=s.n, noise_variance=s.noise.variance,
                     max_edge=s.max_harmonic)  # fmt: skip
    rel = harmonic_relevance(edge.flux, edge.unwarp.parametrize(y), s.d,
                             noise_variance=s.noise.variance, keep=(s.n,))  # fmt: skip
    top = edge.trials[-1] if edge.trials else None
    s.candidates.append(
        Candidate(
            rel.active,
            "static",
            math.nan,
            math.nan,
            (top.residual / max(top.dof, 1)) if top else math.nan,
            "",
            "static",
            len(edge.trials),
            time.perf_counter() - t0,
            True,
        )  # fmt: skip
    )
    return edge, rel


def _better(a: AdequacyReport, b: AdequacyReport) -> bool:
    """Whether report a is better than b (verdict first, then a clearly smaller shape ratio)."""
    if _RANK[a.verdict] != _RANK[b.verdict]:
        return _RANK[a.verdict] < _RANK[b.verdict]
    return a.shape_ratio < b.shape_ratio - 3 * b.ratio_std and a.ratio <= b.ratio * 1.05


def _extend(
    s: _Search, harmonics: tuple[int, ...], sem: SEMResult, rep: AdequacyReport, max_rounds: int
) -> tuple[tuple[int, ...], SEMResult, AdequacyReport, SelectionStatus]:
    """Step 3: add the flux harmonics the adequacy test finds missing, while it helps."""
    rounds = 0
    while rep.suggested_harmonics:
        if rounds >= max_rounds:
            return harmonics, sem, rep, SelectionStatus.MAX_ROUNDS
        new = fill_gaps(set(harmonics) | set(rep.suggested_harmonics), s.n)
        if (budget := s.out_of_budget(new)) is not None:
            return harmonics, sem, rep, budget
        basis = FourierBasis(new)
        theta0 = _expand_theta(sem.flux, basis, s.d - sem.d_sim, sem.y0_sim)
        sem2, rep2 = s.fit(new, theta0, "extended")
        rounds += 1
        if not _better(rep2, rep):
            return harmonics, sem, rep, SelectionStatus.NO_IMPROVEMENT
        s.accept()
        harmonics, sem, rep = new, sem2, rep2
    return harmonics, sem, rep, SelectionStatus.CONVERGED


def shape_off(rep: AdequacyReport) -> bool:
    """Whether the data lie off the model's flux curve by more than the noise explains, and
    that, not unmodelled motion, is what the fit lacks.

    A large motion error (cogging, say) also raises the shape ratio a little, as the curve
    projection is first-order: when the shape explains less than half the excess cost, the
    remedy is the motion model (the cogging search that follows), not a wider band (measured:
    cost 1.40x with the shape at 1.07x under cogging of 0.0034 at 90/rev, shape 1.008x once the
    torque was in the model).

    Parameters
    ----------
    rep : AdequacyReport
        The fit's adequacy report.

    Returns
    -------
    bool
        True when the shape ratio exceeds 1 by more than 3 standard deviations and by at least
        half the excess of the cost ratio.
    """
    off = rep.shape_ratio - 1.0
    return off > 3.0 * rep.ratio_std and off >= 0.5 * (rep.ratio - 1.0)


def _wider_is_better(a: AdequacyReport, b: AdequacyReport) -> bool:
    """Whether the wider fit a explains the flux shape clearly better than b (BIC).

    The shape part of the residual (distance from the model's curve, 2 of 3 dimensions per
    sample) must fall by more than the Bayesian information criterion's penalty of the added
    parameters, ``(2/3) dp ln(3 N) sigma^2`` (Schwarz 1978); the cost must not rise. Both fits
    see the same data and the same noise estimate, so the uncertainty of the noise level, which
    dominates ``ratio_std`` on long records, does not enter the comparison.
    """
    dp = a.n_parameters - b.n_parameters
    n3 = 3 * a.n_samples
    drop = (2.0 / 3.0) * (
        b.shape_ratio * (n3 - b.n_parameters) - a.shape_ratio * (n3 - a.n_parameters)
    )
    return drop > (2.0 / 3.0) * dp * math.log(n3) and a.cost <= b.cost


def _widen(
    s: _Search, edge: BandEdge, harmonics: tuple[int, ...], sem: SEMResult, rep: AdequacyReport,
    status: SelectionStatus,
) -> tuple[tuple[int, ...], SEMResult, AdequacyReport, SelectionStatus]:  # fmt: skip
    """Step 4: widen the band to the next multiple of n_m while the shape stays off the data.

    The wider fit starts from whichever simulates closer to the data: the current fit with the
    new harmonics regressed on its residual, or the view un-warped into the wider band.
    """
    while shape_off(rep) and sem.status is not SEMStatus.DIVERGED:
        top = max(harmonics)
        wider = s.n * (top // s.n + 1)
        if wider > s.max_harmonic:
            return harmonics, sem, rep, status
        new = tuple(sorted(set(harmonics) | set(range(top + 1, wider + 1))))
        if (budget := s.out_of_budget(new)) is not None:
            return harmonics, sem, rep, budget
        basis = FourierBasis(new)
        if wider < edge.view.harmonics and edge.unwarp.warp.size:
            u = unwarp(edge.view, wider, warp_harmonics=edge.unwarp.warp.size // 2)
            theta0 = restrict_theta(u.flux, basis)
        else:
            theta0 = _expand_theta(sem.flux, basis, s.d - sem.d_sim, sem.y0_sim)
        sem2, rep2 = s.fit(new, theta0, "widened")
        if not _wider_is_better(rep2, rep):
            return harmonics, sem, rep, status
        s.accept()
        harmonics, sem, rep = new, sem2, rep2
    return harmonics, sem, rep, status


@dataclass(frozen=True)
class NestedBand:
    """The model with a wide fit's harmonics up to ``edge``: the Wald test of the rest.

    Attributes
    ----------
    edge : int
        E: the nested model keeps the wide fit's harmonics h <= E.
    harmonics : tuple of int
        Those harmonics.
    wald : float
        ``theta_D^T C_DD^-1 theta_D`` for the dropped coefficients D of the wide fit (chi-square
        with ``dof`` degrees of freedom when they are zero in truth).
    dof : int
        Number of dropped coefficients (3 sensors x 2 per harmonic).
    threshold : float
        The test's bound on ``wald``: the larger of ``(1 + slack) chi2.isf(significance, dof)``
        and ``relevance * dof`` (:func:`nested_bands`).
    flux : FluxModel
        The nested model's coefficients, linearized at the wide fit: ``theta_S + K theta_D``
        with ``K = -C_SD C_DD^-1`` (the least-squares re-fit with theta_D = 0), a warm start.
    """

    edge: int
    harmonics: tuple[int, ...]
    wald: float
    dof: int
    threshold: float
    flux: FluxModel = field(repr=False)

    @property
    def adequate(self) -> bool:
        """The dropped harmonics are not needed by the data (``wald <= threshold``)."""
        return self.wald <= self.threshold

    def to_dict(self) -> dict:
        return {"edge": self.edge, "wald": _f(self.wald), "dof": self.dof,
                "threshold": _f(self.threshold)}  # fmt: skip


def _theta_columns(basis: FourierBasis, keep: tuple[int, ...]) -> NDArray[np.int64]:
    """Indices in theta flattened sensor-major (3 m) of the constant and the harmonics ``keep``."""
    m = basis.size
    cols = [0] + [c for h in keep for c in basis.index(h)]
    return np.array(sorted(k * m + c for k in range(3) for c in cols), dtype=np.int64)


def nested_bands(
    sem: SEMResult,
    edges: ArrayLike,
    *,
    significance: float = 1e-3,
    slack: float = 0.1,
    relevance: float = 10.0,
) -> tuple[NestedBand, ...]:
    """Wald tests of the nested models 1..E of a wide Fourier fit (step 5 of the module docstring).

    A model wider than the run can determine fits the data to the noise level but lets a slow
    warp of the angle float (:mod:`hallcal.fit.warp`); the coefficients it holds beyond the
    flux's band are then within their (large) covariance of zero. The Wald statistic of the
    dropped block, ``theta_D^T C_DD^-1 theta_D`` with ``C = sigma^2 (J^T J)^-1`` the fit's
    covariance (Ljung 1999, sec. 9.3; the Wald test, e.g. Ljung sec. 16.4 on model structure
    tests), is the cost increase, in units of sigma^2, of the least-squares re-fit without them
    (linearized at the wide fit): the nested model explains the data as well when it is within
    the chi-square bound. No simulation is needed.

    The bound is also ``relevance`` times the degrees of freedom: the residual of a closed-loop
    fit is not white (the loop's response to the noise moves the angle, which the noise-free
    simulation does not), and coefficients that are zero in truth gave 3.7-4.1 per degree of
    freedom on a 4-pole-pair bench (tests/test_order.py), while a block holding flux content
    gave 2000 to 10^6 per degree of freedom on every bench measured. A block under the bound
    explains at most ``relevance * dof * sigma^2`` of the cost, a few thousand sigma^2 on runs
    of 10^5 samples: an angle error of at most about ``sqrt(W / N)`` (0.15) times the noise
    floor.

    Measured (``benchmarks/bench_choice.txt``): on a 10-pole-pair drive with a slow ramp and
    a flux band 1..60, the wide fit on 1..80 gave 8.1x the noise floor; the Wald statistic per
    dropped coefficient was 2000 for E = 50 and 0.37 for E = 60, whose linearized model gave
    1.7x. An unbiased estimate of the table's risk (Mallows' C_p on the table error) was tried
    first and failed: the wide fit's floating warp swamped its bias term (22 +- 22 floor^2 where
    the truth was 0).

    Parameters
    ----------
    sem : SEMResult
        The wide fit (Fourier basis, finite covariance).
    edges : array_like of int
        Candidate E; those at or above the wide model's top harmonic are skipped.
    significance, slack : float, keyword-only
        The chi-square test's level and relative allowance (as for
        :func:`hallcal.fit.warp.band_edge`).
    relevance : float, keyword-only
        The bound per degree of freedom below which a block is not needed (see above).

    Returns
    -------
    tuple of NestedBand
        One per distinct candidate below the top, in increasing E (empty when the covariance
        is not finite).
    """
    flux = sem.flux
    basis = flux.basis
    C = np.asarray(sem.covariance, dtype=np.float64)
    theta = flux.theta.ravel()
    if not (np.all(np.isfinite(C)) and np.all(np.isfinite(theta))):
        return ()
    top = max(basis.harmonics)
    out: list[NestedBand] = []
    with one_blas_thread():
        for E in sorted({int(e) for e in np.atleast_1d(edges) if 1 <= int(e) < top}):
            keep = tuple(h for h in basis.harmonics if h <= E)
            if not keep:
                continue
            S = _theta_columns(basis, keep)
            D = np.setdiff1d(np.arange(theta.size), S)
            try:
                cf = scipy.linalg.cho_factor(C[np.ix_(D, D)], check_finite=False)
            except np.linalg.LinAlgError:
                continue
            z = scipy.linalg.cho_solve(cf, theta[D], check_finite=False)
            K = -scipy.linalg.cho_solve(cf, C[np.ix_(D, S)], check_finite=False).T
            th = (theta[S] + K @ theta[D]).reshape(3, -1)
            dof = int(D.size)
            thr = max((1.0 + slack) * chi2_isf_even(significance, 2 * ((dof + 1) // 2)),
                      float(relevance) * dof)  # fmt: skip
            out.append(NestedBand(E, keep, float(theta[D] @ z), dof, thr,
                                  FluxModel(FourierBasis(keep), th)))  # fmt: skip
    return tuple(out)


def _narrow(
    s: _Search, edge: BandEdge, harmonics: tuple[int, ...], sem: SEMResult, rep: AdequacyReport,
    status: SelectionStatus,
) -> tuple[
    tuple[int, ...], SEMResult, AdequacyReport, SelectionStatus, tuple[NestedBand, ...]
]:  # fmt: skip
    """Step 5: the narrowest nested band 1..E whose dropped harmonics the data do not need.

    Candidates: the multiples of n_m below the model's top harmonic and the static band edge.
    The narrowest one that passes the Wald test (:func:`nested_bands`) is fitted (SEM from its
    linearized coefficients) and kept unless its cost ratio is clearly worse (3 standard
    deviations) than the wide fit's.
    """
    top = max(harmonics)
    edges = [k * s.n for k in range(1, top // s.n + 1)] + [edge.edge]
    tests = nested_bands(sem, edges, significance=s.significance)
    best = next((t for t in tests if t.adequate), None)
    if best is None or sem.status is SEMStatus.DIVERGED:
        return harmonics, sem, rep, status, tests
    if (budget := s.out_of_budget(best.harmonics)) is not None:
        return harmonics, sem, rep, budget, tests
    sem2, rep2 = s.fit(best.harmonics, best.flux.theta, "narrowed")
    if not (math.isfinite(sem2.cost) and rep2.ratio <= rep.ratio + 3.0 * rep.ratio_std):
        return harmonics, sem, rep, status, tests
    s.accept()
    return best.harmonics, sem2, rep2, status, tests


def _contiguous(
    s: _Search, harmonics: tuple[int, ...], sem: SEMResult, rep: AdequacyReport,
    status: SelectionStatus,
) -> tuple[tuple[int, ...], SEMResult, AdequacyReport, SelectionStatus]:  # fmt: skip
    """Safety net after step 5: a band with holes that the adequacy test does not pass is tried
    whole.

    :func:`fill_gaps` fills the short gaps; a longer one is left to the evidence (a trapezoidal
    flux's empty sidebands), and is right when the fit is adequate. When it is not, the
    contiguous band 1..E (E the model's top harmonic) is fitted from the current fit and kept
    when it explains the shape clearly better (:func:`_wider_is_better`, the BIC).
    """
    top = max(harmonics)
    whole = tuple(range(1, top + 1))
    if harmonics == whole or rep.verdict == "adequate" or sem.status is SEMStatus.DIVERGED:
        return harmonics, sem, rep, status
    if (budget := s.out_of_budget(whole)) is not None:
        return harmonics, sem, rep, budget
    basis = FourierBasis(whole)
    theta0 = _expand_theta(sem.flux, basis, s.d - sem.d_sim, sem.y0_sim)
    sem2, rep2 = s.fit(whole, theta0, "contiguous")
    if not (math.isfinite(sem2.cost) and _wider_is_better(rep2, rep)):
        return harmonics, sem, rep, status
    s.accept()
    return whole, sem2, rep2, status


def _group_centre(active: tuple[int, ...] | list[int], n: int) -> set[int]:
    """The harmonics up to k n_m of the band's top group, when the band stops below its centre.

    The flux of a rotor is a sum of electrical harmonics k n_m, each with sidebands k n_m +- j
    from the magnets' differences; the centre of a group is its strongest member. A band edge
    that takes sidebands of group k (above k n_m - n_m / 2) but stops just below k n_m leaves
    the strongest line of that group out, and the SEM then bends the angle to make up for it
    (a zoo motor with 10 pole pairs: 1..59 chosen, f_star 72x the noise floor; with 60 added,
    3.9x, as predicted).
    """
    if not len(active):
        return set()
    top = int(max(active))
    centre = n * max(1, round(top / n))
    return set(range(top + 1, centre + 1))  # the band reaches the centre: its sidebands too


def fill_gaps(harmonics: Iterable[int], n: int) -> tuple[int, ...]:
    """The harmonics with every short gap below their top filled (a contiguous band).

    A magnet's own shape puts flux at every mechanical harmonic up to several n_m (DESIGN.md,
    "Numerical facts"), so a harmonic missing between determined neighbours is one the evidence
    happened to find small on this run, not one the flux lacks; leaving it out bends the angle
    to make up for it. Measured on the zoo (``benchmarks/bench_zoo.py``): seed 41 (5 pole pairs)
    chose 1..35 without 16 and 20, 3.98x the floor, 1..35 gave 1.004x; seed 113 (4 pole pairs)
    chose 1..32 without 8 and 31, 64x (worse than f_init, 27x), 1..32 gave 4.2x (honestly
    predicted 3.7x). Identical magnets put flux only at the electrical harmonics k n_m, whose
    gaps are at least n_m - 1 long: a gap of at most ``max(1, n_m // 2)`` harmonics is filled,
    the longer ones (a trapezoidal flux's empty sidebands) are left to the evidence. Only a
    dense band is filled (at most :data:`DENSE_HOLES` of 1..top missing: the evidence found
    content nearly everywhere, the signature of magnets that differ in shape); in a sparse one
    the holes are the evidence's finding (filled, the zoo's cogging seed 30 went from 1.34x to
    1.51x and clipping seed 2 from 1.15x to 1.45x).

    Parameters
    ----------
    harmonics : sequence of int
        The harmonics chosen.
    n : int
        n_m.

    Returns
    -------
    tuple of int
        Sorted, with the short gaps (including one below the lowest harmonic) filled.
    """
    hs = sorted({int(h) for h in harmonics if int(h) >= 1})
    if not hs or len(hs) < (1.0 - DENSE_HOLES) * hs[-1]:
        return tuple(hs)
    longest = max(1, int(n) // 2)
    out = set(hs)
    prev = 0
    for h in hs:
        if 1 <= h - prev - 1 <= longest:
            out.update(range(prev + 1, h))
        prev = h
    return tuple(sorted(out))


def select_harmonics(
    loop: ClosedLoop,
    r: ArrayLike,
    d: ArrayLike,
    *,
    y: ArrayLike,
    pole_pairs: int | None = None,
    max_harmonic: int | None = None,
    max_rounds: int = 2,
    significance: float = 1e-3,
    min_amplitude: float = 0.1,
    max_iterations: int = 30,
    tol: float = 1e-7,
    noise: NoiseEstimate | None = None,
    warn_ratio: float = 1.1,
    fail_ratio: float = 1.5,
    dominance: float = 0.05,
    max_fits: int = 6,
    work_budget: float = WORK_BUDGET,
    start: FluxModel | None = None,
    first_iterations: int | None = None,
) -> HarmonicSelection:
    """Choose the mechanical harmonics of the Fourier flux model from the data (``"auto"``).

    See the module docstring for the three steps (the band from f_init's view, the evidence
    within it, SEM with the adequacy test).

    Parameters
    ----------
    loop : ClosedLoop
        The loop model used for SEM (plant, controller, n_m, f_init projection and offsets).
    r : array_like (N,)
        Reference [rad].
    d : array_like (N, 3)
        Hall signals.
    y : array_like (N,), keyword-only
        f_init output recorded in the loop [rad].
    pole_pairs : int, optional
        n_m (default ``loop.pole_pairs``).
    max_harmonic : int, optional
        Widest band considered (default :func:`hallcal.fit.adequacy.default_max_harmonic`,
        8 n_m).
    max_rounds : int
        Maximum number of extension rounds after the first fit.
    significance, min_amplitude, warn_ratio, fail_ratio, dominance : float
        Passed to :func:`hallcal.fit.adequacy.assess`.
    max_iterations, tol : optional
        Passed to every :func:`hallcal.fit.sem.solve_sem` (``[model] max_iterations``).
    noise : NoiseEstimate, optional
        Default :func:`hallcal.fit.adequacy.estimate_noise_variance` of d.
    max_fits : int
        SEM solves at most (the first fit, extension rounds, widening and narrowing together),
        each of at most ``max_iterations`` iterations.
    work_budget : float
        Gauss-Newton work at most, in iterations times N p^2 (:data:`WORK_BUDGET`). With
        ``max_fits`` this bounds the search; there is no wall-clock budget, so that the choice
        is the same at any machine load and thread count.
    start : FluxModel, optional
        A fit to start the first SEM from (its coefficients on the harmonics it shares with
        the chosen ones; the un-warped view elsewhere), e.g. the fit before a cogging torque
        was identified.
    first_iterations : int, optional
        Iteration limit of the first SEM fit only (default ``max_iterations``): when a motion
        model is identified next (the cogging search), the flux-only fit need not crawl to its
        optimum while the flux absorbs the unmodelled motion (measured: 30 iterations, 62 s,
        on a 200 000-sample run with cogging, after which the joint fit converged in 8).

    Returns
    -------
    HarmonicSelection
    """
    t0 = time.perf_counter()
    dd = np.ascontiguousarray(d, dtype=np.float64)
    n = int(loop.pole_pairs if pole_pairs is None else pole_pairs)
    s = _Search(
        loop=loop, r=np.ascontiguousarray(r, dtype=np.float64), d=dd, n=n,
        noise=estimate_noise_variance(dd) if noise is None else noise,
        max_harmonic=int(max_harmonic) if max_harmonic else default_max_harmonic(n),
        max_iterations=int(max_iterations), tol=float(tol),
        assess_options={"significance": significance, "min_amplitude": min_amplitude,
                        "warn_ratio": warn_ratio, "fail_ratio": fail_ratio,
                        "dominance": dominance},
        significance=float(significance), max_fits=max(int(max_fits), 1),
        work_budget=float(work_budget),
    )  # fmt: skip
    edge, rel = _band_step(s, np.ascontiguousarray(y, dtype=np.float64))
    harmonics = fill_gaps(set(rel.active) | {n} | _group_centre(rel.active, n), n)
    basis = FourierBasis(harmonics)
    theta0 = restrict_theta(edge.flux, basis)
    if start is not None:
        warm = restrict_theta(start, basis)
        shared = [h for h in harmonics if h in start.basis.harmonics]
        cols = [0] + [c for h in shared for c in basis.index(h)]
        theta0[:, cols] = warm[:, cols]
    sem, rep = s.fit(harmonics, theta0, "sem", first_iterations)
    s.accept()
    nested: tuple[NestedBand, ...] = ()
    if sem.status is SEMStatus.DIVERGED or not math.isfinite(sem.cost):
        status = SelectionStatus.FAILED
    else:
        harmonics, sem, rep, status = _extend(s, harmonics, sem, rep, max_rounds)
        harmonics, sem, rep, status = _widen(s, edge, harmonics, sem, rep, status)
        harmonics, sem, rep, status, nested = _narrow(s, edge, harmonics, sem, rep, status)
        harmonics, sem, rep, status = _contiguous(s, harmonics, sem, rep, status)
    if s.truncated and status is SelectionStatus.CONVERGED:
        status = SelectionStatus.WORK_BUDGET
    return HarmonicSelection(
        harmonics=harmonics,
        sem=sem,
        report=rep,
        edge=edge,
        relevance=rel,
        noise=s.noise,
        candidates=tuple(s.candidates),
        status=status,
        elapsed=time.perf_counter() - t0,
        max_fits=s.max_fits,
        nested=nested,
    )
