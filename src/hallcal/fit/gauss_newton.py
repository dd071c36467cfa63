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

from hallcal.fit.layout import ParameterLayout
from hallcal.limits import check_work_memory, one_blas_thread
from hallcal.sim.loop import ClosedLoop, LoopStatus
from hallcal.sim.loop_kernel import (
    F64,
    LoopArrays,
    advance,
    advance_sensitivity,
    alpha_beta,
    angle_and_sensitivity,
    at_rails,
    basis_scratch,
    cogging_torque,
    diverged,
    drifted,
    flux_and_slope,
    gather_basis,
    kernel_array,
    output,
    simulate,
    trig_table,
    unwrap,
)

__all__ = [
    "checked_weights",
    "gram_from_moments",
    "GaussNewtonSystem",
    "ParameterLayout",
    "PassStatus",
    "SimulatedLoop",
    "gauss_newton_system",
    "regression_normal_equations",
    "simulate_model",
]


#: Outcome of a simulation or sensitivity pass (OK or DIVERGED).
PassStatus = LoopStatus


# ================================================================================================
# Numba kernels
# ================================================================================================


@nb.njit(cache=True, nogil=True, inline="always")
def _drift_cross(cross, sw, nk, sh, b, gfl, tau, m):
    """cross += the drift columns of ``E^T M E`` for one sample, ``M = S (I - n n^T) S``:
    rows 0..3m-1 the theta columns (sensor-major), rows 3m.. the drift columns."""
    for c in range(6):
        hc = c // 2
        vc = tau * gfl[hc] if c % 2 == 0 else tau
        for h in range(3):
            mh = sw[h] * sw[hc] * ((1.0 if h == hc else 0.0) - nk[h] * nk[hc])
            coef = mh * vc
            if coef != 0.0:
                for j in range(m):
                    cross[h * m + j, c] += coef * sh[h] * b[j]
                for c2 in range(2 * h, 2 * h + 2):
                    v2 = tau * gfl[h] if c2 % 2 == 0 else tau
                    cross[3 * m + c2, c] += v2 * coef


