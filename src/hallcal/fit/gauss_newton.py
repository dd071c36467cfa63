"""The Gauss-Newton system of the SEM problem without the dense Jacobian.

Problem (problem) of van Meer et al., ``min_x ||d - d_sim(x)||^2``, is solved by Gauss-Newton /
Levenberg-Marquardt steps (More 1978; Nocedal & Wright 2006, ch. 10), which need only

    J^T J,   J^T e,   e^T e,      J = d d_sim / d x  (3 N x p),  e = d - d_sim,

never J itself. This module forms the three from the exact forward sensitivities of
:mod:`hallcal.sim.loop` in O(chunk p + p^2) memory, so that large models (p in the hundreds, N in
the hundreds of thousands: the dense J would take gigabytes) cost time and memory that grow
gently with p.

Parameters x (:class:`ParameterLayout`):

* theta (3 m, sensor-major): the flux ``g_h(y0) = beta(y0) theta_h`` on a Fourier basis with an
  arbitrary set of mechanical harmonics (eq. basis);
* optionally ``log c``, a factor on the plant input matrix (the BLA gain of eq. c_hat);
* optionally the coefficients ``(a_k, b_k)`` of a cogging torque
  ``T_c(y0) = sum_k a_k cos(k y0) + b_k sin(k y0)`` added to the plant input
  (:mod:`hallcal.sim.cogging`).

Structure of the Jacobian rows. Per sample k the three rows are (:mod:`hallcal.sim.loop`)

    J_k = g'(y0_k) dy0_k^T + E_k,     E_k = I_3 kron beta(y0_k)  on the theta columns, 0 elsewhere,

because log c and the cogging coefficients act through the plant input only (no direct flux
term). With ``n_k = g'_k / |g'_k|`` and ``u_k = |g'_k| dy0_k + E_k^T n_k``,

    J_k^T J_k = u_k u_k^T + E_k^T (I_3 - n_k n_k^T) E_k,

one rank-one term per sample (``u_k`` is the Jacobian row along the tangent of the flux curve)
plus a term on the theta block only whose entries are sums of products of sines and cosines of
the harmonics: with the product formulas they reduce to the trigonometric moments
``sum_k w_k exp(i n y0_k)``, ``n <= 2 max(harmonics)``, of six weights ``w`` (the entries of
``I - n n^T``), i.e. O(N max(harmonics)) work instead of O(N p^2).

Work split. The sensitivity recursion runs in chunks of samples; two threads (numba releases the
GIL) each advance the sensitivities of one block of parameter columns over a chunk (each thread
re-runs the cheap nominal simulation) and write their columns of the rows u_k into a shared ring
of buffers; once both have written a chunk, each adds a share of ``sum u_k u_k^T`` with
single-threaded BLAS (threadpoolctl: OpenBLAS with two threads was 5-60x slower on these 2-core
machines, docs/design.md). The ring lets one thread run a few chunks ahead of the other.

Strided Hessian. ``stride = s`` accumulates the rank-one part over every s-th sample (times s):
the sensitivities are smooth at the sampling rate (loop bandwidth ~10 Hz at 4 kHz), so this is a
quadrature of a smooth sum with a relative error of order s / N, good enough for the iterations
(the gradient, the cost and the trigonometric part stay exact); the system at the solution, used
for the covariance, is formed with s = 1.
"""

from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from hallcal.limits import check_work_memory
from hallcal.sensor.flux import FourierBasis
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import (
    ClosedLoop,
    LoopStatus,
    _advance,
    _advance_sensitivity,
    _alpha_beta,
    _angle_and_sensitivity,
    _diverged,
    _flux_and_slope,
    _kernel_array,
    _output,
    _unwrap,
)

__all__ = [
    "gram_from_moments",
    "GaussNewtonSystem",
    "ParameterLayout",
    "PassStatus",
    "SimulatedLoop",
    "fourier_gauss_newton",
    "gauss_newton_system",
    "regression_normal_equations",
    "simulate_fourier",
    "simulate_model",
]


#: Outcome of a simulation or sensitivity pass (OK or DIVERGED).
PassStatus = LoopStatus


# ================================================================================================
# Parameter layout
# ================================================================================================


