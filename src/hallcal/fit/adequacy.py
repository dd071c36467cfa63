"""Model adequacy from the calibration data alone: is the SEM fit good enough to trust its table?

A user without an encoder cannot see whether f_star is better than f_init. This module answers the
question from the calibration data, in the spirit of model validation by residual analysis
(Ljung 1999, "System Identification: Theory for the User", sec. 16.5-16.6): compare the residual
of the fit with what noise alone would leave, and look for structure in it.

Four diagnostics feed the verdict of :func:`assess` (the first, third and fourth computed in
:mod:`hallcal.fit._diagnostics`, the table's predicted error in :mod:`hallcal.fit._table_error`;
their public names are re-exported here):

1. **Noise level independent of the model** (:func:`estimate_noise_variance`): the Hall signals
   move slowly compared with the sample rate, so a high-order difference of ``d`` removes the
   signal and keeps the noise with a known gain (Pintelon & Schoukens 2012, "System
   Identification: A Frequency Domain Approach", 2nd ed., sec. 2.4 and 6.7 on nonparametric noise
   estimates from the high-frequency part of the data).
2. **Chi-square ratio** ``J(theta*) / ((3N - p) sigma^2)``: 1 for an adequate model with white
   noise, with standard deviation ``sqrt(2 / (3N - p))`` (Ljung 1999, sec. 16.6).
3. **Shape versus timing** (:func:`curve_projection`): each sample is moved along the model
   curve ``g_theta`` to the nearest point, ``delta_k = argmin |d_k - g_theta(y0_sim,k + delta)|``.
   What remains (the distance of the data from the model's closed curve in R^3, two of the three
   dimensions per sample) can only come from the flux model or the noise: its ratio to the noise
   level is the "shape ratio". What the shift ``delta`` absorbs is a position mismatch between the
   simulated and the actual motion (torque disturbance, cogging, plant-model error).
4. **Residual spectrum over spatial frequency** (:func:`harmonic_content`): ``d - d_sim``
   regressed on mechanical harmonics of y0_sim; harmonics with significant and relevant power are
   "left unexplained". Those that also remain in the shape residual are flux harmonics missing
   from the model ("suggested"); the others come from the motion. A flux error that only shifts
   the angle along the curve cannot be told from a motion error with one ramp: it shows as a
   warning, not as a suggestion.

Thresholds (measured on the virtual bench, 104 000 samples, see the tests):

- An adequate model gives ratio and shape ratio 1.00-1.02 (their statistical spread is 0.005), so
  ``warn_ratio = 1.1`` leaves room for mildly coloured or non-Gaussian noise and ``fail_ratio =
  1.5`` is far outside any noise explanation. Both are raised to ``1 + 5 std`` and ``1 + 10 std``
  for short records.
- The trapezoidal flux (electrical harmonics 3 and 5) fitted with harmonics 1..11 gives a ratio of
  640 and a shape ratio of 920: refused (verdict "inadequate").
- Unmodelled motion leaves the shape ratio near 1 but raises the ratio: torque disturbance 2e-3 /
  5e-3 / 1e-2 / 5e-2 give 1.34 / 3.1 / 9.3 / 208 (position mismatch 0.2 / 0.5 / 1.0 / 5.1 mrad
  RMS), cogging torque 2e-3 / 1e-2 / 5e-2 give 1.15 / 4.6 / 93 (0.14 / 0.67 / 3.4 mrad), a plant
  gain off by a factor 0.6 or 2 gives 3.0 or 2.6. In all of these f_star stayed within 10 % of
  the noise floor (within 0.5 % up to disturbance 1e-2): the flux estimate is insensitive to such
  mismatches, so they give a "warning" that states the mismatch, not a refusal. Only the shape
  ratio and flux harmonics missing from the model make a fit "inadequate".
- Unless the table is poorly determined: a random low-frequency load torque with the plant from
  a BLA (``benchmarks/bench_unseen.py`` case 222, cost ratio 2.15, shape 1.1) bent the slow
  warp directions of a 12-pole-pair table (its offset, harmonics 9, 11, 13) by 618x the noise
  floor that no covariance showed (predicted 124x, the table 670x, f_init 17x). With the cost
  above ``warn_ratio`` the correction in directions the covariance calls poorly determined
  (standard deviation above a quarter of the noise floor) counts as possible bias in the
  predicted error (:func:`motion_bias`): 631x there, and the status policy refuses the table
  (:mod:`hallcal.pipeline.verdict`).
- The exception: when the flux itself has harmonics at the sidebands of the motion error
  (trapezoidal flux with harmonics 33, 55, 77 in the model plus cogging 1e-2 at 66 periods), the
  model absorbs part of it: f_star 2.8x the floor (f_init 19x), shape ratio 1.3, ratio 2.6, a
  "warning" that says the table may carry part of the motion error.
"""

