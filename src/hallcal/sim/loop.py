"""Closed-loop simulation of Fig. cl_scheme / eq. (state_eq) and its exact parameter sensitivities.

Per sample k (zero initial conditions, y(t_{-1}) = y_initial):

    y0[k]  = C_G x_G[k]                              plant output (true angle) [rad]
    d[k]   = g_theta(y0[k]) + v[k]                   Hall signals
    y[k]   = f_init(d[k]; y[k-1])                    eq. (fimp) [rad]
    e[k]   = r[k] - y[k]
    u[k]   = C_C x_C[k] + D_C e[k]                   torque command
    x_C[k+1] = A_C x_C[k] + B_C e[k]
    x_G[k+1] = A_G x_G[k] + B_G (u[k] + T_d[k] + T_cog(y0[k]))

The plant is the exact ZOH discretization of G(s) with its input delay (:mod:`hallcal.sim.lti`), so
it has no direct feedthrough and the loop is explicit.

Sensitivities (forward mode, exact). With ``g_h(y0) = beta(y0) theta_h`` and
``y = Gamma(atan2(beta_ab, alpha_ab), n_m y_prev) / n_m`` the unwrapping adds an integer multiple of
2 pi, so ``dy = (alpha d(beta_ab) - beta_ab d(alpha_ab)) / (n_m (alpha^2 + beta_ab^2))``. Writing
``S_G = dx_G/dtheta`` and ``S_C = dx_C/dtheta``:

    dy0   = C_G S_G
    dd_h  = g_h'(y0) dy0 + e_h kron beta(y0)          (feedback term + direct term)
    dy    = (P_alpha dd, P_beta dd) -> as above
    du    = C_C S_C - D_C dy
    S_C+  = A_C S_C - B_C dy
    S_G+  = A_G S_G + B_G du

The feedback term ``g'(y0) dy0`` is what makes simulation-error minimization converge
(docs/design.md).
The hot loops are compiled with numba; float64 throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.sensor.flux import FluxModel
from hallcal.sensor.reconstruction import clarke_matrix
from hallcal.sim.lti import ContinuousTF, DiscreteTF, StateSpace

__all__ = ["ClosedLoop", "LoopJacobian", "LoopResult", "loop_jacobian", "simulate_loop"]

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class ClosedLoop:
    """The loop of Fig. cl_scheme: discrete plant, discrete controller and f_init.

    Attributes
    ----------
    plant : StateSpace
        Discrete plant from torque to angle [rad per torque unit], no feedthrough.
    controller : StateSpace
        Discrete controller C(q) from e [rad] to u.
    pole_pairs : int
        n_m.
    projection : ndarray (2, 3)
        f_init's projection (Clarke rows by default).
    offset : ndarray (3,)
        f_init's sensor offsets.
    """

    plant: StateSpace
    controller: StateSpace
    pole_pairs: int
    projection: NDArray[np.float64] = field(default_factory=lambda: clarke_matrix()[:2])
    offset: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if self.plant.D != 0.0:
            raise ValueError("the discrete plant must have no direct feedthrough")
        if self.plant.dt is None or self.controller.dt is None:
            raise ValueError("plant and controller must be discrete")

    @classmethod
    def from_transfer_functions(
        cls,
        plant: ContinuousTF,
        controller: DiscreteTF,
        sample_time: float,
        pole_pairs: int,
        *,
        projection: ArrayLike | None = None,
        offset: ArrayLike | None = None,
    ) -> ClosedLoop:
        """Discretize G(s) exactly (ZOH with delay) and realize C(q) in state space."""
        return cls(
            plant.discretize(sample_time),
            controller.state_space(sample_time),
            int(pole_pairs),
            clarke_matrix()[:2] if projection is None else np.asarray(projection, float),
            np.zeros(3) if offset is None else np.asarray(offset, float),
        )

    def with_plant_gain(self, c: float) -> ClosedLoop:
        """The loop with the plant input matrix scaled by c (eq. c_hat: B_G -> c B_G)."""
        p = self.plant
        return ClosedLoop(
            StateSpace(p.A, c * p.B, p.C, p.D, p.dt),
            self.controller,
            self.pole_pairs,
            self.projection,
            self.offset,
        )

    def _arrays(self) -> tuple:
        p, c = self.plant, self.controller
        return (
            np.ascontiguousarray(p.A, dtype=np.float64),
            np.ascontiguousarray(p.B, dtype=np.float64),
            np.ascontiguousarray(p.C, dtype=np.float64),
            np.ascontiguousarray(c.A, dtype=np.float64),
            np.ascontiguousarray(c.B, dtype=np.float64),
            np.ascontiguousarray(c.C, dtype=np.float64),
            float(c.D),
            np.ascontiguousarray(self.projection, dtype=np.float64),
            np.ascontiguousarray(self.offset, dtype=np.float64),
        )


@dataclass(frozen=True)
class LoopResult:
    """Simulated signals, one entry per sample.

    Attributes
    ----------
    y0 : true (simulated) angle [rad]; y : f_init output [rad]; u : torque command;
    d : Hall signals (N, 3) including noise; torque : total plant input u + T_d + T_cog;
    status : "ok", or "diverged" when the loop went unstable: the states left a sane range or the
    angle moved more than half an electrical period in one sample, so that f_init aliases
    (the remaining samples are NaN).
    """

    y0: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    u: NDArray[np.float64] = field(repr=False)
    d: NDArray[np.float64] = field(repr=False)
    torque: NDArray[np.float64] = field(repr=False)
    status: str = "ok"


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
    status : str
        "ok" or "diverged".
    """

    d: NDArray[np.float64] = field(repr=False)
    y0: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    u: NDArray[np.float64] = field(repr=False)
    jac: NDArray[np.float64] = field(repr=False)
    status: str = "ok"