@dataclass(frozen=True)
class ParameterLayout:
    """Layout of the SEM parameter vector ``x = [theta, log c, a_1, b_1, a_2, b_2, ...]``.

    Parameters
    ----------
    basis : FourierBasis
        The flux model's basis (any set of harmonics); theta occupies ``3 m`` entries,
        sensor-major (row h of the (3, m) theta is sensor h).
    fit_gain : bool
        Whether ``log c`` (a factor c on the plant input matrix) follows theta.
    cogging_orders : tuple of int
        Orders k of the cogging torque whose coefficients ``(a_k, b_k)`` come last; order 0 is
        a constant load torque a_0 (its b_0 has a zero column: :attr:`inert` lists it).
    """

    basis: FourierBasis
    fit_gain: bool = False
    cogging_orders: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        k = tuple(int(v) for v in self.cogging_orders)
        if len(set(k)) != len(k) or any(v < 0 for v in k):
            raise ValueError("cogging orders must be distinct integers >= 0")
        object.__setattr__(self, "cogging_orders", k)
        object.__setattr__(self, "fit_gain", bool(self.fit_gain))

    @property
    def n_theta(self) -> int:
        """3 m."""
        return 3 * self.basis.size

    @property
    def gain_index(self) -> int:
        """Index of log c (-1 without it)."""
        return self.n_theta if self.fit_gain else -1

    @property
    def cogging_start(self) -> int:
        """Index of a_1."""
        return self.n_theta + (1 if self.fit_gain else 0)

    @property
    def size(self) -> int:
        """p."""
        return self.cogging_start + 2 * len(self.cogging_orders)

    @property
    def inert(self) -> tuple[int, ...]:
        """Indices of x without effect on the loop: b_0 of a cogging order 0 (sin 0 = 0)."""
        return tuple(
            self.cogging_start + 2 * i + 1 for i, k in enumerate(self.cogging_orders) if k == 0
        )

    def theta(self, x: ArrayLike) -> NDArray[np.float64]:
        """theta (3, m) from x."""
        return np.asarray(x, dtype=np.float64)[: self.n_theta].reshape(3, self.basis.size)

    def log_gain(self, x: ArrayLike) -> float:
        """log c from x (0 without it)."""
        return float(np.asarray(x)[self.gain_index]) if self.fit_gain else 0.0

    def cogging(self, x: ArrayLike, covariance: ArrayLike | None = None) -> CoggingTorque:
        """The cogging torque of x (with the covariance block of its coefficients, if given).

        Parameters
        ----------
        x : array_like, shape (p,)
            A parameter vector of this layout.
        covariance : array_like, shape (p, p), optional
            Covariance of x; its cogging block is attached to the torque.

        Returns
        -------
        CoggingTorque
            T_c(y0) of the orders ``cogging_orders`` [plant input units].
        """
        xx = np.asarray(x, dtype=np.float64)
        sl = slice(self.cogging_start, self.size)
        cov = None if covariance is None else np.asarray(covariance, dtype=np.float64)[sl, sl]
        return CoggingTorque.from_coefficients(self.cogging_orders, xx[sl], cov)

    def pack(
        self, theta: ArrayLike, log_gain: float = 0.0, cogging: CoggingTorque | None = None
    ) -> NDArray[np.float64]:
        """x from its parts (cogging coefficients of orders not in ``cogging`` are zero).

        Parameters
        ----------
        theta : array_like, shape (3, m)
            Flux parameters on ``basis``.
        log_gain : float
            log c, the plant input gain factor (ignored unless ``fit_gain``).
        cogging : CoggingTorque, optional
            Known cogging coefficients to place at their orders.

        Returns
        -------
        ndarray, shape (p,)
            ``x = [theta, log c, a_1, b_1, ...]``.
        """
        x = np.zeros(self.size)
        x[: self.n_theta] = np.asarray(theta, dtype=np.float64).reshape(-1)
        if self.fit_gain:
            x[self.gain_index] = float(log_gain)
        if cogging is not None:
            known = dict(zip(cogging.orders, zip(cogging.a, cogging.b, strict=True), strict=True))
            for i, k in enumerate(self.cogging_orders):
                if k in known:
                    x[self.cogging_start + 2 * i : self.cogging_start + 2 * i + 2] = known[k]
        return x


# ================================================================================================
# Numba kernels
# ================================================================================================


@nb.njit(cache=True, nogil=True, inline="always")
def _trig_table(y0, hmax, cs, sn):
    """cs[n] = cos(n y0), sn[n] = sin(n y0) for n = 0..hmax by the angle-addition recursion
    (rounding error grows like n eps, 1e-14 at n = 100)."""
    c1 = math.cos(y0)
    s1 = math.sin(y0)
    c = 1.0
    s = 0.0
    for n in range(hmax + 1):
        cs[n] = c
        sn[n] = s
        c, s = c * c1 - s * s1, s * c1 + c * s1


@nb.njit(cache=True, nogil=True, inline="always")
def _gather_basis(harm, cs, sn, b, db):
    """beta = [1, sin h_1 y0, cos h_1 y0, ...] and its derivative from the trigonometric table."""
    b[0] = 1.0
    db[0] = 0.0
    for j in range(harm.size):
        h = harm[j]
        b[1 + 2 * j] = sn[h]
        b[2 + 2 * j] = cs[h]
        db[1 + 2 * j] = h * cs[h]
        db[2 + 2 * j] = -h * sn[h]


@nb.njit(cache=True, nogil=True, inline="always")
def _cogging_torque(orders, coef, y0, creg, sreg):
    """T_c(y0), dT_c/dy0 and the regressors cos(k y0), sin(k y0) per order."""
    t = 0.0
    dt = 0.0
    for i in range(orders.size):
        k = orders[i]
        c = math.cos(k * y0)
        s = math.sin(k * y0)
        creg[i] = c
        sreg[i] = s
        t += coef[2 * i] * c + coef[2 * i + 1] * s
        dt += k * (coef[2 * i + 1] * c - coef[2 * i] * s)
    return t, dt