from __future__ import annotations

import enum
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.fit._diagnostics import (
    ContentStatus,
    CurveProjection,
    HarmonicContent,
    NoiseEstimate,
    NoiseStatus,
    _f,
    chi2_isf_even,
    curve_projection,
    default_max_harmonic,
    dominant_harmonics,
    estimate_noise_variance,
    harmonic_content,
    project_fit,
)
from hallcal.fit._table_error import (
    POORLY_DETERMINED,
    UPPER_PROBABILITY,
    _Table,
    _table,
    _table_sd,
    error_sources,
    error_spread,
    motion_bias,
)
from hallcal.fit.error_source import ErrorSource, ErrorSources
from hallcal.fit.sem import SEMResult
from hallcal.limits import one_blas_thread
from hallcal.messages import Outcome
from hallcal.sensor.reconstruction import projection_and_offset

__all__ = [
    "AdequacyReport",
    "AdequacyStatus",
    "ContentStatus",
    "CurveProjection",
    "ErrorSource",
    "ErrorSources",
    "HarmonicContent",
    "NoiseEstimate",
    "NoiseStatus",
    "Verdict",
    "assess",
    "chi2_isf_even",
    "curve_projection",
    "default_max_harmonic",
    "dominant_harmonics",
    "error_sources",
    "error_spread",
    "estimate_noise_variance",
    "POORLY_DETERMINED",
    "UPPER_PROBABILITY",
    "motion_bias",
    "harmonic_content",
    "project_fit",
]


class Verdict(enum.StrEnum):
    """The verdict of :func:`assess`."""

    ADEQUATE = "adequate"
    WARNING = "warning"
    #: the table must not be used (refused unless forced)
    INADEQUATE = "inadequate"

    @property
    def success(self) -> bool:
        return self is not Verdict.INADEQUATE


class AdequacyStatus(Outcome):
    """Whether :func:`assess` could judge the fit."""

    OK = "ok"
    #: the fit itself failed (no finite cost)
    FAILED = "failed"


