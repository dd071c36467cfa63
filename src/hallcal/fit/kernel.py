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
  variance cannot carry signal above the noise and are dropped.

Hyperparameters. ``sf`` only scales the weights (``g`` is unchanged by ``sf -> c sf``,
``w -> w / c^2``), so it cannot be identified from the fit alone; the paper made it a design
variable of the unregularized cost, which is then flat in it. Here the kernel model is estimated
as kernel ridge regression / Gaussian-process MAP through the closed loop:

    min_theta  J(theta) + rho * sum_h ||g_h||^2_{H(k_1)},      rho = sigma^2 / sf^2,

with ``k_1`` the kernel for ``sf = 1`` and sigma^2 the Hall noise variance. ``l`` and ``rho``
(equivalently ``sf``, with sigma^2 profiled out) are chosen by the marginal likelihood (type-II
maximum likelihood; Rasmussen & Williams 2006, sec. 5.4.1; MacKay 1992, "Bayesian
interpolation") of a linear model ``z = J theta + v`` (:func:`select_hyperparameters`; the
solver uses the regression of d at the un-warped angle, which is exact), or alternatively by
generalized cross-validation (Golub, Heath & Wahba 1979; Wahba 1990, ch. 4; Rasmussen & Williams
2006, sec. 5.3). Both criteria need only ``J^T J``, ``J^T e`` and ``e^T e``.

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

Learned spectrum and band (``spectrum="ard"``, the default with ``lengthscale="auto"``). With
the kernel's own (Bessel) spectrum the model stayed 2.5-5.3x above the Hall noise floor on the
experiment-shaped bench (``benchmarks/bench_kernel.txt``): the excess is a slow warp of the angle,
``g(y0 + w(y0))`` with w of a few cycles per revolution, i.e. coefficients at the sidebands
``k n_m +- j``, which the loop reveals only through its small low-frequency sensitivity. A
squared-exponential spectrum never vanishes, so the sidebands just above the flux's highest
harmonic, which alone pin such a warp, keep a prior variance and the warp floats; learning one
variance per harmonic by the evidence at a SEM solution (automatic relevance determination,
MacKay 1992, Tipping 2001), as the previous version did, inherits the warp of the start and kept
it on the rich-shape bench (every magnet different, truth on harmonics 1..55: 1.4-3.7x the floor).
:func:`solve_kernel_sem` therefore (i) limits the model to the flux's band, found from f_init's
view without the loop (:mod:`hallcal.fit.warp`), which also gives an un-warped start, and (ii)
learns the spectrum within the band from the evidence of the data's shape only (the normal-plane
part of the Gauss-Newton system, free of motion errors, :mod:`hallcal.fit.evidence`), started
from the kernel's. The prior is still a stationary periodic kernel (any non-negative spectrum is
one, by Bochner's theorem on the circle); the identified flux is represented exactly by weights on
the paper's m kernel centres (:meth:`KernelBasis.from_fourier`). Measured: 1.01x the floor on the
experiment-shaped bench (tests/test_kernel.py), 1.03-1.07x on the rich-shape benches
(``benchmarks/bench_rich.txt``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.special
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.fit.adequacy import estimate_noise_variance
from hallcal.fit.evidence import HarmonicRelevance, harmonic_relevance
from hallcal.fit.gauss_newton import (
    GaussNewtonSystem,
    regression_normal_equations,
)
from hallcal.fit.order import WORK_BUDGET
from hallcal.fit.sem import SEMResult, SEMStatus, checked_record, solve_sem
from hallcal.fit.warp import BandEdge, band_edge
from hallcal.limits import one_blas_thread
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.reconstruction import f_init
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "CriterionPoint",
    "GaussNewtonSystem",
    "KernelBasis",
    "KernelSEMResult",
    "select_hyperparameters",
    "solve_kernel_sem",
]


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

    # -- spectrum ----------------------------------------------------------------------------
    def spectrum(self, kmax: int) -> NDArray[np.float64]:
        """Fourier coefficients s_k = sf^2 ive(k, 1/l^2) of k(t), k = 0..kmax."""
        k = np.arange(int(kmax) + 1, dtype=np.float64)
        return self.sf**2 * scipy.special.ive(k, self.inverse_square_lengthscale)

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

    # -- spectral maps -----------------------------------------------------------------------
    def from_fourier(self, flux: FluxModel) -> NDArray[np.float64]:
        """Kernel weights w (3, m) whose kernel model equals a Fourier model with harmonics < m/2.

        The inverse of the spectral map (module docstring) on band-limited models:
        ``W_k = G_k / s_k`` for ``|k| <= K`` and zero elsewhere (the minimum-RKHS-norm
        representer). Exact up to the aliases of the kept harmonics, relative size
        ``s_{m-K} / s_K``.
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
    with one_blas_thread():
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
        Marginal likelihood or generalized cross-validation.
    grid : int, keyword-only
        Lengthscales on the log-spaced search grid.
    refine : int, keyword-only
        Bounded-Brent steps after the grid.

    Returns
    -------
    best : CriterionPoint
    tried : list of CriterionPoint
        Every lengthscale evaluated, sorted by l.
    """
    if criterion not in ("evidence", "gcv"):
        raise ValueError('criterion must be "evidence" or "gcv"')
    G, b, th, K = _regression_blocks(gram, gradient, theta)
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
    _search_lengthscale(at, lo, hi, grid=int(grid), refine=refine)
    tried = sorted(cache.values(), key=lambda c: c.lengthscale)
    best = min(tried, key=lambda c: c.value)
    return best, tried


