"""The closed loop of Fig. cl_scheme / eq. (state_eq) and its forward sensitivities, written once.

The numba steps of one sample, shared by the simulator (:mod:`hallcal.sim.loop`: the virtual
bench, the dense Jacobian oracle) and the solver (:mod:`hallcal.fit.gauss_newton`: the model
simulation and the structured Gauss-Newton pass). Per sample k (zero initial conditions,
y(t_{-1}) = y_initial):

    y0[k]  = y0_start + C_G x_G[k]                   plant output (true angle) [rad]
    g[k]   = s_k g_theta(y0[k])                      flux (s_k: sensor gain, default 1), then
    g_h   <- (1 + gamma_h tau) g_h + delta_h tau     drift over the run (tau = k/(N-1) - 1/2)
    d[k]   = ADC(g[k] + v[k])                        what f_init sees (quantizer, then rails)
    y[k]   = f_init(d[k]; y[k-1])                    eq. (fimp) [rad]
    e[k]   = r[k] - y[k]
    u[k]   = C_C x_C[k] + D_C e[k]                   torque command
    x_C[k+1] = A_C x_C[k] + B_C e[k]
    x_G[k+1] = A_G x_G[k] + B_G (u[k] + T_d[k] + T_c(y0[k]))     (T_c: cogging torque)

The plant is the exact ZOH discretization of G(s) with its input delay (:mod:`hallcal.sim.lti`),
so it has no direct feedthrough and the loop is explicit.

Sensitivities (forward mode, exact). With ``g_h(y0) = beta(y0) theta_h`` and
``y = Gamma(atan2(beta_ab, alpha_ab), n_m y_prev) / n_m`` the unwrapping adds an integer multiple
of 2 pi, so ``dy = (alpha d(beta_ab) - beta_ab d(alpha_ab)) / (n_m (alpha^2 + beta_ab^2))``
(a sensor at a rail does not move: its term is 0). Writing ``S_G = dx_G/dx``, ``S_C = dx_C/dx``:

    dy0   = C_G S_G
    dd_h  = g_h'(y0) dy0 + e_h kron beta(y0)          (feedback term + direct term)
    dy    = (P_alpha dd, P_beta dd) -> as above
    dw    = C_C S_C - D_C dy + T_c'(y0) dy0 (+ [cos k y0, sin k y0] for the cogging columns)
    S_C+  = A_C S_C - B_C dy
    S_G+  = A_G S_G + B_G dw (+ B_G w for log c, the plant input gain)

The feedback term ``g'(y0) dy0`` is what makes simulation-error minimization converge
(docs/design.md). The basis comes either from direct sines and cosines per harmonic (the
simulator) or from one sine and cosine per sample and the angle-addition recursion (the solver,
faster; the two differ by rounding, ~n eps at harmonic n). float64 throughout.

The model's kernel arguments (:data:`ModelArrays`): the loop's (A_G, B_G, C_G, A_C, B_C, C_C,
D_C, P, offset), n_m, theta (3, m), harmonics (int64), recursion, cogging orders and interleaved
coefficients, the ADC (low, high, step, origin per sensor) and the drift (6,) or empty.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "F64",
    "LoopArrays",
    "ModelArrays",
    "angle_and_sensitivity",
    "cogging_torque",
    "dense_jacobian",
    "diverged",
    "flux_and_slope",
    "flux_basis",
    "kernel_array",
    "loop_sample",
    "loop_scratch",
    "loop_step",
    "sensitivity_step",
    "sensor_step",
    "simulate",
    "trig_scratch",
    "trig_table",
]

TWO_PI = 2.0 * math.pi

F64 = NDArray[np.float64]
LoopArrays = tuple[F64, F64, F64, F64, F64, F64, float, F64, F64]
"""The kernel arguments of a loop: A_G, B_G, C_G, A_C, B_C, C_C, D_C, P, offset."""

ModelArrays = tuple[
    F64, F64, F64, F64, F64, F64, float, F64, F64,
    float, F64, NDArray[np.int64], bool, F64, F64, F64, F64, F64, F64, F64,
]  # fmt: skip
"""The kernel arguments of a model: LoopArrays, n_m, theta, harm, recursion, cog_k, cog_x,
adc_lo, adc_hi, adc_step, adc_origin, drift."""


def kernel_array(a: ArrayLike) -> NDArray[np.float64]:
    """float64, C-contiguous and writeable: the one array type the numba kernels are compiled for.

    A read-only array (a dataset's column, a frozen theta) would make numba compile and cache a
    second specialization of every kernel it reaches; a copy of such an input is cheap.
    """
    return np.require(a, dtype=np.float64, requirements=("C", "W"))


# ------------------------------------------------------------------------------------------------
# Small steps
# ------------------------------------------------------------------------------------------------


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
def trig_scratch(harm):
    """Two empty tables cs, sn of size max(harm) + 1 for :func:`flux_basis`."""
    hmax = 0
    for j in range(harm.size):
        hmax = max(hmax, harm[j])
    return np.empty(hmax + 1), np.empty(hmax + 1)


@nb.njit(cache=True, nogil=True, inline="always")
def flux_basis(y0, harm, recursion, cs, sn, b, db):
    """beta(y0) = [1, sin h_1 y0, cos h_1 y0, ...] and d beta / d y0, eq. (basis).

    ``recursion``: from :func:`trig_table` into cs, sn (size max(harm) + 1; the solver's
    per-thread tables); else one sine and cosine per harmonic (the simulator's)."""
    b[0] = 1.0
    db[0] = 0.0
    if recursion:
        trig_table(y0, cs.size - 1, cs, sn)
        for j in range(harm.size):
            h = harm[j]
            b[1 + 2 * j] = sn[h]
            b[2 + 2 * j] = cs[h]
            db[1 + 2 * j] = h * cs[h]
            db[2 + 2 * j] = -h * sn[h]
    else:
        for j in range(harm.size):
            h = harm[j]
            s = math.sin(h * y0)
            c = math.cos(h * y0)
            b[1 + 2 * j] = s
            b[2 + 2 * j] = c
            db[1 + 2 * j] = h * c
            db[2 + 2 * j] = -h * s


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
def cogging_torque(orders, coef, y0, creg, sreg):
    """T_c(y0), dT_c/dy0 and the regressors cos(k y0), sin(k y0) per order, for interleaved
    coefficients [a_1, b_1, ...] (:mod:`hallcal.sim.cogging`)."""
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
def _convert(v, lo, hi, step, origin):
    """The ADC: quantize to the code grid (step > 0), then clip to the rails; 1.0 when the
    value is within the rails, 0.0 at a rail (the clipped value does not move with theta)."""
    if step > 0.0:
        v = origin + step * math.floor((v - origin) / step + 0.5)
    if v < lo:
        return lo, 0.0
    if v > hi:
        return hi, 0.0
    return v, 1.0


@nb.njit(cache=True, nogil=True, inline="always")
def _drifted(drift, tau, g, gp, sh):
    """The drifting sensors' signals in place: ``g_h <- (1 + gamma_h tau) g_h + delta_h tau``,
    ``g'_h <- (1 + gamma_h tau) g'_h`` and ``sh_h = 1 + gamma_h tau``."""
    for h in range(3):
        s = 1.0 + drift[2 * h] * tau
        g[h] = s * g[h] + drift[2 * h + 1] * tau
        gp[h] = s * gp[h]
        sh[h] = s


@nb.njit(cache=True, nogil=True, inline="always")
def sensor_step(k, N, theta, b, db, s_gain, drift, noise, lo, hi, step, origin, g, gp, gfl, sh,
                seen, live):  # fmt: skip
    """The Hall signals of sample k: the flux g and its slope g' (times the sensor gain s_k when
    ``s_gain`` has rows; with the drift when ``drift`` has entries: ``gfl`` the flux before it,
    ``sh`` the gain factor 1 + gamma tau), then what f_init sees, ``seen`` = ADC(g + v) (noise
    v when it has rows) and ``live``. Returns tau (0 without drift)."""
    flux_and_slope(theta, b, db, g, gp)
    if s_gain.shape[0] > 0:
        for h in range(3):
            g[h] *= s_gain[k, h]
            gp[h] *= s_gain[k, h]
    tau = 0.0
    if drift.size:
        tau = k / max(N - 1, 1) - 0.5
        gfl[:] = g
        _drifted(drift, tau, g, gp, sh)
    for h in range(3):
        v = g[h] + noise[k, h] if noise.shape[0] > 0 else g[h]
        seen[h], live[h] = _convert(v, lo[h], hi[h], step[h], origin[h])
    return tau


@nb.njit(cache=True, nogil=True, inline="always")
def _unwrap(psi, yprev, n_m):
    """f_init's unwrapping Gamma(psi, n_m y_prev) / n_m, eq. (fimp)."""
    ref = n_m * yprev
    x = psi - ref + math.pi
    return (ref + x - TWO_PI * math.floor(x / TWO_PI) - math.pi) / n_m


@nb.njit(cache=True, nogil=True, inline="always")
def _advance(A, B, x, v, out):
    """out = A x + B v (one state-space step), then x <- out."""
    n = x.size
    for i in range(n):
        acc = B[i] * v
        for j in range(n):
            acc += A[i, j] * x[j]
        out[i] = acc
    x[:] = out


@nb.njit(cache=True, nogil=True, inline="always")
def _advance_sensitivity(A, B, S, dv, out):
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


# ------------------------------------------------------------------------------------------------
# One sample of the loop and of its sensitivities
# ------------------------------------------------------------------------------------------------


@nb.njit(cache=True, nogil=True, inline="always")
def loop_step(Ag, Bg, Ac, Bc, Cc, Dc, P, off, n_m, xg, xc, xg2, xc2, seen, yprev, r_k, td, k, tc):
    """f_init on what it sees, the controller, and one step of both state spaces.

    ``seen``: the Hall signals f_init sees; ``td``: the torque disturbance T_d (N,) or empty;
    ``tc``: T_c(y0). Advances xc, xg in place (xc2, xg2 scratch). Returns
    (alpha, beta, y, u, w) with w = u + T_d + T_c the plant input."""
    al = 0.0
    be = 0.0
    for h in range(3):
        al += P[0, h] * (seen[h] - off[h])
        be += P[1, h] * (seen[h] - off[h])
    y = _unwrap(math.atan2(be, al), yprev, n_m)
    e = r_k - y
    u = Dc * e
    for i in range(xc.size):
        u += Cc[i] * xc[i]
    w = u + td[k] + tc if td.size else u + tc
    _advance(Ac, Bc, xc, e, xc2)
    _advance(Ag, Bg, xg, w, xg2)
    return al, be, y, u, w


@nb.njit(cache=True, nogil=True, inline="always")
def _column_step(Ag, Bg, Ac, Bc, Cc, Dc, P, n_m, al, be, tau, w, dtc, live, gp, sh, gfl, b,
                 creg, sreg, cols, dy0, S, ck, dy, dw):  # fmt: skip
    """Advance the sensitivities of the parameter columns j0..j1-1 by one sample (module
    docstring): ``S = (Sg, Sc, Sg2, Sc2)``, into Sg2, Sc2 the next Sg, Sc.

    ``cols = (j0, j1, jgain, jcog, n_cog_fit, jdrift)``: the block's columns; theta (3 m,
    sensor-major) from 0, log c at ``jgain``, the fitted cogging coefficients from ``jcog`` (the
    first ``n_cog_fit`` orders of creg, sreg), the drift (gamma_h, delta_h) from ``jdrift`` (-1:
    none). al, be, w: f_init's projection and the plant input of :func:`loop_step`; tau, live,
    gp, sh, gfl: of :func:`sensor_step`; dtc, creg, sreg: of :func:`cogging_torque`; dy0 the
    angle's sensitivity; ``ck`` receives d y / d d_h, dy and dw are scratch. Returns False when
    f_init has no angle (alpha = beta = 0, or NaN: the model is degenerate)."""
    j0, j1, jgain, jcog, n_cog_fit, jdrift = cols
    Sg, Sc, Sg2, Sc2 = S
    m = b.size
    rho2 = al * al + be * be
    if not rho2 > 0.0:
        return False
    for h in range(3):
        ck[h] = (al * P[1, h] - be * P[0, h]) / (rho2 * n_m) * live[h]  # d y / d d_h
    q = ck[0] * gp[0] + ck[1] * gp[1] + ck[2] * gp[2]
    pb = j1 - j0
    for jl in range(pb):  # feedback term on every column
        dy[jl] = q * dy0[jl]
    for h in range(3):  # direct term I_3 kron (sh beta) on the theta columns of this block
        for j in range(max(j0, h * m), min(j1, (h + 1) * m)):
            dy[j - j0] += ck[h] * sh[h] * b[j - h * m]
    if jdrift >= 0:  # the drift columns' direct terms (tau g_h, tau) of sensor h
        for h in range(3):
            c = jdrift + 2 * h
            if j0 <= c < j1:
                dy[c - j0] += ck[h] * (tau * gfl[h])
            if j0 <= c + 1 < j1:
                dy[c + 1 - j0] += ck[h] * tau
    for jl in range(pb):  # dw = du + T_c'(y0) dy0 (+ the cogging regressors)
        dw[jl] = -Dc * dy[jl] + dtc * dy0[jl]
    for i in range(Cc.size):
        ci = Cc[i]
        if ci != 0.0:
            for jl in range(pb):
                dw[jl] += ci * Sc[i, jl]
    for i in range(n_cog_fit):
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
        for i in range(Bg.size):
            Sg2[i, jgain - j0] += Bg[i] * w
    return True


@nb.njit(cache=True, nogil=True, inline="always")
def loop_scratch(model, p):
    """The scratch of :func:`loop_sample` and :func:`sensitivity_step` for a model and a block
    of p sensitivity columns (0 for the simulation): (cs, sn, b, db, creg, sreg, v3, dy0, dy,
    dw, none, no_td); the rows of v3 (7, 3) are g, g', the flux before the drift, sh (1), what
    f_init sees, live and d y / d d; none, no_td: an empty (0, 3) and (0,) array."""
    theta, harm, cog_k = model[10], model[11], model[13]
    cs, sn = trig_scratch(harm)
    m = theta.shape[1]
    v3 = np.empty((7, 3))
    v3[3] = 1.0
    return (cs, sn, np.empty(m), np.empty(m), np.empty(cog_k.size), np.empty(cog_k.size), v3,
            np.empty(p), np.empty(p), np.empty(p), np.zeros((0, 3)), np.zeros(0))  # fmt: skip


@nb.njit(cache=True, nogil=True, inline="always")
def loop_sample(model, k, r, y0, yprev, xs, scratch, noise, td, s_gain):
    """Sample k of the loop of ``model`` (:data:`ModelArrays`) at the true angle y0: the flux
    basis, the Hall signals (:func:`sensor_step`), the cogging torque and :func:`loop_step`.

    ``xs = (xg, xc, xg2, xc2)`` advance in place; ``scratch`` of :func:`loop_scratch` receives
    beta, the signals and the cogging regressors; noise, td, s_gain as in :func:`simulate`.
    Returns (tau, dT_c/dy0, alpha, beta, y, u, w)."""
    (Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, off, n_m, theta, harm, recursion, cog_k, cog_x,
     adc_lo, adc_hi, adc_step, adc_origin, drift) = model  # fmt: skip
    cs, sn, b, db, creg, sreg, v3 = scratch[:7]
    flux_basis(y0, harm, recursion, cs, sn, b, db)
    tau = sensor_step(k, r.size, theta, b, db, s_gain, drift, noise, adc_lo, adc_hi, adc_step,
                      adc_origin, v3[0], v3[1], v3[2], v3[3], v3[4], v3[5])  # fmt: skip
    tc, dtc = cogging_torque(cog_k, cog_x, y0, creg, sreg)
    al, be, y, u, w = loop_step(Ag, Bg, Ac, Bc, Cc, Dc, P, off, n_m, xs[0], xs[1], xs[2], xs[3],
                                v3[4], yprev, r[k], td, k, tc)  # fmt: skip
    return tau, dtc, al, be, y, u, w


@nb.njit(cache=True, nogil=True, inline="always")
def sensitivity_step(model, k, r, yprev, flip, state, scratch, cols):
    """Sample k of the noise-free loop of ``model`` (:data:`ModelArrays`) with the
    sensitivities of the columns ``cols = (j0, j1, jgain, jcog, n_cog_fit, jdrift)``
    (:func:`_column_step`).

    ``state = (xg, xc, xg2, xc2, Sg, Sc, Sg2, Sc2)``: the states advance in place; the
    sensitivities alternate between the two pairs (``flip``: the current ones are Sg2, Sc2; the
    caller toggles it after each sample). ``scratch`` of :func:`loop_scratch` holds the
    sample's beta (b), g, g', sh, tau's flux and dy0 for the caller's rows.
    Returns (ok, y0, y, u, tau); ok is False when f_init has no angle."""
    Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, n_m = model[:8] + (model[9],)
    xg, xc, xg2, xc2, Sga, Sca, Sgb, Scb = state
    b, creg, sreg, v3, dy0, dy, dw, none, no_td = scratch[2], *scratch[4:]
    if flip:
        Sg, Sc, Sg2, Sc2 = Sgb, Scb, Sga, Sca
    else:
        Sg, Sc, Sg2, Sc2 = Sga, Sca, Sgb, Scb
    y0 = angle_and_sensitivity(Cg, xg, Sg, dy0)
    tau, dtc, al, be, y, u, w = loop_sample(model, k, r, y0, yprev, (xg, xc, xg2, xc2), scratch,
                                            none, no_td, none)  # fmt: skip
    gp, gfl, sh, live, ck = v3[1], v3[2], v3[3], v3[5], v3[6]
    ok = _column_step(Ag, Bg, Ac, Bc, Cc, Dc, P, n_m, al, be, tau, w, dtc, live, gp, sh, gfl, b,
                      creg, sreg, cols, dy0, (Sg, Sc, Sg2, Sc2), ck, dy, dw)  # fmt: skip
    return ok, y0, y, u, tau


# ------------------------------------------------------------------------------------------------
# The simulation
# ------------------------------------------------------------------------------------------------


@nb.njit(cache=True, nogil=True)
def simulate(model, r, noise, td, s_gain, y_init, y0_start, as_model):
    """The closed loop over the N samples of r (module docstring); NaN after a divergence.

    noise (N, 3), td (N,), s_gain (N, 3): empty for none. ``as_model``: the solver's model
    (d = the model signal before the ADC, the d_sim of the residual, and the diverging sample
    NaN), else the bench (d = what f_init saw; the diverging sample kept).
    Returns (y0, y, u, d, plant input, ok)."""
    Cg, n_m = model[2], model[9]
    N = r.size
    xs = (np.zeros(model[0].shape[0]), np.zeros(model[3].shape[0]),
          np.zeros(model[0].shape[0]), np.zeros(model[3].shape[0]))  # fmt: skip
    scratch = loop_scratch(model, 0)
    g, seen = scratch[6][0], scratch[6][4]
    y0s, ys, us, ts = np.full((4, N), np.nan)
    ds = np.full((N, 3), np.nan)
    yprev = y_init
    y0_last = y0_start
    ok = True
    for k in range(N):
        y0 = y0_start
        for i in range(Cg.size):
            y0 += Cg[i] * xs[0][i]
        _, _, _, _, y, u, w = loop_sample(model, k, r, y0, yprev, xs, scratch, noise, td, s_gain)
        y0s[k], ys[k], us[k], ts[k] = y0, y, u, w
        for h in range(3):
            ds[k, h] = g[h] if as_model else seen[h]
        yprev = y
        if diverged(y0, y0_last, u, n_m):
            ok = False
            if as_model:
                y0s[k], ys[k], us[k], ts[k] = np.nan, np.nan, np.nan, np.nan
                ds[k, :] = np.nan
            break
        y0_last = y0
    return y0s, ys, us, ds, ts, ok


@nb.njit(cache=True, nogil=True)
def dense_jacobian(model, r, y_init, jac, jgain, jcog, n_cog_fit):
    """The noise-free loop of ``model`` (:data:`hallcal.sim.loop_kernel.ModelArrays`) and the
    dense rows ``J_k = g'(y0) dy0^T + I_3 kron beta(y0)`` of every parameter column (theta,
    log c at ``jgain``, cogging from ``jcog``) into jac (N, 3, p): the oracle of the structured
    pass of :mod:`hallcal.fit.gauss_newton`. Returns (y0, y, u, d, ok); after a divergence the
    remaining samples and rows are NaN."""
    N, p = r.size, jac.shape[2]
    ng, nc = model[0].shape[0], model[3].shape[0]
    x0, s0 = (np.zeros(ng), np.zeros(nc)), (np.zeros((ng, p)), np.zeros((nc, p)))
    state = (*x0, np.zeros(ng), np.zeros(nc), *s0, np.zeros((ng, p)), np.zeros((nc, p)))
    scratch = loop_scratch(model, p)
    b, v3, dy0 = scratch[2], scratch[6], scratch[7]
    cols = (0, p, jgain, jcog, n_cog_fit, -1)
    y0s, ys, us = np.full(N, np.nan), np.full(N, np.nan), np.full(N, np.nan)
    ds = np.full((N, 3), np.nan)
    yprev, y0_last, flip = y_init, 0.0, False
    for k in range(N):
        ok, y0, y, u, _ = sensitivity_step(model, k, r, yprev, flip, state, scratch, cols)
        flip = not flip
        for h in range(3):  # feedback term, then the direct term on the theta columns
            for j in range(p):
                jac[k, h, j] = v3[1, h] * dy0[j]
            for j in range(b.size):
                jac[k, h, h * b.size + j] += b[j]
        if not ok or diverged(y0, y0_last, u, model[9]):
            jac[k:] = np.nan  # never hand out uninitialised rows
            return y0s, ys, us, ds, False
        yprev = y
        y0s[k], ys[k], us[k] = y0, y, u
        ds[k, :] = v3[0]
        y0_last = y0
    return y0s, ys, us, ds, True