# --------------------------------------------------------------------------------------------
# The adequacy report
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AdequacyReport:
    """Verdict on a SEM fit from the calibration data alone (see the module docstring).

    Attributes
    ----------
    verdict : Verdict
        ADEQUATE, WARNING or INADEQUATE (refuse the table unless forced).
    message : str
        One line for the user, naming the cause and what to do.
    reasons : tuple of str
        Every rule that fired.
    notes : tuple of str
        Longer explanations for the report.
    suggested_harmonics : tuple of int
        Harmonics to add: the dominant harmonics of the shape residual (distance of the data
        from the model's flux curve) that the model lacks.
    unexplained_harmonics : tuple of int
        Residual harmonics (not in the model) with significant and relevant power.
    dynamics_harmonics : tuple of int
        Unexplained harmonics absent from the shape residual: caused by the motion (cogging...).
    model_harmonics : tuple of int
    n_samples, n_parameters : int
    noise : NoiseEstimate
    cost, expected_cost : float
        J(theta*) and (3N - p) sigma^2.
    ratio, ratio_std : float
        cost / expected_cost and its standard deviation for an adequate model.
    shape_ratio : float
        Distance of the data from the model curve (2 of the 3 dimensions per sample) relative to
        its noise-only value; insensitive to timing (dynamics) errors.
    periodic_fraction : float
        Share of the excess cost ``cost - expected_cost`` found at spatial harmonics of y0_sim
        (1: a periodic cause such as missing flux harmonics or cogging; 0: random, e.g. a torque
        disturbance).
    position_mismatch_rms : float
        RMS [rad] of the shift along the model curve that the data need beyond noise: how far the
        simulated motion is from the actual one.
    residual_angle_rms : float
        RMS [rad] of that shift including noise (the residual seen as an angle).
    noise_floor : float
        RMS angle error [rad] that the noise alone causes, from sigma and the model's amplitude.
    predicted_error : float
        ``sqrt(noise_floor^2 + mean var eta + motion_bias^2)`` [rad]: expected RMS error of
        f_star about zero (the table's constant offset included, as ``reconstruct`` outputs it
        and an encoder measures it): cov(theta) propagated to the table, and with unmodelled
        motion the correction it may carry as bias (``motion_bias``).
    correction_rms : float
        RMS [rad] of the table's correction eta about zero (the model's view of f_init's error,
        its constant offset included).
    bijective : bool
        Whether the table is invertible (eq. recon_biject); False refuses the table.
    min_slope : float
    sem_status : str
    residual_spectrum : HarmonicContent
        SEM residual d - d_sim over harmonics of y0_sim.
    shape_spectrum : HarmonicContent
        Shape residual (distance from the model curve) over harmonics of y0_sim + delta.
    thresholds : dict
        The values of the decision rule actually used.
    status : AdequacyStatus
        OK, or FAILED when the fit itself failed (no finite cost).
    predicted_upper : float
        Upper quantile (:data:`UPPER_PROBABILITY`) of one run's RMS error of f_star about zero
        [rad] (:func:`error_spread`): the predicted error is its expectation.
    error_sources : str
        What carries the predicted variance of the table (:func:`error_sources`), "" when
        nothing stands out; first, with unmodelled motion, the bias it may carry
        (``ErrorSources.text`` of ``limited_by``).
    motion_bias : float
        With the cost above its warning level (unmodelled motion or shape): RMS [rad] of the
        correction in the directions the run determines poorly (:func:`motion_bias`), counted
        in ``predicted_error``; 0 otherwise.
    limited_by : ErrorSources
        The same, typed: what the remedy of a poorly determined table is chosen on
        (:func:`hallcal.pipeline.verdict.decide`).
    """

    verdict: Verdict
    message: str
    reasons: tuple[str, ...]
    notes: tuple[str, ...]
    suggested_harmonics: tuple[int, ...]
    unexplained_harmonics: tuple[int, ...]
    dynamics_harmonics: tuple[int, ...]
    model_harmonics: tuple[int, ...]
    n_samples: int
    n_parameters: int
    noise: NoiseEstimate
    cost: float
    expected_cost: float
    ratio: float
    ratio_std: float
    shape_ratio: float
    periodic_fraction: float
    position_mismatch_rms: float
    residual_angle_rms: float
    noise_floor: float
    predicted_error: float
    correction_rms: float
    bijective: bool
    min_slope: float
    sem_status: str
    residual_spectrum: HarmonicContent | None = field(repr=False)
    shape_spectrum: HarmonicContent | None = field(repr=False)
    thresholds: dict = field(repr=False)
    status: AdequacyStatus = AdequacyStatus.OK
    predicted_upper: float = math.nan
    error_sources: str = ""
    motion_bias: float = 0.0
    limited_by: ErrorSources = field(default_factory=ErrorSources, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "verdict", Verdict(self.verdict))
        object.__setattr__(self, "status", AdequacyStatus(self.status))

    @property
    def refused(self) -> bool:
        """True when the verdict is INADEQUATE."""
        return self.verdict is Verdict.INADEQUATE

    def to_dict(self) -> dict:
        """JSON-ready dictionary (plain floats, ints, strings and lists)."""
        sigma = self.noise.std if self.noise.std > 0 else 1.0
        unexplained = []
        spec = self.residual_spectrum
        if spec is not None:
            for h in self.unexplained_harmonics:
                unexplained.append(
                    {
                        "harmonic": int(h),
                        "amplitude_over_sigma": _f(spec.amplitude_of(h) / sigma),
                        "flux": h in self.suggested_harmonics,
                    }
                )
        return {
            "verdict": str(self.verdict),
            "message": self.message,
            "reasons": list(self.reasons),
            "notes": list(self.notes),
            "suggested_harmonics": list(self.suggested_harmonics),
            "unexplained_harmonics": unexplained,
            "dynamics_harmonics": list(self.dynamics_harmonics),
            "model_harmonics": list(self.model_harmonics),
            "n_samples": self.n_samples,
            "n_parameters": self.n_parameters,
            "noise": self.noise.to_dict(),
            "cost": _f(self.cost),
            "expected_cost": _f(self.expected_cost),
            "ratio": _f(self.ratio),
            "ratio_std": _f(self.ratio_std),
            "shape_ratio": _f(self.shape_ratio),
            "periodic_fraction": _f(self.periodic_fraction),
            "position_mismatch_rms": _f(self.position_mismatch_rms),
            "residual_angle_rms": _f(self.residual_angle_rms),
            "noise_floor": _f(self.noise_floor),
            "predicted_error": _f(self.predicted_error),
            "predicted_error_upper": _f(self.predicted_upper),
            "error_sources": self.error_sources,
            "correction_rms": _f(self.correction_rms),
            "bijective": bool(self.bijective),
            "min_slope": _f(self.min_slope),
            "sem_status": str(self.sem_status),
            "residual_spectrum": None if spec is None else spec.to_dict(scale=sigma),
            "shape_spectrum": (
                None if self.shape_spectrum is None else self.shape_spectrum.to_dict(scale=sigma)
            ),
            "thresholds": {k: _f(v) for k, v in self.thresholds.items()},
            "status": str(self.status),
        }