def _regression_blocks(
    gram: ArrayLike, gradient: ArrayLike, theta: ArrayLike
) -> tuple[NDArray, NDArray, NDArray, int]:
    """J^T J, J^T e* and theta* with one column per sensor block, and the band K they describe."""
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
    return G, b, th, K


def _search_lengthscale(
    at: Callable[[float], CriterionPoint], lo: float, hi: float, *, grid: int, refine: int
) -> None:
    """Evaluate ``at`` on a log-spaced grid of l in [lo, hi], then ``refine`` bounded-Brent steps
    on log l around the best grid value (the evaluations are what ``at`` records)."""
    ls = np.exp(np.linspace(math.log(lo), math.log(hi), grid))
    vals = [at(float(l)).value for l in ls]
    i = int(np.argmin(vals))
    if refine > 0 and 0 < i < ls.size - 1:
        scipy.optimize.minimize_scalar(
            lambda x: at(float(math.exp(x))).value,
            bounds=(math.log(ls[i - 1]), math.log(ls[i + 1])),
            method="bounded",
            options={"maxiter": int(refine), "xatol": 0.01},
        )


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
        aliases of the kept harmonics, relative size ``s_{m-K} / s_K``).
    lengthscale, sf : float
        Chosen hyperparameters of the kernel (the reference spectrum).
    penalty : float
        rho = sigma^2 / sf^2 of the kernel's own spectrum.
    noise_variance : float
        sigma^2 (per Hall channel) the solution was computed with.
    harmonics : int
        K: the band 1..K of the model (:func:`hallcal.fit.warp.band_edge`).
    criterion : str
        "evidence" or "gcv" (the kernel's hyperparameters).
    criterion_values : list of CriterionPoint
        Every lengthscale tried, sorted by l.
    lengthscale_range : (float, float)
        Search range of l (equal bounds when l was given).
    interior : bool
        Whether the chosen l lies strictly inside the search range (always True when given).
    settled : bool
        Whether the learned spectrum, re-estimated at the final SEM solution, confirmed the one
        the solution was computed with (the same strongly supported harmonics, their prior
        variances within a factor 2: :func:`_settled`), or the kernel's own spectrum was used.
    sem : SEMResult
        The final regularized SEM (theta on the kept harmonics, costs, covariance
        sigma^2 (J^T J + R)^-1, d_sim, y0_sim).
    status : SEMStatus
        The final SEM's status (MAX_ITERATIONS when its iteration budget ran out).
    solve_time : float
        Wall time [s] of the whole procedure (a diagnostic only: nothing is decided on it).
    spectrum : str
        "bessel" (the squared-exponential kernel's spectrum) or "ard" (learned per harmonic).
    prior_variance : ndarray (K + 1,)
        Prior variance of each Fourier coefficient of harmonic k = 0..K that the solution was
        computed with (``sf^2`` times the kernel's, or learned; 0 for dropped harmonics).
    edge : BandEdge
        The band and the un-warped start.
    relevance : HarmonicRelevance or None
        The learned spectrum (``spectrum="ard"``).
    ard_rounds : int
        SEM solves with a learned spectrum.
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
    lengthscale_range: tuple[float, float]
    interior: bool
    settled: bool
    sem: SEMResult = field(repr=False)
    status: SEMStatus
    solve_time: float
    spectrum: str
    prior_variance: NDArray[np.float64] = field(repr=False)
    edge: BandEdge = field(repr=False)
    relevance: HarmonicRelevance | None = field(default=None, repr=False)
    ard_rounds: int = 0


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


@dataclass(frozen=True)
class _Options:
    """The checked options of :func:`solve_kernel_sem`."""

    points: int
    cap: int
    lengthscale: float | tuple[float, float]
    lengthscale_range: tuple[float, float]
    criterion: Literal["evidence", "gcv"]
    use_ard: bool
    max_iterations: int
    tol: float
    stride: int | None
    ard_rounds: int
    work_budget: float

    @property
    def lengthscale_fixed(self) -> bool:
        """l was given (not chosen by the criterion within a range)."""
        return not isinstance(self.lengthscale, tuple)


def _options(
    points, lengthscale, lengthscale_range, criterion, spectrum, max_harmonics, max_iterations,
    tol, stride, ard_rounds, work_budget,
) -> _Options:  # fmt: skip
    if criterion not in ("evidence", "gcv"):
        raise ValueError('criterion must be "evidence" or "gcv"')
    if spectrum not in ("auto", "ard", "bessel"):
        raise ValueError('spectrum must be "auto", "ard" or "bessel"')
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
        rng, lsel = (lf, lf), lf
    use_ard = spectrum == "ard" or (spectrum == "auto" and lengthscale == "auto")
    return _Options(
        m, cap, lsel, (float(rng[0]), float(rng[1])), criterion, use_ard, int(max_iterations),
        float(tol), stride, max(1, int(ard_rounds)), float(work_budget),
    )  # fmt: skip


def _kernel_hyperparameters(
    x: NDArray, d: NDArray, K: int, o: _Options
) -> tuple[CriterionPoint, list[CriterionPoint]]:
    """l and rho of the kernel by the criterion on the regression of d at the un-warped angle.

    At the band's un-warped angle x (:mod:`hallcal.fit.warp`) the flux is a linear regression
    ``d ~ beta(x) theta``, whose marginal likelihood (or GCV) :func:`select_hyperparameters`
    evaluates exactly; no loop simulation is needed.
    """
    M, Btd, dd = regression_normal_equations(x, d, np.arange(1, K + 1))
    return select_hyperparameters(
        M, Btd, dd, np.zeros_like(Btd), n=3 * x.size, points=o.points, lengthscale=o.lengthscale,
        criterion=o.criterion,
    )  # fmt: skip


def _bessel_variances(o: _Options, best: CriterionPoint, K: int) -> NDArray[np.float64]:
    """sf^2 times the kernel's prior variance of each harmonic 0..K (one value per harmonic)."""
    v = KernelBasis(o.points, best.lengthscale).prior_variance(K)
    return best.sf**2 * v[np.r_[0, np.arange(2, 2 * K + 1, 2)]]


def _map_sem(
    loop: ClosedLoop, r: NDArray, d: NDArray, start: FluxModel, variances: NDArray,
    noise_variance: float, o: _Options, work_left: float = math.inf,
) -> SEMResult:  # fmt: skip
    """``min J(theta) + sigma^2 sum_k |theta_k|^2 / v_k`` on the harmonics with v_k > 0, in at
    most the iterations that ``work_left`` (iterations x N p^2, :func:`_iteration_work`) pays
    for (at least one)."""
    K = variances.size - 1
    kept = tuple(k for k in range(1, K + 1) if variances[k] > 0)
    basis = FourierBasis(kept)
    v = np.r_[variances[0], np.repeat(variances[list(kept)], 2)]
    ridge = np.tile(noise_variance / np.maximum(v, 1e-300), 3)
    theta0 = np.zeros((3, basis.size))
    theta0[:, 0] = start.theta[:, 0]
    for i, h in enumerate(kept):
        js, jc = start.basis.index(h)
        theta0[:, [1 + 2 * i, 2 + 2 * i]] = start.theta[:, [js, jc]]
    its = min(o.max_iterations, max(1, int(work_left // _iteration_work(r.size, kept)) - 1))
    return solve_sem(loop, r, d, basis, theta0=theta0, regularization=ridge,
                     max_iterations=its, tol=o.tol, stride=o.stride)  # fmt: skip


def _iteration_work(n_samples: int, harmonics: tuple[int, ...]) -> float:
    """Work of one Gauss-Newton iteration, N p^2 (as :data:`hallcal.fit.order.WORK_BUDGET`)."""
    return float(n_samples) * float(3 * (2 * len(harmonics) + 1)) ** 2


def _sem_work(sem: SEMResult, n_samples: int) -> float:
    """Work a solve used: its iterations plus the exact system for the covariance."""
    return (sem.iterations + 1) * _iteration_work(n_samples, sem.flux.basis.harmonics)


def _on_band(flux: FluxModel, K: int) -> FluxModel:
    """The flux on harmonics 1..K (missing harmonics zero)."""
    basis = FourierBasis(tuple(range(1, K + 1)))
    theta = np.zeros((3, basis.size))
    theta[:, 0] = flux.theta[:, 0]
    for h in flux.basis.harmonics:
        js, jc = flux.basis.index(h)
        theta[:, [2 * h - 1, 2 * h]] = flux.theta[:, [js, jc]]
    return FluxModel(basis, theta)


def _settled(a: HarmonicRelevance, b: HarmonicRelevance, *, strong: float = 3.0) -> bool:
    """The same strongly supported harmonics, and their prior variances within a factor 2.

    Strong: an evidence gain above ``strong`` nats (a Bayes factor of 20, "strong" in Kass &
    Raftery 1995). Weaker groups are the evidence's verdict on chance content: they come and go
    between linearization points with prior variances near the coefficients' noise, too small to
    move the solution.
    """
    sa = {h for h, g in zip(a.harmonics, a.gain[1:], strict=True) if g > strong}
    sb = {h for h, g in zip(b.harmonics, b.gain[1:], strict=True) if g > strong}
    if sa != sb:
        return False
    idx = [0] + [1 + a.harmonics.index(h) for h in sorted(sa)]
    va, vb = a.prior_variance[idx], b.prior_variance[idx]
    both = (va > 0) & (vb > 0)
    return bool(np.all(np.abs(np.log(va[both] / vb[both])) <= math.log(2.0)))


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
    tol: float = 1e-6,
    max_harmonics: int | None = None,
    stride: int | None = None,
    spectrum: Literal["auto", "ard", "bessel"] = "auto",
    ard_rounds: int = 2,
    work_budget: float = WORK_BUDGET,
) -> KernelSEMResult:
    """SEM (problem) with the periodic-kernel flux model of the experiment section, fast.

    Procedure:

    1. **Band and start** (:func:`hallcal.fit.warp.band_edge`): the smallest band 1..K into
       which f_init's view of the flux un-warps, and the un-warped flux (no loop simulation).
       The kernel's spectrum never reaches exactly zero, and every harmonic above the flux's
       band lets a slow warp of the angle float (module docstring of
       :mod:`hallcal.fit.warp`): the model is therefore limited to the band, capped by the
       grid's Nyquist harmonic ``(m - 1) // 2`` and ``max_harmonics``.
    2. **Kernel hyperparameters** l and rho = sigma^2 / sf^2 by the marginal likelihood (or
       GCV) of the regression of d at the un-warped angle (:func:`select_hyperparameters`).
    3. **Spectrum.** ``spectrum="ard"`` (the default with ``lengthscale="auto"``): one prior
       variance per harmonic learned by the evidence of the data's shape, started from the
       kernel's ``sf^2 2 s_k`` (:func:`hallcal.fit.evidence.harmonic_relevance`: automatic
       relevance determination, MacKay 1992, Tipping 2001; any non-negative spectrum is a
       stationary periodic kernel by Bochner's theorem on the circle, the paper's squared-
       exponential kernel being its starting point); ``"bessel"``: the kernel's own.
    4. **MAP SEM** through the closed loop, ``J(theta) + sigma^2 sum_k |theta_k|^2 / v_k``
       (:func:`hallcal.fit.sem.solve_sem` with its structured Gauss-Newton system), from the
       un-warped start; with ARD the spectrum is learned again at the solution's simulated
       angle and the SEM repeated while it moves (``ard_rounds`` solves at most; ``settled``).

    Measured on the rich-shape bench (``benchmarks/bench_rich.txt``, 160 000 samples, m = 400):
    1.04-1.07x the noise floor on 10 of 10 runs, against 1.4-3.7x for the learned spectrum of
    the previous version, which started from the kernel's spectrum on all of 1..85 and let the
    warp float.

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
    lengthscale_range : (float, float), optional
        Search range (lo, hi) of l [rad] with ``lengthscale="auto"``; default as above.
    criterion : {"evidence", "gcv"}
        Marginal likelihood (default) or generalized cross-validation, for l and rho.
    y : array_like (N,), optional
        Recorded f_init output; default f_init(d).
    max_iterations : int
        Levenberg-Marquardt iterations per SEM solve (``[model] max_iterations``).
    tol : float
        SEM convergence (:func:`hallcal.fit.sem.solve_sem`).
    max_harmonics : int, optional
        Upper bound on K (speed); default ``(m - 1) // 2``.
    stride : int, optional
        Passed to :func:`hallcal.fit.sem.solve_sem`.
    spectrum : {"auto", "ard", "bessel"}
        Prior spectrum: learned per harmonic ("ard") or the squared-exponential kernel's own
        ("bessel"). "auto": "ard" when ``lengthscale="auto"``, else "bessel".
    ard_rounds : int
        Maximum SEM solves with a learned spectrum. With ``max_iterations`` and
        ``work_budget`` this bounds the work; there is no wall-clock budget, so that the result
        is the same at any machine load. A search stopped by it has ``settled`` False.
    work_budget : float
        Gauss-Newton work at most over the MAP SEM solves, in iterations times N p^2
        (:data:`hallcal.fit.order.WORK_BUDGET`; the first solve always makes one iteration).

    Returns
    -------
    KernelSEMResult
    """
    t_start = time.perf_counter()
    r, d = checked_record(r, d)
    o = _options(points, lengthscale, lengthscale_range, criterion, spectrum, max_harmonics,
                 max_iterations, tol, stride, ard_rounds, work_budget)  # fmt: skip
    band = _band_and_start(loop, d, y, o)  # 1
    best, tried = _kernel_hyperparameters(band.x, d, band.K, o)  # 2
    fit = _spectrum_and_map_sem(loop, r, d, band, _bessel_variances(o, best, band.K), o)  # 3-4
    return _kernel_result(best, tried, band, fit, o, time.perf_counter() - t_start)


@dataclass(frozen=True)
class _Band:
    """Step 1 of :func:`solve_kernel_sem`: the band 1..K, the un-warped angle and sigma^2."""

    edge: BandEdge
    x: NDArray[np.float64]  # f_init's output un-warped onto the band's angle
    noise_variance: float
    pole_pairs: int

    @property
    def K(self) -> int:
        return self.edge.edge


def _band_and_start(loop: ClosedLoop, d: NDArray, y: ArrayLike | None, o: _Options) -> _Band:
    """Step 1 of :func:`solve_kernel_sem`: band and start by :func:`hallcal.fit.warp.band_edge`.

    The smallest band into which f_init's view of the flux un-warps (no loop simulation), capped
    by the grid's Nyquist harmonic, ``max_harmonics`` and ``8 n_m``; sigma^2 is the model-free
    noise level of d (:func:`hallcal.fit.adequacy.estimate_noise_variance`).
    """
    yy = (
        f_init(d, loop.pole_pairs, projection=loop.projection, offset=loop.offset)
        if y is None
        else np.ascontiguousarray(y, dtype=np.float64)
    )
    n_m = int(loop.pole_pairs)
    noise = estimate_noise_variance(d)
    s2 = noise.variance if math.isfinite(noise.variance) and noise.variance > 0 else 1e-12
    edge = band_edge(yy, d, pole_pairs=n_m, noise_variance=s2,
                     max_edge=min(o.cap, 8 * n_m))  # fmt: skip
    return _Band(edge, edge.unwarp.parametrize(yy), s2, n_m)


@dataclass(frozen=True)
class _SpectrumFit:
    """Steps 3-4 of :func:`solve_kernel_sem`: the MAP SEM and the spectrum it was solved with."""

    sem: SEMResult
    variances: NDArray[np.float64]  # prior variance of each harmonic 0..K
    noise_variance: float
    relevance: HarmonicRelevance | None
    settled: bool
    rounds: int  # SEM solves


def _spectrum_and_map_sem(
    loop: ClosedLoop, r: NDArray, d: NDArray, band: _Band, variances: NDArray, o: _Options
) -> _SpectrumFit:
    """Steps 3-4 of :func:`solve_kernel_sem`: learn the spectrum, solve, learn it again.

    With ARD (MacKay 1992, Tipping 2001; :func:`hallcal.fit.evidence.harmonic_relevance`) the
    prior variance of every harmonic is learned from the kernel's ``variances`` at the un-warped
    angle, the MAP SEM solved, and the spectrum learned again at the solution's simulated angle,
    repeating while it moves (:func:`_settled`), at most ``ard_rounds`` solves. Without ARD one
    MAP SEM with the kernel's own spectrum.
    """
    s2, K, n_m = band.noise_variance, band.K, band.pole_pairs
    relevance: HarmonicRelevance | None = None
    settled = not o.use_ard
    if o.use_ard:
        relevance = harmonic_relevance(band.edge.flux, band.x, d, noise_variance=s2, keep=(n_m,),
                                       prior_variance=variances)  # fmt: skip
        variances, s2 = relevance.prior_variance, relevance.noise_variance
    sem = _map_sem(loop, r, d, band.edge.flux, variances, s2, o, o.work_budget)
    work = _sem_work(sem, r.size)
    rounds = 1
    while o.use_ard and relevance is not None:
        again = harmonic_relevance(_on_band(sem.flux, K), sem.y0_sim, d, noise_variance=s2,
                                   keep=(n_m,), prior_variance=variances)  # fmt: skip
        settled = _settled(again, relevance)
        unit = _iteration_work(r.size, sem.flux.basis.harmonics)
        if settled or rounds >= o.ard_rounds or work + 2.0 * unit > o.work_budget:
            break
        relevance, variances, s2 = again, again.prior_variance, again.noise_variance
        sem = _map_sem(loop, r, d, sem.flux, variances, s2, o, o.work_budget - work)
        work += _sem_work(sem, r.size)
        rounds += 1
    return _SpectrumFit(sem, variances, s2, relevance, settled, rounds)


def _kernel_result(
    best: CriterionPoint, tried: list[CriterionPoint], band: _Band, fit: _SpectrumFit,
    o: _Options, solve_time: float,
) -> KernelSEMResult:  # fmt: skip
    """The result of :func:`solve_kernel_sem`: the flux on the band 1..K and its kernel weights."""
    kb = KernelBasis(o.points, best.lengthscale, best.sf)
    fourier = _on_band(fit.sem.flux, band.K)
    ls_tried = [c.lengthscale for c in tried]
    interior = o.lengthscale_fixed or (min(ls_tried) < best.lengthscale < max(ls_tried))
    return KernelSEMResult(
        flux=fourier,
        basis=kb,
        weights=kb.from_fourier(fourier),
        lengthscale=best.lengthscale,
        sf=best.sf,
        penalty=best.penalty,
        noise_variance=fit.noise_variance,
        harmonics=band.K,
        criterion=o.criterion,
        criterion_values=tried,
        lengthscale_range=o.lengthscale_range,
        interior=bool(interior),
        settled=bool(fit.settled),
        sem=fit.sem,
        status=fit.sem.status,
        solve_time=solve_time,
        spectrum="ard" if o.use_ard else "bessel",
        prior_variance=np.asarray(fit.variances, dtype=np.float64),
        edge=band.edge,
        relevance=fit.relevance,
        ard_rounds=fit.rounds if o.use_ard else 0,
    )
