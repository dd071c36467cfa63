"""Best Linear Approximation (BLA) of the plant, measured in closed loop (nonparametric).

Step 2 of Algorithm 1 of the paper (section "Obtaining a Best Linear Approximation"): the BLA of
the plant ``G`` (torque command ``u`` -> position ``y``) is measured in closed loop with
random-phase multisine references, following Pintelon & Schoukens (2012), "System Identification:
A Frequency Domain Approach", 2nd ed., sec. 3.8 (BLA in feedback, indirect method) with the
robust method (M realizations x P periods, sec. 3.8 and 2.5: noise variance from the
period-to-period spread, total variance from the realization-to-realization spread).

The measured position ``y`` comes from the imperfect Hall reconstruction ``f_init``, so the BLA
is ``c G`` with an unknown gain ``c``; the paper corrects it elsewhere (its gain-correction
equation for c-hat). The parametric model, its gain correction and the choice of its order
are in :mod:`hallcal.identify.parametric`.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.identify._serial import (
    _array_from,
    _check_kind,
    _complex_from,
    _complex_pairs,
    _floats,
    _get,
    _int_option,
)

__all__ = [
    "BLAExperimentStatus",
    "NonparametricBLA",
    "nonparametric_bla",
]

_POWER_THRESHOLD = 1e-8  # excited line: reference power above this fraction of the largest line


# --------------------------------------------------------------------------------------------------
# nonparametric BLA


class BLAExperimentStatus(enum.StrEnum):
    """What a multisine experiment cannot estimate (Pintelon & Schoukens 2012, sec. 3.8)."""

    OK = "ok"
    SINGLE_REALIZATION = "single_realization"  # M = 1: no nonlinear-distortion estimate
    SINGLE_PERIOD = "single_period"  # P = 1: no noise estimate
    SINGLE_REALIZATION_AND_PERIOD = "single_realization_and_period"  # both


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
    status : BLAExperimentStatus
        What the experiment cannot estimate (``ok``: nothing missing).
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
    status: BLAExperimentStatus = BLAExperimentStatus.OK

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", BLAExperimentStatus(self.status))

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
            status=BLAExperimentStatus(str(data.get("status", "ok"))),
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
        {"r": r, "u": u, "y": y},
        realization,
        period_samples=period_samples,
        transient_periods=transient_periods,
        sample_time=sample_time,
        detrend=detrend,
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
    columns: dict[str, np.ndarray],
    realization: np.ndarray,
    *,
    period_samples: int,
    transient_periods: int,
    sample_time: float,
    detrend: bool,
) -> _PeriodLayout:
    """Check the columns (``r``, ``u``, ``y`` by name) and options; split the record into M
    realizations of P periods.

    The robust method of Pintelon & Schoukens (2012), sec. 3.8, needs M contiguous realizations
    holding the same whole number of periods; the first ``transient_periods`` of each are dropped.
    """
    n = _int_option(period_samples, "period_samples", minimum=2)
    n_transient = _int_option(transient_periods, "transient_periods", minimum=0)
    ts = float(sample_time)
    if not (np.isfinite(ts) and ts > 0.0):
        raise HallcalInputError(f"sample_time must be positive, got {sample_time!r}")
    signals = {name: _checked_column(name, values) for name, values in columns.items()}
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


def _bla_status(realizations: int, periods: int) -> BLAExperimentStatus:
    """``ok``, or what cannot be estimated (one realization, one period or both)."""
    return {
        (False, False): BLAExperimentStatus.OK,
        (True, False): BLAExperimentStatus.SINGLE_REALIZATION,
        (False, True): BLAExperimentStatus.SINGLE_PERIOD,
        (True, True): BLAExperimentStatus.SINGLE_REALIZATION_AND_PERIOD,
    }[(realizations < 2, periods < 2)]


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