def _format_harmonics(h: tuple[int, ...], limit: int = 12) -> str:
    if not h:
        return "none"
    s = ", ".join(str(v) for v in h[:limit])
    return s + (f" (+{len(h) - limit} more)" if len(h) > limit else "")


def assess(
    sem: SEMResult,
    d: ArrayLike,
    *,
    pole_pairs: int,
    noise: NoiseEstimate | None = None,
    projection: ArrayLike | None = None,
    offset: ArrayLike | None = None,
    max_harmonic: int | None = None,
    warn_ratio: float = 1.1,
    fail_ratio: float = 1.5,
    significance: float = 1e-3,
    min_amplitude: float = 0.1,
    dominance: float = 0.05,
    warn_predicted: float = 1.5,
    lut_points: int = 4096,
    curve: CurveProjection | None = None,
    offset_variance: float | None = None,
    loop_noise_variance: float | None = None,
) -> AdequacyReport:
    """Judge a SEM fit from the calibration data alone (model validation, Ljung 1999, sec. 16).

    Parameters
    ----------
    sem : SEMResult
        The fit of problem (problem) (flux, cost, covariance, d_sim, y0_sim, status).
    d : array_like (N, 3)
        The Hall signals the fit used.
    pole_pairs : int, keyword-only
        n_m.
    noise : NoiseEstimate, optional
        Default :func:`estimate_noise_variance` of d (never the fit's own cost / (3N - p)).
    projection, offset : array_like, optional
        f_init's projection (2 x 3) and sensor offsets, as in the loop (default Clarke, zero).
    max_harmonic : int, optional
        Highest harmonic of the residual spectrum (default :func:`default_max_harmonic`).
    warn_ratio, fail_ratio : float
        Thresholds on the ratios (see the module docstring for the measurements behind them):
        above ``warn_ratio`` a warning, a shape ratio above ``fail_ratio`` refuses the fit.
    significance : float
        Family-wise level of the per-harmonic tests.
    min_amplitude : float
        Relevance: residual harmonics with an RMS below ``min_amplitude * sigma`` are ignored (one
        at 0.1 sigma adds 1 % to the cost and about 1 % to the variance of the angle error).
    dominance : float
        Suggest only missing harmonics with at least this fraction of the largest missing one's
        amplitude: a large missing harmonic also leaves small sidebands in the residual (the
        simulated angle is off while it is missing) that vanish once it is modelled.
    warn_predicted : float
        Warn when the predicted error exceeds this multiple of the noise floor (1.5: the
        parameter uncertainty adds more than the floor itself, in quadrature, times 1.1).
    lut_points : int
        Grid of the table built to check bijectivity and the correction size.
    curve : CurveProjection, optional
        The projection of d on the fit's curve if already computed (:func:`project_fit`: used
        only when it comes from this very fit and these very signals).
    offset_variance : float, optional
        The HAC variance of the table's constant offset [rad^2]
        (:func:`hallcal.fit.offset_variance.offset_long_run`): the predicted error adds what it
        exceeds both covariances' offset variance by (:func:`hallcal.fit._table_error._table`).
    loop_noise_variance : float, optional
        The variance of the table's constant offset with the Hall noise fed back by the loop
        [rad^2] (:func:`hallcal.fit.offset_variance.offset_loop_noise`): counted the same way,
        with or without unmodelled motion.

    Returns
    -------
    AdequacyReport
    """
    dd = np.asarray(d, dtype=np.float64)
    n = int(pole_pairs)
    P, o = projection_and_offset(projection, offset)
    with one_blas_thread():
        lv = _levels(sem, dd, noise, warn_ratio, fail_ratio)
        lv.thresholds.update(significance=significance, min_amplitude_over_sigma=min_amplitude,
                             dominance=dominance, warn_predicted=warn_predicted)  # fmt: skip
        motion = lv.ratio if lv.ratio > lv.warn and not lv.no_noise else None
        tab = _table(sem, n, P, o, lv.sigma2, lut_points, motion=motion,
                     offset_variance=offset_variance,
                     loop_noise_variance=loop_noise_variance)  # fmt: skip
        if not math.isfinite(lv.cost) or sem.status == "diverged":
            return _failed_report(sem, lv, tab)
        sh = _shape_and_timing(project_fit(sem, dd, known=curve), lv)
        hmax = int(max_harmonic) if max_harmonic else default_max_harmonic(n, lv.model_h)
        sp = _spectra(sem, dd, lv, sh, hmax, significance, min_amplitude, dominance)
    fails, warns, notes = _reasons(sem, lv, tab, sh, sp, warn_predicted)
    verdict, msg = _decision(lv, tab, sh, sp, fails, warns)
    return _report(sem, dd.shape[0], lv, tab, sh, sp, verdict, msg, fails + warns, notes)