@nb.njit(cache=True, nogil=True)
def _simulate_kernel(Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, off, n_m, theta, harm, hmax, cog_k, cog_x,
                     r, y_init):  # fmt: skip
    """Noise-free closed loop (eq. state_eq) with the flux on ``harm`` and the cogging torque."""
    N = r.size
    ng = Ag.shape[0]
    nc = Ac.shape[0]
    m = theta.shape[1]
    xg = np.zeros(ng)
    xc = np.zeros(nc)
    xg2 = np.zeros(ng)
    xc2 = np.zeros(nc)
    cs = np.empty(hmax + 1)
    sn = np.empty(hmax + 1)
    b = np.empty(m)
    db = np.empty(m)
    creg = np.empty(cog_k.size)
    sreg = np.empty(cog_k.size)
    y0s = np.full(N, np.nan)
    ys = np.full(N, np.nan)
    us = np.full(N, np.nan)
    ds = np.full((N, 3), np.nan)
    gk = np.empty(3)
    gp = np.empty(3)
    yprev = y_init
    y0_last = 0.0
    ok = True
    for k in range(N):
        y0 = 0.0
        for i in range(ng):
            y0 += Cg[i] * xg[i]
        _trig_table(y0, hmax, cs, sn)
        _gather_basis(harm, cs, sn, b, db)
        _flux_and_slope(theta, b, db, gk, gp)
        al, be = _alpha_beta(P, off, gk)
        y = _unwrap(math.atan2(be, al), yprev, n_m)
        e = r[k] - y
        u = _output(Cc, xc, Dc, e)
        tc, _ = _cogging_torque(cog_k, cog_x, y0, creg, sreg)
        _advance(Ac, Bc, xc, e, xc2)
        _advance(Ag, Bg, xg, u + tc, xg2)
        bad = _diverged(y0, y0_last, u, n_m)
        y0_last = y0
        if bad:
            ok = False
            break
        y0s[k] = y0
        ys[k] = y
        us[k] = u
        for h in range(3):
            ds[k, h] = gk[h]
        yprev = y
    return y0s, ys, us, ds, ok


@nb.njit(cache=True, nogil=True)
def _sens_block(
    Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, off, n_m, theta, harm, hmax, cog_k, cog_x, jgain, jcog,
    r, d, k0, k1, j0, j1, ustride, primary,
    xg, xc, st, Sg, Sc, Sg2, Sc2, U, grad, y0s, ds, nvec,
):  # fmt: skip
    """Advance the sensitivities of the parameter columns j0..j1-1 over the samples k0..k1-1.

    The nominal loop state (xg, xc, st = [y_prev, y0_last]) and the block's sensitivities
    (Sg, Sc: states x (j1 - j0)) are carried between chunks in the arrays. Writes the columns
    j0..j1-1 of the rows u_k of the samples k that are multiples of ``ustride`` into consecutive
    rows of U (none when ustride = 0) and adds the columns of J^T e into ``grad``. The primary
    block also stores y0, d_sim and n_k = g'/|g'| and returns e^T e of the chunk.
    Returns (ok, sum of squared errors).
    """
    ng = Ag.shape[0]
    nc = Ac.shape[0]
    m = theta.shape[1]
    pb = j1 - j0
    xg2 = np.empty(ng)
    xc2 = np.empty(nc)
    cs = np.empty(hmax + 1)
    sn = np.empty(hmax + 1)
    b = np.empty(m)
    db = np.empty(m)
    creg = np.empty(cog_k.size)
    sreg = np.empty(cog_k.size)
    dy0 = np.empty(pb)
    dy = np.empty(pb)
    dw = np.empty(pb)
    gk = np.empty(3)
    gp = np.empty(3)
    ek = np.empty(3)
    nk = np.empty(3)
    ck = np.empty(3)
    yprev = st[0]
    y0_last = st[1]
    sse = 0.0
    ok = True
    swapped = False
    for k in range(k0, k1):
        # nominal flux, residual and f_init slope
        y0 = _angle_and_sensitivity(Cg, xg, Sg, dy0)
        _trig_table(y0, hmax, cs, sn)
        _gather_basis(harm, cs, sn, b, db)
        _flux_and_slope(theta, b, db, gk, gp)
        for h in range(3):
            ek[h] = d[k, h] - gk[h]
        al, be = _alpha_beta(P, off, gk)
        rho2 = al * al + be * be
        if not rho2 > 0.0:  # no angle at alpha = beta = 0 (or NaN): the model is degenerate
            ok = False
            break
        for h in range(3):
            ck[h] = (al * P[1, h] - be * P[0, h]) / (rho2 * n_m)  # d y / d d_h
        q = ck[0] * gp[0] + ck[1] * gp[1] + ck[2] * gp[2]
        gnorm = math.sqrt(gp[0] * gp[0] + gp[1] * gp[1] + gp[2] * gp[2])
        ge = gp[0] * ek[0] + gp[1] * ek[1] + gp[2] * ek[2]
        for h in range(3):
            nk[h] = gp[h] / gnorm if gnorm > 0.0 else 0.0
        if primary:
            y0s[k] = y0
            for h in range(3):
                ds[k, h] = gk[h]
                nvec[k, h] = nk[h]
                sse += ek[h] * ek[h]
        # gradient and dy: feedback term on every column, direct term I_3 kron beta on the
        # theta columns of this block
        for jl in range(pb):
            grad[j0 + jl] += ge * dy0[jl]
            dy[jl] = q * dy0[jl]
        for h in range(3):
            lo = max(j0, h * m)
            hi = min(j1, (h + 1) * m)
            for j in range(lo, hi):
                grad[j] += ek[h] * b[j - h * m]
                dy[j - j0] += ck[h] * b[j - h * m]
        # the row u_k = |g'| dy0 + E^T n
        if ustride > 0 and k % ustride == 0:
            t = k // ustride - (k0 + ustride - 1) // ustride  # rank among multiples in [k0, k1)
            for jl in range(pb):
                U[t, j0 + jl] = gnorm * dy0[jl]
            for h in range(3):
                lo = max(j0, h * m)
                hi = min(j1, (h + 1) * m)
                for j in range(lo, hi):
                    U[t, j] += nk[h] * b[j - h * m]
        # controller and plant input w = u + T_c(y0)
        y = _unwrap(math.atan2(be, al), yprev, n_m)
        err = r[k] - y
        u = _output(Cc, xc, Dc, err)
        tc, dtc = _cogging_torque(cog_k, cog_x, y0, creg, sreg)
        w = u + tc
        for jl in range(pb):
            dw[jl] = -Dc * dy[jl] + dtc * dy0[jl]
        for i in range(nc):
            ci = Cc[i]
            if ci != 0.0:
                for jl in range(pb):
                    dw[jl] += ci * Sc[i, jl]
        for i in range(cog_k.size):
            ja = jcog + 2 * i
            if j0 <= ja < j1:
                dw[ja - j0] += creg[i]
            if j0 <= ja + 1 < j1:
                dw[ja + 1 - j0] += sreg[i]
        for jl in range(pb):
            dy[jl] = -dy[jl]  # de = -dy drives the controller
        _advance_sensitivity(Ac, Bc, Sc, dy, Sc2)
        _advance_sensitivity(Ag, Bg, Sg, dw, Sg2)
        if j0 <= jgain < j1:  # x+ = A x + c B w with Bg = c B: d / d log c adds Bg w
            for i in range(ng):
                Sg2[i, jgain - j0] += Bg[i] * w
        _advance(Ac, Bc, xc, err, xc2)
        _advance(Ag, Bg, xg, w, xg2)
        Sc, Sc2 = Sc2, Sc
        Sg, Sg2 = Sg2, Sg
        swapped = not swapped
        bad = _diverged(y0, y0_last, u, n_m)
        y0_last = y0
        yprev = y
        if bad:
            ok = False
            break
    if swapped:  # the caller's Sg, Sc must hold the current sensitivities
        Sc2[:, :] = Sc
        Sg2[:, :] = Sg
    st[0] = yprev
    st[1] = y0_last
    return ok, sse


