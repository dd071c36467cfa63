"""The diagnostics of the model adequacy check (:mod:`hallcal.fit.adequacy`), each from the data.

1. The noise level independent of the model (:func:`estimate_noise_variance`, high-order
   differences of ``d``; Pintelon & Schoukens 2012, sec. 2.4 and 6.7), with the chi-square
   quantile its tests use (:func:`chi2_isf_even`).
2. The harmonic content of signals over spatial frequency (:func:`harmonic_content`: a
   least-squares Fourier series in an angle with a Wald test per harmonic).
3. The projection of the data on the model's flux curve (:func:`curve_projection`,
   :func:`project_fit`): the shape of the curve apart from the timing along it.

Private to :mod:`hallcal.fit`: the public names are re-exported by :mod:`hallcal.fit.adequacy`,
which combines them (with the chi-square ratio of the fit's cost) into its verdict.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.fit.sem import SEMResult
from hallcal.messages import Outcome
from hallcal.sensor.flux import FluxModel

__all__ = [
    "ContentStatus",
    "CurveProjection",
    "HarmonicContent",
    "NoiseEstimate",
    "NoiseStatus",
    "chi2_isf_even",
    "curve_projection",
    "default_max_harmonic",
    "dominant_harmonics",
    "estimate_noise_variance",
    "harmonic_content",
    "project_fit",
]


class NoiseStatus(Outcome):
    """Outcome of :func:`estimate_noise_variance`."""

    OK = "ok"
    #: the lag-2 / lag-1 variance ratio is outside its tolerance: low-pass noise
    COLOURED = "coloured"
    TOO_SHORT = "too_short"


class ContentStatus(Outcome):
    """Outcome of :func:`harmonic_content`."""

    OK = "ok"
    #: the angle covers less than one revolution: harmonics are not separable
    TOO_SHORT = "too_short"


#: Median of the chi-square distribution with one degree of freedom.
_CHI2_1_MEDIAN = 0.45493642311957283
#: Relative asymptotic variance of the median-based estimate over the mean-based one
#: (chi-square(1): var(median) = 1 / (4 M f(m)^2), relative to m^2, divided by 2 / M).
_MEDIAN_EFFICIENCY = 2.7220


def chi2_isf_even(q: float, df: int) -> float:
    """Upper quantile x of the chi-square distribution with an even number of degrees of freedom.

    The x with ``P(X > x) = q`` for ``X ~ chi2(df)``, the threshold of a test at level q
    (``scipy.stats.chi2.isf(q, df)``, which the tests use as the oracle). For ``df = 2 k`` the
    survival function is a Poisson sum, ``Q(x) = exp(-x/2) sum_{i<k} (x/2)^i / i!`` (Abramowitz
    & Stegun 26.4.21), so a few lines of Newton's method on ``log Q`` find x to rounding
    without loading scipy.stats (0.4 s) or scipy.special.

    Parameters
    ----------
    q : float
        Upper tail probability, 0 < q < 1.
    df : int
        Degrees of freedom, even and >= 2.

    Returns
    -------
    float
        The quantile x > 0.
    """
    if not 0.0 < q < 1.0:
        raise ValueError(f"q must lie in (0, 1), got {q!r}")
    if df < 2 or df % 2:
        raise ValueError(f"df must be even and >= 2, got {df!r}")
    k = df // 2
    log_q = math.log(q)
    # f(t) = log Q(2 t) - log q is decreasing and concave (a gamma survival function is
    # log-concave): from any start where the slope is not tiny, Newton's first step lands on or
    # right of the root and the next ones approach it monotonically from the right.
    t = max(-log_q, k - 1.0)
    i = np.arange(k, dtype=np.float64)
    lgam = np.array([math.lgamma(v + 1.0) for v in i])
    for _ in range(100):
        # the Poisson sum in logarithms: t^i / i! overflows a double beyond df ~ 1300
        logs = i * math.log(t) - lgam  # log(t^i / i!), i < k
        top = float(logs.max())
        log_total = top + math.log(float(np.sum(np.exp(logs - top))))
        f = -t + log_total - log_q
        slope = -math.exp(float(logs[-1]) - log_total)  # d/dt log Q(2 t)
        if slope == 0.0:  # only for q within rounding of 1 and many degrees of freedom
            break
        step = f / slope
        t -= step
        if abs(step) <= 4e-16 * t:
            break
    return 2.0 * t


# --------------------------------------------------------------------------------------------
# 1. Noise level from the data alone
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NoiseEstimate:
    """Noise variance of the Hall channels estimated without any model.

    Attributes
    ----------
    variance : float
        Pooled variance (mean over the channels) [unit of d squared].
    per_channel : ndarray (C,)
        Variance per channel.
    std_error : float
        Standard error of ``variance`` for white Gaussian noise.
    method : str
        Description of the estimator.
    order : int
        Order k of the difference filter.
    n_samples : int
        N.
    white_ratio : float
        Estimate from k-th differences at lag 2 divided by the one at lag 1. Both weight the noise
        spectrum differently, so for white noise the ratio is 1 within ``white_tolerance``; a
        smaller value means low-pass (coloured) noise, whose total variance the lag-1 estimate
        underrates.
    white_tolerance : float
        Accepted deviation of ``white_ratio`` from 1.
    status : NoiseStatus
        OK, COLOURED (white_ratio outside the tolerance) or TOO_SHORT.
    """

    variance: float
    per_channel: NDArray[np.float64] = field(repr=False)
    std_error: float
    method: str
    order: int
    n_samples: int
    white_ratio: float
    white_tolerance: float
    status: str

    @property
    def std(self) -> float:
        """Pooled noise standard deviation sigma."""
        return math.sqrt(self.variance) if self.variance >= 0 else math.nan

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", NoiseStatus(self.status))

    def to_dict(self) -> dict:
        return {
            "variance": _f(self.variance),
            "per_channel": [_f(v) for v in self.per_channel],
            "std_error": _f(self.std_error),
            "method": self.method,
            "order": self.order,
            "n_samples": self.n_samples,
            "white_ratio": _f(self.white_ratio),
            "white_tolerance": _f(self.white_tolerance),
            "status": str(self.status),
        }


def _difference_coefficients(order: int) -> NDArray[np.float64]:
    k = int(order)
    return np.array([(-1) ** j * math.comb(k, j) for j in range(k + 1)], dtype=np.float64)


def _lagged_difference(d: NDArray, order: int, lag: int) -> NDArray:
    """sum_j c_j d[n - j lag] for the k-th difference coefficients c_j (valid part only)."""
    c = _difference_coefficients(order)
    N = d.shape[0]
    span = order * lag
    out = np.zeros((N - span, d.shape[1]))
    for j, cj in enumerate(c):
        out += cj * d[span - j * lag : N - j * lag]
    return out


def estimate_noise_variance(
    d: ArrayLike,
    *,
    order: int = 3,
    robust: bool = False,
) -> NoiseEstimate:
    """Variance of the white noise on each Hall channel from the k-th difference of the data.

    The k-th difference ``z[n] = sum_j (-1)^j C(k, j) d[n - j]`` of white noise with variance
    sigma^2 has variance ``C(2k, k) sigma^2`` (the sum of the squared binomial coefficients), so
    ``sigma^2 = mean(z^2) / C(2k, k)`` (Pintelon & Schoukens 2012, sec. 2.4: noise from the
    high-frequency part of the data, where the signal has no power). No model of the flux, the
    motion or the loop is involved.

    Bias for slowly moving signals: a signal component ``a cos(omega n)`` (omega in rad/sample)
    adds ``a^2 / 2 (2 sin(omega / 2))^(2k) / C(2k, k)`` to the estimate. On the paper's bench
    (fundamental n_m y0 at 0.5 rad/s: omega = 1.4e-3, amplitude 1) this is 4.7e-7 for k = 1 (6 %
    of sigma^2 = 7.5e-6), 1e-12 for k = 2 and 3e-18 for k = 3; the default k = 3 is unbiased for any
    motion below about a tenth of the sample rate. The price of a higher order is a larger variance
    of the estimate (factor ``sum_l rho_l^2`` of the filter's autocorrelation: 1.5 for k = 1, 2.3
    for k = 3), still 0.4 % (pooled) for N = 1e5.

    Coloured noise: the estimate measures the noise density near the Nyquist frequency. Low-pass
    noise has less power there than in total, so the estimate is then too low; ``white_ratio``
    (lag 2 against lag 1) detects this.

    Parameters
    ----------
    d : array_like (N, C) or (N,)
        Hall signals (any number of channels), uniformly sampled.
    order : int, keyword-only
        Difference order k >= 1.
    robust : bool
        Use ``median(z^2)`` (scaled by the median of chi-square(1)) instead of the mean: immune to
        a few glitches or steps in the data, 1.65 times less precise for Gaussian noise.

    Returns
    -------
    NoiseEstimate
    """
    x = np.asarray(d, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2:
        raise ValueError("d must have shape (N, C) or (N,)")
    k = int(order)
    if k < 1:
        raise ValueError("order must be >= 1")
    N, C = x.shape
    method = (
        f"{'median' if robust else 'mean'} of squared {k}-th differences / C({2 * k},{k}) "
        "(high-frequency part of d, Pintelon & Schoukens 2012)"
    )
    if N < 4 * k + 8:
        nan = math.nan
        return NoiseEstimate(
            nan, np.full(C, nan), nan, method, k, N, nan, nan, NoiseStatus.TOO_SHORT
        )
    gain = float(math.comb(2 * k, k))

    def var_of(z: NDArray) -> NDArray:
        if robust:
            return np.median(z * z, axis=0) / (_CHI2_1_MEDIAN * gain)
        return np.mean(z * z, axis=0) / gain

    per = var_of(_lagged_difference(x, k, 1))
    per_lag2 = var_of(_lagged_difference(x, k, 2))
    pooled = float(np.mean(per))
    c = _difference_coefficients(k)
    acf = np.correlate(c, c, mode="full") / np.dot(c, c)
    rel_var = 2.0 * float(np.sum(acf**2)) / (N - k)
    if robust:
        rel_var *= _MEDIAN_EFFICIENCY
    rel_var_pooled = rel_var / C
    std_error = pooled * math.sqrt(rel_var_pooled)
    white_ratio = float(np.mean(per_lag2) / pooled) if pooled > 0 else math.nan
    # the two estimates are partly correlated; 2 sqrt(2) standard errors of one, or 3 %
    tol = max(0.03, 8.0 * math.sqrt(rel_var_pooled))
    status = NoiseStatus.OK if abs(white_ratio - 1.0) <= tol else NoiseStatus.COLOURED
    return NoiseEstimate(pooled, per, std_error, method, k, N, white_ratio, tol, status)


# --------------------------------------------------------------------------------------------
# 2. Harmonic content of signals over spatial frequency
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HarmonicContent:
    """Least-squares Fourier series of signals in an angle, with a significance test per harmonic.

    The model is ``d_c(t) = a_c + sum_h s_ch sin(h x(t)) + c_ch cos(h x(t)) + e_c(t)`` over all
    channels c, fitted jointly over the harmonics h (so leakage between harmonics on a
    non-integer number of revolutions is accounted for).

    Attributes
    ----------
    harmonics : ndarray (K,) of int
        Mechanical harmonics h tested (cycles per revolution).
    amplitude : ndarray (K,)
        RMS of harmonic h per channel, ``sqrt(mean_c (s_ch^2 + c_ch^2) / 2)`` [unit of d].
    wald : ndarray (K,)
        Wald statistic ``tr(R^-1 Theta_h^T V_hh^-1 Theta_h)`` of the 2C coefficients of harmonic h,
        with R the C x C residual covariance and V = (Phi^T Phi)^-1; chi-square with 2C degrees of
        freedom when the harmonic is absent (Ljung 1999, sec. 16.6, test of added regressors).
    threshold : float
        Critical value of the Wald statistic at the family-wise level ``significance``
        (Bonferroni over the K harmonics).
    coefficients : ndarray (C, 1 + 2K)
        [a, s_1, c_1, ...] per channel.
    residual_covariance : ndarray (C, C)
    residual_sum : ndarray (C,)
        Residual sum of squares per channel.
    total_sum : ndarray (C,)
        Sum of squares of the data per channel.
    n_samples : int
    revolutions : float
        Angle range covered by x [revolutions].
    status : ContentStatus
        OK, or TOO_SHORT when x covers less than one revolution (harmonics not separable).
    """

    harmonics: NDArray[np.int64] = field(repr=False)
    amplitude: NDArray[np.float64] = field(repr=False)
    wald: NDArray[np.float64] = field(repr=False)
    threshold: float
    coefficients: NDArray[np.float64] = field(repr=False)
    residual_covariance: NDArray[np.float64] = field(repr=False)
    residual_sum: NDArray[np.float64] = field(repr=False)
    total_sum: NDArray[np.float64] = field(repr=False)
    n_samples: int
    revolutions: float
    status: ContentStatus = ContentStatus.OK

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", ContentStatus(self.status))

    @property
    def significant(self) -> NDArray[np.bool_]:
        """Harmonics whose Wald statistic exceeds the threshold."""
        return self.wald > self.threshold

    def amplitude_of(self, harmonic: int) -> float:
        """``amplitude`` of one harmonic (0 when not tested)."""
        idx = np.flatnonzero(self.harmonics == int(harmonic))
        return float(self.amplitude[idx[0]]) if idx.size else 0.0

    def to_dict(self, *, scale: float = 1.0) -> dict:
        """Per-harmonic table; ``scale`` divides the amplitudes (e.g. by sigma)."""
        return {
            "harmonics": [int(h) for h in self.harmonics],
            "amplitude": [_f(a / scale) for a in self.amplitude],
            "wald": [_f(w) for w in self.wald],
            "threshold": _f(self.threshold),
            "significant": [bool(s) for s in self.significant],
            "revolutions": _f(self.revolutions),
            "status": str(self.status),
        }


def _fourier_normal_equations(
    x: NDArray, d: NDArray, harmonics: NDArray
) -> tuple[NDArray, NDArray]:
    """Phi^T Phi and Phi^T d for the basis [1, sin(h x), cos(h x), ...] in O(N max(h)) time.

    Uses ``sum_n exp(i k x_n)`` for k = 0..2 max(h) and the product formulas of sin and cos, so the
    N x (1 + 2K) regressor matrix is never formed.
    """
    K = harmonics
    H = int(K.max())
    z = np.exp(1j * x)
    w = np.ones_like(z)
    T = np.empty(2 * H + 1, dtype=np.complex128)
    B = np.zeros((H + 1, d.shape[1]), dtype=np.complex128)
    dT = np.ascontiguousarray(d.T)
    for k in range(2 * H + 1):
        T[k] = w.sum()
        if k <= H:
            B[k] = dT @ w.real + 1j * (dT @ w.imag)
        w *= z
    C, S = T.real, T.imag

    def cf(k: NDArray) -> NDArray:
        return C[np.abs(k)]

    def sf(k: NDArray) -> NDArray:
        return np.sign(k) * S[np.abs(k)]

    m = 1 + 2 * K.size
    G = np.empty((m, m))
    G[0, 0] = C[0]
    G[0, 1::2] = S[K]
    G[0, 2::2] = C[K]
    G[1::2, 0] = S[K]
    G[2::2, 0] = C[K]
    a = K[:, None]
    b = K[None, :]
    G[1::2, 1::2] = (cf(a - b) - cf(a + b)) / 2.0  # sin a sin b
    G[2::2, 2::2] = (cf(a - b) + cf(a + b)) / 2.0  # cos a cos b
    G[1::2, 2::2] = (sf(a + b) + sf(a - b)) / 2.0  # sin a cos b
    G[2::2, 1::2] = G[1::2, 2::2].T
    rhs = np.empty((m, d.shape[1]))
    rhs[0] = B[0].real
    rhs[1::2] = B[K].imag
    rhs[2::2] = B[K].real
    return G, rhs


def harmonic_content(
    x: ArrayLike,
    d: ArrayLike,
    *,
    harmonics: ArrayLike,
    significance: float = 1e-3,
) -> HarmonicContent:
    """Fourier regression of signals on an angle and a Wald test per harmonic.

    With ``x`` the measured angle y and ``d`` the Hall signals, this is the "harmonic content of
    the data" by which the paper chooses the model order (section "Model structure"); with ``x``
    the simulated angle y0_sim and ``d`` the SEM residual it is the residual spectrum over spatial
    frequency (Ljung 1999, sec. 16.6: residual analysis against candidate regressors).

    Parameters
    ----------
    x : array_like (N,)
        Angle [rad].
    d : array_like (N, C) or (N,)
        Signals.
    harmonics : array_like of int
        Harmonics h >= 1 to fit and test (all fitted jointly with a constant).
    significance : float, keyword-only
        Family-wise false-alarm probability of the K tests.

    Returns
    -------
    HarmonicContent
    """
    xx = np.asarray(x, dtype=np.float64).ravel()
    dd = np.asarray(d, dtype=np.float64)
    if dd.ndim == 1:
        dd = dd[:, None]
    K = np.unique(np.asarray(harmonics, dtype=np.int64))
    if K.size == 0 or K[0] < 1:
        raise ValueError("harmonics must be integers >= 1")
    if dd.shape[0] != xx.size:
        raise ValueError("x and d must have the same number of samples")
    N, C = dd.shape
    m = 1 + 2 * K.size
    revs = float((xx.max() - xx.min()) / TWO_PI) if N else 0.0
    G, rhs = _fourier_normal_equations(xx, dd, K)
    total = np.einsum("ij,ij->j", dd, dd)
    scale = np.sqrt(np.maximum(np.diag(G), 1e-300))
    Gs = G / np.outer(scale, scale)
    Vs = np.linalg.pinv(Gs, rcond=1e-10, hermitian=True)
    V = Vs / np.outer(scale, scale)
    theta = V @ rhs  # (m, C)
    rss = np.maximum(total - np.einsum("ij,ij->j", theta, rhs), 0.0)
    dof = max(N - m, 1)
    # residual covariance (C x C): (d^T d - theta^T Phi^T d) / (N - m)
    R = (dd.T @ dd - theta.T @ rhs) / dof
    R = 0.5 * (R + R.T)
    Ri = np.linalg.pinv(R, hermitian=True)
    wald = np.empty(K.size)
    for j in range(K.size):
        idx = [1 + 2 * j, 2 + 2 * j]
        Th = theta[idx]  # (2, C)
        Vhh = V[np.ix_(idx, idx)]
        try:
            Vinv = np.linalg.inv(Vhh)
        except np.linalg.LinAlgError:
            wald[j] = 0.0
            continue
        wald[j] = float(np.trace(Ri @ Th.T @ Vinv @ Th))
    amp = np.sqrt(np.mean(theta[1::2] ** 2 + theta[2::2] ** 2, axis=1) / 2.0)
    thr = chi2_isf_even(significance / K.size, 2 * C)
    status = ContentStatus.OK if revs >= 1.0 else ContentStatus.TOO_SHORT
    return HarmonicContent(K, amp, wald, thr, theta.T.copy(), R, rss, total, N, revs, status)


def default_max_harmonic(pole_pairs: int, model_harmonics: ArrayLike = ()) -> int:
    """Highest mechanical harmonic examined by default: ``max(8 n_m, max(model) + n_m)``.

    8 n_m covers the electrical harmonics up to the 7th (mechanical 7 n_m) with the pole-to-pole
    sidebands around them.

    Parameters
    ----------
    pole_pairs : int
        n_m.
    model_harmonics : array_like of int
        Mechanical harmonics of the flux model (may be empty).

    Returns
    -------
    int
        The highest mechanical harmonic [cycles/rev].
    """
    h = [int(v) for v in np.atleast_1d(np.asarray(model_harmonics, dtype=np.int64))]
    return max(8 * int(pole_pairs), (max(h) if h else 0) + int(pole_pairs))


def dominant_harmonics(
    spectrum: HarmonicContent,
    *,
    exclude: tuple[int, ...] = (),
    noise_std: float,
    min_amplitude: float = 0.1,
    dominance: float = 0.05,
) -> tuple[int, ...]:
    """Significant, relevant and dominant harmonics of a residual spectrum, not in ``exclude``.

    Relevant: RMS at least ``min_amplitude * noise_std``. Dominant: at least ``dominance`` times
    the largest such amplitude (a large missing harmonic also leaves small sidebands, because the
    angle it is seen against is off while it is missing; they vanish once it is modelled).

    Parameters
    ----------
    spectrum : HarmonicContent
        Harmonic content of the residual (amplitudes and significance per harmonic).
    exclude : tuple of int, keyword-only
        Harmonics never returned (e.g. the model's own).
    noise_std : float, keyword-only
        Hall noise sigma per channel (sensor's unit).
    min_amplitude : float, keyword-only
        Relevance threshold, as a fraction of ``noise_std``.
    dominance : float, keyword-only
        Dominance threshold, as a fraction of the largest relevant amplitude (0 disables).

    Returns
    -------
    tuple of int
        The selected mechanical harmonics, in the spectrum's order.
    """
    ex = {int(h) for h in exclude}
    sel = spectrum.significant & (spectrum.amplitude >= min_amplitude * noise_std)
    sel &= np.array([int(h) not in ex for h in spectrum.harmonics], dtype=bool)
    if np.any(sel) and dominance > 0:
        top = float(np.max(spectrum.amplitude[sel]))
        sel &= spectrum.amplitude >= dominance * top
    return tuple(int(h) for h in spectrum.harmonics[sel])


def _f(v: float) -> float | None:
    """A JSON-safe float (None for NaN and infinities)."""
    v = float(v)
    return v if math.isfinite(v) else None


@nb.njit(cache=True, nogil=True)
def _curve_kernel(y0, d, col_of_h, theta, iterations, delta, resid, speed2):  # pragma: no cover
    """Per-sample Newton iterations of :func:`curve_projection` (numba)."""
    N = y0.size
    H = col_of_h.size - 1
    C = theta.shape[0]
    g = np.empty(C)
    g1 = np.empty(C)
    g2 = np.empty(C)
    for k in range(N):
        dl = 0.0
        for it in range(iterations + 1):
            y = y0[k] + dl
            cz = math.cos(y)
            sz = math.sin(y)
            for c in range(C):
                g[c] = theta[c, 0]
                g1[c] = 0.0
                g2[c] = 0.0
            cp = 1.0
            sp = 0.0
            for h in range(1, H + 1):
                cp, sp = cp * cz - sp * sz, sp * cz + cp * sz
                j = col_of_h[h]
                if j < 0:
                    continue
                for c in range(C):
                    a = theta[c, j]
                    b = theta[c, j + 1]
                    g[c] += a * sp + b * cp
                    g1[c] += h * (a * cp - b * sp)
                    g2[c] -= h * h * (a * sp + b * cp)
            if it == iterations:
                break
            grad = 0.0
            curv = 0.0
            gn = 0.0
            for c in range(C):
                e = d[k, c] - g[c]
                grad += e * g1[c]
                gn += g1[c] * g1[c]
                curv += g1[c] * g1[c] - e * g2[c]
            if curv < 0.1 * gn:
                curv = gn
            if curv > 0.0:
                dl += grad / curv
        delta[k] = dl
        s2 = 0.0
        for c in range(C):
            resid[k, c] = d[k, c] - g[c]
            s2 += g1[c] * g1[c]
        speed2[k] = s2


def curve_projection(
    flux: FluxModel, y0: ArrayLike, d: ArrayLike, *, iterations: int = 4
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Shift of each sample along the model curve to the nearest point, and what remains.

    Solves ``delta_k = argmin_delta |d_k - g_theta(y0_k + delta)|^2`` per sample by Newton's method
    from delta = 0 (a local minimum, which is the one of interest when the simulation tracks the
    motion to within a fraction of an electrical period; Gauss-Newton where the Hessian is not
    safely positive).

    Parameters
    ----------
    flux : FluxModel
        g_theta on a Fourier basis.
    y0 : array_like (N,)
        Angle of every sample on the model curve, e.g. the simulated y0_sim [rad].
    d : array_like (N, 3)
        Hall signals.
    iterations : int, keyword-only
        Newton steps per sample.

    Returns
    -------
    delta : ndarray (N,)
        Shift [rad].
    residual : ndarray (N, 3)
        ``d - g_theta(y0 + delta)``, orthogonal to the curve.
    speed2 : ndarray (N,)
        ``|g_theta'(y0 + delta)|^2``: the noise variance of delta is sigma^2 / speed2.
    """
    y = np.ascontiguousarray(y0, dtype=np.float64)
    dd = np.ascontiguousarray(d, dtype=np.float64)
    harm = flux.basis.harmonics
    col = -np.ones(max(harm) + 1, dtype=np.int64)
    for j, h in enumerate(harm):
        col[h] = 1 + 2 * j
    delta = np.empty(y.size)
    resid = np.empty_like(dd)
    speed2 = np.empty(y.size)
    theta = np.ascontiguousarray(flux.theta)
    it = int(iterations)
    h = y.size // 2
    if y.size < 8192:
        _curve_kernel(y, dd, col, theta, it, delta, resid, speed2)
        return delta, resid, speed2
    # each sample on its own: two halves in two threads (numba releases the GIL), the same bits
    with ThreadPoolExecutor(1) as pool:
        fut = pool.submit(_curve_kernel, y[h:], dd[h:], col, theta, it, delta[h:], resid[h:],
                          speed2[h:])  # fmt: skip
        _curve_kernel(y[:h], dd[:h], col, theta, it, delta[:h], resid[:h], speed2[:h])
        fut.result()
    return delta, resid, speed2


@dataclass(frozen=True)
class CurveProjection:
    """:func:`curve_projection` of signals d on a fit's flux curve at its simulated angle
    y0_sim, with the fit and the signals it comes from (:func:`project_fit`).

    Attributes
    ----------
    sem : SEMResult
        The fit (its flux g_theta and y0_sim).
    d : ndarray (N, 3)
        The signals.
    delta, residual, speed2 : ndarray
        As returned by :func:`curve_projection`.
    """

    sem: SEMResult = field(repr=False)
    d: NDArray[np.float64] = field(repr=False)
    delta: NDArray[np.float64] = field(repr=False)
    residual: NDArray[np.float64] = field(repr=False)
    speed2: NDArray[np.float64] = field(repr=False)


def project_fit(
    sem: SEMResult, d: NDArray[np.float64], *, known: CurveProjection | None = None
) -> CurveProjection:
    """:func:`curve_projection` of d on the fit's curve at its y0_sim, or ``known`` when that was
    computed from this very fit and these very signals (the same objects: the cogging search's
    spectrum and the adequacy check of a fit it left unchanged see the same projection).

    Parameters
    ----------
    sem : SEMResult
        The fit.
    d : ndarray (N, 3)
        The signals it used.
    known : CurveProjection, optional
        A projection computed before.

    Returns
    -------
    CurveProjection
    """
    if known is not None and known.sem is sem and known.d is d:
        return known
    delta, resid, speed2 = curve_projection(sem.flux, sem.y0_sim, d)
    return CurveProjection(sem, d, delta, resid, speed2)