@nb.njit(cache=True, nogil=True)
def _sens_block(
    Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, off, n_m, theta, harm, hmax, cog_k, cog_x, rlo, rhi, drift,
    jgain, jcog, n_cog_fit, jdrift, r, d, wt, k0, k1, j0, j1, ustride, primary,
    xg, xc, st, Sg, Sc, Sg2, Sc2, U, grad, y0s, ds, nvec, cross,
):  # fmt: skip
    """Advance the sensitivities of the parameter columns j0..j1-1 over the samples k0..k1-1.

    The nominal loop state (xg, xc, st = [y_prev, y0_last]) and the block's sensitivities
    (Sg, Sc: states x (j1 - j0)) are carried between chunks in the arrays. Writes the columns
    j0..j1-1 of the rows u_k of the samples k that are multiples of ``ustride`` into consecutive
    rows of U (none when ustride = 0) and adds the columns of J^T e into ``grad``. The primary
    block also stores y0, d_sim and n_k = g'/|g'| and returns e^T e of the chunk.
    Returns (ok, sum of squared errors).

    Weights (``wt``, N x 3, or 0 x 3 for none): the cost is ``sum_k e_k^T W_k e_k`` with
    ``W_k = diag(wt[k])`` (0 for a censored sample of a channel). With ``s = sqrt(wt[k])`` the
    rows of ``W^(1/2) J_k`` are ``(s o g') dy0^T + diag(s) E_k``, so u_k uses
    ``a = s o g'``, ``n_k = a / |a|`` and ``diag(s) E_k^T n_k`` (module docstring with g' -> a).
    Rails (``rlo``, ``rhi``): f_init sees the model flux clipped to them (:func:`_at_rails`).

    Drift (``drift``: (gamma_h, delta_h) per sensor, empty for none; its columns from
    ``jdrift`` when fitted, -1 otherwise): the model signal is ``sh_h g_h + delta_h tau`` with
    ``sh_h = 1 + gamma_h tau`` (:func:`_drifted`), so E_k holds ``sh_h beta`` on the theta
    columns and ``(tau g_h, tau)`` on the drift columns of sensor h. The primary block adds the
    drift rows and columns of ``E^T S (I - n n^T) S E`` into ``cross`` (3 m + 6, 6): their
    trigonometric-moment shortcut does not apply (the theta block's does, with the weights
    ``w sh^2``, :func:`_normal_part`).
    """
    ng = Ag.shape[0]
    nc = Ac.shape[0]
    m = theta.shape[1]
    pb = j1 - j0
    xg2 = np.empty(ng)
    xc2 = np.empty(nc)
    cs, sn, b, db, creg, sreg = basis_scratch(harm, m, cog_k.size)
    dy0 = np.empty(pb)
    dy = np.empty(pb)
    dw = np.empty(pb)
    gk = np.empty(3)
    gp = np.empty(3)
    ek = np.empty(3)
    nk = np.empty(3)
    ck = np.empty(3)
    gf = np.empty(3)
    live = np.empty(3)
    sw = np.ones(3)
    sh = np.ones(3)
    gfl = np.empty(3)
    has_w = wt.shape[0] > 0
    N = r.size
    tau = 0.0
    yprev = st[0]
    y0_last = st[1]
    sse = 0.0
    ok = True
    swapped = False
    for k in range(k0, k1):
        # nominal flux, residual and f_init slope
        y0 = angle_and_sensitivity(Cg, xg, Sg, dy0)
        trig_table(y0, hmax, cs, sn)
        gather_basis(harm, cs, sn, b, db)
        flux_and_slope(theta, b, db, gk, gp)
        if drift.size:
            tau = k / max(N - 1, 1) - 0.5
            gfl[:] = gk
            drifted(drift, tau, gk, gp, sh)
        at_rails(gk, rlo, rhi, gf, live)
        for h in range(3):
            ek[h] = d[k, h] - gk[h]
            if has_w:
                sw[h] = math.sqrt(wt[k, h])
        al, be = alpha_beta(P, off, gf)
        rho2 = al * al + be * be
        if not rho2 > 0.0:  # no angle at alpha = beta = 0 (or NaN): the model is degenerate
            ok = False
            break
        for h in range(3):
            ck[h] = (al * P[1, h] - be * P[0, h]) / (rho2 * n_m) * live[h]  # d y / d d_h
        q = ck[0] * gp[0] + ck[1] * gp[1] + ck[2] * gp[2]
        gnorm = 0.0
        ge = 0.0
        for h in range(3):
            gnorm += (sw[h] * gp[h]) ** 2
            ek[h] = wt[k, h] * ek[h] if has_w else ek[h]  # W e, and e^T W e below
        gnorm = math.sqrt(gnorm)
        for h in range(3):
            ge += gp[h] * ek[h]
            nk[h] = sw[h] * gp[h] / gnorm if gnorm > 0.0 else 0.0
        if primary:
            y0s[k] = y0
            for h in range(3):
                ds[k, h] = gk[h]
                nvec[k, h] = nk[h]
                sse += ek[h] * (d[k, h] - gk[h])
        # gradient and dy: feedback term on every column, direct term I_3 kron beta on the
        # theta columns of this block
        for jl in range(pb):
            grad[j0 + jl] += ge * dy0[jl]
            dy[jl] = q * dy0[jl]
        for h in range(3):
            lo = max(j0, h * m)
            hi = min(j1, (h + 1) * m)
            for j in range(lo, hi):
                grad[j] += ek[h] * sh[h] * b[j - h * m]
                dy[j - j0] += ck[h] * sh[h] * b[j - h * m]
        if jdrift >= 0:  # the drift columns' direct terms (tau g_h, tau) of sensor h
            for h in range(3):
                for c, v in ((jdrift + 2 * h, tau * gfl[h]), (jdrift + 2 * h + 1, tau)):
                    if j0 <= c < j1:
                        grad[c] += ek[h] * v
                        dy[c - j0] += ck[h] * v
        # the row u_k = |g'| dy0 + E^T n
        if ustride > 0 and k % ustride == 0:
            t = k // ustride - (k0 + ustride - 1) // ustride  # rank among multiples in [k0, k1)
            for jl in range(pb):
                U[t, j0 + jl] = gnorm * dy0[jl]
            for h in range(3):
                lo = max(j0, h * m)
                hi = min(j1, (h + 1) * m)
                for j in range(lo, hi):
                    U[t, j] += sw[h] * nk[h] * sh[h] * b[j - h * m]
            if jdrift >= 0:
                for h in range(3):
                    for c, v in ((jdrift + 2 * h, tau * gfl[h]), (jdrift + 2 * h + 1, tau)):
                        if j0 <= c < j1:
                            U[t, c] += sw[h] * nk[h] * v
        if primary and jdrift >= 0 and ustride > 0:  # every sample, whatever the stride
            _drift_cross(cross, sw, nk, sh, b, gfl, tau, m)
        # controller and plant input w = u + T_c(y0)
        y = unwrap(math.atan2(be, al), yprev, n_m)
        err = r[k] - y
        u = output(Cc, xc, Dc, err)
        tc, dtc = cogging_torque(cog_k, cog_x, y0, creg, sreg)
        w = u + tc
        for jl in range(pb):
            dw[jl] = -Dc * dy[jl] + dtc * dy0[jl]
        for i in range(nc):
            ci = Cc[i]
            if ci != 0.0:
                for jl in range(pb):
                    dw[jl] += ci * Sc[i, jl]
        for i in range(n_cog_fit):  # the fitted orders only (the loop's own follow them)
            ja = jcog + 2 * i
            if j0 <= ja < j1:
                dw[ja - j0] += creg[i]
            if j0 <= ja + 1 < j1:
                dw[ja + 1 - j0] += sreg[i]
        for jl in range(pb):
            dy[jl] = -dy[jl]  # de = -dy drives the controller
        advance_sensitivity(Ac, Bc, Sc, dy, Sc2)
        advance_sensitivity(Ag, Bg, Sg, dw, Sg2)
        if j0 <= jgain < j1:  # x+ = A x + c B w with Bg = c B: d / d log c adds Bg w
            for i in range(ng):
                Sg2[i, jgain - j0] += Bg[i] * w
        advance(Ac, Bc, xc, err, xc2)
        advance(Ag, Bg, xg, w, xg2)
        Sc, Sc2 = Sc2, Sc
        Sg, Sg2 = Sg2, Sg
        swapped = not swapped
        bad = diverged(y0, y0_last, u, n_m)
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
    return _moments_kernel(kernel_array(y0), kernel_array(W), int(nmax))