def _moments(y0: ArrayLike, W: ArrayLike, nmax: int) -> tuple[NDArray, NDArray]:
    """C[w, n] = sum_k W[k, w] cos(n y0_k), S[w, n] = sum_k W[k, w] sin(n y0_k), n = 0..nmax."""
    return _moments_kernel(_kernel_array(y0), _kernel_array(W), int(nmax))


@nb.njit(cache=True, nogil=True)
def _moments_kernel(y0, W, nmax):
    """C[w, n] = sum_k W[k, w] cos(n y0_k), S[w, n] = sum_k W[k, w] sin(n y0_k), n = 0..nmax."""
    N = y0.size
    nw = W.shape[1]
    C = np.zeros((nw, nmax + 1))
    S = np.zeros((nw, nmax + 1))
    cs = np.empty(nmax + 1)
    sn = np.empty(nmax + 1)
    for k in range(N):
        _trig_table(y0[k], nmax, cs, sn)
        for w in range(nw):
            wk = W[k, w]
            if wk != 0.0:
                for n in range(nmax + 1):
                    C[w, n] += wk * cs[n]
                    S[w, n] += wk * sn[n]
    return C, S


def _moments_threaded(y0: NDArray, W: NDArray, nmax: int, threads: int) -> tuple[NDArray, NDArray]:
    """:func:`_moments` over the two halves of the samples, summed: in two threads (nogil) or
    one after the other, with the same result to the bit."""
    N = y0.size
    y0, W = _kernel_array(y0), _kernel_array(W)
    if N < 4096:
        return _moments_kernel(y0, W, int(nmax))
    h = N // 2
    if threads < 2:
        C0, S0 = _moments_kernel(y0[:h], W[:h], int(nmax))
        C1, S1 = _moments_kernel(y0[h:], W[h:], int(nmax))
        return C0 + C1, S0 + S1
    with ThreadPoolExecutor(1) as pool:
        fut = pool.submit(_moments_kernel, y0[h:], W[h:], int(nmax))
        C0, S0 = _moments_kernel(y0[:h], W[:h], int(nmax))
        C1, S1 = fut.result()
    return C0 + C1, S0 + S1


def gram_from_moments(C: NDArray, S: NDArray, harmonics: ArrayLike | int) -> NDArray[np.float64]:
    """``sum_k w_k beta_k beta_k^T`` for ``beta = [1, sin h_1 y, cos h_1 y, ...]`` from moments.

    Uses sin a sin b = (cos(a-b) - cos(a+b))/2, cos a cos b = (cos(a-b) + cos(a+b))/2 and
    sin a cos b = (sin(a+b) + sin(a-b))/2, so N samples cost O(N max h) for the moments instead
    of O(N m^2) for the products.

    Parameters
    ----------
    C, S : ndarray (H + 1,)
        Weighted moments ``sum_k w_k cos(j y_k)`` and ``sum_k w_k sin(j y_k)``, j = 0..H, with H
        at least twice the largest harmonic.
    harmonics : array_like of int, or int
        The h_j, or an int K for 1..K.

    Returns
    -------
    ndarray (1 + 2 m, 1 + 2 m)
        The weighted Gram matrix of the basis.
    """
    if np.isscalar(harmonics):
        a = np.arange(1, int(harmonics) + 1)  # type: ignore[arg-type]
    else:
        a = np.asarray(harmonics, dtype=np.int64)
    mb = 1 + 2 * a.size
    M = np.empty((mb, mb))
    dif = np.abs(np.subtract.outer(a, a))
    sgn = np.sign(np.subtract.outer(a, a))
    sm = np.add.outer(a, a)
    M[0, 0] = C[0]
    M[0, 1::2] = M[1::2, 0] = S[a]
    M[0, 2::2] = M[2::2, 0] = C[a]
    M[1::2, 1::2] = 0.5 * (C[dif] - C[sm])
    M[2::2, 2::2] = 0.5 * (C[dif] + C[sm])
    sc = 0.5 * (S[sm] + sgn * S[dif])  # sin(a y) cos(b y), rows a, columns b
    M[1::2, 2::2] = sc
    M[2::2, 1::2] = sc.T
    return M