@dataclass
class _Levels:
    """Step 1 of :func:`assess`: the noise level, the cost ratio and the thresholds."""

    noise: NoiseEstimate
    sigma2: float
    no_noise: bool
    model_h: tuple[int, ...]
    p: int
    dof: int
    cost: float
    expected: float
    ratio: float
    ratio_std: float
    warn: float
    fail: float
    thresholds: dict

    @property
    def sigma(self) -> float:
        return math.sqrt(self.sigma2) if self.sigma2 > 0 else math.nan


def _levels(
    sem: SEMResult, dd: NDArray, noise: NoiseEstimate | None, warn_ratio: float, fail_ratio: float
) -> _Levels:
    """Noise level (model-free), chi-square ratio and its spread, thresholds raised for short
    records to ``1 + 5 std`` and ``1 + 10 std``."""
    if noise is None:
        noise = estimate_noise_variance(dd)
    sigma2 = noise.variance
    no_noise = not (math.isfinite(sigma2) and sigma2 > 0)
    if no_noise:  # no model-free level (record too short or constant): the fit's own, uninformative
        sigma2 = float(sem.noise_variance)
    p = int(sem.theta.size)
    dof = max(3 * dd.shape[0] - p, 1)
    expected = dof * sigma2
    cost = float(sem.cost)
    ratio = cost / expected if expected > 0 else math.inf
    rel_noise = noise.std_error / sigma2 if not no_noise else 0.0
    ratio_std = math.sqrt(2.0 / dof + rel_noise**2)
    warn = max(warn_ratio, 1.0 + 5.0 * ratio_std)
    fail = max(fail_ratio, 1.0 + 10.0 * ratio_std)
    model_h = tuple(int(h) for h in sem.flux.basis.harmonics)
    return _Levels(noise, sigma2, no_noise, model_h, p, dof, cost, expected, ratio, ratio_std,
                   warn, fail, {"warn_ratio": warn, "fail_ratio": fail})  # fmt: skip


def _failed_report(sem: SEMResult, lv: _Levels, tab: _Table) -> AdequacyReport:
    msg = (
        f"inadequate: the SEM fit failed ({sem.status}); the closed loop with this model "
        "does not reproduce the data"
    )
    nan = math.nan
    return AdequacyReport(
        verdict=Verdict.INADEQUATE, message=msg, reasons=("fit failed",), notes=(),
        suggested_harmonics=(), unexplained_harmonics=(), dynamics_harmonics=(),
        model_harmonics=lv.model_h, n_samples=sem.n_samples, n_parameters=lv.p, noise=lv.noise,
        cost=lv.cost, expected_cost=lv.expected, ratio=lv.ratio, ratio_std=lv.ratio_std,
        shape_ratio=nan, periodic_fraction=nan, position_mismatch_rms=nan,
        residual_angle_rms=nan, noise_floor=tab.floor, predicted_error=tab.predicted,
        correction_rms=tab.correction_rms, bijective=bool(tab.lut.bijective),
        min_slope=float(tab.lut.min_slope), sem_status=str(sem.status), residual_spectrum=None,
        shape_spectrum=None, thresholds=lv.thresholds, status=AdequacyStatus.FAILED,
        predicted_upper=tab.upper,
    )  # fmt: skip


@dataclass
class _Shape:
    """Step 3 of :func:`assess`: distance from the model curve versus shift along it."""

    shape_ratio: float
    delta: NDArray[np.float64]
    e_curve: NDArray[np.float64]
    residual_angle_rms: float
    mismatch: float


def _shape_and_timing(curve: CurveProjection, lv: _Levels) -> _Shape:
    """Shape ratio (distance from the curve, 2 of 3 dimensions per sample, over its noise-only
    value) and the position mismatch (RMS shift along the curve beyond its noise part)."""
    delta, e_curve, speed2 = curve.delta, curve.residual, curve.speed2
    shape_expected = (2.0 / 3.0) * lv.dof * lv.sigma2
    shape_ratio = float(np.vdot(e_curve, e_curve) / shape_expected) if lv.sigma2 > 0 else math.inf
    delta = delta - delta.mean()
    residual_angle_rms = float(np.sqrt(np.mean(delta**2)))
    noise_delta2 = float(np.mean(lv.sigma2 / np.maximum(speed2, 1e-300)))
    mismatch = math.sqrt(max(residual_angle_rms**2 - noise_delta2, 0.0))
    return _Shape(shape_ratio, delta, e_curve, residual_angle_rms, mismatch)


@dataclass
class _Spectra:
    """Step 4 of :func:`assess`: residual harmonics, from the flux or from the motion."""

    spec: HarmonicContent
    shape_spec: HarmonicContent
    periodic_fraction: float
    unexplained: tuple[int, ...]
    suggested: tuple[int, ...]
    dynamics: tuple[int, ...]