@nb.njit(cache=True, nogil=True)
def _moments_kernel(y0, W, nmax):
    """C[w, n] = sum_k W[k, w] cos(n y0_k), S[w, n] = sum_k W[k, w] sin(n y0_k), n = 0..nmax.

    Two samples at a time: the tables of :func:`~hallcal.sim.loop_kernel.trig_table` (the same
    recursion, each a chain of dependent products) of samples k and k + 1 are built in one loop,
    so the processor overlaps the two chains (measured 1.8x at nmax = 264); every sum still adds
    sample k before sample k + 1, so the result is the one-sample loop's to the bit.
    """
    N = y0.size
    nw = W.shape[1]
    C = np.zeros((nw, nmax + 1))
    S = np.zeros((nw, nmax + 1))
    cs = np.empty((2, nmax + 1))
    sn = np.empty((2, nmax + 1))
    for k in range(0, N, 2):
        kb = min(k + 1, N - 1)  # the last sample of an odd N pairs with itself, weight 0
        ca1, sa1 = math.cos(y0[k]), math.sin(y0[k])
        cb1, sb1 = math.cos(y0[kb]), math.sin(y0[kb])
        ca, sa, cb, sb = 1.0, 0.0, 1.0, 0.0
        for n in range(nmax + 1):
            cs[0, n], sn[0, n], cs[1, n], sn[1, n] = ca, sa, cb, sb
            ca, sa = ca * ca1 - sa * sa1, sa * ca1 + ca * sa1
            cb, sb = cb * cb1 - sb * sb1, sb * cb1 + cb * sb1
        for w in range(nw):
            wa = W[k, w]
            wb = W[kb, w] if kb > k else 0.0
            if wa != 0.0 and wb != 0.0:
                for n in range(nmax + 1):
                    C[w, n] = (C[w, n] + wa * cs[0, n]) + wb * cs[1, n]
                    S[w, n] = (S[w, n] + wa * sn[0, n]) + wb * sn[1, n]
            elif wa != 0.0 or wb != 0.0:
                j = 0 if wa != 0.0 else 1
                wk = wa if wa != 0.0 else wb
                for n in range(nmax + 1):
                    C[w, n] += wk * cs[j, n]
                    S[w, n] += wk * sn[j, n]
    return C, S