def regression_normal_equations(
    y: ArrayLike, d: ArrayLike, harmonics: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """``B^T B``, ``B^T d`` and ``d^T d`` for the regression of d (N, c) on beta(y).

    From trigonometric moments (O(N max(harmonics)) time, no N x m matrix): the normal
    equations of the linear least-squares fit ``d ~ beta(y) theta^T``.

    Parameters
    ----------
    y : array_like (N,)
        Angle the basis is evaluated at [rad].
    d : array_like (N,) or (N, c)
        Regressands (e.g. the three Hall signals).
    harmonics : array_like of int
        Mechanical harmonics of the Fourier basis beta (eq. (basis)); the constant term is
        always included.

    Returns
    -------
    gram : ndarray (m, m)
        ``B^T B`` with ``B = beta(y)``, m = 1 + 2 len(harmonics).
    rhs : ndarray (m, c)
        ``B^T d``.
    sse : float
        ``d^T d`` summed over the columns.
    """
    yy = _kernel_array(y)
    dd = np.asarray(d, dtype=np.float64)
    dd = dd[:, None] if dd.ndim == 1 else dd
    h = np.asarray(harmonics, dtype=np.int64)
    W = np.column_stack([np.ones(yy.size), dd])
    C, S = _moments(yy, W, 2 * int(h.max()) if h.size else 0)
    M = gram_from_moments(C[0], S[0], h)
    Btd = np.empty((1 + 2 * h.size, dd.shape[1]))
    Btd[0] = C[1:, 0]
    Btd[1::2] = S[1:, h].T
    Btd[2::2] = C[1:, h].T
    return M, Btd, float(np.sum(dd * dd))


# ================================================================================================
# Simulation
# ================================================================================================


@dataclass(frozen=True)
class SimulatedLoop:
    """Noise-free closed loop of a model: y0, y, u (N,), d (N, 3); NaN after a divergence."""

    y0: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    u: NDArray[np.float64] = field(repr=False)
    d: NDArray[np.float64] = field(repr=False)
    status: PassStatus = PassStatus.OK


def _model_arrays(loop: ClosedLoop, layout: ParameterLayout, x: ArrayLike) -> tuple:
    """Kernel arguments of a model: loop arrays (B_G scaled by c), theta, harmonics, cogging."""
    xx = np.asarray(x, dtype=np.float64).reshape(-1)
    if xx.size != layout.size:
        raise ValueError(f"x must have {layout.size} entries for this layout, got {xx.size}")
    arrs = list(loop._arrays())
    if layout.fit_gain:
        arrs[1] = arrs[1] * math.exp(layout.log_gain(xx))
    harm = np.asarray(layout.basis.harmonics, dtype=np.int64)
    hmax = int(harm.max()) if harm.size else 0
    theta = _kernel_array(layout.theta(xx))
    # the fitted cogging orders first (their columns), then the loop's own, fixed cogging torque
    cog_k = np.asarray(layout.cogging_orders, dtype=np.float64)
    cog_x = _kernel_array(xx[layout.cogging_start :])
    if loop.cogging is not None and loop.cogging.size:
        cog_k = np.concatenate([cog_k, np.asarray(loop.cogging.orders, dtype=np.float64)])
        cog_x = np.concatenate([cog_x, loop.cogging.coefficients])
    return (*arrs, float(loop.pole_pairs), theta, harm, hmax, cog_k, cog_x)


def simulate_model(
    loop: ClosedLoop,
    layout: ParameterLayout,
    x: ArrayLike,
    r: ArrayLike,
    *,
    y_initial: float = 0.0,
) -> SimulatedLoop:
    """Noise-free closed loop (eq. state_eq) of the model x (flux, gain, cogging).

    Same equations as :func:`hallcal.sim.loop.simulate_loop`; the basis comes from a
    trigonometric recursion (one sine and cosine per sample).

    Parameters
    ----------
    loop : ClosedLoop
        Plant model, controller, n_m and f_init.
    layout : ParameterLayout
        What x holds (flux harmonics, gain, cogging orders).
    x : array_like (p,)
        Parameters ``[theta, log c, a_1, b_1, ...]``.
    r : array_like (N,)
        Reference [rad].
    y_initial : float, keyword-only
        f_init's estimate before the first sample [rad].

    Returns
    -------
    SimulatedLoop
        y0, y, u, d and the pass status.
    """
    r = _kernel_array(r)
    y0, y, u, d, ok = _simulate_kernel(*_model_arrays(loop, layout, x), r, float(y_initial))
    return SimulatedLoop(y0, y, u, d, PassStatus.OK if ok else PassStatus.DIVERGED)


# ================================================================================================
# Gauss-Newton system
# ================================================================================================


@dataclass(frozen=True)
class GaussNewtonSystem:
    """Noise-free simulation at x with the Gauss-Newton quantities of problem (problem).

    Attributes
    ----------
    gram : ndarray (p, p)
        J^T J (exact for stride 1, see :func:`gauss_newton_system`).
    gradient : ndarray (p,)
        J^T e with e = d - d_sim.
    sse : float
        e^T e.
    d : ndarray (N, 3)
        Simulated Hall signals.
    y0 : ndarray (N,)
        Simulated angle [rad].
    batch_gradients : ndarray (B, p)
        J^T e summed over consecutive batches of ``chunk`` samples (they add up to ``gradient``):
        the scores a batch-means (long-run) covariance needs.
    status : PassStatus
        OK, or DIVERGED (then every array is NaN and sse is inf).
    """

    gram: NDArray[np.float64] = field(repr=False)
    gradient: NDArray[np.float64] = field(repr=False)
    sse: float
    d: NDArray[np.float64] = field(repr=False)
    y0: NDArray[np.float64] = field(repr=False)
    batch_gradients: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)),
                                                 repr=False)  # fmt: skip
    status: PassStatus = PassStatus.OK


