"""Automatic choice of the Fourier model order: ``[model] harmonics = "auto"``.

The paper (section "Model structure") notes that "the order m can be chosen by analyzing the
harmonic content of data d". :func:`select_harmonics` does that in four steps:

1. **Content of the data.** d is regressed on a wide Fourier basis of the measured angle y (the
   f_init output; linear, a fraction of a second with :func:`hallcal.fit.adequacy.harmonic_content`)
   and every harmonic gets a Wald test. Over y rather than the true angle, the content is wider
   than the flux's own: the f_init error modulates the pole-pair harmonic, which puts sidebands
   n_m +- j on the content (on the paper's bench harmonics 12..32 show 0.5-2 sigma although the
   flux has none). The initial set therefore keeps the significant and relevant harmonics where
   physics puts flux content: 1..n_m (magnet-to-magnet variations) and the multiples k n_m
   (distortion of the electrical waveform), plus n_m itself.
2. **Static shape test** (:func:`fit_curve`, no loop simulation). The data d_k lie on the closed
   curve {g(y0)} in R^3 whatever the motion; the curve is fitted with the chosen harmonics by
   alternating linear least squares and projection of each sample onto the curve, and harmonics
   that remain in the distance from the curve are added (dominant ones first, a few rounds). This
   finds, e.g., the sidebands n_m +- j of per-pole strength differences, which step 1 cannot tell
   from the f_init sidebands. With a set that pins the parametrization the fitted angle is the
   true angle within the noise floor, so the fit is also an excellent SEM start.
3. **Confirmation by SEM and the adequacy test.** The set is fitted by SEM and judged by
   :func:`hallcal.fit.adequacy.assess`; harmonics that remain in the shape residual are added with a
   warm start and the fit repeated while the time budget allows (model validation by residual
   analysis, Ljung 1999, sec. 16.6).
4. **Pruning.** Harmonics whose SEM coefficients are neither significant (Wald test with the SEM
   covariance) nor relevant (RMS below ``min_amplitude`` sigma) are dropped and the model refit;
   the pruned model is kept when its adequacy does not degrade beyond the statistical spread.

Residual harmonics that only the motion leaves (cogging, disturbances: they vanish when the
samples may slide along the flux curve) are never added: a flux model with them would absorb the
motion error into the table.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.fit.adequacy import (
    AdequacyReport,
    HarmonicContent,
    NoiseEstimate,
    _f,
    _fourier_normal_equations,
    assess,
    chi2_isf_even,
    curve_projection,
    default_max_harmonic,
    dominant_harmonics,
    estimate_noise_variance,
    harmonic_content,
)
from hallcal.fit.sem import SEMResult, least_squares_start, solve_sem
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "Candidate",
    "CurveFit",
    "HarmonicSelection",
    "fit_curve",
    "initial_harmonics",
    "select_harmonics",
]

_RANK = {"adequate": 0, "warning": 1, "inadequate": 2}


@dataclass(frozen=True)
class Candidate:
    """One model tried by :func:`select_harmonics`.

    Attributes
    ----------
    harmonics : tuple of int
    stage : str
        "static" (:func:`fit_curve` only), "initial" (first SEM fit), "extended" (harmonics added
        from the residual) or "pruned".
    cost, ratio, shape_ratio : float
        SEM cost and the ratios of :class:`hallcal.fit.adequacy.AdequacyReport` (static stage: cost
        and ratio NaN, shape ratio of the curve fit).
    verdict : str
        Verdict of the adequacy test ("" for the static stage).
    sem_status : str
        SEM status ("static" for the static stage).
    iterations : int
        SEM iterations (alternations for the static stage).
    solve_time : float
        Wall time of the fit [s].
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
    initial_harmonics : tuple of int
        The set chosen from the harmonic content of the data (step 1).
    content : HarmonicContent
        Content of d over the measured angle y.
    noise : NoiseEstimate
    candidates : tuple of Candidate
        Every model fitted, in order.
    status : str
        "converged" (the residual asks for nothing more), "time_budget" or "max_rounds" (stopped
        while the residual still suggested harmonics), "no_improvement" (adding the suggested
        harmonics did not improve the fit) or "failed" (the first fit failed).
    elapsed : float
        Wall time [s].
    """

    harmonics: tuple[int, ...]
    sem: SEMResult = field(repr=False)
    report: AdequacyReport = field(repr=False)
    initial_harmonics: tuple[int, ...]
    content: HarmonicContent = field(repr=False)
    noise: NoiseEstimate = field(repr=False)
    candidates: tuple[Candidate, ...] = field(repr=False)
    status: str
    elapsed: float

    @property
    def verdict(self) -> str:
        return self.report.verdict

    @property
    def adequacy(self) -> AdequacyReport:
        """Alias of ``report`` (the name the calibration pipeline looks for)."""
        return self.report

    def to_dict(self) -> dict:
        sigma = self.noise.std if self.noise.std > 0 else 1.0
        return {
            "harmonics": list(self.harmonics),
            "initial_harmonics": list(self.initial_harmonics),
            "status": self.status,
            "elapsed": _f(self.elapsed),
            "candidates": [c.to_dict() for c in self.candidates],
            "content": self.content.to_dict(scale=sigma),
            "report": self.report.to_dict(),
        }


def initial_harmonics(
    content: HarmonicContent,
    pole_pairs: int,
    *,
    noise_std: float,
    min_amplitude: float = 0.1,
) -> tuple[int, ...]:
    """Step 1 of :func:`select_harmonics`: the physically placed part of the data's content.

    Significant harmonics of d over the measured angle with an RMS of at least ``min_amplitude``
    noise standard deviations, restricted to 1..n_m and multiples of n_m, plus n_m.
    """
    n = int(pole_pairs)
    strong = content.significant_harmonics(min_amplitude * noise_std)
    chosen = {h for h in strong if h <= n or h % n == 0}
    chosen.add(n)
    return tuple(sorted(chosen))


@dataclass(frozen=True)
class CurveFit:
    """Static fit of the flux curve, free in its parametrization (see :func:`fit_curve`).

    Attributes
    ----------
    flux : FluxModel
        g_theta fitted at the parametrization ``x``.
    x : ndarray (N,)
        Angle of each sample on the curve [rad] (close to y0 when the harmonics pin the
        parametrization, e.g. on the paper's bench within the noise floor).
    shape_ratio : float
        Sum of squared distances from the curve over 2 N sigma^2.
    alternations : int
    residual : ndarray (N, 3)
        Distance vectors from the curve.
    """

    flux: FluxModel
    x: NDArray[np.float64] = field(repr=False)
    shape_ratio: float
    alternations: int
    residual: NDArray[np.float64] = field(repr=False)


def fit_curve(
    y: ArrayLike,
    d: ArrayLike,
    harmonics: tuple[int, ...],
    *,
    noise_variance: float,
    max_alternations: int = 12,
    rel_tol: float = 0.02,
    target: float = 1.03,
) -> CurveFit:
    """Fit the closed curve g(x) in R^3 with given harmonics, free in the parametrization x.

    Alternates (i) linear least squares of d on the Fourier basis at x and (ii) moving each sample
    to the nearest point of the curve (:func:`hallcal.fit.adequacy.curve_projection`), starting from
    x = y, the f_init output (orthogonal distance regression by alternation, a principal-curve
    fit). The distance of the data from the curve does not depend on how the curve is
    parametrized, so it tests whether the harmonics can represent the *shape* of the flux without
    the loop dynamics, at the cost of a few linear fits. Stops when the shape ratio is below
    ``target`` or improves by less than ``rel_tol`` per alternation.
    """
    yy = np.ascontiguousarray(y, dtype=np.float64)
    dd = np.ascontiguousarray(d, dtype=np.float64)
    K = np.asarray(sorted(harmonics), dtype=np.int64)
    basis = FourierBasis(tuple(int(h) for h in K))
    x = yy.copy()
    best: CurveFit | None = None
    scale = 2.0 * yy.size * noise_variance
    for it in range(1, max_alternations + 1):
        G, rhs = _fourier_normal_equations(x, dd, K)
        theta = np.linalg.lstsq(G, rhs, rcond=None)[0]
        flux = FluxModel(basis, theta.T)
        delta, resid, _ = curve_projection(flux, x, dd)
        ratio = float(np.vdot(resid, resid) / scale) if scale > 0 else math.inf
        if best is not None and not ratio < best.shape_ratio:
            break
        improved = best is None or ratio < best.shape_ratio * (1.0 - rel_tol)
        best = CurveFit(flux, x, ratio, it, resid)
        if ratio < target or not improved:
            break
        x = x + delta
    assert best is not None
    return best


def _expand_theta(
    flux: FluxModel, basis: FourierBasis, residual: NDArray, y0: NDArray
) -> NDArray[np.float64]:
    """theta for a new basis: old coefficients kept, new harmonics from the residual at y0."""
    theta = np.zeros((3, basis.size))
    theta[:, 0] = flux.theta[:, 0]
    new = [h for h in basis.harmonics if h not in flux.basis.harmonics]
    for h in basis.harmonics:
        if h in flux.basis.harmonics:
            js, jc = flux.basis.index(h)
            ks, kc = basis.index(h)
            theta[:, ks] = flux.theta[:, js]
            theta[:, kc] = flux.theta[:, jc]
    if new:
        sub = FourierBasis(tuple(new))
        coef = least_squares_start(sub, residual, y0)  # (3, 1 + 2 len(new))
        for j, h in enumerate(new):
            ks, kc = basis.index(h)
            theta[:, ks] = coef[:, 1 + 2 * j]
            theta[:, kc] = coef[:, 2 + 2 * j]
    return theta


def _coefficient_tests(
    sem: SEMResult, *, significance: float
) -> tuple[dict[int, float], dict[int, float], float]:
    """Wald statistic (chi-square, 6 dof) and RMS amplitude of each model harmonic."""
    basis = sem.flux.basis
    m = basis.size
    th = sem.theta.ravel()
    cov = np.asarray(sem.covariance, dtype=np.float64)
    wald: dict[int, float] = {}
    amp: dict[int, float] = {}
    for h in basis.harmonics:
        js, jc = basis.index(h)
        idx = [c * m + j for c in range(3) for j in (js, jc)]
        v = th[idx]
        amp[h] = math.sqrt(float(np.mean(v**2)))  # sqrt(mean_c (s^2 + c^2) / 2)
        try:
            wald[h] = float(v @ np.linalg.solve(cov[np.ix_(idx, idx)], v))
        except np.linalg.LinAlgError:
            wald[h] = math.inf
    thr = chi2_isf_even(significance / max(len(basis.harmonics), 1), 6)
    return wald, amp, thr


def select_harmonics(
    loop: ClosedLoop,
    r: ArrayLike,
    d: ArrayLike,
    *,
    y: ArrayLike,
    pole_pairs: int | None = None,
    max_harmonic: int | None = None,
    time_budget: float = 30.0,
    max_rounds: int = 4,
    significance: float = 1e-3,
    min_amplitude: float = 0.1,
    prune: bool = True,
    max_iterations: int = 30,
    tol: float = 1e-7,
    noise: NoiseEstimate | None = None,
    warn_ratio: float = 1.1,
    fail_ratio: float = 1.5,
    dominance: float = 0.05,
    static_rounds: int = 4,
) -> HarmonicSelection:
    """Choose the mechanical harmonics of the Fourier flux model from the data (``"auto"``).

    See the module docstring for the four steps (content of d over y, static shape test, SEM
    confirmed by the adequacy test and extended by the shape residual, pruning).

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
        Highest harmonic examined (default
        :func:`hallcal.fit.adequacy.default_max_harmonic`, 8 n_m).
    time_budget : float
        Wall-time budget [s]. The first fit always runs; a further fit starts only when its
        estimated time (the last fit's, scaled by the parameter count) fits in the budget.
    max_rounds : int
        Maximum number of extension rounds after the first fit.
    significance, min_amplitude : float
        As in :func:`hallcal.fit.adequacy.assess`.
    prune : bool
        Drop insignificant harmonics at the end and refit.
    max_iterations, tol : optional
        Passed to :func:`hallcal.fit.sem.solve_sem`.
    noise : NoiseEstimate, optional
        Default :func:`hallcal.fit.adequacy.estimate_noise_variance` of d.
    warn_ratio, fail_ratio, dominance : float
        Passed to :func:`hallcal.fit.adequacy.assess`.
    static_rounds : int
        Rounds of the static stage (:func:`fit_curve`, extended by the dominant harmonics of the
        distance from the curve); 0 skips it and starts SEM from the least-squares fit at y.

    Returns
    -------
    HarmonicSelection
    """
    t0 = time.perf_counter()
    r = np.ascontiguousarray(r, dtype=np.float64)
    dd = np.ascontiguousarray(d, dtype=np.float64)
    yy = np.ascontiguousarray(y, dtype=np.float64)
    n = int(loop.pole_pairs if pole_pairs is None else pole_pairs)
    if noise is None:
        noise = estimate_noise_variance(dd)
    sigma = noise.std
    hmax = int(max_harmonic) if max_harmonic else default_max_harmonic(n)
    content = harmonic_content(yy, dd, harmonics=np.arange(1, hmax + 1), significance=significance)
    start = initial_harmonics(content, n, noise_std=sigma, min_amplitude=min_amplitude)
    proj, off = loop.projection, loop.offset
    candidates: list[Candidate] = []

    def fit(
        harmonics: tuple[int, ...], theta0: NDArray | None, stage: str
    ) -> tuple[SEMResult, AdequacyReport]:
        basis = FourierBasis(harmonics)
        sem = solve_sem(loop, r, dd, basis, theta0=theta0, y=yy, max_iterations=max_iterations,
                        tol=tol)  # fmt: skip
        rep = assess(sem, dd, pole_pairs=n, noise=noise, projection=proj, offset=off,
                     max_harmonic=max(hmax, default_max_harmonic(n, harmonics)),
                     significance=significance, min_amplitude=min_amplitude,
                     warn_ratio=warn_ratio, fail_ratio=fail_ratio,
                     dominance=dominance)  # fmt: skip
        candidates.append(
            Candidate(
                harmonics,
                stage,
                sem.cost,
                rep.ratio,
                rep.shape_ratio,
                rep.verdict,
                sem.status,
                sem.iterations,
                sem.solve_time,
                False,
            )  # fmt: skip
        )
        return sem, rep

    def accept() -> None:
        candidates[-1] = replace(candidates[-1], accepted=True)

    def better(a: AdequacyReport, b: AdequacyReport) -> bool:
        """Whether report a is better than b."""
        if _RANK[a.verdict] != _RANK[b.verdict]:
            return _RANK[a.verdict] < _RANK[b.verdict]
        return a.shape_ratio < b.shape_ratio - 3 * b.ratio_std and a.ratio <= b.ratio * 1.05

    def time_left() -> float:
        return time_budget - (time.perf_counter() - t0)

    # static stage: does the set represent the shape of the flux curve? (cheap, no loop)
    harmonics = start
    curve: CurveFit | None = None
    if static_rounds > 0:
        for k in range(static_rounds):
            tc = time.perf_counter()
            curve = fit_curve(yy, dd, harmonics, noise_variance=noise.variance)
            candidates.append(
                Candidate(harmonics, "static", math.nan, math.nan, curve.shape_ratio, "",
                          "static", curve.alternations, time.perf_counter() - tc, True)
            )  # fmt: skip
            if (
                k == static_rounds - 1
                or curve.shape_ratio <= warn_ratio
                or time_left() < 0.5 * time_budget  # keep at least half for SEM
            ):
                break
            spec = harmonic_content(curve.x, curve.residual, harmonics=np.arange(1, hmax + 1),
                                    significance=significance)  # fmt: skip
            add = dominant_harmonics(spec, exclude=harmonics, noise_std=sigma,
                                     min_amplitude=min_amplitude, dominance=dominance)  # fmt: skip
            if not add:
                break
            harmonics = tuple(sorted(set(harmonics) | set(add)))

    theta_start = None if curve is None else np.array(curve.flux.theta)
    sem, rep = fit(harmonics, theta_start, "initial")
    if theta_start is not None and (sem.status == "diverged" or not math.isfinite(sem.cost)):
        sem, rep = fit(harmonics, None, "initial")  # least-squares start at y instead
    accept()
    status = "converged"
    if not math.isfinite(sem.cost) or sem.status == "diverged":
        status = "failed"
    rounds = 0
    while status == "converged" and rep.suggested_harmonics:
        if rounds >= max_rounds:
            status = "max_rounds"
            break
        new = tuple(sorted(set(harmonics) | set(rep.suggested_harmonics)))
        est = (sem.solve_time + 1.0) * (len(new) / max(len(harmonics), 1))
        if est > time_left():
            status = "time_budget"
            break
        basis = FourierBasis(new)
        theta0 = _expand_theta(sem.flux, basis, dd - sem.d_sim, sem.y0_sim)
        sem2, rep2 = fit(new, theta0, "extended")
        rounds += 1
        if better(rep2, rep):
            accept()
            harmonics, sem, rep = new, sem2, rep2
        else:
            status = "no_improvement"
            break

    if prune and status != "failed" and sem.status != "diverged":
        wald, amp, thr = _coefficient_tests(sem, significance=significance)
        drop = [
            h for h in harmonics
            if h != n and (wald[h] < thr or amp[h] < min_amplitude * sigma)
        ]  # fmt: skip
        est = (sem.solve_time + 1.0) * 0.5
        if drop and est <= time_left():
            kept = tuple(h for h in harmonics if h not in drop)
            basis = FourierBasis(kept)
            theta0 = np.zeros((3, basis.size))
            theta0[:, 0] = sem.theta[:, 0]
            for h in kept:
                js, jc = sem.flux.basis.index(h)
                ks, kc = basis.index(h)
                theta0[:, [ks, kc]] = sem.theta[:, [js, jc]]
            sem3, rep3 = fit(kept, theta0, "pruned")
            tol_ratio = max(5.0 * rep.ratio_std, 0.02)
            if (
                _RANK[rep3.verdict] <= _RANK[rep.verdict]
                and rep3.shape_ratio <= rep.shape_ratio + tol_ratio
                and rep3.ratio <= rep.ratio + tol_ratio
            ):
                accept()
                harmonics, sem, rep = kept, sem3, rep3

    return HarmonicSelection(
        harmonics=tuple(harmonics),
        sem=sem,
        report=rep,
        initial_harmonics=start,
        content=content,
        noise=noise,
        candidates=tuple(candidates),
        status=status,
        elapsed=time.perf_counter() - t0,
    )
