"""The dense forward-sensitivity Jacobian of the closed loop: the tests' independent oracle.

The straightforward recursion of :mod:`hallcal.sim.loop`'s docstring, one dense (N, 3, p) array
d d_sim / d x. The solver never forms it: its structured pass (``_sens_block`` of
:mod:`hallcal.fit.gauss_newton`) accumulates J^T J, J^T e and e^T e per sample block. The tests
compare that pass against this one and both against central differences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.sensor.flux import FluxModel
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import ClosedLoop, LoopStatus, _cogging_arrays
from hallcal.sim.loop_kernel import (
    advance,
    advance_sensitivity,
    alpha_beta,
    angle_and_sensitivity,
    basis_scratch,
    cogging_torque,
    direct_basis,
    diverged,
    flux_and_slope,
    kernel_array,
    nan_signals,
    output,
    unwrap,
)


@dataclass(frozen=True)
class LoopJacobian:
    """Noise-free simulation and the exact Jacobian of d_sim with respect to theta.

    Attributes
    ----------
    d : ndarray (N, 3)
        Simulated Hall signals.
    y0, y, u : ndarray (N,)
        Simulated angle, f_init output and torque command.
    jac : ndarray (N, 3, p)
        d d_sim[k, h] / d theta_j with theta flattened row-major (sensor-major, 3 x m).
    status : LoopStatus
        OK or DIVERGED.
    """

    d: NDArray[np.float64] = field(repr=False)
    y0: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    u: NDArray[np.float64] = field(repr=False)
    jac: NDArray[np.float64] = field(repr=False)
    status: LoopStatus = LoopStatus.OK


@nb.njit(cache=True)
def _jacobian_kernel(
    Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, off, n_m, harm, theta, r, y_init, jac, fit_gain, cog_k, cog_x,
    n_cog_fit,
):  # fmt: skip
    N = r.size
    ng = Ag.shape[0]
    nc = Ac.shape[0]
    m = theta.shape[1]
    jg = 3 * m  # column d / d log(c), plant input gain (when fit_gain)
    jc0 = 3 * m + (1 if fit_gain else 0)  # first cogging column (a_1, b_1, a_2, ...)
    p = jc0 + 2 * n_cog_fit  # the first n_cog_fit cogging terms are fitted
    xg = np.zeros(ng)
    xc = np.zeros(nc)
    xg2 = np.zeros(ng)
    xc2 = np.zeros(nc)
    Sg = np.zeros((ng, p))
    Sc = np.zeros((nc, p))
    Sg2 = np.zeros((ng, p))
    Sc2 = np.zeros((nc, p))
    dy0 = np.empty(p)
    dy = np.empty(p)
    du = np.empty(p)
    _, _, b, db, creg, sreg = basis_scratch(harm, m, cog_k.size)
    y0s, ys, us, ds = nan_signals(N)
    gp = np.empty(3)
    dk = np.empty(3)
    yprev = y_init
    y0_last = 0.0
    ok = True
    for k in range(N):
        y0 = angle_and_sensitivity(Cg, xg, Sg, dy0)
        direct_basis(y0, harm, b, db)
        flux_and_slope(theta, b, db, dk, gp)
        al, be = alpha_beta(P, off, dk)
        rho2 = al * al + be * be
        if not rho2 > 0.0:  # no angle at alpha = beta = 0 (or NaN): the model is degenerate
            ok = False
            break
        # d psi / d d_h
        c0 = (al * P[1, 0] - be * P[0, 0]) / (rho2 * n_m)
        c1 = (al * P[1, 1] - be * P[0, 1]) / (rho2 * n_m)
        c2 = (al * P[1, 2] - be * P[0, 2]) / (rho2 * n_m)
        q = c0 * gp[0] + c1 * gp[1] + c2 * gp[2]
        # Jacobian rows of d and dy
        for j in range(p):
            fb = dy0[j]
            jac[k, 0, j] = gp[0] * fb
            jac[k, 1, j] = gp[1] * fb
            jac[k, 2, j] = gp[2] * fb
            dy[j] = q * fb
        for j in range(m):
            jac[k, 0, j] += b[j]
            jac[k, 1, m + j] += b[j]
            jac[k, 2, 2 * m + j] += b[j]
            dy[j] += c0 * b[j]
            dy[m + j] += c1 * b[j]
            dy[2 * m + j] += c2 * b[j]
        y = unwrap(math.atan2(be, al), yprev, n_m)
        e = r[k] - y
        u = output(Cc, xc, Dc, e)
        tc, dtc = cogging_torque(cog_k, cog_x, y0, creg, sreg)
        w = u + tc  # plant input
        # dw = du + T_c'(y0) dy0 (+ the cogging regressors in their own columns)
        for j in range(p):
            du[j] = -Dc * dy[j] + dtc * dy0[j]
        for i in range(nc):
            ci = Cc[i]
            if ci != 0.0:
                for j in range(p):
                    du[j] += ci * Sc[i, j]
        for i in range(n_cog_fit):
            du[jc0 + 2 * i] += creg[i]
            du[jc0 + 2 * i + 1] += sreg[i]
        # state and sensitivity updates
        for j in range(p):
            dy[j] = -dy[j]  # de = -dy drives the controller
        advance_sensitivity(Ac, Bc, Sc, dy, Sc2)
        advance_sensitivity(Ag, Bg, Sg, du, Sg2)
        if fit_gain:
            # x+ = A x + c B w with Bg = c B: d/d log c adds Bg w
            for i in range(ng):
                Sg2[i, jg] += Bg[i] * w
        advance(Ac, Bc, xc, e, xc2)
        advance(Ag, Bg, xg, w, xg2)
        Sc, Sc2 = Sc2, Sc
        Sg, Sg2 = Sg2, Sg
        bad = diverged(y0, y0_last, u, n_m)
        y0_last = y0
        if bad:
            ok = False
            break
        y0s[k] = y0
        ys[k] = y
        us[k] = u
        for h in range(3):
            ds[k, h] = dk[h]
        yprev = y
    if not ok:  # never hand out uninitialised rows
        for kk in range(k, N):
            for h in range(3):
                for j in range(p):
                    jac[kk, h, j] = np.nan
    return y0s, ys, us, ds, ok


def loop_jacobian(
    loop: ClosedLoop,
    flux: FluxModel,
    r: ArrayLike,
    *,
    y_initial: float = 0.0,
    out: NDArray[np.float64] | None = None,
    fit_gain: bool = False,
    cogging: CoggingTorque | None = None,
    fit_cogging: bool = False,
) -> LoopJacobian:
    """Noise-free simulation of eq. (state_eq) with the exact, dense Jacobian d d_sim / d x.

    The straightforward forward-sensitivity recursion of :mod:`hallcal.sim.loop`'s docstring,
    one dense (N, 3, p) array: the reference against which the structured Gauss-Newton system
    of :mod:`hallcal.fit.gauss_newton` is tested (the fit itself never forms it).

    Parameters
    ----------
    loop : ClosedLoop
        Plant, controller and f_init of the loop (eq. (state_eq)).
    flux : FluxModel
        g_theta with a Fourier basis; the derivatives are taken with respect to its theta.
    r : array_like (N,)
        Reference [rad].
    y_initial : float, keyword-only
        f_init's estimate before the first sample [rad].
    out : ndarray (N, 3, p), keyword-only, optional
        Preallocated Jacobian storage.
    fit_gain : bool, keyword-only
        Append the column d d_sim / d log(c) for a factor c on the plant input matrix
        (``B_G -> c B_G``, the unknown BLA gain of eq. c_hat), so that c can be refined jointly.
    cogging : CoggingTorque, optional
        Cogging torque T_c(y0) at the plant input (part of the simulated loop).
    fit_cogging : bool
        Append the columns d d_sim / d (a_1, b_1, a_2, b_2, ...) of the cogging coefficients,
        including the feedback term ``dT_c/dy0 dy0`` in every column.

    Returns
    -------
    LoopJacobian
        Simulated d, y0, y, u and the Jacobian; its columns are theta (3 m, sensor-major),
        then log c (``fit_gain``), then the cogging coefficients. After a divergence the
        remaining samples and Jacobian rows are NaN and the status is DIVERGED.
    """
    r = kernel_array(r)
    N = r.size
    n_fit = len(cogging.orders) if (fit_cogging and cogging is not None) else 0
    # the fitted orders first (their columns), then the loop's own, fixed cogging torque
    cog_k, cog_x = _cogging_arrays(cogging, loop.cogging)
    p = flux.theta.size + (1 if fit_gain else 0) + 2 * n_fit
    jac = np.empty((N, 3, p)) if out is None else out
    if jac.shape != (N, 3, p):
        raise ValueError(f"out must have shape {(N, 3, p)}")
    y0, y, u, d, ok = _jacobian_kernel(
        *loop.kernel_arrays(),
        float(loop.pole_pairs),
        np.asarray(flux.basis.harmonics, dtype=np.int64),
        kernel_array(flux.theta),
        r,
        float(y_initial),
        jac,
        bool(fit_gain),
        cog_k,
        cog_x,
        n_fit,
    )
    return LoopJacobian(d, y0, y, u, jac, LoopStatus.OK if ok else LoopStatus.DIVERGED)
