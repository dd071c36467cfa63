"""The periodic-kernel flux model of the experiment section and its fast, regularized SEM.

Section "Experimental results" of van Meer et al. models each Hall signal with ``m = 400`` kernel
functions centred on a uniform grid ``y_j = 2 pi j / m``,

    beta_j(y0) = k(y0, y_j),    k(y, y') = sf^2 exp(-|x - x'|^2 / (2 l^2)),  x = [sin y, cos y],

so ``k(y, y') = sf^2 exp(-(1 - cos(y - y')) / l^2)``: a stationary, periodic kernel (the periodic
kernel of MacKay 1998; Rasmussen & Williams 2006, eq. 4.31). With ``a = 1 / l^2`` and the generating
function of the modified Bessel functions, ``exp(a cos t) = sum_k I_k(a) e^{ikt}`` (Abramowitz &
Stegun 9.6.34), its Fourier coefficients are

    k(t) = sum_{k in Z} s_k e^{ikt},   s_k = sf^2 e^{-a} I_|k|(a) = sf^2 ive(|k|, a),

computed stably with ``scipy.special.ive``. Consequences used here (Wahba 1990, ch. 2):

* Spectral map. ``g(y) = sum_j w_j k(y, y_j)`` has the Fourier coefficients
  ``G_k = s_k W_{k mod m}`` with ``W = DFT(w)``: a Fourier series whose coefficients at k and at
  its aliases k + m, k - m, ... are tied. When ``s_k`` is negligible beyond m / 2 (the lengthscale
  is resolved by the grid), the kernel model is exactly a Fourier model with harmonics 0..m/2.
* The Gram matrix ``K_ij = k(y_i, y_j)`` is circulant with eigenvalues
  ``lambda_q = m sum_{k = q mod m} s_k``.
* RKHS norm. ``w^T K w = sum_k |G_k|^2 / s_k``: in the real Fourier coefficients of
  :class:`~hallcal.sensor.flux.FourierBasis` (``[1, sin ky, cos ky, ...]``) the kernel norm is the
  diagonal ridge ``theta_0^2 / s_0 + sum_k (theta_sk^2 + theta_ck^2) / (2 s_k)``, i.e. the
  Gaussian-process prior ``theta_0 ~ N(0, s_0)``, ``theta_sk, theta_ck ~ N(0, 2 s_k)``.
* Truncation. Modes whose prior variance ``2 s_k`` is negligible relative to the Hall noise
  variance cannot carry signal above the noise and are dropped (:meth:`KernelBasis.truncation`).

Hyperparameters. ``sf`` only scales the weights (``g`` is unchanged by ``sf -> c sf``,
``w -> w / c^2``), so it cannot be identified from the fit alone; the paper made it a design
variable of the unregularized cost, which is then flat in it. Here the kernel model is estimated
as kernel ridge regression / Gaussian-process MAP through the closed loop:

    min_theta  J(theta) + rho * sum_h ||g_h||^2_{H(k_1)},      rho = sigma^2 / sf^2,

with ``k_1`` the kernel for ``sf = 1`` and sigma^2 the Hall noise variance. ``l`` and ``rho``
(equivalently ``sf``, with sigma^2 profiled out) are chosen by the marginal likelihood (type-II
maximum likelihood; Rasmussen & Williams 2006, sec. 5.4.1; MacKay 1992, "Bayesian
interpolation") of the model linearized around the SEM solution,
``d - d_sim(theta*) + J theta* = J theta + v``, or alternatively by generalized cross-validation
(Golub, Heath & Wahba 1979; Wahba 1990, ch. 4; Rasmussen & Williams 2006, sec. 5.3). Both
criteria need only ``J^T J``, ``J^T e`` and ``e^T e``, which the Gauss-Newton solver forms anyway.

Speed (:mod:`hallcal.fit.gauss_newton`). The dense Jacobian at the experiment size (480 000 x
1200) is never formed. Its rows have
the structure ``J[k, h, :] = g_h'(y0_k) dy0_k + e_h kron beta(y0_k)`` (:mod:`hallcal.sim.loop`), so

    J^T J = sum_k u_k u_k^T + sum_k (I_3 - n_k n_k^T) kron beta_k beta_k^T,
    u_k = |g'_k| dy0_k + n_k kron beta_k,   n_k = g'_k / |g'_k|,

one rank-one update per sample (a third of the dense rows), accumulated in chunks while the
sensitivity recursion runs (the two overlap on two cores), plus trigonometric sums: products of
sines and cosines reduce to the moments ``sum_k w_k e^{i n y0_k}``, n <= 2K, so the second term
costs O(N K) instead of O(N K^2). (``u_k`` is the Jacobian row of the Hall residual along the
tangent n_k of the flux curve, the second term the two normal directions.) Levenberg-Marquardt
iterations may take the Gram part from every 4th sample; the system at each solution is exact.

Learned spectrum (``spectrum="ard"``, the default with ``lengthscale="auto"``). With the kernel's
own (Bessel) spectrum the model stays 2.5-5.3x above the Hall noise floor on the experiment-shaped
bench (``benchmarks/bench_kernel.txt``). The excess is variance in slow warps of the angle,
``g(y0 + w(y0))`` with w of 1..3 cycles per revolution, i.e. the Fourier directions at the
sidebands ``k n_m +- j``: the loop tracks such warps out of the f_init output, so they show in the
simulation error only through the loop's small low-frequency sensitivity, and a stationary
squared-exponential prior gives these sidebands a prior variance as large as that of the
harmonics the flux really has. The spectrum is therefore learned: automatic relevance
determination (MacKay 1992, "Bayesian interpolation"; Neal 1996; Tipping 2001, "Sparse Bayesian
learning and the relevance vector machine") with one prior variance per harmonic k, shared by the
three sensors and by sin/cos, started from the Bessel spectrum and set by the evidence fixed point
on the Gauss-Newton linearization at the SEM solution (:func:`ard_spectrum`); the SEM is then
re-solved with the learned ridge. The prior is still a stationary periodic kernel (any
non-negative spectrum is one, by Bochner's theorem on the circle), with the paper's
squared-exponential kernel as its starting point; the identified flux is represented exactly by
weights on the paper's m kernel centres (:meth:`KernelBasis.from_fourier`). Measured (4 seeds
each): 1.01x the noise floor on the bench without per-pole modulation (Bessel spectrum 2.5-5.6x;
the truth's exact harmonics 1.0x), 1.12-1.40x with per-pole modulation 0.02 (Bessel spectrum
2.5-5.3x; the truth's exact harmonics as a Fourier model 1.2-3.6x).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.special
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from hallcal.fit.gauss_newton import (
    GaussNewtonSystem,
    _gram_from_moments,
    _moments,
    fourier_gauss_newton,
    simulate_fourier,
)
from hallcal.fit.sem import SEMResult
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.reconstruction import f_init
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "ARDSpectrum",
    "CriterionPoint",
    "GaussNewtonSystem",
    "KernelBasis",
    "KernelSEMResult",
    "ard_spectrum",
    "fourier_gauss_newton",
    "fourier_rkhs_norm2",
    "select_hyperparameters",
    "simulate_fourier",
    "solve_kernel_sem",
]

TWO_PI = 2.0 * math.pi


# ================================================================================================
# The kernel basis and its spectral (Fourier) equivalent
# ================================================================================================


@dataclass(frozen=True)
class KernelBasis:
    """Periodic kernel basis of the experiment section on m uniform centres.

    ``beta_j(y0) = k(y0, y_j)`` with ``y_j = 2 pi j / m`` and
    ``k(y, y') = sf^2 exp(-(1 - cos(y - y')) / l^2)``.

    Parameters
    ----------
    points : int
        Number of centres m.
    lengthscale : float
        l [rad of the embedding circle; about rad of angle for small l].
    sf : float
        Signal standard deviation sf (the kernel's amplitude), keyword or positional.
    """

    points: int
    lengthscale: float
    sf: float = 1.0

    def __post_init__(self) -> None:
        if int(self.points) < 3:
            raise ValueError("points must be >= 3")
        if not (self.lengthscale > 0 and math.isfinite(self.lengthscale)):
            raise ValueError("lengthscale must be a finite number > 0")
        if not (self.sf > 0 and math.isfinite(self.sf)):
            raise ValueError("sf must be a finite number > 0")
        object.__setattr__(self, "points", int(self.points))
        object.__setattr__(self, "lengthscale", float(self.lengthscale))
        object.__setattr__(self, "sf", float(self.sf))

    # -- kernel form -------------------------------------------------------------------------
    @property
    def size(self) -> int:
        """m."""
        return self.points

    @property
    def centres(self) -> NDArray[np.float64]:
        """y_j = 2 pi j / m [rad]."""
        return TWO_PI * np.arange(self.points) / self.points

    @property
    def inverse_square_lengthscale(self) -> float:
        """a = 1 / l^2."""
        return 1.0 / self.lengthscale**2

    def evaluate(self, y0: ArrayLike) -> NDArray[np.float64]:
        """beta(y0) = [k(y0, y_j)]_j, shape (N, m): the paper's kernel basis."""
        y = np.atleast_1d(np.asarray(y0, dtype=np.float64))
        t = np.subtract.outer(y, self.centres)
        return self.sf**2 * np.exp((np.cos(t) - 1.0) * self.inverse_square_lengthscale)

    def derivative(self, y0: ArrayLike) -> NDArray[np.float64]:
        """d beta / d y0, shape (N, m) [1/rad]."""
        y = np.atleast_1d(np.asarray(y0, dtype=np.float64))
        t = np.subtract.outer(y, self.centres)
        a = self.inverse_square_lengthscale
        return -a * np.sin(t) * self.sf**2 * np.exp((np.cos(t) - 1.0) * a)

    def kernel_flux(self, w: ArrayLike, y0: ArrayLike) -> NDArray[np.float64]:
        """g(y0) = beta(y0) w_h^T for the three sensors, shape (N, 3); w of shape (3, m)."""
        return self.evaluate(y0) @ self._weights(w).T

    def gram(self) -> NDArray[np.float64]:
        """K_ij = k(y_i, y_j), shape (m, m) (circulant)."""
        return self.evaluate(self.centres)

    # -- spectrum ----------------------------------------------------------------------------
    def spectrum(self, kmax: int) -> NDArray[np.float64]:
        """Fourier coefficients s_k = sf^2 ive(k, 1/l^2) of k(t), k = 0..kmax."""
        k = np.arange(int(kmax) + 1, dtype=np.float64)
        return self.sf**2 * scipy.special.ive(k, self.inverse_square_lengthscale)

    def gram_eigenvalues(self) -> NDArray[np.float64]:
        """Eigenvalues of the circulant Gram matrix, lambda_q = m sum_{k = q mod m} s_k.

        Ordered as the DFT bins q = 0..m-1 (eigenvector e^{i q y_j}); aliases are summed until
        s_k underflows.
        """
        m = self.points
        kmax = max(self.exact_harmonics(), m)
        s = self.spectrum(kmax + m)
        lam = np.zeros(m)
        for k in range(-(kmax + m), kmax + m + 1):
            lam[k % m] += s[abs(k)]
        return m * lam

    def exact_harmonics(self, rtol: float = 1e-17) -> int:
        """Smallest K with s_k < rtol s_0 for all k > K (the series is exact to rtol beyond K)."""
        a = self.inverse_square_lengthscale
        # s_k / s_0 decreases monotonically in k; bracket then bisect.
        hi = max(8, int(4 * math.sqrt(a) + 8))
        while scipy.special.ive(hi, a) >= rtol * scipy.special.ive(0, a):
            hi *= 2
        lo = 0
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if scipy.special.ive(mid, a) >= rtol * scipy.special.ive(0, a):
                lo = mid
            else:
                hi = mid
        return lo

    def prior_variance(self, harmonics: int) -> NDArray[np.float64]:
        """Prior variances of the Fourier coefficients ``[1, sin 1y, cos 1y, ..., cos Ky]``.

        For a Gaussian process with covariance k (no aliasing): ``var theta_0 = s_0`` and
        ``var theta_sk = var theta_ck = 2 s_k``. Shape (2K + 1,), one sensor.
        """
        K = int(harmonics)
        s = self.spectrum(K)
        v = np.empty(2 * K + 1)
        v[0] = s[0]
        v[1::2] = 2.0 * s[1:]
        v[2::2] = 2.0 * s[1:]
        return v

    def ridge_weights(self, harmonics: int) -> NDArray[np.float64]:
        """Diagonal ridge of the RKHS norm in the Fourier coefficients, shape (3 (2K + 1),).

        ``sum_h ||g_h||^2_H = sum_j ridge_j theta_j^2`` with theta flattened sensor-major (the
        layout of :func:`hallcal.fit.sem.solve_sem`'s ``regularization``).
        """
        return np.tile(1.0 / np.maximum(self.prior_variance(harmonics), 1e-300), 3)

    def truncation(self, noise_variance: float, *, tol: float = 1e-3) -> int:
        """Highest harmonic K worth modelling: the last k with ``2 s_k >= tol^2 sigma^2``.

        A mode whose prior standard deviation is below ``tol`` times the Hall noise standard
        deviation changes the fitted signal by less than ``tol`` sigma, i.e. the angle by less
        than ``tol`` times the noise floor; dropping it is exact to that level. Capped at
        ``(m - 1) // 2`` (the grid's Nyquist harmonic) and at least 1.
        """
        if not noise_variance > 0:
            raise ValueError("noise_variance must be > 0")
        cap = (self.points - 1) // 2
        s = self.spectrum(cap)
        keep = np.nonzero(2.0 * s[1:] >= tol**2 * noise_variance)[0]
        return int(max(1, min(cap, (keep[-1] + 1) if keep.size else 1)))

    def aliasing(self, harmonics: int) -> float:
        """Relative size s_{m-K} / s_K of the first alias of harmonic K on the m-point grid."""
        K = int(harmonics)
        s = self.spectrum(max(self.points - K, K))
        return float(s[self.points - K] / s[K]) if s[K] > 0 else math.inf

    def fourier_basis(self, harmonics: int) -> FourierBasis:
        """The equivalent Fourier basis with harmonics 1..K (and the constant term)."""
        return FourierBasis(tuple(range(1, int(harmonics) + 1)))

    # -- spectral maps -----------------------------------------------------------------------
    def _weights(self, w: ArrayLike) -> NDArray[np.float64]:
        W = np.asarray(w, dtype=np.float64)
        if W.ndim == 1:
            W = W[None, :]
        if W.shape[-1] != self.points:
            raise ValueError(f"weights must have {self.points} columns")
        return W

    def to_fourier(self, w: ArrayLike, *, harmonics: int | None = None) -> FluxModel:
        """The kernel model ``g_h(y) = sum_j w_hj k(y, y_j)`` as a Fourier :class:`FluxModel`.

        Parameters
        ----------
        w : array_like, shape (3, m)
            Kernel weights.
        harmonics : int, keyword-only, optional
            Highest harmonic K kept; default :meth:`exact_harmonics` (exact to about 1e-17
            relative). Harmonics above m / 2 are the aliases ``G_k = s_k W_{k mod m}``.
        """
        W = self._weights(w)
        if W.shape[0] != 3:
            raise ValueError("to_fourier needs the weights of three sensors, shape (3, m)")
        K = self.exact_harmonics() if harmonics is None else int(harmonics)
        F = np.fft.fft(W, axis=-1)  # W_q = sum_j w_j e^{-i q y_j}
        k = np.arange(K + 1)
        G = self.spectrum(K)[None, :] * F[:, k % self.points]
        theta = np.empty((W.shape[0], 2 * K + 1))
        theta[:, 0] = G[:, 0].real
        theta[:, 1::2] = -2.0 * G[:, 1:].imag
        theta[:, 2::2] = 2.0 * G[:, 1:].real
        return FluxModel(self.fourier_basis(K), theta)

    def from_fourier(self, flux: FluxModel) -> NDArray[np.float64]:
        """Kernel weights w (3, m) whose kernel model equals a Fourier model with harmonics < m/2.

        The inverse of :meth:`to_fourier` on band-limited models: ``W_k = G_k / s_k`` for
        ``|k| <= K`` and zero elsewhere (the minimum-RKHS-norm representer). Exact up to the
        aliases of the kept harmonics, relative size :meth:`aliasing`.
        """
        harm = np.asarray(flux.basis.harmonics, dtype=int)
        m = self.points
        if harm.size and harm.max() > (m - 1) // 2:
            raise ValueError(f"harmonics must be below m/2 = {m / 2} to map to kernel weights")
        th = np.asarray(flux.theta, dtype=np.float64)
        s = self.spectrum(int(harm.max()) if harm.size else 0)
        if np.any(s[harm] <= 0) or s[0] <= 0:
            raise ValueError("the kernel spectrum underflows at these harmonics")
        F = np.zeros((th.shape[0], m), dtype=np.complex128)
        F[:, 0] = th[:, 0] / s[0]
        Gk = 0.5 * (th[:, 2::2] - 1j * th[:, 1::2])  # complex coefficient of e^{iky}
        F[:, harm] = Gk / s[harm]
        F[:, (m - harm) % m] = np.conj(Gk) / s[harm]
        return np.fft.ifft(F, axis=-1).real.copy()

    def rkhs_norm2(self, w: ArrayLike) -> NDArray[np.float64]:
        """||g_h||^2_H = w_h^T K w_h for each sensor, via the circulant eigenvalues."""
        W = self._weights(w)
        F = np.fft.fft(W, axis=-1)
        return (np.abs(F) ** 2 @ self.gram_eigenvalues()) / self.points


def fourier_rkhs_norm2(basis: KernelBasis, flux: FluxModel) -> NDArray[np.float64]:
    """RKHS norm of a Fourier model with harmonics 1..K in the kernel's space, per sensor."""
    K = len(flux.basis.harmonics)
    if flux.basis.harmonics != tuple(range(1, K + 1)):
        raise ValueError("needs harmonics 1..K")
    return (np.asarray(flux.theta) ** 2) @ (1.0 / basis.prior_variance(K))


# ================================================================================================
# Hyperparameters: marginal likelihood or GCV of the linearized model
# ================================================================================================


@dataclass(frozen=True)
class CriterionPoint:
    """The hyperparameter criterion at one lengthscale, minimized over the penalty.

    Attributes
    ----------
    lengthscale : float
        l [rad].
    penalty : float
        rho = sigma^2 / sf^2, the weight of the RKHS norm of the unit-amplitude kernel.
    value : float
        Criterion: ``-2 log p(z)`` with sigma^2 profiled out (evidence) or the GCV score.
    noise_variance : float
        sigma^2 estimate: ``Q / n`` (evidence) or ``R / (n - dof)`` (GCV).
    sf : float
        sqrt(sigma^2 / rho).
    dof : float
        Effective number of parameters ``tr(H) = sum_i D_i / (D_i + rho)``.
    """

    lengthscale: float
    penalty: float
    value: float
    noise_variance: float
    sf: float
    dof: float


def _criterion_at_lengthscale(
    lengthscale: float,
    gram: NDArray,
    gradient: NDArray,
    sse: float,
    theta: NDArray,
    *,
    n: int,
    harmonics: int,
    points: int,
    criterion: str,
    penalty: float | None = None,
) -> CriterionPoint:
    """Minimize the criterion over rho at one l (see :func:`select_hyperparameters`)."""
    K = harmonics
    q = gram.shape[0]
    reps = q // (2 * K + 1)  # prior repeated over the sensors sharing this Gram block
    v = np.tile(KernelBasis(points, lengthscale).prior_variance(K), reps)
    act = v > 1e-30 * v.max()
    ia = np.nonzero(act)[0]
    sv = np.sqrt(v[ia])
    Gaa = gram[np.ix_(ia, ia)]
    with threadpool_limits(limits=1, user_api="blas"):
        D, V = scipy.linalg.eigh(sv[:, None] * Gaa * sv[None, :], check_finite=False)
    D = np.maximum(D, 0.0)
    c = gradient.shape[1]
    Jtz = gradient + gram @ theta  # J^T z, (q, c)
    t = V.T @ (sv[:, None] * Jtz[ia])

    # The residual ||z - J theta_rho||^2 = e*'e* - 2 D' J'e* + D' J'J D with D = theta_rho - theta*,
    # formed in theta coordinates (stable when theta* has weight on modes of tiny prior variance).
    def parts(lam: float) -> tuple[float, float, float]:
        phi = t / (D[:, None] + lam)
        delta = -theta.copy()
        delta[ia] += sv[:, None] * (V @ phi)
        R = sse - 2.0 * float(np.sum(delta * gradient)) + float(np.sum(delta * (gram @ delta)))
        R = max(R, 1e-300)
        pen = float(np.sum(phi**2))
        dof = c * float(np.sum(D / (D + lam)))
        return R, pen, dof

    def value(loglam: float) -> float:
        lam = math.exp(loglam)
        R, pen, dof = parts(lam)
        if criterion == "gcv":
            return n * R / max(n - dof, 1.0) ** 2
        Q = R + lam * pen
        return n * math.log(TWO_PI * Q / n) + n + c * float(np.sum(np.log1p(D / lam)))

    if penalty is None:
        top = max(float(D.max()), 1e-300)
        grid = np.log(top) + np.linspace(math.log(1e-14), math.log(1e2), 49)
        vals = np.array([value(g) for g in grid])
        i = int(np.argmin(vals))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        res = scipy.optimize.minimize_scalar(
            value, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3}
        )
        loglam = float(res.x) if res.fun <= vals[i] else float(grid[i])
    else:
        loglam = math.log(penalty)
    lam = math.exp(loglam)
    R, pen, dof = parts(lam)
    s2 = (R + lam * pen) / n if criterion != "gcv" else R / max(n - dof, 1.0)
    return CriterionPoint(
        lengthscale=float(lengthscale),
        penalty=lam,
        value=value(loglam),
        noise_variance=s2,
        sf=math.sqrt(s2 / lam),
        dof=dof,
    )