@dataclass
class _Block:
    """One thread's share: sensitivity columns j0..j1-1, its copy of the nominal loop state."""

    j0: int
    j1: int
    xg: NDArray
    xc: NDArray
    st: NDArray
    Sg: NDArray
    Sc: NDArray
    Sg2: NDArray
    Sc2: NDArray

    @classmethod
    def start(cls, j0: int, j1: int, ng: int, nc: int, y_initial: float) -> _Block:
        pb = j1 - j0
        return cls(
            j0, j1, np.zeros(ng), np.zeros(nc), np.array([float(y_initial), 0.0]),
            np.zeros((ng, pb)), np.zeros((nc, pb)), np.zeros((ng, pb)), np.zeros((nc, pb)),
        )  # fmt: skip


def _gram_shares(p: int) -> list[tuple[slice, slice]]:
    """Blocks (rows, columns) of the upper triangle of a p x p Gram matrix, as two equal shares.

    [0, s) x [0, s) (a symmetric rank-k update, s^2 / 2 multiply-adds per row of U) and
    [0, p) x [s, p) (a general product, p (p - s)): 0.25 p^2 and 0.29 p^2 for s = p / sqrt(2).
    Only the upper triangle is used. One thread adds both, two threads one each: the same BLAS
    calls, so the same result to the bit.
    """
    s = int(round(p / math.sqrt(2.0)))
    return [(slice(0, s), slice(0, s)), (slice(0, p), slice(s, p))]


def _add_gram_share(G: NDArray, U: NDArray, rows: slice, cols: slice, weight: float) -> None:
    """G[rows, cols] += weight U[:, rows]^T U[:, cols] (numpy uses syrk when rows == cols)."""
    Ur = U[:, rows]
    prod = Ur.T @ Ur if rows == cols else Ur.T @ U[:, cols]
    if weight != 1.0:
        prod *= weight
    G[rows, cols] += prod