@nb.njit(cache=True, fastmath=False)
def _basis(y0, harm, out, dout):
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


@nb.njit(cache=True, inline="always")
def _unwrap(psi, yprev, n_m):
    """f_init's unwrapping Gamma(psi, n_m y_prev) / n_m, eq. (fimp)."""
    ref = n_m * yprev
    x = psi - ref + math.pi
    return (ref + x - TWO_PI * math.floor(x / TWO_PI) - math.pi) / n_m


@nb.njit(cache=True, inline="always")
def _alpha_beta(P, off, dk):
    """f_init's projection (alpha, beta) = P (d - offset)."""
    al = 0.0
    be = 0.0
    for h in range(3):
        al += P[0, h] * (dk[h] - off[h])
        be += P[1, h] * (dk[h] - off[h])
    return al, be


@nb.njit(cache=True, inline="always")
def _advance(A, B, x, v, out):
    """out = A x + B v (one state-space step), then x <- out."""
    n = x.size
    for i in range(n):
        acc = B[i] * v
        for j in range(n):
            acc += A[i, j] * x[j]
        out[i] = acc
    x[:] = out


@nb.njit(cache=True, inline="always")
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


@nb.njit(cache=True, inline="always")
def _diverged(y0, y0_last, u, n_m):
    """The loop left a sane range, or the angle moved half an electrical period in one sample
    (f_init aliases: the simulation no longer means anything)."""
    return not (abs(y0) < 1e12 and abs(u) < 1e15 and n_m * abs(y0 - y0_last) < math.pi)


@nb.njit(cache=True, inline="always")
def _angle_and_sensitivity(Cg, xg, Sg, dy0):
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


@nb.njit(cache=True, inline="always")
def _flux_and_slope(theta, b, db, g, gp):
    """g_h = theta_h . beta(y0) and g'_h = theta_h . beta'(y0) for the three sensors."""
    for h in range(3):
        acc = 0.0
        dacc = 0.0
        for j in range(b.size):
            acc += theta[h, j] * b[j]
            dacc += theta[h, j] * db[j]
        g[h] = acc
        gp[h] = dacc


@nb.njit(cache=True, inline="always")
def _output(C, x, D, e):
    """C x + D e of a single-output state space."""
    u = D * e
    for i in range(x.size):
        u += C[i] * x[i]
    return u