def select_hyperparameters(
    gram: ArrayLike,
    gradient: ArrayLike,
    sse: float,
    theta: ArrayLike,
    *,
    n: int,
    points: int,
    lengthscale: float | tuple[float, float] = (0.03, 1.0),
    criterion: Literal["evidence", "gcv"] = "evidence",
    grid: int = 12,
    refine: int = 8,
) -> tuple[CriterionPoint, list[CriterionPoint]]:
    """Choose l and rho = sigma^2 / sf^2 for the linearized model ``z = J theta + v``.

    At a linearization point theta* with residual e* = d - d_sim(theta*),
    ``z = e* + J theta*`` is linear in theta with ``theta ~ N(0, sf^2 Lambda(l))`` (the kernel's
    Fourier prior, :meth:`KernelBasis.prior_variance`) and ``v ~ N(0, sigma^2 I_n)``. With the
    eigendecomposition ``Lambda^{1/2} J^T J Lambda^{1/2} = V D V^T``:

    * evidence (type-II maximum likelihood, Rasmussen & Williams 2006, eq. 5.8, with sigma^2
      profiled out): ``n log(2 pi Q / n) + n + sum_i log(1 + D_i / rho)``,
      ``Q = ||z - J theta_rho||^2 + rho theta_rho^T Lambda^{-1} theta_rho``;
    * GCV (Golub, Heath & Wahba 1979; Wahba 1990, eq. 4.3.1):
      ``n ||z - J theta_rho||^2 / (n - tr H)^2``, ``tr H = sum_i D_i / (D_i + rho)``,

    where theta_rho is the kernel-ridge (MAP) estimate. Everything is computed from J^T J, J^T e*
    and e*^T e* (p x p work per lengthscale, O(p) per rho). Modes with vanishing prior variance
    are held at zero (their parameters are then exactly ``theta = 0`` in the linear model).

    Parameters
    ----------
    gram : array_like (q, q)
        J^T J at theta* for harmonics 1..K.
    gradient : array_like (q,) or (q, c)
        J^T e*. One-dimensional: the three sensors stacked, q = 3 (2K + 1), prior tiled. Two-
        dimensional: c columns (e.g. the three sensors of a regression at a known angle) share
        one Gram block, q = 2K + 1.
    sse : float
        e*^T e*, summed over the columns.
    theta : array_like, same shape as gradient
        theta*.
    n : int
        Number of observations (3 N).
    points : int
        m of the kernel basis (only its spectrum matters here).
    lengthscale : float or (lo, hi), keyword-only
        A fixed l, or the search range: a log-spaced grid of ``grid`` values, then ``refine``
        bounded-Brent steps on log l around the best grid value.
    criterion : {"evidence", "gcv"}

    Returns
    -------
    best : CriterionPoint
    tried : list of CriterionPoint
        Every lengthscale evaluated, sorted by l.
    """
    if criterion not in ("evidence", "gcv"):
        raise ValueError('criterion must be "evidence" or "gcv"')
    G = np.asarray(gram, dtype=np.float64)
    b = np.asarray(gradient, dtype=np.float64)
    th = np.asarray(theta, dtype=np.float64)
    if b.ndim == 1:
        b = b[:, None]
        th = th.reshape(-1, 1)
    q = G.shape[0]
    reps = 3 if np.ndim(gradient) == 1 else 1
    K = (q // reps - 1) // 2
    if reps * (2 * K + 1) != q or th.shape != b.shape:
        raise ValueError("gram, gradient and theta do not describe harmonics 1..K")
    cache: dict[float, CriterionPoint] = {}

    def at(l: float) -> CriterionPoint:
        if l not in cache:
            cache[l] = _criterion_at_lengthscale(
                l, G, b, float(sse), th, n=n, harmonics=K, points=points, criterion=criterion
            )
        return cache[l]

    if np.isscalar(lengthscale):
        best = at(float(lengthscale))  # type: ignore[arg-type]
        return best, [best]
    lo, hi = (float(v) for v in lengthscale)  # type: ignore[union-attr]
    if not 0 < lo < hi:
        raise ValueError("lengthscale range must satisfy 0 < lo < hi")
    ls = np.exp(np.linspace(math.log(lo), math.log(hi), int(grid)))
    vals = [at(float(l)).value for l in ls]
    i = int(np.argmin(vals))
    if refine > 0 and 0 < i < ls.size - 1:
        res = scipy.optimize.minimize_scalar(
            lambda x: at(float(math.exp(x))).value,
            bounds=(math.log(ls[i - 1]), math.log(ls[i + 1])),
            method="bounded",
            options={"maxiter": int(refine), "xatol": 0.01},
        )
        del res
    tried = sorted(cache.values(), key=lambda c: c.lengthscale)
    best = min(tried, key=lambda c: c.value)
    return best, tried


# ================================================================================================
# Regularized Levenberg-Marquardt on the structured Gauss-Newton system
# ================================================================================================


@dataclass
class _LMOutcome:
    theta: NDArray[np.float64]
    system: GaussNewtonSystem
    history: list[float]
    iterations: int
    status: str
    decrement: float


def _regularized_lm(
    loop: ClosedLoop,
    r: NDArray,
    d: NDArray,
    theta0: NDArray,
    ridge: NDArray,
    *,
    max_iterations: int,
    tol: float,
    noise_variance: float,
    deadline: float,
    system: GaussNewtonSystem | None = None,
    chunk: int = 4096,
    stride: int = 1,
) -> _LMOutcome:
    """Minimize ``F = ||d - d_sim(theta)||^2 + theta^T diag(ridge) theta`` (More 1978).

    Gauss-Newton steps ``(J^T J + R + mu diag(J^T J + R)) delta = J^T e - R theta`` with mu = 0
    first and raised only when a step fails to decrease F. Converged when the Gauss-Newton decrement
    ``g^T (J^T J + R)^{-1} g`` (twice the predicted decrease) falls below ``tol sigma^2``: the
    remaining step is then far inside the parameters' statistical uncertainty.
    """
    theta = np.array(theta0, dtype=np.float64)
    shape = theta.shape
    sys_ = system
    if sys_ is None:
        sys_ = fourier_gauss_newton(loop, theta, r, d, chunk=chunk, stride=stride)
    if sys_.status != "ok":
        return _LMOutcome(theta, sys_, [math.inf], 0, "diverged", math.inf)
    th = theta.ravel()
    F = sys_.sse + float(ridge @ th**2)
    history = [F]
    mu = 0.0
    status = "max_iterations"
    it = 0
    dec = math.inf
    while True:
        A = sys_.gram + np.diag(ridge)
        g = sys_.gradient - ridge * th
        with threadpool_limits(limits=1, user_api="blas"):
            try:
                cf = scipy.linalg.cho_factor(A, check_finite=False)
                dec = float(g @ scipy.linalg.cho_solve(cf, g, check_finite=False))
            except np.linalg.LinAlgError:
                dec = math.inf
        if dec <= tol * noise_variance:
            status = "converged"
            break
        if it >= max_iterations:
            status = "max_iterations"
            break
        if time.perf_counter() > deadline:
            status = "time_budget"
            break
        dA = np.diag(A).copy()
        dA[dA <= 0] = 1.0
        accepted = False
        for _ in range(12):
            with threadpool_limits(limits=1, user_api="blas"):
                try:
                    if mu == 0.0 and math.isfinite(dec):
                        step = scipy.linalg.cho_solve(cf, g, check_finite=False)
                    else:
                        step = scipy.linalg.solve(
                            A + mu * np.diag(dA), g, assume_a="pos", check_finite=False
                        )
                except (np.linalg.LinAlgError, ValueError):
                    mu = max(10.0 * mu, 1e-6)
                    continue
            cand = th + step
            _, _, _, dc, st = simulate_fourier(loop, cand.reshape(shape), r)
            Fc = math.inf if st != "ok" else float(np.sum((d - dc) ** 2) + ridge @ cand**2)
            if Fc < F:
                accepted = True
                break
            mu = max(8.0 * mu, 1e-5)
        if not accepted:
            status = "stalled"
            break
        mu = mu / 8.0 if mu > 1e-5 else 0.0
        th = cand
        it += 1
        sys_ = fourier_gauss_newton(loop, th.reshape(shape), r, d, chunk=chunk, stride=stride)
        if sys_.status != "ok":  # cannot happen after a finite simulated cost, but be safe
            status = "diverged"
            break
        F = sys_.sse + float(ridge @ th**2)
        history.append(F)
    return _LMOutcome(th.reshape(shape), sys_, history, it, status, dec)


# ================================================================================================
# Learned spectrum: automatic relevance determination per harmonic
# ================================================================================================


@dataclass(frozen=True)
class ARDSpectrum:
    """Outcome of :func:`ard_spectrum`: one prior precision per harmonic.

    Attributes
    ----------
    precision : ndarray (K + 1,)
        alpha_k, the prior precision of each Fourier coefficient of harmonic k (shared by the
        three sensors and by sin/cos); ``inf`` for pruned harmonics.
    pruned : ndarray of bool (K + 1,)
        Harmonics whose prior variance collapsed (held at zero).
    noise_variance : float
        sigma^2 re-estimated with the effective number of parameters ``sum gamma``.
    gamma : ndarray (K + 1,)
        Well-determined parameters per harmonic, ``sum_group (1 - alpha_k Sigma_jj)``.
    mean : ndarray (p,)
        Posterior mean of the linearized model (theta layout, flattened sensor-major).
    iterations : int
        Fixed-point iterations.
    converged : bool
        Whether the active log-precisions settled (change below ``tol``).
    """

    precision: NDArray[np.float64]
    pruned: NDArray[np.bool_]
    noise_variance: float
    gamma: NDArray[np.float64]
    mean: NDArray[np.float64] = field(repr=False)
    iterations: int
    converged: bool


def _harmonic_groups(K: int) -> NDArray[np.int64]:
    """Harmonic of every coefficient of theta (3, 2K + 1) flattened sensor-major."""
    j = np.arange(2 * K + 1)
    return np.tile((j + 1) // 2, 3)


def ard_spectrum(
    gram: ArrayLike,
    gradient: ArrayLike,
    sse: float,
    theta: ArrayLike,
    precision: ArrayLike,
    noise_variance: float,
    *,
    n: int,
    max_iterations: int = 100,
    tol: float = 1e-2,
    prune: float = 1e6,
    update_noise: bool = True,
) -> ARDSpectrum:
    """Evidence fixed point for one prior variance per harmonic on the linearized model.

    The model linearized at theta* (``z = e* + J theta* = J theta + v``, ``v ~ N(0, sigma^2 I)``)
    with the prior ``theta_j ~ N(0, 1 / alpha_k(j))``, one precision per harmonic k shared by the
    six coefficients (three sensors, sin and cos; three for k = 0): automatic relevance
    determination (MacKay 1992, "Bayesian interpolation", and 1994; Neal 1996, "Bayesian learning
    for neural networks"; Tipping 2001, "Sparse Bayesian learning and the relevance vector
    machine", eqs. 12-13, 16-18). With ``Sigma = (J^T J / sigma^2 + A)^-1`` and
    ``mu = Sigma J^T z / sigma^2``, the evidence is maximized by iterating

        gamma_j = 1 - alpha_k Sigma_jj,   alpha_k <- sum_{j in k} gamma_j / sum_{j in k} mu_j^2,
        sigma^2 <- ||z - J mu||^2 / (n - sum_j gamma_j),

    pruning a harmonic when its precision exceeds ``prune`` times the data precision of its
    coefficients (mean of ``(J^T J)_jj / sigma^2``): its posterior mean is then below 1e-6 of
    its least-squares value, and the harmonic is held at zero. Only ``J^T J``, ``J^T e*`` and
    ``e*^T e*`` are needed; each iteration is one Cholesky factorization of the active block.

    Parameters
    ----------
    gram, gradient, sse, theta
        J^T J (p, p), J^T e* (p,), e*^T e* and theta* (p,) with p = 3 (2K + 1).
    precision : array_like (K + 1,)
        Starting alpha_k (e.g. the kernel's: ``1 / (sf^2 prior_variance)``); ``inf`` = pruned.
    noise_variance : float
        Starting sigma^2.
    n : int
        Number of observations (3 N).
    """
    G = np.asarray(gram, dtype=np.float64)
    b0 = np.asarray(gradient, dtype=np.float64).ravel()
    th = np.asarray(theta, dtype=np.float64).ravel()
    p = G.shape[0]
    K = (p // 3 - 1) // 2
    if 3 * (2 * K + 1) != p or b0.size != p or th.size != p:
        raise ValueError("gram, gradient and theta do not describe harmonics 1..K")
    grp = _harmonic_groups(K)
    alpha = np.array(precision, dtype=np.float64)
    if alpha.shape != (K + 1,):
        raise ValueError("precision must have one entry per harmonic 0..K")
    pruned = ~np.isfinite(alpha)
    s2 = float(noise_variance)
    Jtz = b0 + G @ th
    dG = np.diag(G).copy()
    counts = np.bincount(grp, minlength=K + 1).astype(float)
    mu = np.zeros(p)
    gam = np.zeros(K + 1)
    converged = False
    it = 0
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(int(max_iterations)):
            it += 1
            act = ~pruned[grp]
            ia = np.nonzero(act)[0]
            a_j = alpha[grp[ia]]
            H = G[np.ix_(ia, ia)] / s2
            H[np.diag_indices_from(H)] += a_j
            try:
                L = scipy.linalg.cholesky(H, lower=True, check_finite=False)
            except np.linalg.LinAlgError:
                break
            mu_a = scipy.linalg.cho_solve((L, True), Jtz[ia] / s2, check_finite=False)
            Li = scipy.linalg.solve_triangular(L, np.eye(ia.size), lower=True, check_finite=False)
            diag_sigma = np.einsum("ij,ij->j", Li, Li)
            mu = np.zeros(p)
            mu[ia] = mu_a
            g_j = np.zeros(p)
            g_j[ia] = np.clip(1.0 - a_j * diag_sigma, 0.0, 1.0)
            gam = np.bincount(grp, weights=g_j, minlength=K + 1)
            m2 = np.bincount(grp, weights=mu**2, minlength=K + 1)
            data_prec = np.bincount(grp, weights=dG, minlength=K + 1) / counts / s2
            new = np.where(pruned, np.inf, gam / np.maximum(m2, 1e-300))
            newly = ~pruned & (new > prune * np.maximum(data_prec, 1e-300))
            delta = mu - th
            R = sse - 2.0 * float(delta @ b0) + float(delta @ (G @ delta))
            if update_noise:
                s2 = max(R, 1e-300) / max(n - float(gam.sum()), 1.0)
            # settled when the precisions of the harmonics the data inform (gamma_k > 1e-2)
            # stop moving; the others only approach their pruning threshold
            keep = ~pruned & ~newly & (gam > 1e-2)
            change = float(np.max(np.abs(np.log(new[keep] / alpha[keep])))) if keep.any() else 0.0
            alpha = new
            alpha[newly] = np.inf
            pruned = pruned | newly
            if change < tol and not newly.any():
                converged = True
                break
    return ARDSpectrum(alpha, pruned, s2, gam, mu, it, converged)


# ================================================================================================
# The solver
# ================================================================================================


@dataclass(frozen=True)
class KernelSEMResult:
    """Outcome of :func:`solve_kernel_sem`.

    Attributes
    ----------
    flux : FluxModel
        The identified flux as its exact Fourier equivalent (harmonics 1..K): usable by
        :func:`hallcal.sensor.lut.build_lut`, the artifact and the C export.
    basis : KernelBasis
        The kernel basis with the chosen lengthscale and sf.
    weights : ndarray (3, m)
        Kernel weights w with ``g_h(y) = sum_j w_hj k(y, y_j)`` (equal to ``flux`` up to the
        truncated modes, see :meth:`KernelBasis.truncation`).
    lengthscale, sf : float
        Chosen hyperparameters.
    penalty : float
        rho = sigma^2 / sf^2: the cost is ``J(theta) + rho sum_h ||g_h||^2_{H(k_1)}``.
    noise_variance : float
        sigma^2 from the criterion (per Hall channel).
    harmonics : int
        K, the highest harmonic kept.
    criterion : str
        "evidence" or "gcv".
    criterion_values : list of CriterionPoint
        Every lengthscale tried in the last hyperparameter round, sorted by l.
    rounds : list of CriterionPoint
        The chosen point of every hyperparameter round (the first at the f_init angle).
    lengthscale_range : (float, float)
        Search range of l (equal bounds when l was given).
    interior : bool
        Whether the chosen l lies strictly inside the search range (always True when given).
    settled : bool
        Whether the last criterion evaluation, at the final solution, confirmed the
        hyperparameters the solution was computed with (l within 5 %, rho within a factor 2, no
        further harmonics needed).
    sem : SEMResult
        The final regularized SEM (theta, costs, covariance sigma^2 (J^T J + R)^-1, d_sim, y0_sim).
    status : str
        The SEM status ("converged", "max_iterations", "time_budget", "stalled", "diverged").
    solve_time : float
        Wall time [s] of the whole procedure.
    gauss_newton_systems : int
        Number of structured Gauss-Newton systems formed (the dominant cost).
    spectrum : str
        "bessel" (the squared-exponential kernel's spectrum) or "ard" (learned per harmonic).
    prior_variance : ndarray (K + 1,)
        Prior variance of each Fourier coefficient of harmonic k = 0..K that the solution was
        computed with (``sf^2 prior_variance`` of the kernel, or ``1 / alpha_k`` learned by ARD;
        0 for pruned harmonics).
    ard : ARDSpectrum or None
        The last evidence fixed point (``spectrum="ard"``).
    ard_rounds : int
        Number of ARD re-solves.
    """

    flux: FluxModel
    basis: KernelBasis
    weights: NDArray[np.float64] = field(repr=False)
    lengthscale: float
    sf: float
    penalty: float
    noise_variance: float
    harmonics: int
    criterion: str
    criterion_values: list[CriterionPoint] = field(repr=False)
    rounds: list[CriterionPoint] = field(repr=False)
    lengthscale_range: tuple[float, float]
    interior: bool
    settled: bool
    sem: SEMResult = field(repr=False)
    status: str
    solve_time: float
    gauss_newton_systems: int
    spectrum: str = "bessel"
    prior_variance: NDArray[np.float64] | None = field(default=None, repr=False)
    ard: ARDSpectrum | None = field(default=None, repr=False)
    ard_rounds: int = 0


def _regression_at_angle(
    y: NDArray, d: NDArray, K: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Gram (2K+1)^2, B^T d (2K+1, 3) and d^T d of the regression of d on beta(y)."""
    W = np.ascontiguousarray(np.column_stack([np.ones(y.size), d]))
    C, S = _moments(np.ascontiguousarray(y), W, 2 * K)
    M = _gram_from_moments(C[0], S[0], K)
    Btd = np.empty((2 * K + 1, 3))
    k = np.arange(1, K + 1)
    Btd[0] = C[1:, 0]
    Btd[1::2] = S[1:, k].T
    Btd[2::2] = C[1:, k].T
    return M, Btd, float(np.sum(d * d))


def _auto_range(points: int) -> tuple[float, float]:
    """Default search range of l.

    From the l at which the kernel spectrum at the grid's Nyquist harmonic m / 2 is 1e-12 of its
    peak (a shorter l would alias on the m-point grid, and the kernel model would no longer be a
    Fourier model with independent harmonics) up to max(1, 4 lo) rad.
    """
    half = points // 2

    def excess(l: float) -> float:
        a = 1.0 / l**2
        ratio = max(float(scipy.special.ive(half, a)), 1e-300) / float(scipy.special.ive(0, a))
        return math.log(ratio) - math.log(1e-12)

    lo = scipy.optimize.brentq(excess, 1e-3, 10.0) if excess(1e-3) > 0 > excess(10.0) else 0.02
    return float(lo), float(max(1.0, 4.0 * lo))


def solve_kernel_sem(
    loop: ClosedLoop,
    r: ArrayLike,
    d: ArrayLike,
    *,
    points: int = 400,
    lengthscale: float | Literal["auto"] = "auto",
    lengthscale_range: tuple[float, float] | None = None,
    criterion: Literal["evidence", "gcv"] = "evidence",
    y: ArrayLike | None = None,
    max_iterations: int = 30,
    tol: float = 1e-2,
    truncation_tol: float = 1e-2,
    max_harmonics: int | None = None,
    initial_lengthscale: float = 0.1,
    rounds: int = 3,
    time_budget: float = 300.0,
    chunk: int = 4096,
    stride: int = 4,
    spectrum: Literal["auto", "ard", "bessel"] = "auto",
    ard_rounds: int = 2,
) -> KernelSEMResult:
    """SEM (problem) with the periodic-kernel flux model of the experiment section, fast.

    Procedure (every step exact for the kernel model up to the documented truncation):

    1. Start, at the f_init angle: regress d on the kernel's Fourier modes at ``y`` (the
       recorded f_init output; linear, Gram matrix from trigonometric moments) with
       ``l = initial_lengthscale`` (or the given l) and rho by the criterion; the MAP estimate is
       the start. (l is not chosen here: as a function of y the data are ``g(y + eta(y))``, whose
       spectrum the f_init error eta broadens, with the tangential noise absorbed by f_init.)
    2. Keep the harmonics 1..K whose prior variance is not negligible relative to the noise
       (:meth:`KernelBasis.truncation`) and minimize ``J(theta) + rho ||g||^2_H`` by
       Levenberg-Marquardt on the structured Gauss-Newton system (:func:`fourier_gauss_newton`).
    3. Re-choose l and rho at the SEM solution from its exact Gauss-Newton system (the
       linearization of the closed loop, :func:`select_hyperparameters`); when they moved (l by
       more than 5 %, rho by more than a factor 2, or K changed), re-solve from the current
       point with the new prior. Up to ``rounds`` solves; the result reports the
       hyperparameters the returned solution was computed with.
    4. With ``spectrum="ard"`` (the default when l is chosen, ``lengthscale="auto"``): learn one
       prior variance per harmonic by the evidence of the linearized model at the solution
       (:func:`ard_spectrum`, started from the kernel's spectrum sf^2 2 s_k), re-solve with the
       learned ridge ``sigma^2 alpha_k``, and repeat at the new solution, up to ``ard_rounds``
       re-solves; a final fixed point checks that the solution is the MAP estimate under its
       spectrum (``settled``).

    Measured on the experiment-shaped bench (``benchmarks/bench_kernel.py``): 160 000 samples,
    m = 400, about 15-20 s on two cores with the Bessel spectrum, 20-25 s with ARD; the
    criterion picks l ~ 0.07 rad (K ~ 85 harmonics) with an interior minimum.

    Parameters
    ----------
    loop : ClosedLoop
        Plant model (BLA or known G), controller and the f_init of the experiment.
    r : array_like (N,)
        Recorded reference [rad].
    d : array_like (N, 3)
        Recorded Hall signals.
    points : int, keyword-only
        m, kernel centres on [0, 2 pi) (the paper: 400).
    lengthscale : float or "auto"
        Fixed l, or chosen by the criterion within ``lengthscale_range`` (default: from the
        shortest l the m-point grid resolves, see :func:`_auto_range`, to max(1, 4 lo) rad).
    criterion : {"evidence", "gcv"}
        Marginal likelihood (default) or generalized cross-validation.
    y : array_like (N,), optional
        Recorded f_init output; default f_init(d).
    max_iterations : int
        Levenberg-Marquardt iterations per round.
    tol : float
        Convergence when the Gauss-Newton decrement is below ``tol sigma^2``.
    truncation_tol : float
        Modes with prior standard deviation below ``truncation_tol`` sigma are dropped.
    max_harmonics : int, optional
        Upper bound on K (speed); default ``(m - 1) // 2``.
    rounds : int
        Maximum hyperparameter rounds at SEM solutions.
    time_budget : float
        Wall-time budget [s]; Levenberg-Marquardt stops (status "time_budget") when exceeded.
    chunk : int
        Samples per chunk of the Gram accumulation.
    stride : int
        Gauss-Newton Hessian of the iterations from every stride-th sample (see
        :func:`fourier_gauss_newton`); the system at each solution, used by the criterion and the
        covariance, is exact.
    spectrum : {"auto", "ard", "bessel"}
        Prior spectrum of the final solution: learned per harmonic ("ard") or the squared-
        exponential kernel's own ("bessel"). "auto": "ard" when ``lengthscale="auto"``, else
        "bessel".
    ard_rounds : int
        Maximum re-solves with a learned spectrum.

    Returns
    -------
    KernelSEMResult
    """
    t_start = time.perf_counter()
    deadline = t_start + float(time_budget)
    r = np.ascontiguousarray(r, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    N = r.size
    if d.shape != (N, 3):
        raise ValueError("d must have shape (N, 3) with N = len(r)")
    if criterion not in ("evidence", "gcv"):
        raise ValueError('criterion must be "evidence" or "gcv"')
    if spectrum not in ("auto", "ard", "bessel"):
        raise ValueError('spectrum must be "auto", "ard" or "bessel"')
    use_ard = spectrum == "ard" or (spectrum == "auto" and lengthscale == "auto")
    m = int(points)
    if m < 8:
        raise ValueError("points must be >= 8")
    cap = (m - 1) // 2 if max_harmonics is None else max(1, min(int(max_harmonics), (m - 1) // 2))
    if lengthscale == "auto":
        rng = _auto_range(m) if lengthscale_range is None else tuple(map(float, lengthscale_range))
        lsel: float | tuple[float, float] = (rng[0], rng[1])
    else:
        lf = float(lengthscale)
        if not lf > 0:
            raise ValueError('lengthscale must be > 0 or "auto"')
        rng = (lf, lf)
        lsel = lf
    yy = (
        f_init(d, loop.pole_pairs, projection=loop.projection, offset=loop.offset)
        if y is None
        else np.ascontiguousarray(y, dtype=np.float64)
    )
    n_obs = 3 * N

    # Start: regression at the f_init angle with l0; the criterion there only sets rho.
    l0 = (
        min(max(float(initial_lengthscale), rng[0]), rng[1])
        if lengthscale == "auto"
        else float(lengthscale)
    )
    k0 = min(cap, KernelBasis(m, l0).exact_harmonics(1e-15))
    M, Btd, dd = _regression_at_angle(yy, d, k0)
    best, tried = select_hyperparameters(
        M, Btd, dd, np.zeros_like(Btd), n=n_obs, points=m, lengthscale=l0, criterion=criterion
    )
    history_pts = [best]
    K = min(cap, KernelBasis(m, l0, best.sf).truncation(best.noise_variance, tol=truncation_tol))
    v = KernelBasis(m, l0).prior_variance(K)
    with threadpool_limits(limits=1, user_api="blas"):
        th0 = scipy.linalg.solve(
            M[: 2 * K + 1, : 2 * K + 1] + best.penalty * np.diag(1.0 / v),
            Btd[: 2 * K + 1],
            assume_a="pos",
        )
    theta = np.ascontiguousarray(th0.T)
    theta0 = theta.copy()

    systems = 0
    cost_history: list[float] = []
    iterations = 0
    status = "max_iterations"
    settled = False
    hp = best  # the hyperparameters the current theta is solved with
    system: GaussNewtonSystem | None = None
    for rnd in range(max(1, int(rounds))):
        ridge = hp.penalty * KernelBasis(m, hp.lengthscale).ridge_weights(K)
        out = _regularized_lm(
            loop, r, d, theta, ridge,
            max_iterations=max_iterations, tol=tol, noise_variance=hp.noise_variance,
            deadline=deadline, system=system, chunk=chunk, stride=stride,
        )  # fmt: skip
        systems += out.iterations + (0 if system is not None else 1)
        iterations += out.iterations
        cost_history.extend(out.history if not cost_history else out.history[1:])
        theta, status, system = out.theta, out.status, out.system
        if status == "diverged":
            break
        # The exact Gauss-Newton system at the solution: the linearization for the criterion.
        if stride != 1:
            system = fourier_gauss_newton(loop, theta, r, d, chunk=chunk)
            systems += 1
        if status == "time_budget":
            break
        sel, tried = select_hyperparameters(
            system.gram, system.gradient, system.sse, theta.ravel(),
            n=n_obs, points=m, lengthscale=lsel, criterion=criterion,
        )  # fmt: skip
        history_pts.append(sel)
        K_new = min(
            cap,
            KernelBasis(m, sel.lengthscale, sel.sf).truncation(
                sel.noise_variance, tol=truncation_tol
            ),
        )
        moved = (
            abs(math.log(sel.lengthscale / hp.lengthscale)) > 0.05
            or abs(math.log(sel.penalty / hp.penalty)) > math.log(2.0)
            or K_new > K
        )
        if not moved:
            settled = True
            hp = CriterionPoint(
                hp.lengthscale, hp.penalty, hp.value, sel.noise_variance,
                math.sqrt(sel.noise_variance / hp.penalty), hp.dof,
            )  # fmt: skip
            break
        if rnd == max(1, int(rounds)) - 1 or time.perf_counter() > deadline:
            break  # keep the solved-for hyperparameters; the last selection is in `rounds`
        hp = sel
        if K_new != K:  # pad with zeros, or drop modes the new prior makes negligible
            resized = np.zeros((3, 2 * K_new + 1))
            keep = 2 * min(K, K_new) + 1
            resized[:, :keep] = theta[:, :keep]
            theta, K, system = resized, K_new, None
    assert system is not None
    ridge = hp.penalty * KernelBasis(m, hp.lengthscale).ridge_weights(K)
    noise_variance = hp.noise_variance
    harm0 = np.r_[0, np.arange(2, 2 * K + 1, 2)]  # one coefficient per harmonic 0..K
    prior_var = hp.sf**2 * KernelBasis(m, hp.lengthscale).prior_variance(K)[harm0]
    ard: ARDSpectrum | None = None
    n_ard = 0
    if use_ard and status not in ("diverged", "time_budget"):
        # Learn the spectrum: one prior variance per harmonic by the evidence of the linearized
        # model at the SEM solution, started from the kernel's spectrum; re-solve with it.
        grp = _harmonic_groups(K)
        alpha = 1.0 / np.maximum(prior_var, 1e-300)
        s2 = hp.noise_variance
        settled = False
        n_rounds = max(1, int(ard_rounds))
        for rnd in range(n_rounds + 1):
            fixed = ard_spectrum(
                system.gram, system.gradient, system.sse, theta.ravel(), alpha, s2, n=n_obs
            )
            new_ridge = fixed.noise_variance * fixed.precision[grp]
            off = ~np.isfinite(new_ridge)  # pruned: held at zero by a ridge dominating the data
            new_ridge[off] = 1e8 * np.maximum(np.diag(system.gram)[off], 1.0)
            if rnd == n_rounds:  # rounds used up: only check that the solution is the MAP
                check = _regularized_lm(
                    loop, r, d, theta, new_ridge,
                    max_iterations=0, tol=tol, noise_variance=fixed.noise_variance,
                    deadline=deadline, system=system, chunk=chunk, stride=stride,
                )  # fmt: skip
                if check.status == "converged":
                    settled = True
                    ard, alpha, s2, ridge = fixed, fixed.precision, fixed.noise_variance, new_ridge
                break
            ard, alpha, s2, ridge = fixed, fixed.precision, fixed.noise_variance, new_ridge
            out = _regularized_lm(
                loop, r, d, theta, ridge,
                max_iterations=max_iterations, tol=tol, noise_variance=s2,
                deadline=deadline, system=system, chunk=chunk, stride=stride,
            )  # fmt: skip
            n_ard += 1
            systems += out.iterations
            iterations += out.iterations
            cost_history.extend(out.history[1:])
            theta, status, system = out.theta, out.status, out.system
            if status == "diverged":
                break
            if out.iterations == 0:  # already the MAP estimate under the learned spectrum
                settled = True
                break
            if stride != 1:
                system = fourier_gauss_newton(loop, theta, r, d, chunk=chunk)
                systems += 1
            if status == "time_budget" or time.perf_counter() > deadline:
                break
        noise_variance = s2
        prior_var = np.where(np.isfinite(alpha), 1.0 / alpha, 0.0)
    kb = KernelBasis(m, hp.lengthscale, hp.sf)
    fourier = FluxModel(kb.fourier_basis(K), theta)
    with threadpool_limits(limits=1, user_api="blas"):
        try:
            cov = noise_variance * np.linalg.inv(system.gram + np.diag(ridge))
        except np.linalg.LinAlgError:
            cov = np.full((theta.size, theta.size), np.nan)
    th0 = np.zeros_like(theta)
    th0[:, : theta0.shape[1]] = theta0[:, : theta.shape[1]]
    sem = SEMResult(
        flux=fourier,
        theta0=th0,
        cost_history=np.asarray(cost_history if cost_history else [math.inf]),
        iterations=iterations,
        status=status,
        solve_time=time.perf_counter() - t_start,
        noise_variance=noise_variance,
        covariance=cov,
        n_samples=N,
        d_sim=system.d,
        y0_sim=system.y0,
    )
    ls_tried = [c.lengthscale for c in tried]
    interior = lengthscale != "auto" or (min(ls_tried) < hp.lengthscale < max(ls_tried))
    return KernelSEMResult(
        flux=fourier,
        basis=kb,
        weights=kb.from_fourier(fourier),
        lengthscale=hp.lengthscale,
        sf=hp.sf,
        penalty=hp.penalty,
        noise_variance=noise_variance,
        harmonics=K,
        criterion=criterion,
        criterion_values=tried,
        rounds=history_pts,
        lengthscale_range=(float(rng[0]), float(rng[1])),
        interior=bool(interior),
        settled=bool(settled),
        sem=sem,
        status=status,
        solve_time=time.perf_counter() - t_start,
        gauss_newton_systems=systems,
        spectrum="ard" if ard is not None else "bessel",
        prior_variance=prior_var,
        ard=ard,
        ard_rounds=n_ard,
    )