def _spectra(
    sem: SEMResult, dd: NDArray, lv: _Levels, sh: _Shape, hmax: int, significance: float,
    min_amplitude: float, dominance: float,
) -> _Spectra:  # fmt: skip
    """Residual spectrum over the simulated angle and shape-residual spectrum over the shifted
    angle: harmonics in both are missing flux harmonics ("suggested"), harmonics only in the
    former come from the motion ("dynamics")."""
    e = dd - sem.d_sim
    harm = np.arange(1, hmax + 1)
    # the two spectra are independent: the shape one in a second thread (NumPy releases the GIL
    # in its array operations; each spectrum's arithmetic is the same in either thread)
    with ThreadPoolExecutor(1) as pool:
        shape_future = pool.submit(harmonic_content, sem.y0_sim + sh.delta, sh.e_curve,
                                   harmonics=harm, significance=significance)  # fmt: skip
        spec = harmonic_content(sem.y0_sim, e, harmonics=harm, significance=significance)
        shape_spec = shape_future.result()
    explained = float(np.sum(spec.total_sum - spec.residual_sum))
    excess = lv.cost - lv.expected
    periodic_fraction = (
        float(np.clip(explained / excess, 0.0, 1.0))
        if excess > 3 * lv.ratio_std * lv.expected
        else 0.0
    )
    relevant = spec.significant & (spec.amplitude >= min_amplitude * lv.sigma)
    unexplained = tuple(
        int(h) for h, r in zip(spec.harmonics, relevant, strict=True) if r and h not in lv.model_h
    )
    suggested = dominant_harmonics(shape_spec, exclude=lv.model_h, noise_std=lv.sigma,
                                   min_amplitude=min_amplitude, dominance=dominance)  # fmt: skip
    flux_any = set(dominant_harmonics(shape_spec, exclude=lv.model_h, noise_std=lv.sigma,
                                      min_amplitude=min_amplitude, dominance=0.0))  # fmt: skip
    dynamics = tuple(h for h in unexplained if h not in flux_any)
    return _Spectra(spec, shape_spec, periodic_fraction, unexplained, suggested, dynamics)


def _noise_reasons(lv: _Levels) -> list[str]:
    """Warnings on the noise level the verdict rests on."""
    out = []
    if lv.no_noise:
        out.append(
            "the noise level could not be estimated from the data (record too short): the cost "
            "ratio is not informative"
        )
    if lv.noise.status is NoiseStatus.COLOURED:
        out.append(
            f"the noise is not white (lag-2/lag-1 variance ratio {lv.noise.white_ratio:.3f}): the "
            "expected cost is uncertain"
        )
    return out


def _gain_reason(tab: _Table) -> str | None:
    """A warning when the table's own predicted error is comparable to its correction.

    The table's correction eta is f_init's error as the model sees it; when the table's own
    predicted error is comparable, f_star is not reliably better than f_init. When it is at
    least the correction, f_star is predicted worse than f_init (``predicted >= hypot(floor,
    correction)``). The calibration's status policy refuses the table in both cases (from half
    the correction on, beyond half the noise floor: one run's table error scatters up to 2x
    its prediction; :func:`hallcal.pipeline.verdict.decide`); here it is a reason of a warning.
    """
    table_sd = _table_sd(tab)
    if not (table_sd > tab.floor and table_sd >= 0.5 * tab.correction_rms):
        return None
    worse = table_sd >= tab.correction_rms
    return (
        ("f_star may be worse than f_init" if worse else "the improvement over f_init is uncertain")
        + f": the table's own predicted error {1e3 * table_sd:.3g} mrad is "
        + ("at least" if worse else "more than half")
        + f" the correction it applies ({1e3 * tab.correction_rms:.3g} mrad RMS)"
    )