def gauss_newton_system(
    loop: ClosedLoop,
    layout: ParameterLayout,
    x: ArrayLike,
    r: ArrayLike,
    d: ArrayLike,
    *,
    y_initial: float = 0.0,
    chunk: int = 4096,
    gram: bool = True,
    stride: int = 1,
    threads: int | None = None,
) -> GaussNewtonSystem:
    """J^T J, J^T e and e^T e of problem (problem) at x, without the dense Jacobian.

    See the module docstring for the structure used. Memory is O(chunk p + p^2 + N); time is one
    sensitivity recursion (O(N p n^2) for n loop states), the rank-one products (O(N p^2 /
    stride)) and the moments (O(N max(harmonics))).

    Parameters
    ----------
    loop : ClosedLoop
        Plant model, controller, n_m and the f_init of the experiment.
    layout : ParameterLayout
        What x holds (flux harmonics, gain, cogging orders).
    x : array_like (p,)
        Parameters.
    r : array_like (N,)
        Reference [rad].
    d : array_like (N, 3)
        Recorded Hall signals.
    y_initial : float
        f_init's estimate before the first sample [rad].
    chunk : int
        Samples per chunk (also the batch of ``batch_gradients``).
    gram : bool
        False skips J^T J (gradient and cost only).
    stride : int
        Rank-one part of J^T J from every stride-th sample, times stride (see the module
        docstring); 1 for the exact system.
    threads : int, optional
        1 or 2 (default: 2 when the machine has two cores or more).

    Returns
    -------
    GaussNewtonSystem
    """
    r = _kernel_array(r)
    d = _kernel_array(d)
    N = r.size
    if d.shape != (N, 3):
        raise ValueError("d must have shape (N, 3)")
    args = _model_arrays(loop, layout, x)
    p = layout.size
    nthreads = _threads(threads, p)
    stride = max(1, int(stride))
    T = max(64, min(int(chunk), N))
    # before allocating: the Gram matrix and its symmetrized copies (p x p), the sensitivity
    # buffers of each thread (T x p, twice) and the gradient of every chunk (N / T x p)
    check_work_memory(
        8.0 * p * (3 * p + 4 * nthreads * T + -(-N // T)),
        f"the Gauss-Newton system ({p} parameters, {N} samples)",
        "use fewer harmonics (or kernel points) or a shorter recording",
    )
    passes = _SensitivityPass(args, layout, r, d, y_initial, T, stride if gram else 0, nthreads)
    with threadpool_limits(limits=1, user_api="blas"):
        if not passes.run(gram):
            return _diverged_system(N, p, passes.n_chunks)
        G = passes.gram
        if gram:
            G = np.triu(G) + np.triu(G, 1).T
            G[: layout.n_theta, : layout.n_theta] += _normal_part(
                passes.y0s, passes.nvec, layout, nthreads
            )
    grads = passes.batch_grad
    return GaussNewtonSystem(
        G, grads.sum(axis=0), float(passes.sse), passes.ds, passes.y0s, grads, PassStatus.OK
    )


def _threads(threads: int | None, p: int) -> int:
    """Threads of a pass: the given number (1 or 2), else 2 when a second core is idle.

    The second thread pays only on an idle core: on these 2-core machines it gave 1.3-1.5x with
    the other core free, but cost 30-50 % more with the 1-minute load average above 3 (each
    thread repeats the nominal simulation and waits for the other at each chunk). The results
    do not depend on the choice (same column sums, same BLAS calls, see :func:`_gram_shares`).
    """
    if threads is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        cores = cores or 1
        threads = 2 if cores >= 2 and os.getloadavg()[0] < cores - 0.5 else 1
    # a column block needs enough columns to amortize its own nominal simulation
    return 2 if int(threads) >= 2 and p >= 16 else 1


def _diverged_system(N: int, p: int, n_chunks: int) -> GaussNewtonSystem:
    nan = math.nan
    return GaussNewtonSystem(
        np.full((p, p), nan), np.full(p, nan), math.inf, np.full((N, 3), nan), np.full(N, nan),
        np.full((n_chunks, p), nan), PassStatus.DIVERGED,
    )  # fmt: skip


def _normal_part(
    y0: NDArray, nvec: NDArray, layout: ParameterLayout, threads: int
) -> NDArray[np.float64]:
    """``sum_k (I_3 - n_k n_k^T) kron beta_k beta_k^T`` from trigonometric moments."""
    n = nvec
    W = np.column_stack(
        [
            1.0 - n[:, 0] ** 2,
            1.0 - n[:, 1] ** 2,
            1.0 - n[:, 2] ** 2,
            -n[:, 0] * n[:, 1],
            -n[:, 0] * n[:, 2],
            -n[:, 1] * n[:, 2],
        ]
    )
    harm = np.asarray(layout.basis.harmonics, dtype=np.int64)
    hmax = int(harm.max()) if harm.size else 0
    C, S = _moments_threaded(y0, W, 2 * hmax, threads)
    mb = layout.basis.size
    out = np.zeros((3 * mb, 3 * mb))
    pairs = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    for w, (h1, h2) in enumerate(pairs):
        M = gram_from_moments(C[w], S[w], harm)
        out[h1 * mb : (h1 + 1) * mb, h2 * mb : (h2 + 1) * mb] += M
        if h1 != h2:
            out[h2 * mb : (h2 + 1) * mb, h1 * mb : (h1 + 1) * mb] += M.T
    return out


class _SensitivityPass:
    """One pass of the sensitivity recursion over all chunks, split over column blocks.

    Each block runs in its own thread (the first in the caller's), advancing its sensitivity
    columns chunk by chunk into a ring of ``ring`` buffers of rows u_k. Once every block has
    written chunk i, each thread adds its share of the Gram matrix (:func:`_gram_shares`) from
    that chunk's rows; a buffer is reused only after every share of its previous chunk is added.
    The ring lets a thread run a few chunks ahead of the other (on a shared machine one thread
    is often descheduled for a while) instead of meeting it at a barrier every chunk.
    """

    def __init__(self, args, layout, r, d, y_initial, T, ustride, nthreads, ring=4) -> None:
        self.args = args
        self.layout = layout
        self.r, self.d = r, d
        self.T = T
        self.ustride = ustride
        N = r.size
        p = layout.size
        ng = args[0].shape[0]
        nc = args[3].shape[0]
        cuts = np.linspace(0, p, nthreads + 1).round().astype(int)
        self.blocks = [
            _Block.start(int(a), int(b), ng, nc, y_initial)
            for a, b in zip(cuts[:-1], cuts[1:], strict=True)
        ]
        rows = -(-T // ustride) if ustride else 1
        self.ring = max(2, int(ring)) if ustride else 1
        self.bufs = [np.empty((rows, p)) for _ in range(self.ring)]
        self.shares = _gram_shares(p)
        self.gram = np.zeros((p, p)) if ustride else np.zeros((0, 0))
        self.n_chunks = -(-N // T)
        self.batch_grad = np.zeros((self.n_chunks, p))
        self.y0s = np.full(N, np.nan)
        self.ds = np.full((N, 3), np.nan)
        self.nvec = np.zeros((N, 3))
        self.sse = 0.0
        self.failed = False
        self._cond = threading.Condition()
        self._sens_done = [0] * self.n_chunks
        self._gram_done = [0] * self.n_chunks

    def _bounds(self, i: int) -> tuple[int, int]:
        k0 = i * self.T
        return k0, min(self.r.size, k0 + self.T)

    def _sensitivities(self, b: int, i: int) -> bool:
        blk = self.blocks[b]
        k0, k1 = self._bounds(i)
        ok, sse = _sens_block(
            *self.args, self.layout.gain_index, self.layout.cogging_start,
            self.r, self.d, k0, k1, blk.j0, blk.j1, self.ustride, b == 0,
            blk.xg, blk.xc, blk.st, blk.Sg, blk.Sc, blk.Sg2, blk.Sc2,
            self.bufs[i % self.ring], self.batch_grad[i], self.y0s, self.ds, self.nvec,
        )  # fmt: skip
        if b == 0:
            self.sse += sse
        return bool(ok)

    def _gram_share(self, b: int, i: int) -> None:
        k0, k1 = self._bounds(i)
        s = self.ustride
        n_rows = (k1 + s - 1) // s - (k0 + s - 1) // s  # multiples of s in [k0, k1)
        buf = self.bufs[i % self.ring][:n_rows]
        mine = self.shares if len(self.blocks) == 1 else [self.shares[b]]
        for rows, cols in mine:
            _add_gram_share(self.gram, buf, rows, cols, float(self.ustride))

    def _wait(self, ready) -> bool:
        """Wait until ready() or a failure; False on failure."""
        with self._cond:
            self._cond.wait_for(lambda: self.failed or ready())
            return not self.failed

    def _signal(self, counts: list[int], i: int) -> None:
        with self._cond:
            counts[i] += 1
            self._cond.notify_all()

    def _fail(self) -> None:
        with self._cond:
            self.failed = True
            self._cond.notify_all()

    def _worker(self, b: int, gram: bool) -> None:
        nb_ = len(self.blocks)
        try:
            for i in range(self.n_chunks):
                if gram and i >= self.ring:  # the buffer's previous chunk must be consumed
                    if not self._wait(lambda i=i: self._gram_done[i - self.ring] == nb_):
                        return
                if not self._sensitivities(b, i):
                    self._fail()
                    return
                if not gram:
                    continue
                self._signal(self._sens_done, i)
                if not self._wait(lambda i=i: self._sens_done[i] == nb_):
                    return
                self._gram_share(b, i)
                self._signal(self._gram_done, i)
        except BaseException:
            self._fail()
            raise

    def run(self, gram: bool) -> bool:
        """Run every chunk; False when the loop diverged."""
        if len(self.blocks) == 1:
            self._worker(0, gram)
            return not self.failed
        with ThreadPoolExecutor(len(self.blocks) - 1) as pool:
            futures = [pool.submit(self._worker, b, gram) for b in range(1, len(self.blocks))]
            self._worker(0, gram)
            for f in futures:
                f.result()
        return not self.failed


# ================================================================================================
# Harmonics 1..K (the kernel basis' Fourier equivalent)
# ================================================================================================


def _layout_of_theta(theta: ArrayLike) -> tuple[NDArray[np.float64], ParameterLayout]:
    th = np.ascontiguousarray(theta, dtype=np.float64)
    if th.ndim != 2 or th.shape[0] != 3 or th.shape[1] % 2 != 1:
        raise ValueError("theta must have shape (3, 2K + 1) (harmonics 1..K)")
    K = (th.shape[1] - 1) // 2
    return th, ParameterLayout(FourierBasis(tuple(range(1, K + 1))))


def simulate_fourier(
    loop: ClosedLoop, theta: ArrayLike, r: ArrayLike, *, y_initial: float = 0.0
) -> tuple[NDArray, NDArray, NDArray, NDArray, PassStatus]:
    """:func:`simulate_model` for a flux on harmonics 1..K: ``(y0, y, u, d, status)``.

    Parameters
    ----------
    loop : ClosedLoop
        Plant model, controller, n_m and f_init.
    theta : array_like, shape (3, 2K + 1)
        Flux parameters on ``[1, sin 1y, cos 1y, ..., cos Ky]``.
    r : array_like (N,)
        Reference [rad].
    y_initial : float, keyword-only
        f_init's estimate before the first sample [rad].

    Returns
    -------
    y0, y, u : ndarray (N,)
        Simulated true angle [rad], f_init output [rad] and torque command.
    d : ndarray (N, 3)
        Simulated Hall signals.
    status : PassStatus
        OK or DIVERGED (then NaN after the divergence).
    """
    th, layout = _layout_of_theta(theta)
    res = simulate_model(loop, layout, th.ravel(), r, y_initial=y_initial)
    return res.y0, res.y, res.u, res.d, res.status


def fourier_gauss_newton(
    loop: ClosedLoop,
    theta: ArrayLike,
    r: ArrayLike,
    d: ArrayLike,
    *,
    y_initial: float = 0.0,
    chunk: int = 4096,
    gram: bool = True,
    stride: int = 1,
    threads: int | None = None,
) -> GaussNewtonSystem:
    """:func:`gauss_newton_system` for a flux on harmonics 1..K, theta (3, 2K + 1).

    Parameters
    ----------
    loop : ClosedLoop
        Plant model, controller, n_m and the f_init of the experiment.
    theta : array_like, shape (3, 2K + 1)
        Flux parameters on ``[1, sin 1y, cos 1y, ..., cos Ky]``.
    r : array_like (N,)
        Reference [rad].
    d : array_like (N, 3)
        Recorded Hall signals.
    y_initial : float, keyword-only
        f_init's estimate before the first sample [rad].
    chunk, gram, stride, threads
        As for :func:`gauss_newton_system`.

    Returns
    -------
    GaussNewtonSystem
        J^T J, J^T e and e^T e of problem (problem) at theta (no gain, no cogging).
    """
    th, layout = _layout_of_theta(theta)
    return gauss_newton_system(
        loop, layout, th.ravel(), r, d, y_initial=y_initial, chunk=chunk, gram=gram,
        stride=stride, threads=threads,
    )  # fmt: skip
