"""The power-up lock's gate (step 7 of :mod:`hallcal.sensor.absolute`): the checks of its
options, its chi-square half's root-free test (:func:`within_gate`), and its bias half: does
the winning pole pair's residual have a mean?

The chi-square half of the gate tests the winner's whole cost Q over k samples against the
chi-square(2 k) quantile. It has little power against what a changed sensor does at standstill:
the measured point sits at a fixed offset ``delta`` from the nearest wrong pole pair's curve,
so its residual is white noise plus a *constant* vector, and the cost grows by only
``k |delta|^2`` against a quantile margin of about ``z sqrt(4 k)`` (at k = 96 a bias of 0.9
noise sigmas goes unseen half the time). Measured on ``benchmarks/bench_powerup_margin.txt``
(five plain-lock motors, eleven sensor changes, 40 power-ups each): all 16 wrong locks of the
gated decoder locked at K0 = 96 samples with a cost 1.05-1.42 times the noise's per degree of
freedom, and their residual's mean, as the statistic below, 10-109 (healthy power-ups: median
1.5, 99 % below 8.9, as chi-square(2)).

The test. Per sample and hypothesis the residual across the curve is ``r_k = (a_k, b_k)``
(step 5: ``a = rho - R_j``, ``b = zeta - Z_j``) with the noise metric ``G_k = [[Guu, Gun],
[Gun, C]] - g g' / tt``, ``g = (tu, tn)`` the tangent's products (the curve's direction
profiled out; ``e_k = r_k' G_k r_k`` is the sample's cost). Under H0 (sensors as calibrated, the
hypothesis right) ``r_k`` has mean 0 and information ``G_k``; under H1 a constant mean delta.
The generalized likelihood ratio (Neyman-Pearson with delta profiled out; the uniformly most
powerful invariant test for a Gaussian mean, Lehmann & Romano, Testing Statistical Hypotheses,
3rd ed., sec. 7.1) is

    S_k = h' H^-1 h,     h = sum_k G_k r_k,   H = sum_k G_k,

chi-square with 2 degrees of freedom under H0 whatever k, and noncentral with
``delta' H delta`` under H1. Each sample enters with Huber's weight ``u = cap / max(e, cap)``
(the decoder's censoring; Huber 1964, Ann. Math. Statist. 35(1)) in both sums, so that one
glitch cannot reach the bound (its term in h is at most ``cap / sqrt(e)`` sigmas); under H0
the weighted sums have ``Var(h) = sum u^2 G <= H``, so the weighting only makes the test
conservative. The gate passes when ``S <= phi_b 2 ln(2 / alpha_g)``: the chi-square(2)
quantile of ``1 - alpha_g / 2``, the chi-square half taking the other ``alpha_g / 2``
(Bonferroni: the gate's false alarm stays at most alpha_g; 1.13 alpha_g where the sensors'
quantizer leaves the largest allowed mean at standstill, :data:`QUANTIZER_NONCENTRALITY`), and
``phi_b >= 1`` the dispersion
the calibration recording shows for this statistic over K0-sample windows (the model's own
error along the turn is a bias too; ``bias_dispersion`` of :mod:`hallcal.sensor.absolute`,
used only where :func:`bias_is_white`). Written without a division:
``n <= c det`` with ``n = Hbb ha^2 - 2 Hab ha hb + Haa hb^2`` and ``det = Haa Hbb - Hab^2``.

What it cannot do: a wrong curve within a third of a noise sigma of the changed point gives
``S`` about ``2 + k / 9``, inside the healthy spread at k = 96; only more samples would tell
(the lock comes at K0 for healthy power-ups, and stays there).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: A float (the sample-by-sample identifier) or an array (the batch decoder).
_Num = Any


def bias_terms(
    a: _Num, b: _Num, tu: _Num, tn: _Num, tt: _Num, gram: tuple[_Num, ...], cap: float
) -> tuple[_Num, _Num, _Num, _Num, _Num]:
    """One sample's terms of the bias sums (module doc): ``u G r`` and ``u G``.

    Parameters
    ----------
    a, b : float or ndarray
        The residual's components along u and nv (``rho - R_j``, ``zeta - Z_j``) [sensor's
        unit].
    tu, tn, tt : float or ndarray
        <t, u>, <t, nv> and <t, t> of the curve's tangent (``tangent_terms`` of the decoder).
    gram : tuple
        The metric's terms guu, gvv, guv, gun, gvn, gnn at the sample's angle.
    cap : float
        The decoder's censoring level c [noise sigma^2].

    Returns
    -------
    (ha, hb, haa, hab, hbb)
        The sample's terms of h (2) and H (3 of the symmetric 2 x 2), weighted by Huber's
        ``u = cap / max(e, cap)``.
    """
    guu, _, _, gun, _, gnn = gram
    rt = a * tu + b * tn
    ga = a * guu + b * gun - tu * rt / tt
    gb = a * gun + b * gnn - tn * rt / tt
    e = a * ga + b * gb  # the sample's cost e_j of step 5, uncensored
    u = cap / np.maximum(e, cap)
    return (u * ga, u * gb, u * (guu - tu * tu / tt), u * (gun - tu * tn / tt),
            u * (gnn - tn * tn / tt))  # fmt: skip


def bias_statistic(sums: ArrayLike) -> NDArray[np.float64]:
    """S = h' H^-1 h from the sums (..., 5) of :func:`bias_terms` (0 where H is singular)."""
    s = np.asarray(sums, dtype=np.float64)
    ha, hb, haa, hab, hbb = (s[..., i] for i in range(5))
    det = haa * hbb - hab * hab
    num = hbb * ha * ha - 2.0 * hab * ha * hb + haa * hb * hb
    return np.where(det > 0.0, num / np.where(det > 0.0, det, 1.0), 0.0)


