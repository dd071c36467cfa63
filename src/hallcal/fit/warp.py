"""Where the flux's harmonics stop, and its true parametrization, from f_init's view of the data.

Regressing the Hall signals on the f_init angle y (the paper's "harmonic content of the data",
section "Model structure") gives the flux curve as f_init sees it: ``d ~ gamma(y) =
g(F^-1(y))`` with ``F = f_init o g``. Along the same closed curve in R^3, only the
parametrization differs from the truth: gamma is g warped by the f_init error, and the warp
spreads the flux's harmonics far beyond its own band (on the rich-shape bench, flux harmonics
1..55, the view has content up to harmonic 275). Conversely, for a flux that is band-limited to
harmonics 1..E, there is exactly one warp w (up to the noise) that brings the view back into the
band: ``gamma(x + w(x))`` has no content above E. Each warp harmonic j moves content from every
flux harmonic h to h +- j, among them from the top harmonics to above E, so every w_j is pinned
(the view's coefficients have a noise of about ``sqrt(2 sigma^2 / N)``, 7e-6 on that bench, and
the top harmonic 55 at 4 % moves 1.1 of a warp amplitude to 56: w_j is pinned to about 0.01
mrad). With a band wider than the flux's, the warps of low order j (< E - edge) move no content
above E and are not determined: the table then carries whatever warp the start had. This is the
structure that makes closed-loop SEM hard on rotors whose magnets all differ: the loop reveals a
slow warp of the angle only through its small low-frequency sensitivity (DESIGN.md), and a model
one harmonic wider than the flux lets the warp float (measured: f_star 3.7x the noise floor with
harmonics 1..56 against 1.03x with 1..55, rich-shape bench, seed 3).

:func:`unwarp` finds the warp for a given band by Gauss-Newton on the content above it (an exact
resampling of the view on a grid, no loop simulation); :func:`band_edge` finds the smallest band
whose un-warped residual is consistent with the noise (chi-square test), by bisection. Both need
neither the plant nor the controller: the relation between y and the true angle is static, so
motion errors (torque disturbance, cogging, the loop's response to the noise) do not enter.
Static un-warping alone brings f_init's error on the rich-shape bench (29x the noise floor, seed 3,
f_init 5.9 mrad) to 1.03x; SEM started there converges in two iterations.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.fit.adequacy import chi2_isf_even
from hallcal.fit.gauss_newton import regression_normal_equations
from hallcal.limits import one_blas_thread
from hallcal.messages import Outcome
from hallcal.sensor.flux import FluxModel, FourierBasis

__all__ = [
    "BandEdge",
    "BandEdgeStatus",
    "EdgeTrial",
    "FInitView",
    "Unwarp",
    "UnwarpStatus",
    "band_edge",
    "f_init_view",
    "unwarp",
]


# ================================================================================================
# The view: d regressed on the f_init angle
# ================================================================================================


@dataclass(frozen=True)
class FInitView:
    """The flux curve as a Fourier series in the f_init angle y (least squares).

    Attributes
    ----------
    theta : ndarray (3, 2 L + 1)
        Coefficients on ``[1, sin 1y, cos 1y, ..., cos Ly]`` per sensor.
    coefficient_variance : float
        Mean noise variance of one coefficient, ``sigma^2 mean diag((B^T B)^-1)`` over the
        harmonics (about ``2 sigma^2 / N`` for whole revolutions).
    noise_variance : float
        sigma^2 used.
    """

    theta: NDArray[np.float64] = field(repr=False)
    coefficient_variance: float
    noise_variance: float

    @property
    def harmonics(self) -> int:
        """L."""
        return (self.theta.shape[1] - 1) // 2

    def amplitude(self) -> NDArray[np.float64]:
        """RMS over the sensors of each harmonic 1..L, ``sqrt(mean (s^2 + c^2) / 2)``."""
        th = self.theta
        return np.sqrt(np.mean(th[:, 1::2] ** 2 + th[:, 2::2] ** 2, axis=0) / 2.0)


def f_init_view(y: ArrayLike, d: ArrayLike, *, harmonics: int, noise_variance: float) -> FInitView:
    """Least-squares fit of d on the Fourier basis 1..L of the f_init angle y.

    Normal equations from trigonometric moments
    (:func:`hallcal.fit.gauss_newton.regression_normal_equations`), Cholesky solve.

    Parameters
    ----------
    y : array_like (N,)
        f_init angle recorded in the loop [rad].
    d : array_like (N, 3)
        Hall signals.
    harmonics : int, keyword-only
        L, the view's highest harmonic (>= 1).
    noise_variance : float, keyword-only
        Hall noise sigma^2, for the coefficient variance.

    Returns
    -------
    FInitView
        theta (3, 2 L + 1) and the coefficient variance.
    """
    L = int(harmonics)
    if L < 1:
        raise ValueError("harmonics must be >= 1")
    M, Btd, _ = regression_normal_equations(y, d, np.arange(1, L + 1))
    return _view_from_normal_equations(M, Btd, noise_variance)


def _view_from_normal_equations(M: NDArray, Btd: NDArray, noise_variance: float) -> FInitView:
    """:func:`f_init_view` from its normal equations on 1..L. Those of 1..L' < L are their
    leading ``2 L' + 1`` rows and columns (the same moments, bit for bit): a narrower view
    needs no second pass over the samples."""
    L = (M.shape[0] - 1) // 2
    with one_blas_thread():
        try:
            cf = scipy.linalg.cho_factor(M, check_finite=False)
            theta = scipy.linalg.cho_solve(cf, Btd, check_finite=False).T
            # diag(M^-1): the squared column norms of U^-1 (M = U^T U), p^3 / 3 work
            Ui, info = scipy.linalg.lapack.dtrtri(np.triu(cf[0]) if not cf[1] else
                                                  np.tril(cf[0]).T, lower=False)  # fmt: skip
            if info != 0:
                raise np.linalg.LinAlgError("singular normal equations")
            Minv_diag = np.sum(Ui * Ui, axis=1)
        except np.linalg.LinAlgError as exc:
            raise ValueError(
                f"the f_init angle does not cover enough of a revolution to resolve {L} harmonics"
            ) from exc
    cvar = float(noise_variance) * float(np.mean(Minv_diag[1:]))
    return FInitView(np.ascontiguousarray(theta), cvar, float(noise_variance))


# ================================================================================================
# Un-warping for a given band
# ================================================================================================


class UnwarpStatus(Outcome):
    """How :func:`unwarp` ended."""

    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"


@dataclass(frozen=True)
class Unwarp:
    """Outcome of :func:`unwarp`.

    Attributes
    ----------
    edge : int
        E: the model's harmonics are 1..E.
    warp : ndarray (2 J,)
        Coefficients of ``w(x) = sum_j a_j cos(j x) + b_j sin(j x)`` ([a_1..a_J, b_1..b_J]).
    flux : FluxModel
        ``gamma(x + w(x))`` on harmonics 1..E: the flux in the un-warped parametrization.
    residual : float
        Content of ``gamma(x + w(x))`` above E (harmonics E+1..L), sum of squared real
        coefficients over the sensors, in units of the view's coefficient variance: chi-square
        with about ``dof`` degrees of freedom when the band holds the flux.
    dof : int
        ``6 (L - E) - 2 J``.
    iterations : int
    status : UnwarpStatus
    """

    edge: int
    warp: NDArray[np.float64] = field(repr=False)
    flux: FluxModel = field(repr=False)
    residual: float
    dof: int
    iterations: int
    status: UnwarpStatus

    def warp_at(self, x: ArrayLike) -> NDArray[np.float64]:
        """w(x) [rad]."""
        xx = np.ascontiguousarray(np.atleast_1d(np.asarray(x, dtype=np.float64)))
        J = self.warp.size // 2
        return _series(xx, np.ascontiguousarray(self.warp[:J]), np.ascontiguousarray(self.warp[J:]))

    def parametrize(self, y: ArrayLike, *, iterations: int = 8) -> NDArray[np.float64]:
        """The un-warped angle x of samples at f_init angles y: ``x + w(x) = y``.

        Fixed-point iteration (a contraction while ``|w'| < 1``; 8 steps reach 1e-12 rad for
        ``|w'| < 0.03``) on w tabulated on 8 times the grid of its highest harmonic and
        interpolated linearly (error ``h^2 max|w''| / 8``, below 1e-8 rad for the warps met on
        the benches).

        Parameters
        ----------
        y : array_like (N,)
            f_init angles [rad].
        iterations : int, keyword-only
            Fixed-point steps.

        Returns
        -------
        ndarray (N,)
            x [rad], the flux model's angle for each sample.
        """
        yy = np.asarray(y, dtype=np.float64)
        J = self.warp.size // 2
        if J == 0:
            return yy.copy()
        M = 1 << int(math.ceil(math.log2(16 * J)))
        grid = TWO_PI * np.arange(M + 1) / M
        table = self.warp_at(grid)
        x = yy.copy()
        for _ in range(int(iterations)):
            x = yy - np.interp(np.mod(x, TWO_PI), grid, table)
        return x


@nb.njit(cache=True, nogil=True)
def _series(x, a, b):  # pragma: no cover - numba
    """sum_j a_j cos(j x) + b_j sin(j x) at every x (angle-addition recursion)."""
    out = np.empty(x.size)
    for i in range(x.size):
        c1 = math.cos(x[i])
        s1 = math.sin(x[i])
        c = 1.0
        s = 0.0
        acc = 0.0
        for j in range(a.size):
            c, s = c * c1 - s * s1, s * c1 + c * s1
            acc += a[j] * c + b[j] * s
        out[i] = acc
    return out


@nb.njit(cache=True, nogil=True)
def _curve(theta, x):  # pragma: no cover - numba
    """g(x) and g'(x), (M, 3), of a Fourier series on harmonics 1..L (angle-addition recursion)."""
    L = (theta.shape[1] - 1) // 2
    M = x.size
    g = np.empty((M, 3))
    gp = np.empty((M, 3))
    for i in range(M):
        c1 = math.cos(x[i])
        s1 = math.sin(x[i])
        for h in range(3):
            g[i, h] = theta[h, 0]
            gp[i, h] = 0.0
        c = 1.0
        s = 0.0
        for k in range(1, L + 1):
            c, s = c * c1 - s * s1, s * c1 + c * s1
            for h in range(3):
                a = theta[h, 2 * k - 1]
                b = theta[h, 2 * k]
                g[i, h] += a * s + b * c
                gp[i, h] += k * (a * c - b * s)
    return g, gp


def _real_coefficients(F: NDArray) -> NDArray[np.float64]:
    """[-2 Im F, 2 Re F] (sin and cos coefficients) from rfft / M values, flattened."""
    return np.concatenate([(-2.0 * F.imag).ravel(), (2.0 * F.real).ravel()])


def unwarp(
    view: FInitView,
    edge: int,
    *,
    warp_harmonics: int,
    grid: int | None = None,
    start: ArrayLike | None = None,
    max_iterations: int = 10,
    tol: float = 1e-8,
    reference: bool = False,
) -> Unwarp:
    """The warp w (harmonics 1..J) that leaves the least content above E in ``gamma(x + w(x))``.

    Gauss-Newton on ``r(w)`` = the Fourier coefficients E+1..L of ``gamma(x + w(x))`` on a
    uniform grid of ``grid`` points (FFT; the Jacobian column of a warp harmonic is the transform
    of ``gamma'(x + w(x)) cos(j x)`` or ``sin(j x)``), with a relative Levenberg term of 1e-9
    that keeps undetermined warps (a band wider than the flux) where they are. Converged when
    the largest warp step is below ``tol`` rad.

    Parameters
    ----------
    view : FInitView
    edge : int
        E >= 1.
    warp_harmonics : int, keyword-only
        J.
    grid : int, optional
        Grid size (default: the power of two >= 2 L; the warped view's content above the
        Nyquist harmonic is below the noise on the benches).
    start : array_like (2 J,), optional
        Starting warp (default zero: f_init's parametrization).
    max_iterations : int, keyword-only
        Gauss-Newton steps at most.
    tol : float, keyword-only
        Convergence threshold on the largest warp step [rad].
    reference : bool, keyword-only
        Form the Jacobian (2 J x 3 transforms) and its product explicitly instead of from one
        transform of g' (:func:`_warp_normal_equations`, 10-30x less work): the same system
        to about 1e-14, but not to the bit. The flux that starts the model choice is computed
        this way (:func:`band_edge`): the evidence step that follows
        (:func:`hallcal.fit.evidence.harmonic_relevance`) was measured to flip between 87
        and 34 harmonics on a relative change of 1e-14 in its input (tests/test_order.py's
        clean-sensor drive), so its input stays the one of the explicit products.

    Returns
    -------
    Unwarp
        The warp, the un-warped flux on 1..E, the residual content above E and the status.
    """
    th = view.theta
    L = view.harmonics
    E = int(edge)
    J = int(warp_harmonics)
    if not 1 <= E < L:
        raise ValueError("edge must satisfy 1 <= edge < the view's harmonics")
    M = int(grid) if grid else 1 << int(math.ceil(math.log2(2 * L + 2)))
    x = TWO_PI * np.arange(M) / M
    j = np.arange(1, J + 1)
    Bw = np.hstack([np.cos(np.multiply.outer(x, j)), np.sin(np.multiply.outer(x, j))])
    c = np.zeros(2 * J) if start is None else np.array(start, dtype=np.float64)
    status = UnwarpStatus.MAX_ITERATIONS
    it = 0
    with one_blas_thread():
        while it < int(max_iterations):
            it += 1
            g, gp = _curve(th, x + Bw @ c)
            F = np.fft.rfft(g, axis=0)[E + 1 : L + 1] / M  # (L - E, 3)
            if reference:
                Jc = np.fft.rfft(gp[:, None, :] * Bw[:, :, None], axis=0)[E + 1 : L + 1] / M
                Jr = np.concatenate(
                    [(-2.0 * Jc.imag).transpose(0, 2, 1).reshape(-1, 2 * J),
                     (2.0 * Jc.real).transpose(0, 2, 1).reshape(-1, 2 * J)]
                )  # fmt: skip
                A, grad = Jr.T @ Jr, Jr.T @ _real_coefficients(F)
            else:
                A, grad = _warp_normal_equations(np.fft.fft(gp, axis=0) / M, F, E, L, J)
            A[np.diag_indices_from(A)] += 1e-9 * max(float(np.trace(A)) / A.shape[0], 1e-300)
            step = scipy.linalg.solve(A, -grad, assume_a="pos", check_finite=False)
            c = c + step
            if float(np.max(np.abs(step))) < tol:
                status = UnwarpStatus.CONVERGED
                break
        g, _ = _curve(th, x + Bw @ c)
    F = np.fft.rfft(g, axis=0) / M
    r = _real_coefficients(F[E + 1 : L + 1])
    theta = np.empty((3, 2 * E + 1))
    theta[:, 0] = F[0].real
    theta[:, 1::2] = -2.0 * F[1 : E + 1].imag.T
    theta[:, 2::2] = 2.0 * F[1 : E + 1].real.T
    flux = FluxModel(FourierBasis(tuple(range(1, E + 1))), theta)
    residual = float(r @ r) / view.coefficient_variance
    return Unwarp(E, c, flux, residual, 6 * (L - E) - 2 * J, it, status)


@nb.njit(cache=True, nogil=True)
def _lag_prefix(gc, ext, nl):  # pragma: no cover - numba
    """P[l, t] = sum_{i < t} sum_h gc[h, i] ext[h, i + l]: prefix sums of the lagged products
    (gc: the conjugated factor (3, T); ext: (3, T + nl - 1))."""
    T = gc.shape[1]
    P = np.zeros((nl, T + 1), dtype=np.complex128)
    for li in range(nl):
        acc = 0.0j
        for i in range(T):
            acc += gc[0, i] * ext[0, i + li] + gc[1, i] * ext[1, i + li] + gc[2, i] * ext[2, i + li]
            P[li, i + 1] = acc
    return P


@nb.njit(cache=True, nogil=True)
def _shifted_products(Gt, Ft, E, J):  # pragma: no cover - numba
    """pl[j] = sum_{k, h} conj(Gt[h, k - j]) Ft[h, k], ph[j] the same at k + j (k = E+1..L,
    indices modulo M): ``lo_j^H F`` and ``hi_j^H F`` of :func:`_warp_normal_equations`."""
    M = Gt.shape[1]
    K = Ft.shape[1]
    pl = np.zeros(J, dtype=np.complex128)
    ph = np.zeros(J, dtype=np.complex128)
    for jj in range(J):
        j = jj + 1
        a = 0.0j
        b = 0.0j
        for i in range(K):
            k = E + 1 + i
            lo = (k - j) % M
            hi = (k + j) % M
            for h in range(3):
                a += Gt[h, lo].conjugate() * Ft[h, i]
                b += Gt[h, hi].conjugate() * Ft[h, i]
        pl[jj] = a
        ph[jj] = b
    return pl, ph


def _warp_normal_equations(
    Gp: NDArray, F: NDArray, E: int, L: int, J: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``Jr^T Jr`` and ``Jr^T r`` of :func:`unwarp`'s Gauss-Newton step without Jr.

    Jr holds the coefficients E+1..L (sin and cos parts, three sensors) of ``gp(x) cos(j x)``
    and ``gp(x) sin(j x)``, j = 1..J. With ``cos(j x) = (e^{ijx} + e^{-ijx}) / 2`` their
    transforms are the transform of gp shifted by -+j: the columns are ``(lo_j + hi_j) / 2``
    and ``-i (lo_j - hi_j) / 2`` with ``lo_j[k] = Gp[k - j]``, ``hi_j[k] = Gp[k + j]`` (exact for
    the DFT on the grid), so every entry of ``Jr^T Jr = 4 Re(Jc^H Jc)`` is a sum over a window
    of k of the lagged products ``q_l[m] = sum_h conj(Gp_h[m]) Gp_h[m + l]``: the difference
    of two prefix sums of q_l. That is O(J (L - E + J)) work instead of the O((L - E) J^2)
    of the product (measured: 644 x 644 from 3100 rows, 10 times per trial of
    :func:`band_edge`, the larger part of its time). The prefix sums' rounding, about
    ``1e-16`` of the largest partial sum, stays far below the step's relative ridge of 1e-9.

    Parameters
    ----------
    Gp : ndarray (M, 3), complex
        ``fft(gp, axis=0) / M`` of g' on the grid.
    F : ndarray (L - E, 3), complex
        The residual coefficients E+1..L (``rfft(g) / M``).
    E, L, J : int
        Band edge, view harmonics, warp harmonics (J + L < M).

    Returns
    -------
    A : ndarray (2 J, 2 J)
        ``Jr^T Jr`` (cos columns first, then sin, as the warp's coefficients).
    grad : ndarray (2 J,)
        ``Jr^T r`` with r the real coefficients of F.
    """
    M = Gp.shape[0]
    j = np.arange(1, J + 1)
    Gt = np.ascontiguousarray(Gp.T)  # (3, M)
    # Jr^T r = 4 Re(Jc^H F) for the columns (lo + hi) / 2 and -i (lo - hi) / 2
    pl, ph = _shifted_products(Gt, np.ascontiguousarray(F.T), E, J)
    grad = np.concatenate([2.0 * (pl + ph).real, -2.0 * (pl - ph).imag])
    # prefix sums of q_l[m] over m = E+1-J .. L+J, lags l = -(J-1) .. 2J
    m0 = E + 1 - J
    m = np.arange(m0, L + J + 1)
    lags = np.arange(-(J - 1), 2 * J + 1)
    # lag l's factor Gp[m + l] is a window of the periodic extension starting at lags[0]
    ext = np.ascontiguousarray(Gt[:, np.arange(m0 + lags[0], L + J + lags[-1] + 1) % M])
    P = _lag_prefix(np.ascontiguousarray(Gt[:, m % M].conj()), ext, lags.size)

    def window(lag: NDArray, a: NDArray, b: NDArray) -> NDArray:
        """sum_{m=a}^{b} q_lag[m] (a, b inclusive, one row of bounds per j)."""
        li = lag + (J - 1)
        return P[li, b - m0 + 1] - P[li, a - m0]

    jr, jc = j[:, None], j[None, :]
    LL = window(jr - jc, E + 1 - jr, L - jr)  # conj(lo_j) . lo_j'
    LH = window(jr + jc, E + 1 - jr, L - jr)  # conj(lo_j) . hi_j'
    HH = window(jc - jr, E + 1 + jr, L + jr)  # conj(hi_j) . hi_j'
    HL = LH.conj().T  # conj(hi_j) . lo_j'
    A = np.empty((2 * J, 2 * J))
    A[:J, :J] = (LL + LH + HL + HH).real
    A[:J, J:] = (LL - LH + HL - HH).imag
    A[J:, :J] = A[:J, J:].T
    A[J:, J:] = (LL - LH - HL + HH).real
    return A, grad


# ================================================================================================
# The band edge
# ================================================================================================


class BandEdgeStatus(Outcome):
    """Outcome of :func:`band_edge`."""

    #: the smallest adequate band was found
    FOUND = "found"
    #: no band up to the upper bound leaves only noise: the bound is used
    AT_BOUND = "at_bound"
    #: the f_init angle covers less than a revolution: harmonics are not separable, no band
    #: is chosen (the fundamental's band 1..n_m, at f_init's parametrization, is returned)
    TOO_SHORT = "too_short"


@dataclass(frozen=True)
class EdgeTrial:
    """One band tried by :func:`band_edge`: E, residual (chi-square units), dof, threshold."""

    edge: int
    residual: float
    dof: int
    threshold: float

    @property
    def adequate(self) -> bool:
        return self.residual <= self.threshold


@dataclass(frozen=True)
class BandEdge:
    """Outcome of :func:`band_edge`.

    Attributes
    ----------
    edge : int
        E: the flux needs harmonics 1..E.
    unwarp : Unwarp
        The un-warped flux on 1..E and its warp.
    view : FInitView
    trials : tuple of EdgeTrial
        Every band tried, in order.
    status : BandEdgeStatus
    elapsed : float
        Wall time [s].
    """

    edge: int
    unwarp: Unwarp = field(repr=False)
    view: FInitView = field(repr=False)
    trials: tuple[EdgeTrial, ...] = field(repr=False)
    status: BandEdgeStatus
    elapsed: float

    @property
    def flux(self) -> FluxModel:
        return self.unwarp.flux


def _view_band(view_amplitude: NDArray, coefficient_std: float, *, pole_pairs: int) -> int:
    """Harmonics of the view worth fitting: the last one with 3-sigma content, plus 4 n_m."""
    strong = np.nonzero(view_amplitude > 3.0 * coefficient_std)[0]
    top = int(strong[-1]) + 1 if strong.size else int(pole_pairs)
    return top + 4 * int(pole_pairs)


def band_edge(
    y: ArrayLike,
    d: ArrayLike,
    *,
    pole_pairs: int,
    noise_variance: float,
    max_edge: int | None = None,
    view_harmonics: int | None = None,
    significance: float = 1e-3,
    slack: float = 0.1,
) -> BandEdge:
    """The smallest band 1..E that holds the flux, and the flux un-warped into it.

    1. The view (:func:`f_init_view`) on ``L0 = 32 n_m`` harmonics shows how far f_init's
       view of the flux reaches; it is refitted on L = the last harmonic with 3-sigma content
       plus 4 n_m (:func:`_view_band`), or on ``view_harmonics``.
    2. Bisection on E in ``[n_m, max_edge]`` (default 8 n_m, the 7th electrical harmonic with
       its pole-to-pole sidebands): a band is adequate when the content left above it by the
       best warp (:func:`unwarp`, J = L // 2 warp harmonics, from f_init's parametrization) is
       within ``(1 + slack) chi2.isf(significance, dof)`` (dof = 6 (L - E) - 2 J is even:
       :func:`hallcal.fit.adequacy.chi2_isf_even`). The
       residual only decreases as E grows, so the smallest adequate E is found in
       ``log2(7 n_m)`` trials. ``slack`` allows for the approximations in the bound (dof count,
       coefficient variance averaged over the band); measured on the rich-shape bench the
       residual at the true edge is 0.8-1.0 dof, one harmonic below it 10^3-10^4 dof.

    Parameters
    ----------
    y : array_like (N,)
        f_init angle recorded in the loop [rad].
    d : array_like (N, 3)
        Hall signals.
    pole_pairs : int
        n_m.
    noise_variance : float
        Hall noise variance (e.g. :func:`hallcal.fit.adequacy.estimate_noise_variance`).
    max_edge : int, optional
        Largest E tried; default 8 n_m.
    view_harmonics : int, optional
        L of the view, fixed; default chosen from the content of a 32 n_m view (step 1).
    significance : float
        Tail probability of the chi-square bound (step 2).
    slack : float
        Relative allowance on that bound (step 2).

    Returns
    -------
    BandEdge
        E, the un-warped flux on 1..E with its warp, the view, every trial and the status.
    """
    t0 = time.perf_counter()
    n = int(pole_pairs)
    top = int(max_edge) if max_edge else 8 * n
    yy = np.asarray(y, dtype=np.float64)
    if yy.size == 0 or float(yy.max() - yy.min()) < TWO_PI:
        return _too_short(yy, d, n, noise_variance, t0)
    # a view needs a few samples per coefficient (1 + 2 L < N / 8)
    L0 = min(32 * n, max(yy.size // 16, n + 1))
    Lp = L0 if view_harmonics is None else int(view_harmonics)
    try:
        normal, rhs, _ = regression_normal_equations(y, d, np.arange(1, Lp + 1))
        probe = _view_from_normal_equations(normal, rhs, noise_variance)
    except ValueError:  # the angle does not cover the view's harmonics well enough
        return _too_short(yy, d, n, noise_variance, t0)
    view = probe
    if view_harmonics is None:
        amp, std = probe.amplitude(), math.sqrt(probe.coefficient_variance)
        L = min(max(_view_band(amp, std, pole_pairs=n), top + 2 * n), L0)
        if L < 0.75 * L0:  # a narrower view: the leading block of the probe's equations
            view = _view_from_normal_equations(
                normal[: 2 * L + 1, : 2 * L + 1], rhs[: 2 * L + 1], noise_variance
            )
    L = view.harmonics
    top = max(min(top, L - 1), n)
    J = max(L // 2, 1)
    done: dict[int, Unwarp] = {}
    trials: list[EdgeTrial] = []

    def trial(E: int) -> bool:
        # always from f_init's parametrization: a wider band's warp is partly undetermined
        # (left where it started), and from there a narrower band converges slowly
        u = unwarp(view, E, warp_harmonics=J)
        done[E] = u
        dof = max(u.dof, 1)
        thr = (1.0 + slack) * chi2_isf_even(significance, 2 * ((dof + 1) // 2))
        trials.append(EdgeTrial(E, u.residual, u.dof, thr))
        return u.residual <= thr

    lo, hi = n - 1, top  # lo: inadequate (or below the fundamental), hi: assumed adequate
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if trial(mid):
            hi = mid
        else:
            lo = mid
    status = BandEdgeStatus.FOUND
    if hi not in done:
        if not trial(hi):
            status = BandEdgeStatus.AT_BOUND
    # the trials decide on residuals (fast system); the chosen band's flux, which the evidence
    # and the SEM start from, with the explicit products (see unwarp's ``reference``)
    chosen = unwarp(view, hi, warp_harmonics=J, reference=True)
    return BandEdge(hi, chosen, view, tuple(trials), status, time.perf_counter() - t0)


def _too_short(y: NDArray, d: ArrayLike, n: int, noise_variance: float, t0: float) -> BandEdge:
    """Less than a revolution: harmonics 1..n_m by least squares at y, no warp."""
    basis = FourierBasis(tuple(range(1, n + 1)))
    dd = np.asarray(d, dtype=np.float64)
    theta = np.ascontiguousarray(
        np.linalg.lstsq(basis.evaluate(y), dd, rcond=None)[0].T
        if y.size
        else np.zeros((3, basis.size)),
        dtype=np.float64,
    )
    view = FInitView(theta, math.nan, float(noise_variance))
    u = Unwarp(n, np.zeros(0), FluxModel(basis, theta), math.nan, 0, 0, UnwarpStatus.CONVERGED)
    return BandEdge(n, u, view, (), BandEdgeStatus.TOO_SHORT, time.perf_counter() - t0)