def _reasons(
    sem: SEMResult, lv: _Levels, tab: _Table, sh: _Shape, sp: _Spectra, warn_predicted: float
) -> tuple[list[str], list[str], list[str]]:
    """Step 5 of :func:`assess`: the rules that fire (refusal, warning) and the notes."""
    fails: list[str] = []
    warns: list[str] = []
    notes: list[str] = []
    lut, warn, fail = tab.lut, lv.warn, lv.fail
    if not lut.bijective:
        fails.append(
            f"the table is not bijective (min slope {lut.min_slope:.3g}): the paper's bijectivity "
            "condition fails"
        )
    if sh.shape_ratio > fail:
        fails.append(
            "the data lie off the model's flux curve: shape ratio "
            f"{sh.shape_ratio:.3g} > {fail:.3g}"
        )
    if sp.suggested and lv.ratio > fail:
        fails.append(f"flux harmonics missing from the model: {_format_harmonics(sp.suggested)}")
    if warn < sh.shape_ratio <= fail:
        warns.append(f"shape ratio {sh.shape_ratio:.3g} > {warn:.3g}")
    if lv.ratio > warn:
        warns.append(f"cost ratio {lv.ratio:.3g} > {warn:.3g}")
    if sp.suggested and not lv.ratio > fail:
        warns.append(f"small flux harmonics missing: {_format_harmonics(sp.suggested)}")
    if sp.dynamics:
        warns.append(
            f"residual harmonics from the motion, not the flux: {_format_harmonics(sp.dynamics)}"
        )
    if sem.status != "converged":
        warns.append(f"SEM status {sem.status}")
    warns += _noise_reasons(lv)
    if not sp.spec.status.success:
        warns.append("the run covers less than one revolution")
    gain = _gain_reason(tab)
    if gain is not None:
        warns.append(gain)
    if math.isfinite(tab.predicted) and tab.predicted > warn_predicted * tab.floor:
        warns.append(
            f"the data determine the table poorly (the covariance of theta predicts "
            f"{tab.predicted / tab.floor:.2g}x the noise floor"
            + (f"; {tab.sources.text}" if tab.sources.text else "")
            + ")"
        )
        notes.append(
            "The covariance of theta gives a table error well above the noise floor: some "
            "combinations of harmonics are weakly identified by this run (e.g. sidebands "
            "n_m ± j together with n_m ∓ j shift the angle at harmonic j, which the closed "
            "loop barely reveals at low spatial frequency). A longer run or fewer harmonics help."
        )
    if lv.ratio > warn and sh.shape_ratio <= warn:
        notes.append(
            f"The residual is {lv.ratio:.3g} times the noise level but the data lie on the "
            f"model's flux curve (shape ratio {sh.shape_ratio:.3g}): the excess is a position "
            f"mismatch of {1e3 * sh.mismatch:.3g} mrad RMS between the simulated and the actual "
            "motion (torque disturbance, cogging torque or plant-model error, not in the model). "
            "On the virtual bench such mismatches up to 5 mrad left f_star within 10 % of the "
            "noise floor."
        )
    notes += _motion_notes(tab)
    if sp.dynamics:
        notes.append(
            f"Residual harmonics {_format_harmonics(sp.dynamics)} vanish when each sample may "
            "slide along the model's flux curve, so they come from the motion (e.g. a cogging "
            "torque at their mean harmonic; a flux error that only shifts the angle looks the "
            "same), not from the flux shape; adding them to the model would let it absorb the "
            "motion error."
        )
    if sp.suggested:
        notes.append(
            f"Residual harmonics {_format_harmonics(sp.suggested)} remain at a distance from the "
            "model's flux curve: flux harmonics the model lacks."
        )
    if not math.isfinite(tab.predicted):
        notes.append("The covariance of theta is not available; no predicted error.")
    return fails, warns, notes


def _motion_notes(tab: _Table) -> list[str]:
    """The report's note on the bias unmodelled motion may carry (:func:`motion_bias`)."""
    if not tab.motion_bias > 0.0:
        return []
    return [
        f"Unmodelled motion bends the directions of the table the run determines poorly, and "
        f"no covariance shows it: {1e3 * tab.motion_bias:.3g} mrad RMS of the correction lies "
        "there and may be the motion's imprint rather than f_init's error, so the predicted "
        "error counts it. A calibration run under a steady load (no varying torque), a longer "
        "or a faster ramp determines them better."
    ]


