"""Automatic choice of the Fourier model: ``[model] harmonics = "auto"``.

The paper (section "Model structure") notes that "the order m can be chosen by analyzing the
harmonic content of data d". On a rotor whose magnets all differ, that content is everywhere
(every mechanical harmonic up to a few n_m, every sideband ``k n_m +- j``), and a model wider
than the flux's own band costs more than variance: a slow warp of the angle, which the closed loop
reveals only weakly, is then free, and the table carries it. Measured on the issue-13 bench
(``benchmarks/bench_rich.txt``: 11 pole pairs, per-magnet shape variation over harmonics 1..55):
the Fourier model with the truth's harmonics 1..55 reaches 1.04-1.07x the noise floor; with
1..56 3.7x, with 1..88 5-35x, although every one of these fits the data to the noise level.

:func:`select_harmonics` therefore chooses in three steps, each with its own honest criterion:

1. **The band** (:func:`hallcal.fit.warp.band_edge`): the smallest 1..E into which f_init's
   view of the flux can be un-warped, leaving only noise above E (chi-square test on the
   content above E; no loop simulation, so no motion error enters). A narrower band leaves
   flux content out (bias); a wider one leaves low-order warps undetermined (unbounded
   variance of the table). The un-warped flux is also the SEM start (1.02-1.07x the floor
   already on the issue-13 bench).
2. **The harmonics within the band** (:func:`hallcal.fit.evidence.harmonic_relevance`):
   harmonics whose coefficients the evidence of the data's shape (normal-plane part, free of
   motion errors) does not support are dropped, e.g. 40 of 55 for a trapezoidal flux with
   identical magnets (MacKay 1992; Tipping & Faul 2003).
3. **SEM and the adequacy test** (:func:`hallcal.fit.sem.solve_sem`,
   :func:`hallcal.fit.adequacy.assess`): the chosen harmonics are fitted through the closed loop;
   flux harmonics that remain in the shape residual (model validation by residual analysis,
   Ljung 1999, sec. 16.6) are added and the fit repeated while the budget allows. Residual
   harmonics that only the motion leaves (cogging, disturbances) are never added.
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.fit.adequacy import (
    AdequacyReport,
    NoiseEstimate,
    _f,
    assess,
    default_max_harmonic,
    estimate_noise_variance,
)
from hallcal.fit.evidence import HarmonicRelevance, harmonic_relevance
from hallcal.fit.sem import SEMResult, SEMStatus, least_squares_start, solve_sem
from hallcal.fit.warp import BandEdge, band_edge
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "Candidate",
    "HarmonicSelection",
    "SelectionStatus",
    "restrict_theta",
    "select_harmonics",
]

_RANK = {"adequate": 0, "warning": 1, "inadequate": 2}


class SelectionStatus(enum.StrEnum):
    """How :func:`select_harmonics` ended."""

    #: the adequacy test asks for no further flux harmonics
    CONVERGED = "converged"
    #: stopped with harmonics still suggested: the budget ran out
    TIME_BUDGET = "time_budget"
    #: stopped with harmonics still suggested: the extension rounds ran out
    MAX_ROUNDS = "max_rounds"
    #: adding the suggested harmonics did not improve the fit
    NO_IMPROVEMENT = "no_improvement"
    #: the SEM fit failed (the loop diverged)
    FAILED = "failed"

    @property
    def success(self) -> bool:
        return self is SelectionStatus.CONVERGED


@dataclass(frozen=True)
class Candidate:
    """One model tried by :func:`select_harmonics`.

    Attributes
    ----------
    harmonics : tuple of int
    stage : str
        "static" (the un-warped band, no loop), "sem" (the first SEM fit) or "extended"
        (harmonics added from the residual).
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
        Wall time of the step [s].
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

    def to_dict(self) -> dict:
        return {
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
        Wall time [s].
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

    @property
    def verdict(self) -> str:
        return self.report.verdict

    @property
    def adequacy(self) -> AdequacyReport:
        """Alias of ``report``."""
        return self.report

    def to_dict(self) -> dict:
        return {
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
            "elapsed": _f(self.elapsed),
            "candidates": [c.to_dict() for c in self.candidates],
            "report": self.report.to_dict(),
        }


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
    deadline: float
    candidates: list[Candidate] = field(default_factory=list)

    def time_left(self) -> float:
        return self.deadline - time.perf_counter()

    def fit(
        self, harmonics: tuple[int, ...], theta0: NDArray, stage: str
    ) -> tuple[SEMResult, AdequacyReport]:
        """SEM with these harmonics from theta0, judged by the adequacy test."""
        sem = solve_sem(self.loop, self.r, self.d, FourierBasis(harmonics), theta0=theta0,
                        max_iterations=self.max_iterations, tol=self.tol)  # fmt: skip
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
        new = tuple(sorted(set(harmonics) | set(rep.suggested_harmonics)))
        if (sem.solve_time + 1.0) * (len(new) / max(len(harmonics), 1)) > s.time_left():
            return harmonics, sem, rep, SelectionStatus.TIME_BUDGET
        basis = FourierBasis(new)
        theta0 = _expand_theta(sem.flux, basis, s.d - sem.d_sim, sem.y0_sim)
        sem2, rep2 = s.fit(new, theta0, "extended")
        rounds += 1
        if not _better(rep2, rep):
            return harmonics, sem, rep, SelectionStatus.NO_IMPROVEMENT
        s.accept()
        harmonics, sem, rep = new, sem2, rep2
    return harmonics, sem, rep, SelectionStatus.CONVERGED


def select_harmonics(
    loop: ClosedLoop,
    r: ArrayLike,
    d: ArrayLike,
    *,
    y: ArrayLike,
    pole_pairs: int | None = None,
    max_harmonic: int | None = None,
    time_budget: float = 30.0,
    max_rounds: int = 2,
    significance: float = 1e-3,
    min_amplitude: float = 0.1,
    max_iterations: int = 30,
    tol: float = 1e-7,
    noise: NoiseEstimate | None = None,
    warn_ratio: float = 1.1,
    fail_ratio: float = 1.5,
    dominance: float = 0.05,
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
    time_budget : float
        Wall-time budget [s] for the extension rounds (the first fit always runs).
    max_rounds : int
        Maximum number of extension rounds after the first fit.
    significance, min_amplitude, warn_ratio, fail_ratio, dominance : float
        Passed to :func:`hallcal.fit.adequacy.assess`.
    max_iterations, tol : optional
        Passed to every :func:`hallcal.fit.sem.solve_sem` (``[model] max_iterations``).
    noise : NoiseEstimate, optional
        Default :func:`hallcal.fit.adequacy.estimate_noise_variance` of d.

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
        deadline=t0 + float(time_budget),
    )  # fmt: skip
    edge, rel = _band_step(s, np.ascontiguousarray(y, dtype=np.float64))
    harmonics = tuple(sorted(set(rel.active) | {n}))
    basis = FourierBasis(harmonics)
    sem, rep = s.fit(harmonics, restrict_theta(edge.flux, basis), "sem")
    s.accept()
    if sem.status is SEMStatus.DIVERGED or not math.isfinite(sem.cost):
        status = SelectionStatus.FAILED
    else:
        harmonics, sem, rep, status = _extend(s, harmonics, sem, rep, max_rounds)
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
    )
