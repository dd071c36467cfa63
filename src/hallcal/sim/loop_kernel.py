"""The closed loop's numba steps, written once: what the simulator and the solver share.

The per-sample pieces of eq. (state_eq) and of its forward sensitivities (the equations:
:mod:`hallcal.sim.loop`): the flux basis beta(y0) (direct sines per harmonic, or the
angle-addition recursion of the solver's per-thread tables), the flux and its slope, the
cogging torque T_c(y0) with its regressors, the ADC (quantizer, rails), the sensors' drift,
f_init's projection and unwrapping, the controller output, the state-space steps, the angle's
sensitivity and the divergence test. The kernels here (the one simulation, used by
:mod:`hallcal.sim.loop` and the solver's model simulation) and of :mod:`hallcal.fit.gauss_newton`
(the structured Gauss-Newton pass) are built from these steps only.

Each step is a small leaf function inlined into the kernels (``inline="always"``). Measured on
the paper run: a per-sample step that takes a dozen arrays, or nests other steps, costs about
10 ns per array per sample in numba's reference counting of inlined arguments (a kernel whose
sample was one such ``loop_sample`` step was 2.2-2.5x slower), so the kernels keep their
per-sample loop and call only these leaves. float64 throughout.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI

__all__ = [
    "F64",
    "LoopArrays",
    "TWO_PI",
    "advance",
    "advance_sensitivity",
    "alpha_beta",
    "basis_scratch",
    "angle_and_sensitivity",
    "at_rails",
    "cogging_torque",
    "convert",
    "direct_basis",
    "diverged",
    "drifted",
    "flux_and_slope",
    "gather_basis",
    "kernel_array",
    "nan_signals",
    "output",
    "simulate",
    "trig_table",
    "unwrap",
]

F64 = NDArray[np.float64]
LoopArrays = tuple[F64, F64, F64, F64, F64, F64, float, F64, F64]
"""The kernel arguments of a loop: A_G, B_G, C_G, A_C, B_C, C_C, D_C, P, offset."""


def kernel_array(a: ArrayLike) -> NDArray[np.float64]:
    """float64, C-contiguous and writeable: the one array type the numba kernels are compiled for.

    A read-only array (a dataset's column, a frozen theta) would make numba compile and cache a
    second specialization of every kernel it reaches; a copy of such an input is cheap.

    Parameters
    ----------
    a : array_like
        Any numeric array.

    Returns
    -------
    ndarray of float64
        ``a`` itself when it already is one, else a copy.
    """
    return np.require(a, dtype=np.float64, requirements=("C", "W"))


@nb.njit(cache=True, nogil=True, fastmath=False)
def direct_basis(y0, harm, out, dout):
    m = out.size
    out[0] = 1.0
    dout[0] = 0.0
    for j in range(harm.size):
        h = harm[j]
        s = math.sin(h * y0)
        c = math.cos(h * y0)
        out[1 + 2 * j] = s
        out[2 + 2 * j] = c
        dout[1 + 2 * j] = h * c
        dout[2 + 2 * j] = -h * s
    return m


@nb.njit(cache=True, nogil=True, inline="always")
def unwrap(psi, yprev, n_m):
    """f_init's unwrapping Gamma(psi, n_m y_prev) / n_m, eq. (fimp)."""
    ref = n_m * yprev
    x = psi - ref + math.pi
    return (ref + x - TWO_PI * math.floor(x / TWO_PI) - math.pi) / n_m


@nb.njit(cache=True, nogil=True, inline="always")
def alpha_beta(P, off, dk):
    """f_init's projection (alpha, beta) = P (d - offset)."""
    al = 0.0
    be = 0.0
    for h in range(3):
        al += P[0, h] * (dk[h] - off[h])
        be += P[1, h] * (dk[h] - off[h])
    return al, be


@nb.njit(cache=True, nogil=True, inline="always")
def advance(A, B, x, v, out):
    """out = A x + B v (one state-space step), then x <- out."""
    n = x.size
    for i in range(n):
        acc = B[i] * v
        for j in range(n):
            acc += A[i, j] * x[j]
        out[i] = acc
    x[:] = out


@nb.njit(cache=True, nogil=True, inline="always")
def advance_sensitivity(A, B, S, dv, out):
    """out = A S + B dv for a sensitivity matrix S (states x parameters), p innermost."""
    n, p = S.shape
    for i in range(n):
        bi = B[i]
        for j in range(p):
            out[i, j] = bi * dv[j]
        for l in range(n):
            a = A[i, l]
            if a != 0.0:
                for j in range(p):
                    out[i, j] += a * S[l, j]


@nb.njit(cache=True, nogil=True, inline="always")
def diverged(y0, y0_last, u, n_m):
    """The loop left a sane range, or the angle moved half an electrical period in one sample
    (f_init aliases: the simulation no longer means anything)."""
    return not (abs(y0) < 1e12 and abs(u) < 1e15 and n_m * abs(y0 - y0_last) < math.pi)


@nb.njit(cache=True, nogil=True, inline="always")
def angle_and_sensitivity(Cg, xg, Sg, dy0):
    """y0 = C_G x_G and, into dy0, its sensitivity C_G S_G (p innermost)."""
    y0 = 0.0
    for i in range(xg.size):
        y0 += Cg[i] * xg[i]
    dy0[:] = 0.0
    for i in range(xg.size):
        ci = Cg[i]
        if ci != 0.0:
            for j in range(dy0.size):
                dy0[j] += ci * Sg[i, j]
    return y0


@nb.njit(cache=True, nogil=True, inline="always")
def flux_and_slope(theta, b, db, g, gp):
    """g_h = theta_h . beta(y0) and g'_h = theta_h . beta'(y0) for the three sensors."""
    for h in range(3):
        acc = 0.0
        dacc = 0.0
        for j in range(b.size):
            acc += theta[h, j] * b[j]
            dacc += theta[h, j] * db[j]
        g[h] = acc
        gp[h] = dacc


@nb.njit(cache=True, nogil=True, inline="always")
def output(C, x, D, e):
    """C x + D e of a single-output state space."""
    u = D * e
    for i in range(x.size):
        u += C[i] * x[i]
    return u


@nb.njit(cache=True, nogil=True, inline="always")
def convert(v, lo, hi, step, origin):
    """The ADC of :class:`SensorADC`: quantize to the code grid, then clip to the rails."""
    if step > 0.0:
        v = origin + step * math.floor((v - origin) / step + 0.5)
    if v < lo:
        v = lo
    elif v > hi:
        v = hi
    return v


@nb.njit(cache=True, nogil=True, inline="always")
def trig_table(y0, hmax, cs, sn):
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
def gather_basis(harm, cs, sn, b, db):
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
def cogging_torque(orders, coef, y0, creg, sreg):
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


@nb.njit(cache=True, nogil=True, inline="always")
def at_rails(gk, rlo, rhi, gf, live):
    """What f_init sees of the model flux: gf = gk clipped to the ADC rails [rlo, rhi] (the
    drive's f_init saw the clipped values), live_h = 1 where sensor h is within them, else 0
    (the clipped value does not move with theta)."""
    for h in range(3):
        v = gk[h]
        live[h] = 1.0
        if v < rlo[h]:
            v = rlo[h]
            live[h] = 0.0
        elif v > rhi[h]:
            v = rhi[h]
            live[h] = 0.0
        gf[h] = v


@nb.njit(cache=True, nogil=True, inline="always")
def drifted(drift, tau, gk, gp, sh):
    """The drifting sensors' signals in place: ``g_h <- (1 + gamma_h tau) g_h + delta_h tau``,
    ``g'_h <- (1 + gamma_h tau) g'_h`` and ``sh_h = 1 + gamma_h tau``."""
    for h in range(3):
        s = 1.0 + drift[2 * h] * tau
        gk[h] = s * gk[h] + drift[2 * h + 1] * tau
        gp[h] = s * gp[h]
        sh[h] = s


@nb.njit(cache=True, nogil=True)
def basis_scratch(harm, m, n_cog):
    """The scratch of one sample's basis and cogging torque, allocated once per kernel: cs, sn
    (max(harm) + 1, the trigonometric table), b, db (m, beta and its derivative), creg, sreg
    (n_cog, the cogging regressors)."""
    hmax = 0
    for j in range(harm.size):
        hmax = max(hmax, harm[j])
    return (np.empty(hmax + 1), np.empty(hmax + 1), np.empty(m), np.empty(m), np.empty(n_cog),
            np.empty(n_cog))  # fmt: skip


@nb.njit(cache=True, nogil=True)
def nan_signals(N):
    """y0, y, u (N,) and d (N, 3) of a simulation, NaN until written (NaN stays after a
    divergence)."""
    return np.full(N, np.nan), np.full(N, np.nan), np.full(N, np.nan), np.full((N, 3), np.nan)


@nb.njit(cache=True, nogil=True)
def simulate(Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, off, n_m, theta, harm, recursion, cog_k, cog_x,
             adc_lo, adc_hi, adc_step, adc_origin, drift, r, noise, td, s_gain, y_init, y0_start,
             as_model):  # fmt: skip
    """The closed loop of eq. (state_eq) over the N samples of r; NaN after a divergence.

    The one simulation of the bench (:func:`hallcal.sim.loop.simulate_loop`) and of the
    solver's model (:func:`hallcal.fit.gauss_newton.simulate_model`). harm: int64 harmonics;
    recursion: the basis by :func:`trig_table` (the solver's) or by direct sines (the bench's);
    the ADC (adc_*: per sensor; step 0 = no quantizer); drift (6,) or empty; noise (N, 3),
    td (N,), s_gain (N, 3): empty for none; y0_start: the true angle at rest [rad].
    ``as_model``: d is the model signal before the ADC (the d_sim of the residual) and the
    diverging sample is NaN; else d is what f_init saw and the diverging sample is kept.
    Returns (y0, y, u, d, plant input, ok)."""
    N = r.size
    ng = Ag.shape[0]
    nc = Ac.shape[0]
    m = theta.shape[1]
    xg = np.zeros(ng)
    xc = np.zeros(nc)
    xg2 = np.zeros(ng)
    xc2 = np.zeros(nc)
    cs, sn, b, db, creg, sreg = basis_scratch(harm, m, cog_k.size)
    hmax = cs.size - 1
    y0s, ys, us, ds = nan_signals(N)
    ts = np.full(N, np.nan)
    gk = np.empty(3)
    gp = np.empty(3)
    gf = np.empty(3)
    sh = np.empty(3)
    has_noise = noise.shape[0] > 0
    has_gain = s_gain.shape[0] > 0
    has_td = td.size > 0
    yprev = y_init
    y0_last = y0_start
    ok = True
    for k in range(N):
        y0 = y0_start
        for i in range(ng):
            y0 += Cg[i] * xg[i]
        if recursion:
            trig_table(y0, hmax, cs, sn)
            gather_basis(harm, cs, sn, b, db)
        else:
            direct_basis(y0, harm, b, db)
        flux_and_slope(theta, b, db, gk, gp)
        if has_gain:
            for h in range(3):
                gk[h] *= s_gain[k, h]
        if drift.size:
            drifted(drift, k / max(N - 1, 1) - 0.5, gk, gp, sh)
        for h in range(3):
            v = gk[h] + noise[k, h] if has_noise else gk[h]
            gf[h] = convert(v, adc_lo[h], adc_hi[h], adc_step[h], adc_origin[h])
        al, be = alpha_beta(P, off, gf)
        y = unwrap(math.atan2(be, al), yprev, n_m)
        e = r[k] - y
        u = output(Cc, xc, Dc, e)
        tc = cogging_torque(cog_k, cog_x, y0, creg, sreg)[0]
        tq = u + td[k] + tc if has_td else u + tc
        advance(Ac, Bc, xc, e, xc2)
        advance(Ag, Bg, xg, tq, xg2)
        y0s[k], ys[k], us[k], ts[k] = y0, y, u, tq
        for h in range(3):
            ds[k, h] = gk[h] if as_model else gf[h]
        yprev = y
        bad = diverged(y0, y0_last, u, n_m)
        y0_last = y0
        if bad:
            ok = False
            if as_model:
                y0s[k], ys[k], us[k], ts[k] = np.nan, np.nan, np.nan, np.nan
                for h in range(3):
                    ds[k, h] = np.nan
            break
    return y0s, ys, us, ds, ts, ok