@nb.njit(cache=True)
def _simulate_kernel(
    Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, off, n_m, harm, theta, r, noise, td, cog_amp, cog_per, y_init
):
    N = r.size
    ng = Ag.shape[0]
    nc = Ac.shape[0]
    m = theta.shape[1]
    xg = np.zeros(ng)
    xc = np.zeros(nc)
    xg2 = np.zeros(ng)
    xc2 = np.zeros(nc)
    b = np.empty(m)
    db = np.empty(m)
    y0s = np.empty(N)
    ys = np.empty(N)
    us = np.empty(N)
    ds = np.empty((N, 3))
    ts = np.empty(N)
    yprev = y_init
    y0_last = 0.0
    ok = True
    dk = np.empty(3)
    for k in range(N):
        y0 = 0.0
        for i in range(ng):
            y0 += Cg[i] * xg[i]
        _basis(y0, harm, b, db)
        for h in range(3):
            acc = 0.0
            for j in range(m):
                acc += theta[h, j] * b[j]
            dk[h] = acc + noise[k, h]
            ds[k, h] = dk[h]
        al, be = _alpha_beta(P, off, dk)
        y = _unwrap(math.atan2(be, al), yprev, n_m)
        e = r[k] - y
        u = _output(Cc, xc, Dc, e)
        tq = u + td[k]
        if cog_amp != 0.0:
            tq += cog_amp * math.sin(cog_per * y0)
        _advance(Ac, Bc, xc, e, xc2)
        _advance(Ag, Bg, xg, tq, xg2)
        y0s[k] = y0
        ys[k] = y
        us[k] = u
        ts[k] = tq
        yprev = y
        bad = _diverged(y0, y0_last, u, n_m)
        y0_last = y0
        if bad:
            ok = False
            for kk in range(k + 1, N):
                y0s[kk] = np.nan
                ys[kk] = np.nan
                us[kk] = np.nan
                ts[kk] = np.nan
                for h in range(3):
                    ds[kk, h] = np.nan
            break
    return y0s, ys, us, ds, ts, ok


@nb.njit(cache=True)
def _jacobian_kernel(
    Ag, Bg, Cg, Ac, Bc, Cc, Dc, P, off, n_m, harm, theta, r, y_init, jac, fit_gain
):
    N = r.size
    ng = Ag.shape[0]
    nc = Ac.shape[0]
    m = theta.shape[1]
    p = 3 * m + (1 if fit_gain else 0)  # last column: d / d log(c), plant input gain
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
    b = np.empty(m)
    db = np.empty(m)
    y0s = np.empty(N)
    ys = np.empty(N)
    us = np.empty(N)
    ds = np.empty((N, 3))
    gp = np.empty(3)
    dk = np.empty(3)
    yprev = y_init
    y0_last = 0.0
    ok = True
    for k in range(N):
        y0 = _angle_and_sensitivity(Cg, xg, Sg, dy0)
        _basis(y0, harm, b, db)
        _flux_and_slope(theta, b, db, dk, gp)
        for h in range(3):
            ds[k, h] = dk[h]
        al, be = _alpha_beta(P, off, dk)
        rho2 = al * al + be * be
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
        y = _unwrap(math.atan2(be, al), yprev, n_m)
        e = r[k] - y
        u = _output(Cc, xc, Dc, e)
        for j in range(p):
            du[j] = -Dc * dy[j]
        for i in range(nc):
            ci = Cc[i]
            if ci != 0.0:
                for j in range(p):
                    du[j] += ci * Sc[i, j]
        # state and sensitivity updates
        for j in range(p):
            dy[j] = -dy[j]  # de = -dy drives the controller
        _advance_sensitivity(Ac, Bc, Sc, dy, Sc2)
        _advance_sensitivity(Ag, Bg, Sg, du, Sg2)
        if fit_gain:
            # x+ = A x + c B u with Bg = c B: d/d log c adds Bg u
            for i in range(ng):
                Sg2[i, p - 1] += Bg[i] * u
        _advance(Ac, Bc, xc, e, xc2)
        _advance(Ag, Bg, xg, u, xg2)
        Sc, Sc2 = Sc2, Sc
        Sg, Sg2 = Sg2, Sg
        y0s[k] = y0
        ys[k] = y
        us[k] = u
        yprev = y
        bad = _diverged(y0, y0_last, u, n_m)
        y0_last = y0
        if bad:
            ok = False
            break
    return y0s, ys, us, ds, ok