def within_bias_gate(sums: Any, bound: float) -> Any:
    """The bias half of step 7's gate on the sums (5, or (..., 5)): ``n <= bound det`` (the
    statistic within ``bound`` without a division; a singular H passes: no evidence of a
    bias). One expression for the batch decoder and the sample-by-sample identifier."""
    ha, hb, haa, hab, hbb = (sums[..., i] for i in range(5)) if hasattr(sums, "ndim") else sums
    det = haa * hbb - hab * hab
    num = hbb * ha * ha - 2.0 * hab * ha * hb + haa * hb * hb
    return num <= bound * det


def bias_bound(gate_rate: float, dispersion: float) -> float:
    """``phi_b 2 ln(2 / alpha_g)``: the chi-square(2) quantile of ``1 - alpha_g / 2`` (exact:
    chi-square(2) is exponential with mean 2), times the dispersion."""
    return dispersion * 2.0 * math.log(2.0 / gate_rate)


#: Standard errors of phi_b's estimate under white noise that :func:`bias_is_white` allows.
WHITE_BIAS_ERRORS = 4.0


def bias_is_white(dispersion: float, samples: int, recording: int) -> bool:
    """Does the calibration recording show the right hypothesis's residual without a mean, as
    the bias half's null hypothesis needs (so that its false alarm is what it states)?

    Under white noise S / 2 over a window is exponential with mean 1 and variance 1, and a
    recording of N samples holds about N / K independent windows of K: the estimate phi_b has
    a standard error of ``sqrt(K / N)``. Within :data:`WHITE_BIAS_ERRORS` of them of 1 the
    residual is white as calibrated (measured: the benches 1.00-1.01 on 104 000 samples, bound
    1.12); beyond, the model's own error along the turn is a bias of its own, which on a real
    rig moves from revolution to revolution (the ring jig: phi_b 2.3-2.9 on the calibration's
    2 revolutions, 3-4 times that on held-out ones, where the bias half scaled by phi_b refused
    3-13 % of healthy power-ups), and the gate keeps its chi-square half alone.

    Parameters
    ----------
    dispersion : float
        phi_b (:func:`~hallcal.sensor._absolute_analysis.bias_dispersion`).
    samples : int
        K, the window (the gate's K0).
    recording : int
        N, the calibration samples it was measured on.

    Returns
    -------
    bool
        ``phi_b <= 1 + WHITE_BIAS_ERRORS sqrt(K / N)``.
    """
    if recording < 2 * samples or samples < 1:
        return False
    return dispersion <= 1.0 + WHITE_BIAS_ERRORS * math.sqrt(samples / recording)


#: Largest noncentrality the sensors' quantizer may give the bias half's statistic over K0
#: samples at standstill (:func:`quantizer_noncentrality`): a noncentral chi-square(2) with
#: 0.05 exceeds the bound 2 ln(2 / alpha_g) at alpha_g = 1e-4 with 1.26 times the stated
#: probability (scipy.stats.ncx2; 0.25: 2.6 times, 1: 12.5 times).
QUANTIZER_NONCENTRALITY = 0.05

#: Noncentrality of :func:`quantizer_noncentrality` over K0 samples above which the standstill
#: lock is not used at all (``analyze_calibration``: the lock waits for one electrical revolution
#: of motion, reason ``quantizer``). At rest every sample of a channel rounds to the same one or
#: two codes (Widrow & Kollar, ch. 4: the quantization noise is white only when the analog noise
#: dithers the quantizer, sigma_a above about half a code), so the K0 samples are not K0
#: independent draws: their rounding error is one constant, the cost does not average it down
#: and the lock's posterior grows with K on a difference the samples repeat. The chi-square
#: half's mean moves by up to this much, 0.05 of its quantile margin z sqrt(4 K0) = 73 at 1.
#: Measured at rest (40 power-ups each) on the unseen motors with 0.23-0.30 codes of analog
#: noise, noncentrality 5.7-31: the right hypothesis's cost over K0 varies 5.0-12.1 times
#: chi-square's (the gate's phi from the moving calibration recording: 1.00), false
#: "mismatch" 0-7 of 40 and, on 174 (31), a wrong lock that won on the rounding error; 218
#: (0.48 codes, 0.014): 0.97 times, none.
QUANTIZER_STANDSTILL = 1.0


