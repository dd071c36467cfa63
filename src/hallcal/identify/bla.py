"""Best Linear Approximation (BLA) of the plant, measured in closed loop, and its parametric fit.

Step 2 of Algorithm 1 of the paper (section "Obtaining a Best Linear Approximation"): the BLA of
the plant ``G`` (torque command ``u`` -> position ``y``) is measured in closed loop with
random-phase multisine references, following Pintelon & Schoukens (2012), "System Identification:
A Frequency Domain Approach", 2nd ed., sec. 3.8 (BLA in feedback, indirect method) with the
robust method (M realizations x P periods, sec. 3.8 and 2.5: noise variance from the
period-to-period spread, total variance from the realization-to-realization spread). A
continuous-time model with an input delay is then fitted to the nonparametric BLA with the
frequency-domain estimators of ch. 9: Levy (1959) linear least squares, Sanathanan & Koerner
(1963) iterations, and a weighted nonlinear least-squares refinement.

The measured position ``y`` comes from the imperfect Hall reconstruction ``f_init``, so the BLA
is ``c G`` with an unknown gain ``c``; the paper corrects it elsewhere (its gain-correction
equation for c-hat), see :meth:`ParametricBLA.scaled`. The model order can be chosen from the data
(:func:`select_order`: weighted output-error cost against the BLA's variance, with Rissanen's
minimum-description-length criterion, stable fits preferred).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from hallcal.errors import HallcalInputError

__all__ = [
    "NonparametricBLA",
    "OrderCandidate",
    "OrderSelection",
    "ParametricBLA",
    "fit_parametric",
    "model_poles",
    "nonparametric_bla",
    "select_order",
]

_POWER_THRESHOLD = 1e-8  # excited line: reference power above this fraction of the largest line


# --------------------------------------------------------------------------------------------------
# nonparametric BLA


@dataclass(frozen=True, eq=False)
class NonparametricBLA:
    """Nonparametric closed-loop BLA of the plant at the excited frequencies.

    All variances are variances of the complex estimates themselves (``E|G_hat - E G_hat|^2``,
    i.e. of the mean over the M realizations), to first order. The variance of the stochastic
    nonlinear distortion of one realization is ``realizations * var_nonlinear``
    (Pintelon & Schoukens 2012, sec. 3.8, robust method).

    Attributes
    ----------
    freq : ndarray, shape (F,)
        Frequencies [Hz] of the excited lines.
    lines : ndarray of int, shape (F,)
        DFT line indices ``k`` in one period (``freq = k / (N Ts)``).
    G : ndarray of complex, shape (F,)
        BLA of the plant, ``G_ry / G_ru`` (discrete-time FRF, input through the hold).
    var_noise : ndarray, shape (F,)
        Noise variance of ``G`` (period-to-period spread); NaN with a single steady-state period.
    var_total : ndarray, shape (F,)
        Total variance of ``G``: noise plus stochastic nonlinear distortion
        (realization-to-realization spread); equal to ``var_noise`` with a single realization.
    var_nonlinear : ndarray, shape (F,)
        ``var_total - var_noise`` clipped at 0; NaN when it cannot be estimated.
    G_ry, G_ru : ndarray of complex, shape (F,)
        BLAs from the reference to the output and to the input (averaged over realizations).
    realizations : int
        Number of realizations M.
    periods : int
        Steady-state periods per realization P (transient periods excluded).
    period_samples : int
        Period N in samples.
    sample_time : float
        Sample time Ts [s].
    status : str
        ``"ok"``; ``"single-realization"`` (M = 1: no nonlinear-distortion estimate);
        ``"single-period"`` (P = 1: no noise estimate); or both joined by ``"+"``.
    """

    freq: np.ndarray
    lines: np.ndarray
    G: np.ndarray
    var_noise: np.ndarray
    var_total: np.ndarray
    var_nonlinear: np.ndarray
    G_ry: np.ndarray
    G_ru: np.ndarray
    realizations: int
    periods: int
    period_samples: int
    sample_time: float
    status: str = "ok"

    def to_frd(self) -> Any:
        """The BLA as a ``control.FRD`` (python-control, imported lazily), omega in rad/s."""
        import control

        return control.FRD(np.asarray(self.G), 2.0 * np.pi * np.asarray(self.freq))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary: floats, lists of floats, complex values as ``[re, im]`` pairs.

        Non-finite floats are written as ``None``.
        """
        return {
            "kind": "nonparametric-bla",
            "freq": _floats(self.freq),
            "lines": [int(k) for k in self.lines],
            "G": _complex_pairs(self.G),
            "var_noise": _floats(self.var_noise),
            "var_total": _floats(self.var_total),
            "var_nonlinear": _floats(self.var_nonlinear),
            "G_ry": _complex_pairs(self.G_ry),
            "G_ru": _complex_pairs(self.G_ru),
            "realizations": int(self.realizations),
            "periods": int(self.periods),
            "period_samples": int(self.period_samples),
            "sample_time": float(self.sample_time),
            "status": str(self.status),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> NonparametricBLA:
        """Inverse of :meth:`to_dict`.

        Raises
        ------
        HallcalInputError
            If a key is missing or malformed (the message names it).
        """
        _check_kind(data, "nonparametric-bla")
        return cls(
            freq=_array_from(data, "freq"),
            lines=np.asarray(_get(data, "lines"), dtype=np.int64),
            G=_complex_from(data, "G"),
            var_noise=_array_from(data, "var_noise"),
            var_total=_array_from(data, "var_total"),
            var_nonlinear=_array_from(data, "var_nonlinear"),
            G_ry=_complex_from(data, "G_ry"),
            G_ru=_complex_from(data, "G_ru"),
            realizations=int(_get(data, "realizations")),
            periods=int(_get(data, "periods")),
            period_samples=int(_get(data, "period_samples")),
            sample_time=float(_get(data, "sample_time")),
            status=str(data.get("status", "ok")),
        )


def nonparametric_bla(
    r: np.ndarray,
    u: np.ndarray,
    y: np.ndarray,
    realization: np.ndarray,
    *,
    period_samples: int,
    transient_periods: int,
    sample_time: float,
    lines: Sequence[int] | np.ndarray | None = None,
    detrend: bool = True,
) -> NonparametricBLA:
    """Closed-loop BLA by the indirect method, averaged over periods and realizations.

    Pintelon & Schoukens (2012), sec. 3.8 (indirect method: ``G_BLA = G_ry / G_ru`` with the
    reference ``r`` as the external, known excitation) with the robust method (M realizations x P
    periods) and the variance expressions of sec. 2.5 (sample means and variances of periodic
    data):

    1. per realization ``m``, drop the first ``transient_periods`` periods and keep the
       ``P`` steady-state periods;
    2. detrend (if ``detrend``): subtract from ``r``, ``u`` and ``y`` the least-squares line
       through their ``P`` period means. A slow ramp under the multisine (see
       :func:`hallcal.identify.excitation.multisine_experiment`) gives a linear trend in steady
       state, and a ramp leaks into every DFT line; the periodic part has the same mean in every
       period, so this slope is the least-squares slope with the periodic part left free and is not
       biased by the excitation. Only the slope matters: a constant offset lives at DC only. The
       noise in the estimated slope leaks into the low lines identically in all periods of a
       realization, so it is counted in ``var_total`` (not in ``var_noise``); for white noise it
       adds about ``12 / ((P^2 - 1) (2 pi k)^2)`` of the noise variance at line ``k``;
    3. per period ``p`` the DFT ``R, U, Y`` at the excited lines; ``G_ry^[m] = mean_p Y / R``
       and ``G_ru^[m] = mean_p U / R`` with their noise (co)variances from the period-to-period
       sample (co)variance divided by ``P``;
    4. over realizations: ``G_ry = mean_m G_ry^[m]``, ``G_ru = mean_m G_ru^[m]``; total
       (co)variances from the realization-to-realization sample (co)variance divided by ``M``,
       noise (co)variances as the sum of the per-realization ones divided by ``M^2``;
    5. ``G = G_ry / G_ru`` with first-order propagation
       ``var G = (var G_ry + |G|^2 var G_ru - 2 Re(conj(G) cov(G_ry, G_ru))) / |G_ru|^2``.

    The ratio of means (rather than the mean of the per-realization ratios ``Y^[m] / U^[m]``) is
    used because the reference is noise free: ``G_ry^[m]`` and ``G_ru^[m]`` are linear in the
    noise and the nonlinear distortions, so their means are unbiased, and the division once at the
    end leaves a bias of order ``var G_ru / |G_ru|^2`` that vanishes as M grows. Each ratio
    ``Y^[m] / U^[m]`` instead divides by a noisy ``U`` (feedback correlates its noise with that of
    ``Y``); that bias does not decrease with M.

    Parameters
    ----------
    r, u, y : ndarray, shape (n,)
        Reference, plant input (torque command) and measured output (position from the Hall
        reconstruction), one sample per entry.
    realization : ndarray of int, shape (n,)
        Realization index of every sample; each realization is one contiguous block holding a
        whole number of periods, the same number for all realizations.
    period_samples : int
        Period N of the multisine in samples.
    transient_periods : int
        Periods dropped at the start of every realization.
    sample_time : float
        Sample time Ts [s].
    lines : sequence of int, optional
        Excited DFT lines (index k in one period). Default: the lines where the reference power
        exceeds 1e-8 of its largest line (DC and Nyquist excluded).
    detrend : bool
        Remove a linear trend per realization and signal (step 2); needs ``P >= 2``.

    Returns
    -------
    NonparametricBLA

    Raises
    ------
    HallcalInputError
        If the data do not fit the period/realization layout (the message names the column or
        option at fault).
    """
    lay = _period_layout(
        r, u, y, realization, period_samples, transient_periods, sample_time, detrend
    )
    spectra = _steady_state_spectra(lay, detrend=detrend)  # steps 1-2
    k = _excited_lines(spectra.r, lay.n, lines)
    at_lines = spectra.at(k)
    frf = _indirect_frf(at_lines)  # steps 3-5
    var = _frf_variances(at_lines, frf)
    return NonparametricBLA(
        freq=k / (lay.n * lay.sample_time),
        lines=k,
        G=frf.G,
        var_noise=var.noise,
        var_total=var.total,
        var_nonlinear=var.nonlinear,
        G_ry=frf.G_ry,
        G_ru=frf.G_ru,
        realizations=lay.realizations,
        periods=lay.periods,
        period_samples=lay.n,
        sample_time=lay.sample_time,
        status=_bla_status(lay.realizations, lay.periods),
    )


@dataclass(frozen=True, eq=False)
class _PeriodLayout:
    """The checked signals of :func:`nonparametric_bla`, in realizations of whole periods."""

    signals: dict[str, np.ndarray]  # "r", "u", "y"
    blocks: list[np.ndarray]  # sample indices of every realization
    n: int  # period N in samples
    transient: int  # periods dropped at the start of every realization
    periods: int  # steady-state periods P per realization
    sample_time: float

    @property
    def realizations(self) -> int:
        return len(self.blocks)


def _period_layout(
    r: np.ndarray,
    u: np.ndarray,
    y: np.ndarray,
    realization: np.ndarray,
    period_samples: int,
    transient_periods: int,
    sample_time: float,
    detrend: bool,
) -> _PeriodLayout:
    """Check the columns and options; split the record into M realizations of P periods.

    The robust method of Pintelon & Schoukens (2012), sec. 3.8, needs M contiguous realizations
    holding the same whole number of periods; the first ``transient_periods`` of each are dropped.
    """
    n = _int_option(period_samples, "period_samples", minimum=2)
    n_transient = _int_option(transient_periods, "transient_periods", minimum=0)
    ts = float(sample_time)
    if not (np.isfinite(ts) and ts > 0.0):
        raise HallcalInputError(f"sample_time must be positive, got {sample_time!r}")
    signals = {
        name: _checked_column(name, values) for name, values in (("r", r), ("u", u), ("y", y))
    }
    real = _checked_realization(realization)
    lengths = {name: arr.size for name, arr in signals.items()} | {"realization": real.size}
    if len(set(lengths.values())) != 1:
        raise HallcalInputError(f"columns r, u, y, realization differ in length: {lengths}")
    blocks = _realization_blocks(real, n)
    total_periods = {idx.size // n for idx in blocks}
    if len(total_periods) != 1:
        raise HallcalInputError(
            "column realization: realizations hold different numbers of periods "
            f"{sorted(total_periods)}"
        )
    p = total_periods.pop() - n_transient
    if p < 1:
        raise HallcalInputError(
            f"transient_periods={n_transient} leaves no steady-state period "
            f"(each realization holds {p + n_transient})"
        )
    if detrend and p < 2:
        raise HallcalInputError(
            "detrending needs at least 2 steady-state periods per realization; "
            "lower transient_periods or pass detrend=False"
        )
    return _PeriodLayout(signals, blocks, n, n_transient, p, ts)


def _checked_column(name: str, values: np.ndarray) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 1:
        raise HallcalInputError(f"column {name} must be one-dimensional")
    if not np.all(np.isfinite(arr)):
        raise HallcalInputError(f"column {name} holds non-finite values")
    return arr


def _checked_realization(realization: np.ndarray) -> np.ndarray:
    real = np.asarray(realization)
    if real.ndim != 1 or not np.issubdtype(real.dtype, np.integer):
        if (
            real.ndim == 1
            and np.issubdtype(real.dtype, np.floating)
            and np.all(real == np.round(real))
        ):
            real = real.astype(np.int64)
        else:
            raise HallcalInputError("column realization must hold integers")
    return real


def _realization_blocks(real: np.ndarray, n: int) -> list[np.ndarray]:
    """Sample indices of every realization: contiguous blocks of whole periods."""
    blocks = []
    for rid in np.unique(real):
        idx = np.flatnonzero(real == rid)
        if np.any(np.diff(idx) != 1):
            raise HallcalInputError(f"column realization: realization {rid} is not contiguous")
        if idx.size % n:
            raise HallcalInputError(
                f"column realization: realization {rid} has {idx.size} samples, "
                f"not a multiple of period_samples={n}"
            )
        blocks.append(idx)
    return blocks


@dataclass(frozen=True, eq=False)
class _PeriodSpectra:
    """DFTs of every steady-state period of r, u and y, shape (M, P, lines)."""

    r: np.ndarray
    u: np.ndarray
    y: np.ndarray

    def at(self, k: np.ndarray) -> _PeriodSpectra:
        """The spectra at the DFT lines ``k`` only."""
        return _PeriodSpectra(self.r[:, :, k], self.u[:, :, k], self.y[:, :, k])


def _steady_state_spectra(lay: _PeriodLayout, *, detrend: bool) -> _PeriodSpectra:
    """Steps 1-2 of :func:`nonparametric_bla`: steady-state periods, detrended, to the DFT.

    The transient periods are dropped; with ``detrend`` the least-squares line through the P
    period means is removed from every signal and realization. Its offset lives at DC only, so
    only its slope is removed, as the DFT of the ramp inside one period (why this slope is not
    biased by the excitation: step 2 of :func:`nonparametric_bla`).
    """
    n, p = lay.n, lay.periods
    ramp_dft = np.fft.rfft(np.arange(n, dtype=np.float64))
    spectra = {}
    for name, arr in lay.signals.items():
        spec = np.empty((lay.realizations, p, n // 2 + 1), dtype=np.complex128)
        for i, idx in enumerate(lay.blocks):
            periods_data = arr[idx[lay.transient * n :]].reshape(p, n)
            spec[i] = np.fft.rfft(periods_data, axis=1)
            if detrend:
                means = periods_data.mean(axis=1)
                slope = np.polyfit(np.arange(p, dtype=np.float64), means, 1)[0] / n
                # the per-period offset of the line lives at DC only; remove the ramp inside
                spec[i] -= slope * ramp_dft
        spectra[name] = spec
    return _PeriodSpectra(spectra["r"], spectra["u"], spectra["y"])


def _excited_lines(
    r_spectra: np.ndarray, n: int, lines: Sequence[int] | np.ndarray | None
) -> np.ndarray:
    """The DFT lines of the BLA: those given, or where the reference power exceeds 1e-8 of its
    largest line (DC and Nyquist excluded)."""
    if lines is None:
        power = np.mean(np.abs(r_spectra) ** 2, axis=(0, 1))
        power[0] = 0.0
        if n % 2 == 0:
            power[-1] = 0.0
        if not np.any(power > 0.0):
            raise HallcalInputError("column r: the reference excites no frequency line")
        return np.flatnonzero(power > _POWER_THRESHOLD * power.max())
    k = np.unique(np.asarray(lines, dtype=np.int64))
    if k.size == 0 or k.min() < 1 or k.max() >= (n + 1) // 2:
        raise HallcalInputError(
            f"lines must be DFT lines between 1 and {(n + 1) // 2 - 1} for period_samples={n}"
        )
    return k


@dataclass(frozen=True, eq=False)
class _IndirectFRF:
    """Period means per realization and their means over realizations (indirect method)."""

    R_m: np.ndarray  # (M, F) reference, identical in every period
    Y_m: np.ndarray  # (M, F) output, mean over the periods
    U_m: np.ndarray  # (M, F) input, mean over the periods
    G_ry_m: np.ndarray  # (M, F) Y_m / R_m
    G_ru_m: np.ndarray  # (M, F) U_m / R_m
    G_ry: np.ndarray  # (F,) mean over realizations
    G_ru: np.ndarray  # (F,)
    G: np.ndarray  # (F,) G_ry / G_ru


def _indirect_frf(spec: _PeriodSpectra) -> _IndirectFRF:
    """Steps 3-5 of :func:`nonparametric_bla`: ``G = mean_m G_ry^[m] / mean_m G_ru^[m]``.

    Indirect method of Pintelon & Schoukens (2012), sec. 3.8: the reference is the known
    excitation; the ratio of the means over periods and realizations, divided once at the end.
    """
    R_m = spec.r.mean(axis=1)  # (M, F); the reference is periodic: identical periods
    if np.any(np.abs(R_m) == 0.0):
        raise HallcalInputError("column r: a selected line is not excited in every realization")
    Y_m = spec.y.mean(axis=1)
    U_m = spec.u.mean(axis=1)
    G_ry_m = Y_m / R_m
    G_ru_m = U_m / R_m
    G_ry = G_ry_m.mean(axis=0)
    G_ru = G_ru_m.mean(axis=0)
    return _IndirectFRF(R_m, Y_m, U_m, G_ry_m, G_ru_m, G_ry, G_ru, G_ry / G_ru)


@dataclass(frozen=True, eq=False)
class _FRFVariances:
    """Variances of the BLA: noise, total and stochastic nonlinear distortion (NaN if unknown)."""

    noise: np.ndarray
    total: np.ndarray
    nonlinear: np.ndarray


def _frf_variances(spec: _PeriodSpectra, frf: _IndirectFRF) -> _FRFVariances:
    """Variances of steps 3-5 of :func:`nonparametric_bla` (robust method).

    Noise: from the period-to-period spread, per realization (Pintelon & Schoukens 2012,
    sec. 2.5); total: from the realization-to-realization spread (sec. 3.8); each propagated
    through the ratio by :func:`_ratio_variance`.
    """
    m, p, f = spec.r.shape
    # noise (co)variances from the period-to-period spread (sec. 2.5), per realization then mean
    if p >= 2:
        dY = spec.y - frf.Y_m[:, None, :]
        dU = spec.u - frf.U_m[:, None, :]
        scale = 1.0 / (p * (p - 1) * np.abs(frf.R_m) ** 2)
        v_ry_n = (np.sum(np.abs(dY) ** 2, axis=1) * scale).sum(axis=0) / m**2
        v_ru_n = (np.sum(np.abs(dU) ** 2, axis=1) * scale).sum(axis=0) / m**2
        c_n = (np.sum(dY * np.conj(dU), axis=1) * scale).sum(axis=0) / m**2
        var_noise = _ratio_variance(frf.G, frf.G_ru, v_ry_n, v_ru_n, c_n)
    else:
        var_noise = np.full(f, np.nan)

    # total (co)variances from the realization-to-realization spread (sec. 3.8)
    if m >= 2:
        dGy = frf.G_ry_m - frf.G_ry
        dGu = frf.G_ru_m - frf.G_ru
        scale_m = 1.0 / (m * (m - 1))
        v_ry_t = np.sum(np.abs(dGy) ** 2, axis=0) * scale_m
        v_ru_t = np.sum(np.abs(dGu) ** 2, axis=0) * scale_m
        c_t = np.sum(dGy * np.conj(dGu), axis=0) * scale_m
        var_total = _ratio_variance(frf.G, frf.G_ru, v_ry_t, v_ru_t, c_t)
        if p >= 2:
            var_nonlinear = np.maximum(var_total - var_noise, 0.0)
        else:
            var_nonlinear = np.full(f, np.nan)
    else:
        var_total = var_noise.copy()
        var_nonlinear = np.full(f, np.nan)
    return _FRFVariances(var_noise, var_total, var_nonlinear)


def _bla_status(realizations: int, periods: int) -> str:
    """``"ok"``, or what cannot be estimated: ``"single-realization"``, ``"single-period"``."""
    status = []
    if realizations < 2:
        status.append("single-realization")
    if periods < 2:
        status.append("single-period")
    return "+".join(status) if status else "ok"


def _ratio_variance(
    g: np.ndarray, den: np.ndarray, var_num: np.ndarray, var_den: np.ndarray, cov: np.ndarray
) -> np.ndarray:
    """First-order variance of ``g = num / den`` from the (co)variances of ``num`` and ``den``.

    ``d g = (d num - g d den) / den``, so
    ``var g = (var num + |g|^2 var den - 2 Re(conj(g) cov(num, den))) / |den|^2`` with
    ``cov(a, b) = E[da conj(db)]`` (Pintelon & Schoukens 2012, sec. 2.5 / 3.8).
    """
    v = (var_num + np.abs(g) ** 2 * var_den - 2.0 * np.real(np.conj(g) * cov)) / np.abs(den) ** 2
    return np.maximum(v, 0.0)


# --------------------------------------------------------------------------------------------------
# parametric fit


@dataclass(frozen=True, eq=False)
class ParametricBLA:
    """Continuous-time model ``G(s) = exp(-s delay) num(s) / den(s)`` fitted to a BLA.

    Attributes
    ----------
    num : ndarray, shape (nb + 1,)
        Numerator coefficients in descending powers of s.
    den : ndarray, shape (na + integrator + 1,)
        Denominator coefficients in descending powers of s, monic; includes the ``integrator``
        poles at s = 0 (trailing zeros), as in the ``[plant]`` table of the setup file.
    delay : float
        Input delay [s], ``>= 0``.
    integrator : int
        Number of poles at s = 0 imposed by the model structure.
    cost : float
        Weighted least-squares cost of the fit, ``sum_k w_k |G_model - G_data|^2`` (with
        ``weights="variance"``: ``w_k = 1 / var_total``, so about the number of lines for a good
        fit). It refers to the fit, before any :meth:`scaled`.
    freq : ndarray, shape (F,)
        Frequencies [Hz] of the data the model was fitted to.
    hold : str
        ``"zoh"``: the data were a sampled FRF with a zero-order-hold input and the model is the
        continuous plant (the hold was accounted for in the fit); ``"none"``: continuous FRF data.
    sample_time : float or None
        Sample time [s] of the data (used by the hold).
    weights : str
        Weighting used: ``"variance"``, ``"relative"`` or ``"uniform"``.
    stable : bool
        Whether all poles other than the imposed integrators have negative real parts.
    nfev : int
        Model evaluations of the nonlinear least-squares refinement.
    gain_scale : float
        Product of the factors applied by :meth:`scaled` since the fit (1 for a fresh fit).
    status : str
        ``"ok"`` or ``"not-converged"`` (evaluation budget exhausted).
    """

    num: np.ndarray
    den: np.ndarray
    delay: float
    integrator: int
    cost: float
    freq: np.ndarray = field(repr=False)
    hold: str = "none"
    sample_time: float | None = None
    weights: str = "variance"
    stable: bool = True
    nfev: int = 0
    gain_scale: float = 1.0
    status: str = "ok"

    def frequency_response(self, freq_hz: np.ndarray | float, *, zoh: bool = False) -> np.ndarray:
        """``G(j 2 pi f) = exp(-j 2 pi f delay) num / den`` at the frequencies ``freq_hz`` [Hz].

        Parameters
        ----------
        freq_hz : array_like
            Frequencies [Hz]; the response is infinite at 0 with an integrator.
        zoh : bool
            Multiply by the zero-order-hold factor ``(1 - exp(-j w Ts)) / (j w Ts)`` (needs
            ``sample_time``): the FRF seen from a sampled input, aliasing neglected, comparable to
            the nonparametric BLA.
        """
        f = np.asarray(freq_hz, dtype=np.float64)
        s = 2j * np.pi * f
        with np.errstate(divide="ignore", invalid="ignore"):
            g = np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay)
            if zoh:
                if self.sample_time is None:
                    raise ValueError("zoh=True needs sample_time")
                g = g * _zoh_factor(f, self.sample_time)
        return g

    def scaled(self, c: float) -> ParametricBLA:
        """The same model with its gain multiplied by ``c`` (numerator times ``c``).

        The paper corrects the BLA gain with ``G_BLA <- G_BLA / c_hat`` (Algorithm 1, step
        "correct"; the gain-correction equation for c-hat); that is ``model.scaled(1 / c_hat)``.
        """
        c = float(c)
        if not np.isfinite(c) or c == 0.0:
            raise ValueError(f"scale factor must be finite and nonzero, got {c!r}")
        return replace(self, num=np.asarray(self.num) * c, gain_scale=self.gain_scale * c)

    def to_control(self) -> Any:
        """The rational part ``num / den`` as a continuous ``control.TransferFunction``.

        python-control is imported lazily. The delay cannot be represented exactly by a
        transfer function and is left out: it is in :attr:`delay` (discretize it exactly, not
        with a Pade approximation).
        """
        import control

        return control.TransferFunction(np.asarray(self.num), np.asarray(self.den))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (floats and lists of floats).

        ``num``, ``den`` and ``delay`` use the names of the setup file's ``[plant]`` table.
        """
        return {
            "kind": "parametric-bla",
            "num": _floats(self.num),
            "den": _floats(self.den),
            "delay": float(self.delay),
            "integrator": int(self.integrator),
            "cost": _float_or_none(self.cost),
            "freq": _floats(self.freq),
            "hold": str(self.hold),
            "sample_time": None if self.sample_time is None else float(self.sample_time),
            "weights": str(self.weights),
            "stable": bool(self.stable),
            "nfev": int(self.nfev),
            "gain_scale": float(self.gain_scale),
            "status": str(self.status),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ParametricBLA:
        """Inverse of :meth:`to_dict`; only ``num``, ``den`` and ``delay`` are required.

        Raises
        ------
        HallcalInputError
            If a required key is missing or malformed (the message names it).
        """
        _check_kind(data, "parametric-bla")
        num = _array_from(data, "num")
        den = _array_from(data, "den")
        if den.size == 0 or den[0] == 0.0:
            raise HallcalInputError("key den: leading coefficient must be nonzero")
        num, den = num / den[0], den / den[0]
        delay = float(_get(data, "delay"))
        if not (np.isfinite(delay) and delay >= 0.0):
            raise HallcalInputError(f"key delay must be >= 0, got {delay!r}")
        integrator = data.get("integrator")
        if integrator is None:
            integrator = int(den.size - 1 - np.max(np.flatnonzero(den)))
        sample_time = data.get("sample_time")
        cost = data.get("cost")
        return cls(
            num=num,
            den=den,
            delay=delay,
            integrator=int(integrator),
            cost=float("nan") if cost is None else float(cost),
            freq=np.asarray(data.get("freq", []), dtype=np.float64),
            hold=str(data.get("hold", "none")),
            sample_time=None if sample_time is None else float(sample_time),
            weights=str(data.get("weights", "variance")),
            stable=bool(data.get("stable", True)),
            nfev=int(data.get("nfev", 0)),
            gain_scale=float(data.get("gain_scale", 1.0)),
            status=str(data.get("status", "ok")),
        )


def fit_parametric(
    bla: NonparametricBLA,
    *,
    numerator_order: int,
    denominator_order: int,
    integrator: bool | int = True,
    fit_delay: bool = True,
    delay: float = 0.0,
    max_delay: float | None = None,
    weights: Literal["variance", "relative", "uniform"] = "variance",
    hold: Literal["zoh", "none"] = "zoh",
    sk_iterations: int = 5,
    delay_grid: int = 41,
) -> ParametricBLA:
    """Fit ``G(s) = exp(-s tau) B(s) / (s^I A(s))`` to a nonparametric BLA.

    Frequency-domain estimation of a continuous-time model (Pintelon & Schoukens 2012, ch. 9):

    1. scaling: ``s`` is divided by ``w0 = sqrt(w_min w_max)`` and the data by their median
       magnitude, so the regressors are of order one (numerical conditioning);
    2. start: for every delay on a grid of ``delay_grid`` values in ``[0, max_delay]`` the data
       are de-rotated by ``exp(j w tau)`` and the rational part is fitted by Levy's (1959) linear
       least squares on ``s^I A G - B``, followed by ``sk_iterations`` Sanathanan-Koerner (1963)
       iterations (equation error divided by ``|s^I A_prev|``, approximating the output error;
       ch. 9); the grid point with the smallest weighted output error is kept;
    3. refinement: all parameters (coefficients and ``tau >= 0``) by weighted nonlinear least
       squares (``scipy.optimize.least_squares``, analytic Jacobian) on the complex output error
       ``G_model - G_data`` with weight ``1 / var_total`` (the maximum-likelihood cost of
       ch. 9, with a noise-free reference and known variances).

    With ``hold="zoh"`` the data are a discrete-time FRF of the plant seen through a zero-order
    hold (as measured by :func:`nonparametric_bla`): the model response is multiplied by
    ``(1 - exp(-j w Ts)) / (j w Ts)`` in the fit, so the fitted ``num``, ``den`` and ``delay``
    describe the continuous plant and its exact zero-order-hold discretization reproduces the
    data. Aliasing (the terms at ``w + 2 pi m / Ts``, ``m != 0``) is neglected, which is accurate
    when the plant rolls off well before the Nyquist frequency.

    Parameters
    ----------
    bla : NonparametricBLA
        The data: ``freq``, ``G`` and (for ``weights="variance"``) ``var_total``.
    numerator_order : int
        Order of ``B``.
    denominator_order : int
        Order of the monic ``A`` (the integrator poles not included).
    integrator : bool or int
        Number ``I`` of poles at s = 0 imposed (True = 1).
    fit_delay : bool
        Estimate the input delay; otherwise it is fixed to ``delay``.
    delay : float
        Fixed delay [s] when ``fit_delay`` is False.
    max_delay : float, optional
        Upper end of the delay grid of the start [s]; default ``0.25 / f_max`` (a quarter period
        at the highest frequency). The refinement may leave the grid.
    weights : {"variance", "relative", "uniform"}
        ``1 / var_total``, ``1 / |G|^2`` (relative error) or 1.
    hold : {"zoh", "none"}
        Account for a zero-order hold at ``bla.sample_time`` (see above) or not (continuous
        FRF data).
    sk_iterations : int
        Sanathanan-Koerner iterations per grid point.
    delay_grid : int
        Number of delays in the start grid.

    Returns
    -------
    ParametricBLA

    Raises
    ------
    HallcalInputError
        For invalid orders, too few data or unusable weights.
    """
    nb = _int_option(numerator_order, "numerator_order", minimum=0)
    na = _int_option(denominator_order, "denominator_order", minimum=0)
    n_int = _int_option(int(integrator), "integrator", minimum=0)
    n_par = nb + 1 + na + (1 if fit_delay else 0)
    data = _fit_data(bla, weights=weights, hold=hold, parameters=n_par)
    sc = _scaled_problem(data, _OrderSpec(nb, na, n_int, fit_delay), delay=delay)  # step 1
    start = _delay_grid_start(sc, _delay_grid(sc, data, max_delay, delay_grid), sk_iterations)
    fit = _output_error_refinement(sc, start)  # step 3
    num, den, stable = _unscaled_model(sc, fit)
    return ParametricBLA(
        num=num,
        den=den,
        delay=float(fit.tau / sc.w0),
        integrator=n_int,
        cost=fit.cost,
        freq=data.f,
        hold=hold,
        sample_time=data.sample_time,
        weights=weights,
        stable=stable,
        nfev=fit.nfev,
        status="ok" if fit.converged else "not-converged",
    )


@dataclass(frozen=True, eq=False)
class _FitData:
    """The lines :func:`fit_parametric` fits: continuous-equivalent data and their variances."""

    f: np.ndarray  # frequencies [Hz]
    g: np.ndarray  # the BLA, divided by the zero-order-hold factor with hold="zoh"
    var: np.ndarray  # variance of g (or |G|^2 or 1, as the weights say)
    sample_time: float | None  # of the hold, None with hold="none"


def _fit_data(bla: NonparametricBLA, *, weights: str, hold: str, parameters: int) -> _FitData:
    """The usable lines of ``bla`` with their weights; the hold divided out with ``"zoh"``.

    With ``hold="zoh"`` the data and their variances are divided by the zero-order-hold factor
    ``(1 - exp(-j w Ts)) / (j w Ts)``, aliasing neglected (see :func:`fit_parametric`).
    """
    if hold not in ("zoh", "none"):
        raise HallcalInputError(f"hold must be 'zoh' or 'none', got {hold!r}")
    f = np.asarray(bla.freq, dtype=np.float64)
    g_data = np.asarray(bla.G, dtype=np.complex128)
    good = np.isfinite(f) & (f > 0.0) & np.isfinite(g_data)
    if weights == "variance":
        var = np.asarray(bla.var_total, dtype=np.float64)
        good &= np.isfinite(var)
        if not np.all(var[good] > 0.0):
            raise HallcalInputError(
                "weights='variance' needs positive var_total on every line; "
                "use weights='relative' for noise-free data"
            )
    elif weights == "relative":
        var = np.abs(g_data) ** 2
        good &= var > 0.0
    elif weights == "uniform":
        var = np.ones(f.size)
    else:
        raise HallcalInputError(
            f"weights must be 'variance', 'relative' or 'uniform', got {weights!r}"
        )
    f, g_data, var = f[good], g_data[good], var[good]
    if 2 * f.size < parameters + 1:
        raise HallcalInputError(f"{f.size} frequency lines are too few for {parameters} parameters")
    ts = bla.sample_time if hold == "zoh" else None
    if hold == "zoh":
        if ts is None or not (np.isfinite(ts) and ts > 0.0):
            raise HallcalInputError("hold='zoh' needs the sample_time of the BLA")
        zf = _zoh_factor(f, ts)
        g_data = g_data / zf  # continuous-equivalent data
        var = var / np.abs(zf) ** 2
    return _FitData(f, g_data, var, None if ts is None else float(ts))


@dataclass(frozen=True)
class _OrderSpec:
    """The model structure ``exp(-s tau) B(s) / (s^I A(s))``: orders of B and A, I, delay."""

    nb: int
    na: int
    n_int: int
    fit_delay: bool


@dataclass(frozen=True, eq=False)
class _ScaledProblem:
    """Step 1 of :func:`fit_parametric`: the data in the scaled Laplace variable ``s / w0``."""

    order: _OrderSpec
    w0: float  # frequency scale [rad/s]
    g0: float  # magnitude scale of the data
    s: np.ndarray  # scaled Laplace variable j w / w0
    gd: np.ndarray  # scaled data g / g0
    inv_sigma: np.ndarray  # 1 / standard deviation of gd
    fixed_tau: float  # the fixed delay, scaled by w0 (used without fit_delay)


def _scaled_problem(data: _FitData, order: _OrderSpec, *, delay: float) -> _ScaledProblem:
    """Step 1 of :func:`fit_parametric`: ``s`` divided by ``w0 = sqrt(w_min w_max)`` and the data
    by their median magnitude, so the regressors are of order one (Pintelon & Schoukens 2012,
    ch. 9, numerical conditioning)."""
    w = 2.0 * np.pi * data.f
    w0 = math.sqrt(w.min() * w.max())
    g0 = float(np.median(np.abs(data.g)))
    if g0 == 0.0:
        raise HallcalInputError("the BLA is zero")
    sigma = np.sqrt(data.var) / g0  # standard deviation of the scaled data
    fixed_tau = float(delay) * w0
    if not order.fit_delay and not (np.isfinite(fixed_tau) and fixed_tau >= 0.0):
        raise HallcalInputError(f"delay must be >= 0, got {delay!r}")
    return _ScaledProblem(order, w0, g0, 1j * w / w0, data.g / g0, 1.0 / sigma, fixed_tau)


def _delay_grid(
    sc: _ScaledProblem, data: _FitData, max_delay: float | None, points: int
) -> np.ndarray:
    """Scaled delays of the start grid: ``[0, max_delay]`` (default a quarter period at the
    highest frequency), or the fixed delay alone."""
    if not sc.order.fit_delay:
        return np.array([sc.fixed_tau])
    tau_max = (0.25 / data.f.max() if max_delay is None else float(max_delay)) * sc.w0
    return np.linspace(0.0, tau_max, max(int(points), 1))


@dataclass(frozen=True, eq=False)
class _StartValues:
    """Step 2 of :func:`fit_parametric`: the best grid point (scaled delay and coefficients)."""

    tau: float
    b: np.ndarray  # ascending coefficients of B
    a: np.ndarray  # ascending coefficients of A without its leading 1


def _delay_grid_start(sc: _ScaledProblem, taus: np.ndarray, sk_iterations: int) -> _StartValues:
    """Step 2 of :func:`fit_parametric`: Levy and Sanathanan-Koerner on every de-rotated delay.

    For every delay the data are de-rotated by ``exp(j w tau)`` and the rational part is fitted
    by :func:`_levy_sk` (Levy 1959; Sanathanan & Koerner 1963; Pintelon & Schoukens 2012,
    ch. 9); the delay with the smallest weighted output error is kept.
    """
    o = sc.order
    best: tuple[float, np.ndarray, np.ndarray, float] | None = None
    for tau in taus:
        b, a, cost = _levy_sk(
            sc.s, sc.gd * np.exp(sc.s * tau), sc.inv_sigma, o.nb, o.na, o.n_int, sk_iterations
        )
        if best is None or cost < best[3]:
            best = (tau, b, a, cost)
    assert best is not None
    return _StartValues(best[0], best[1], best[2])


class _OutputError:
    """Weighted output error ``(G_model - G_data) / sigma`` and its analytic Jacobian.

    Parameters theta: ascending coefficients of B, of A without its leading 1, and (with
    ``fit_delay``) the scaled delay; real and imaginary parts stacked (Pintelon & Schoukens 2012,
    ch. 9, the maximum-likelihood cost with known variances).
    """

    def __init__(self, sc: _ScaledProblem) -> None:
        o = sc.order
        self.sc, self.o = sc, o
        self.pow_b = sc.s[:, None] ** np.arange(o.nb + 1)  # ascending powers
        self.pow_a = sc.s[:, None] ** np.arange(o.na + 1)
        self.s_int = sc.s**o.n_int

    def unpack(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        o = self.o
        b = theta[: o.nb + 1]
        a = theta[o.nb + 1 : o.nb + 1 + o.na]
        tau = theta[-1] if o.fit_delay else self.sc.fixed_tau
        return b, a, tau

    def model(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        b, a, tau = self.unpack(theta)
        bs = self.pow_b @ b
        as_ = self.pow_a[:, : self.o.na] @ a + self.pow_a[:, self.o.na]
        e = np.exp(-self.sc.s * tau)
        return e * bs / (self.s_int * as_), bs, as_, e

    def residual(self, theta: np.ndarray) -> np.ndarray:
        err = (self.model(theta)[0] - self.sc.gd) * self.sc.inv_sigma
        return np.concatenate([err.real, err.imag])

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        gm, _, as_, e = self.model(theta)
        cols = [
            e[:, None] * self.pow_b / (self.s_int * as_)[:, None],
            -gm[:, None] * self.pow_a[:, : self.o.na] / as_[:, None],
        ]
        if self.o.fit_delay:
            cols.append((-self.sc.s * gm)[:, None])
        jac = np.concatenate(cols, axis=1) * self.sc.inv_sigma[:, None]
        return np.concatenate([jac.real, jac.imag], axis=0)


@dataclass(frozen=True, eq=False)
class _RefinedFit:
    """Step 3 of :func:`fit_parametric`: scaled coefficients, delay, cost and solver outcome."""

    b: np.ndarray
    a: np.ndarray
    tau: float
    cost: float
    nfev: int
    converged: bool


def _output_error_refinement(sc: _ScaledProblem, start: _StartValues) -> _RefinedFit:
    """Step 3 of :func:`fit_parametric`: weighted nonlinear least squares on the output error.

    All parameters (coefficients and ``tau >= 0``) by ``scipy.optimize.least_squares`` with the
    analytic Jacobian of :class:`_OutputError` (Pintelon & Schoukens 2012, ch. 9); never worse
    than the start.
    """
    oe = _OutputError(sc)
    fit_delay = sc.order.fit_delay
    theta0 = np.concatenate([start.b, start.a, [start.tau] if fit_delay else []])
    lower = np.full(theta0.size, -np.inf)
    if fit_delay:
        lower[-1] = 0.0
    from scipy.optimize import least_squares  # only when a BLA is fitted (0.15 s import)

    sol = least_squares(
        oe.residual,
        theta0,
        jac=oe.jacobian,
        bounds=(lower, np.full(theta0.size, np.inf)),
        method="trf",
        x_scale="jac",
        ftol=1e-14,
        xtol=1e-14,
        gtol=1e-14,
        max_nfev=200 * (theta0.size + 1),
    )
    theta = sol.x
    b, a, tau = oe.unpack(theta)
    cost = float(np.sum(oe.residual(theta) ** 2))
    start_cost = float(np.sum(oe.residual(theta0) ** 2))
    if start_cost < cost:  # never worse than the linear start
        b, a, tau = oe.unpack(theta0)
        cost = start_cost
    return _RefinedFit(b, a, tau, cost, int(sol.nfev), sol.status > 0)


def _unscaled_model(sc: _ScaledProblem, fit: _RefinedFit) -> tuple[np.ndarray, np.ndarray, bool]:
    """``num``, ``den`` in descending powers of the unscaled s, and whether A is stable."""
    nb, na, n_int = sc.order.nb, sc.order.na, sc.order.n_int
    w0 = sc.w0
    num_asc = sc.g0 * fit.b * w0 ** (na + n_int - np.arange(nb + 1))
    a_full = np.concatenate([fit.a, [1.0]])
    den_asc = a_full * w0 ** (na - np.arange(na + 1))
    num = num_asc[::-1].copy()
    den = np.concatenate([den_asc[::-1], np.zeros(n_int)])
    poles = np.roots(den_asc[::-1]) if na > 0 else np.array([])
    return num, den, bool(np.all(poles.real < 0.0))


def model_poles(model: ParametricBLA) -> np.ndarray:
    """Poles [rad/s] of a fitted model other than its imposed integrators, fastest first.

    Parameters
    ----------
    model : ParametricBLA
        The parametric fit of G(s) (section "Obtaining a Best Linear Approximation").

    Returns
    -------
    ndarray of complex
        Roots of the denominator in s [rad/s] without the integrators, largest magnitude first.
    """
    den = np.asarray(model.den, dtype=np.float64)
    core = den[: den.size - int(model.integrator)] if model.integrator else den
    poles = np.roots(core) if core.size > 1 else np.array([], dtype=np.complex128)
    return poles[np.argsort(-np.abs(poles))]


@dataclass(frozen=True, eq=False)
class OrderCandidate:
    """One model structure tried by :func:`select_order`.

    Attributes
    ----------
    numerator_order, denominator_order : int
        Orders of ``B`` and of the monic ``A`` (integrators not counted).
    parameters : int
        Real parameters fitted: ``numerator_order + 1 + denominator_order`` (+ 1 for the delay).
    cost : float
        Weighted output-error cost ``V = sum_k |G_model - G_data|^2 / var_total`` at the optimum.
    criterion : float
        Minimum description length ``V + parameters / 2 * ln(2 F)`` (F lines, 2F real data).
    stable : bool
        All poles other than the integrators in the open left half-plane.
    poles : tuple of complex
        Those poles [rad/s], fastest first.
    fit : ParametricBLA
        The fitted model.
    """

    numerator_order: int
    denominator_order: int
    parameters: int
    cost: float
    criterion: float
    stable: bool
    poles: tuple[complex, ...]
    fit: ParametricBLA = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (poles as ``[re, im]`` pairs in rad/s)."""
        return {
            "numerator_order": self.numerator_order,
            "denominator_order": self.denominator_order,
            "parameters": self.parameters,
            "cost": _float_or_none(self.cost),
            "criterion": _float_or_none(self.criterion),
            "stable": self.stable,
            "poles": _complex_pairs(np.asarray(self.poles, dtype=np.complex128)),
        }


@dataclass(frozen=True, eq=False)
class OrderSelection:
    """The model order chosen from the data (:func:`select_order`).

    Attributes
    ----------
    candidates : tuple of OrderCandidate
        Every structure tried, in increasing denominator order.
    chosen : OrderCandidate or None
        The stable candidate with the smallest criterion; None when no candidate is stable.
    lines : int
        Number F of frequency lines fitted.
    """

    candidates: tuple[OrderCandidate, ...]
    chosen: OrderCandidate | None
    lines: int

    @property
    def best_unstable(self) -> OrderCandidate | None:
        """The candidate with the smallest criterion when it is unstable (then not chosen)."""
        best = min(self.candidates, key=lambda c: c.criterion)
        return None if best.stable else best

    def to_dict(self) -> dict[str, Any]:
        return {
            "criterion": "minimum description length: cost + parameters / 2 * ln(2 lines)",
            "lines": self.lines,
            "chosen_denominator_order": (
                None if self.chosen is None else self.chosen.denominator_order
            ),
            "chosen_numerator_order": None if self.chosen is None else self.chosen.numerator_order,
            "candidates": [c.to_dict() for c in self.candidates],
        }


def select_order(
    bla: NonparametricBLA,
    *,
    numerator_order: int = 0,
    denominator_orders: Sequence[int] = (0, 1, 2, 3),
    integrator: bool | int = True,
    fit_delay: bool = True,
    **options: Any,
) -> OrderSelection:
    """Choose the denominator order of ``G(s) = exp(-s tau) B(s) / (s^I A(s))`` from the data.

    Every order in ``denominator_orders`` (from ``numerator_order`` up; the integrators are
    imposed, not counted) is fitted with :func:`fit_parametric` and weights ``1 / var_total``.
    For a model that explains the BLA within its variance the cost ``V`` is about the number of
    lines F, so a structure with too few poles shows as ``V >> F`` and extra poles buy little;
    the minimum description length ``V + n / 2 * ln(2 F)`` (n parameters, 2F real data; Pintelon
    & Schoukens 2012, ch. 11, model selection) weighs the two. Unstable fits (a pole in the right
    half-plane, typically an order the data do not support) are never chosen: the stable
    candidate with the smallest criterion is.

    Parameters
    ----------
    bla : NonparametricBLA
    numerator_order : int
        Order of ``B`` for every candidate (orders below it are skipped).
    denominator_orders : sequence of int
        Orders of ``A`` to try.
    integrator, fit_delay
        As for :func:`fit_parametric`.
    **options
        Passed to :func:`fit_parametric` (``weights``, ``hold``, ...).

    Returns
    -------
    OrderSelection
    """
    nb = _int_option(numerator_order, "numerator_order", minimum=0)
    n_int = _int_option(int(integrator), "integrator", minimum=0)
    orders = sorted({int(o) for o in denominator_orders if int(o) >= 0})
    lines = int(np.count_nonzero(np.isfinite(np.asarray(bla.G)) & (np.asarray(bla.freq) > 0)))
    candidates = []
    for na in orders:
        if nb > na + n_int:
            continue  # improper
        n_par = nb + 1 + na + (1 if fit_delay else 0)
        if 2 * lines < n_par + 1:
            continue
        fit = fit_parametric(
            bla,
            numerator_order=nb,
            denominator_order=na,
            integrator=n_int,
            fit_delay=fit_delay,
            **options,
        )
        poles = model_poles(fit)
        cost = float(fit.cost) if np.isfinite(fit.cost) else math.inf
        candidates.append(
            OrderCandidate(
                numerator_order=nb,
                denominator_order=na,
                parameters=n_par,
                cost=cost,
                criterion=cost + 0.5 * n_par * math.log(2 * max(lines, 1)),
                stable=bool(np.all(poles.real < 0.0)),
                poles=tuple(complex(p) for p in poles),
                fit=fit,
            )
        )
    if not candidates:
        raise HallcalInputError(
            f"no model order in {orders} can be fitted to {lines} lines with numerator order {nb}"
        )
    stable = [c for c in candidates if c.stable]
    chosen = min(stable, key=lambda c: c.criterion) if stable else None
    return OrderSelection(tuple(candidates), chosen, lines)


def _levy_sk(
    s: np.ndarray,
    g: np.ndarray,
    inv_sigma: np.ndarray,
    nb: int,
    na: int,
    n_int: int,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Levy start and Sanathanan-Koerner iterations for ``g ~ B(s) / (s^I A(s))``, A monic.

    Linear least squares on the weighted equation error ``(s^I A g - B) / (sigma |s^I A_prev|)``
    (Levy 1959 with ``A_prev = 1``; Sanathanan & Koerner 1963; Pintelon & Schoukens 2012,
    ch. 9). Returns the ascending coefficients of B and of A without its leading 1, and the
    weighted output-error cost of the best iterate.
    """
    h = g * s**n_int
    pow_b = s[:, None] ** np.arange(nb + 1)
    pow_a = s[:, None] ** np.arange(na + 1)
    phi = np.concatenate([pow_b, -h[:, None] * pow_a[:, :na]], axis=1)
    rhs = h * pow_a[:, na]
    weight = inv_sigma.copy()
    best: tuple[np.ndarray, np.ndarray, float] | None = None
    for _ in range(max(iterations, 0) + 1):
        mat = phi * weight[:, None]
        vec = rhs * weight
        mat_r = np.concatenate([mat.real, mat.imag])
        vec_r = np.concatenate([vec.real, vec.imag])
        norms = np.linalg.norm(mat_r, axis=0)
        norms[norms == 0.0] = 1.0
        theta = np.linalg.lstsq(mat_r / norms, vec_r, rcond=None)[0] / norms
        b = theta[: nb + 1]
        a = theta[nb + 1 :]
        a_s = pow_a[:, :na] @ a + pow_a[:, na]
        with np.errstate(divide="ignore", invalid="ignore"):
            out_err = (pow_b @ b / (s**n_int * a_s) - g) * inv_sigma
            cost = float(np.sum(np.abs(out_err) ** 2))
        if not np.isfinite(cost):
            cost = np.inf
        if best is None or cost < best[2]:
            best = (b, a, cost)
        if na == 0:
            break
        denom = np.abs(s**n_int * a_s)
        if not np.all(np.isfinite(denom) & (denom > 0.0)):
            break
        weight = inv_sigma / denom
    assert best is not None
    return best


def _zoh_factor(f: np.ndarray, ts: float) -> np.ndarray:
    """Zero-order-hold factor ``(1 - exp(-j w Ts)) / (j w Ts)`` (1 at w = 0)."""
    x = 2j * np.pi * np.asarray(f, dtype=np.float64) * ts
    out = np.ones(x.shape, dtype=np.complex128)
    nz = x != 0
    out[nz] = -np.expm1(-x[nz]) / x[nz]
    return out


# --------------------------------------------------------------------------------------------------
# small helpers


def _int_option(value: int, name: str, *, minimum: int) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < minimum:
        raise HallcalInputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _float_or_none(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _floats(values: np.ndarray) -> list[float | None]:
    return [_float_or_none(v) for v in np.asarray(values, dtype=np.float64).ravel()]


def _complex_pairs(values: np.ndarray) -> list[list[float | None]]:
    z = np.asarray(values, dtype=np.complex128).ravel()
    return [[_float_or_none(v.real), _float_or_none(v.imag)] for v in z]


def _check_kind(data: dict[str, Any], kind: str) -> None:
    if not isinstance(data, dict):
        raise HallcalInputError(f"a {kind} must be a JSON object")
    found = data.get("kind", kind)
    if found != kind:
        raise HallcalInputError(f"key kind: expected {kind!r}, got {found!r}")


def _get(data: dict[str, Any], key: str) -> Any:
    if key not in data:
        raise HallcalInputError(f"missing key {key}")
    return data[key]


def _array_from(data: dict[str, Any], key: str) -> np.ndarray:
    raw = _get(data, key)
    try:
        return np.array([np.nan if v is None else float(v) for v in raw], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise HallcalInputError(f"key {key} must be a list of numbers") from exc


def _complex_from(data: dict[str, Any], key: str) -> np.ndarray:
    raw = _get(data, key)
    try:
        pairs = [
            complex(np.nan if re is None else re, np.nan if im is None else im) for re, im in raw
        ]
    except (TypeError, ValueError) as exc:
        raise HallcalInputError(f"key {key} must be a list of [re, im] pairs") from exc
    return np.array(pairs, dtype=np.complex128)