def _harmonics_of(flux: FluxModel) -> NDArray[np.float64]:
    return np.ascontiguousarray(flux.basis.harmonic_array)


def simulate_loop(
    loop: ClosedLoop,
    flux: FluxModel,
    r: ArrayLike,
    *,
    noise: ArrayLike | None = None,
    torque_disturbance: ArrayLike | None = None,
    cogging_amplitude: float = 0.0,
    cogging_periods: int = 0,
    y_initial: float = 0.0,
) -> LoopResult:
    """Simulate eq. (state_eq) with optional sensor noise, torque disturbance and cogging.

    Parameters
    ----------
    loop : ClosedLoop
    flux : FluxModel
        The flux g(y0) (the truth on the virtual bench, the model g_theta in SEM).
    r : array_like (N,)
        Reference [rad].
    noise : array_like (N, 3), optional
        Additive Hall noise v[k].
    torque_disturbance : array_like (N,), optional
        T_d[k], added to the plant input.
    cogging_amplitude, cogging_periods : keyword-only
        Position-dependent torque ``a sin(periods * y0)`` added to the plant input.
    y_initial : float
        f_init's estimate before the first sample [rad].

    Returns
    -------
    LoopResult
    """
    r = np.ascontiguousarray(r, dtype=np.float64)
    N = r.size
    v = np.zeros((N, 3)) if noise is None else np.ascontiguousarray(noise, dtype=np.float64)
    td = (
        np.zeros(N)
        if torque_disturbance is None
        else np.ascontiguousarray(torque_disturbance, dtype=np.float64)
    )
    if v.shape != (N, 3) or td.shape != (N,):
        raise ValueError("noise must be (N, 3) and torque_disturbance (N,)")
    y0, y, u, d, tq, ok = _simulate_kernel(
        *loop._arrays(),
        float(loop.pole_pairs),
        _harmonics_of(flux),
        np.ascontiguousarray(flux.theta),
        r,
        v,
        td,
        float(cogging_amplitude),
        float(cogging_periods),
        float(y_initial),
    )
    return LoopResult(y0, y, u, d, tq, "ok" if ok else "diverged")


def loop_jacobian(
    loop: ClosedLoop,
    flux: FluxModel,
    r: ArrayLike,
    *,
    y_initial: float = 0.0,
    out: NDArray[np.float64] | None = None,
    fit_gain: bool = False,
) -> LoopJacobian:
    """Noise-free simulation of eq. (state_eq) with the exact Jacobian d d_sim / d theta.

    Parameters
    ----------
    out : ndarray (N, 3, 3 m [+ 1]), optional
        Preallocated Jacobian storage (reused between Gauss-Newton iterations).
    fit_gain : bool, keyword-only
        Append the column d d_sim / d log(c) for a factor c on the plant input matrix
        (``B_G -> c B_G``, the unknown BLA gain of eq. c_hat), so that c can be refined jointly.

    Returns
    -------
    LoopJacobian
    """
    r = np.ascontiguousarray(r, dtype=np.float64)
    N = r.size
    p = flux.theta.size + (1 if fit_gain else 0)
    jac = np.empty((N, 3, p)) if out is None else out
    if jac.shape != (N, 3, p):
        raise ValueError(f"out must have shape {(N, 3, p)}")
    y0, y, u, d, ok = _jacobian_kernel(
        *loop._arrays(),
        float(loop.pole_pairs),
        _harmonics_of(flux),
        np.ascontiguousarray(flux.theta),
        r,
        float(y_initial),
        jac,
        bool(fit_gain),
    )
    return LoopJacobian(d, y0, y, u, jac, "ok" if ok else "diverged")