def _moments_threaded(y0: NDArray, W: NDArray, nmax: int, threads: int) -> tuple[NDArray, NDArray]:
    """:func:`_moments` over the two halves of the samples, summed: in two threads (nogil) or
    one after the other, with the same result to the bit."""
    N = y0.size
    y0, W = kernel_array(y0), kernel_array(W)
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
    y: ArrayLike, d: ArrayLike, harmonics: ArrayLike, *, weights: ArrayLike | None = None
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
    weights : array_like (N,), keyword-only, optional
        Sample weights w >= 0 (weighted least squares; 0 leaves a sample out).

    Returns
    -------
    gram : ndarray (m, m)
        ``B^T W B`` with ``B = beta(y)``, m = 1 + 2 len(harmonics) (W = I without weights).
    rhs : ndarray (m, c)
        ``B^T W d``.
    sse : float
        ``d^T W d`` summed over the columns.
    """
    yy = kernel_array(y)
    dd = np.asarray(d, dtype=np.float64)
    dd = dd[:, None] if dd.ndim == 1 else dd
    h = np.asarray(harmonics, dtype=np.int64)
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        W = np.column_stack([w, w[:, None] * dd])
        C, S = _moments(yy, W, 2 * int(h.max()) if h.size else 0)
        M = gram_from_moments(C[0], S[0], h)
        return M, _rhs_from_moments(C, S, h, dd.shape[1]), float(np.sum(w[:, None] * dd * dd))
    W = np.column_stack([np.ones(yy.size), dd])
    C, S = _moments(yy, W, 2 * int(h.max()) if h.size else 0)
    M = gram_from_moments(C[0], S[0], h)
    return M, _rhs_from_moments(C, S, h, dd.shape[1]), float(np.sum(dd * dd))


def _rhs_from_moments(C: NDArray, S: NDArray, h: NDArray, c: int) -> NDArray[np.float64]:
    """``B^T d`` (m, c) from the moments of the columns 1..c of the weights (column 0: w)."""
    Btd = np.empty((1 + 2 * h.size, c))
    Btd[0] = C[1:, 0]
    Btd[1::2] = S[1:, h].T
    Btd[2::2] = C[1:, h].T
    return Btd


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


# the kernel arguments of a model: the loop's (LoopArrays), n_m, theta, harm, hmax, cog_k, cog_x,
# rlo, rhi, drift
ModelArrays = tuple[
    F64, F64, F64, F64, F64, F64, float, F64, F64,
    float, F64, NDArray[np.int64], int, F64, F64, F64, F64, F64,
]  # fmt: skip


def _model_arrays(loop: ClosedLoop, layout: ParameterLayout, x: ArrayLike) -> ModelArrays:
    """Kernel arguments of a model: loop arrays (B_G scaled by c), theta, harmonics, cogging,
    the loop's rails."""
    xx = np.asarray(x, dtype=np.float64).reshape(-1)
    if xx.size != layout.size:
        raise ValueError(f"x must have {layout.size} entries for this layout, got {xx.size}")
    arrs: LoopArrays = loop.kernel_arrays()
    if layout.fit_gain:
        arrs = (arrs[0], arrs[1] * math.exp(layout.log_gain(xx)), *arrs[2:])
    harm = np.asarray(layout.basis.harmonics, dtype=np.int64)
    hmax = int(harm.max()) if harm.size else 0
    theta = kernel_array(layout.theta(xx))
    # the fitted cogging orders first (their columns), then the loop's own, fixed cogging torque
    cog_k = np.asarray(layout.cogging_orders, dtype=np.float64)
    cog_x = kernel_array(xx[layout.cogging_start : layout.cogging_stop])
    if loop.cogging is not None and loop.cogging.size:
        cog_k = np.concatenate([cog_k, np.asarray(loop.cogging.orders, dtype=np.float64)])
        cog_x = np.concatenate([cog_x, loop.cogging.coefficients])
    rlo, rhi = (kernel_array(v) for v in loop.rails)
    drift = kernel_array(layout.drift(xx).ravel() if layout.fit_drift else np.zeros(0))
    return (*arrs, float(loop.pole_pairs), theta, harm, hmax, cog_k, cog_x, rlo, rhi, drift)


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
    r = kernel_array(r)
    args = _model_arrays(loop, layout, x)
    none = np.zeros((0, 3))
    y0, y, u, d, _, ok = simulate(
        *args[:12], True, *args[13:17], np.zeros(3), np.zeros(3), args[17], r, none, np.zeros(0),
        none, float(y_initial), 0.0, True,
    )  # fmt: skip
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
    weights: ArrayLike | None = None,
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
    weights : array_like (N, 3), optional
        Per-sample, per-channel weights w >= 0 of the cost ``sum w e^2`` (0: a censored
        sample, :mod:`hallcal.fit.censor`); then gram, gradient and sse are J^T W J, J^T W e
        and e^T W e. Default: 1 everywhere.

    Returns
    -------
    GaussNewtonSystem
    """
    r = kernel_array(r)
    d = kernel_array(d)
    N = r.size
    if d.shape != (N, 3):
        raise ValueError("d must have shape (N, 3)")
    wt = checked_weights(weights, N)
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
    passes = _SensitivityPass(args, layout, r, d, wt, y_initial, T, stride if gram else 0,
                              nthreads)  # fmt: skip
    with one_blas_thread():
        if not passes.run(gram):
            return _diverged_system(N, p, passes.n_chunks)
        G = passes.gram
        if gram:
            G = np.triu(G) + np.triu(G, 1).T
            G[: layout.n_theta, : layout.n_theta] += _normal_part(
                passes.y0s, passes.nvec, layout, nthreads, _drift_weights(layout, x, wt, N)
            )
            if layout.fit_drift:
                nt, jd = layout.n_theta, layout.drift_start
                G[:nt, jd : jd + 6] += passes.cross[:nt]
                G[jd : jd + 6, :nt] += passes.cross[:nt].T
                G[jd : jd + 6, jd : jd + 6] += passes.cross[nt:]
    grads = passes.batch_grad
    return GaussNewtonSystem(
        G, grads.sum(axis=0), float(passes.sse), passes.ds, passes.y0s, grads, PassStatus.OK
    )


def checked_weights(weights: ArrayLike | None, n_samples: int) -> NDArray[np.float64]:
    """Per-sample, per-channel weights as the kernels take them: (N, 3) float64, finite, >= 0,
    or an empty (0, 3) array for none (every weight 1).

    Parameters
    ----------
    weights : array_like (N, 3) or None
        Weights w of the cost ``sum_k sum_h w_kh e_kh^2`` (0: censored).
    n_samples : int
        N.

    Returns
    -------
    ndarray (N, 3) or (0, 3)
    """
    if weights is None:
        return np.zeros((0, 3))
    w = kernel_array(weights)
    if w.shape != (int(n_samples), 3) or not np.all(np.isfinite(w)) or (w < 0).any():
        raise ValueError("weights must be (N, 3), finite and >= 0")
    return w


def _drift_weights(layout: ParameterLayout, x: ArrayLike, wt: NDArray, N: int) -> NDArray:
    """The weights of the theta block's moments: ``w sh^2`` with ``sh = 1 + gamma tau`` of the
    drifting sensors (:func:`_drifted`); the given weights without the drift."""
    if not layout.fit_drift:
        return wt
    tau = np.arange(N) / max(N - 1, 1) - 0.5
    sh = 1.0 + np.outer(tau, layout.drift(x)[:, 0])
    return sh * sh * (wt if wt.shape[0] else 1.0)


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
    y0: NDArray, nvec: NDArray, layout: ParameterLayout, threads: int, wt: NDArray | None = None
) -> NDArray[np.float64]:
    """``sum_k (S_k (I_3 - n_k n_k^T) S_k) kron beta_k beta_k^T`` from trigonometric moments
    (``S_k = diag(sqrt(w_k))``, the identity without weights)."""
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
    if wt is not None and wt.shape[0]:
        sw = np.sqrt(wt)
        W *= np.column_stack([wt, sw[:, 0] * sw[:, 1], sw[:, 0] * sw[:, 2], sw[:, 1] * sw[:, 2]])
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

    def __init__(
        self,
        args: ModelArrays,
        layout: ParameterLayout,
        r: F64,
        d: F64,
        wt: F64,
        y_initial: float,
        T: int,
        ustride: int,
        nthreads: int,
        ring: int = 4,
    ) -> None:
        self.args = args
        self.layout = layout
        self.r, self.d, self.wt = r, d, wt
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
        self.cross = np.zeros((layout.n_theta + 6, 6) if layout.fit_drift else (0, 6))
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
            len(self.layout.cogging_orders), self.layout.drift_start, self.r, self.d, self.wt,
            k0, k1, blk.j0, blk.j1, self.ustride, b == 0,
            blk.xg, blk.xc, blk.st, blk.Sg, blk.Sc, blk.Sg2, blk.Sc2,
            self.bufs[i % self.ring], self.batch_grad[i], self.y0s, self.ds, self.nvec,
            self.cross,
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