def _decision(
    lv: _Levels, tab: _Table, sh: _Shape, sp: _Spectra, fails: list[str], warns: list[str]
) -> tuple[Verdict, str]:
    """Step 6 of :func:`assess`: the verdict and its one-line message."""
    mrad = 1e3
    if fails:
        return Verdict.INADEQUATE, _refusal_message(lv, tab, sh, sp)
    if warns:
        # first whether the table helps at all, then why the fit is not clean
        parts: list[str] = [w for w in warns if w.startswith(("f_star may be", "the improvement"))]
        if sp.suggested:
            parts.append(
                f"small flux harmonics {_format_harmonics(sp.suggested)} are missing (cost "
                f"{lv.ratio:.3g}x the noise level, shape {sh.shape_ratio:.3g}x)"
            )
        elif lv.ratio > lv.warn:
            if sp.dynamics and sp.periodic_fraction > 0.5:
                cause = (
                    f" at harmonics {_format_harmonics(sp.dynamics, 6)} (periodic: cogging-like)"
                )
            elif sp.periodic_fraction <= 0.5:
                cause = " (not periodic in the angle: e.g. a torque disturbance)"
            else:
                cause = ""
            parts.append(
                f"cost {lv.ratio:.3g}x the noise level with the flux shape at "
                f"{sh.shape_ratio:.3g}x: unmodelled motion{cause}, a position mismatch of "
                f"{mrad * sh.mismatch:.3g} mrad RMS (disturbance, cogging or plant model)"
            )
            if sh.shape_ratio > lv.warn:
                parts.append(
                    "the data also lie off the model's flux curve: the table may carry part of "
                    "the motion error"
                )
        elif sh.shape_ratio > lv.warn:
            parts.append(
                f"the data lie slightly off the model's flux curve ({sh.shape_ratio:.3g}x)"
            )
        for reason in warns:
            if reason.startswith(("SEM status", "the noise", "the run", "the data determine")):
                parts.append(reason)
        if not parts:
            parts = warns[:2]
        return Verdict.WARNING, (
            "warning: "
            + "; ".join(parts)
            + f"; predicted error {mrad * tab.predicted:.3g} mrad (floor "
            f"{mrad * tab.floor:.3g} mrad)"
        )
    return Verdict.ADEQUATE, (
        f"adequate: cost {lv.ratio:.3g}x the noise level (expected 1 ± {lv.ratio_std:.2g}), "
        f"predicted error {mrad * tab.predicted:.3g} mrad (noise floor {mrad * tab.floor:.3g} "
        "mrad)"
    )


def _report(
    sem: SEMResult, n_samples: int, lv: _Levels, tab: _Table, sh: _Shape, sp: _Spectra,
    verdict: Verdict, msg: str, reasons: list[str], notes: list[str],
) -> AdequacyReport:  # fmt: skip
    """The report of :func:`assess` from its steps (levels, table, shape, spectra, decision)."""
    return AdequacyReport(
        verdict=verdict,
        message=msg,
        reasons=tuple(reasons),
        notes=tuple(notes),
        suggested_harmonics=sp.suggested,
        unexplained_harmonics=sp.unexplained,
        dynamics_harmonics=sp.dynamics,
        model_harmonics=lv.model_h,
        n_samples=n_samples,
        n_parameters=lv.p,
        noise=lv.noise,
        cost=lv.cost,
        expected_cost=lv.expected,
        ratio=lv.ratio,
        ratio_std=lv.ratio_std,
        shape_ratio=sh.shape_ratio,
        periodic_fraction=sp.periodic_fraction,
        position_mismatch_rms=sh.mismatch,
        residual_angle_rms=sh.residual_angle_rms,
        noise_floor=tab.floor,
        predicted_error=tab.predicted,
        correction_rms=tab.correction_rms,
        bijective=bool(tab.lut.bijective),
        min_slope=float(tab.lut.min_slope),
        sem_status=str(sem.status),
        residual_spectrum=sp.spec,
        shape_spectrum=sp.shape_spec,
        thresholds=lv.thresholds,
        status=AdequacyStatus.OK,
        predicted_upper=tab.upper,
        error_sources=tab.sources.text,
        motion_bias=tab.motion_bias,
        limited_by=tab.sources,
    )


def _refusal_message(lv: _Levels, tab: _Table, sh: _Shape, sp: _Spectra) -> str:
    lut = tab.lut
    if not lut.bijective:
        return (
            "inadequate: the identified model gives a non-bijective lookup table (min slope "
            f"{lut.min_slope:.3g}); f_star would give wrong angles"
            + (
                f"; the residual shows harmonics {_format_harmonics(sp.suggested, 6)} missing"
                if sp.suggested
                else ""
            )
        )
    if sp.suggested:
        add = sorted(set(lv.model_h) | set(sp.suggested))
        return (
            f"inadequate: model cost {lv.ratio:.3g}x the noise level (shape "
            f"{sh.shape_ratio:.3g}x); the residual shows mechanical harmonics "
            f"{_format_harmonics(sp.suggested)} missing from the model: add them (harmonics = "
            f'{_compact(add)}) or use harmonics = "auto"'
        )
    return (
        f"inadequate: the data lie off the model's flux curve (shape {sh.shape_ratio:.3g}x the "
        f"noise level, cost {lv.ratio:.3g}x) without a clear missing harmonic: use harmonics = "
        '"auto" or a richer basis'
    )


def _compact(h: list[int]) -> str:
    """[1, 2, 3, 4, 7] -> "[1..4, 7]"."""
    out: list[str] = []
    i = 0
    while i < len(h):
        j = i
        while j + 1 < len(h) and h[j + 1] == h[j] + 1:
            j += 1
        out.append(f"{h[i]}..{h[j]}" if j - i >= 2 else ", ".join(str(v) for v in h[i : j + 1]))
        i = j + 1
    return "[" + ", ".join(out) + "]"