def quantizer_noncentrality(d: ArrayLike, white_std: float, sigma: float, samples: int) -> float:
    """The bias half's noncentrality over ``samples`` samples at standstill that the sensors'
    own quantizer gives a healthy power-up (0 for signals that are not quantized).

    A quantizer of step Delta fed a constant input plus Gaussian noise of sigma_a (the analog
    noise, which dithers it) has a mean error that depends on the input: its first Fourier
    term has the amplitude ``(Delta / pi) exp(-2 pi^2 sigma_a^2 / Delta^2)`` (Widrow & Kollar,
    Quantization Noise, Cambridge 2008, ch. 4 and 19: the characteristic function of the
    Gaussian at the quantizer's harmonics). At standstill that mean is a fixed residual the
    bias half sees (a moving calibration recording shows it as white noise: phi_b does not);
    with ``a`` the largest amplitude over the channels, the noncentrality after K samples is
    at most ``K 3 a^2 / sigma^2``. Measured on the unseen motors with a 10-11-bit ADC and 0.23-
    0.27 codes of analog noise (174, 185, 240, 40 power-ups at rest each): false "mismatch"
    11 of 120 with the gate alone, 24 with the bias half; this function gives them 9.6-31
    (no bias half), and 0.014 for 218 (0.48 codes, no false "mismatch" with the bias half).

    Parameters
    ----------
    d : array_like, shape (N, 3)
        The calibration recording (the samples the model was fitted on).
    white_std : float
        The white noise per channel it shows (quantization included) [sensor's unit].
    sigma : float
        The decoder's noise sigma [sensor's unit].
    samples : int
        K (the gate's K0).

    Returns
    -------
    float
        ``K 3 a^2 / sigma^2``; 0 where no channel's values lie on a lattice (fewer distinct
        values than a quarter of the samples, their gaps whole multiples of the smallest).
    """
    x = np.atleast_2d(np.asarray(d, dtype=np.float64))
    worst = 0.0
    for h in range(x.shape[1]):
        u = np.unique(x[:, h])
        if u.size < 2 or u.size > x.shape[0] // 4:
            continue  # continuous signals, or a constant channel
        gaps = np.diff(u)
        step = float(gaps.min())
        ratio = gaps / step
        if not (step > 0.0 and np.allclose(ratio, np.round(ratio), rtol=0.0, atol=1e-6)):
            continue
        analog2 = max(white_std**2 - step**2 / 12.0, 0.0)
        a = step / math.pi * math.exp(-2.0 * math.pi**2 * analog2 / step**2)
        worst = max(worst, a)
    return samples * 3.0 * worst**2 / sigma**2 if sigma > 0.0 else math.inf


def check_gate(gate_rate: float, gate_samples: int, gate_dispersion: float) -> None:
    """``build_decoder``'s checks of the gate's alpha_g, K0 and phi (ValueError)."""
    if not 0.0 <= gate_rate < 0.5:
        raise ValueError("gate_rate must be in [0, 0.5)")
    if int(gate_samples) != gate_samples or gate_samples < 0:
        raise ValueError("gate_samples must be an integer >= 0")
    if not (gate_dispersion >= 1.0 and math.isfinite(gate_dispersion)):
        raise ValueError("gate_dispersion must be a finite number >= 1")


def check_bias(dispersion: float, gate_rate: float, gain_sd: float) -> None:
    """``build_decoder``'s check of the bias half's phi_b (ValueError): 0 (none) or a finite
    number >= 1, only with the gate and without the gain profile (its residual is s = 1's)."""
    if dispersion == 0.0:
        return
    if not (dispersion >= 1.0 and math.isfinite(dispersion)):
        raise ValueError("gate_bias_dispersion must be 0 or a finite number >= 1")
    if not gate_rate > 0.0 or gain_sd > 0.0:
        raise ValueError("gate_bias_dispersion needs gate_rate > 0 and gain_sd = 0")


def within_gate(total: Any, samples: Any, gz: float, g4: float) -> Any:
    """Step 7's gate on Q = ``total`` over k = ``samples`` (floats, or arrays that broadcast):
    ``x = Q - 2 k - gz <= 0`` or ``x^2 <= g4 k``, the chi-square(2 k) quantile in Cornish-Fisher
    form without a root (``PowerUpDecoder.gate_terms``); one expression for the batch
    decoder and the sample-by-sample identifier."""
    x = total - 2.0 * samples - gz
    return (x <= 0.0) | (x * x <= g4 * samples)
