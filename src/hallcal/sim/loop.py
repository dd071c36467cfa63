"""Closed-loop simulation of Fig. cl_scheme / eq. (state_eq) and its exact parameter sensitivities.

Per sample k (zero initial conditions, y(t_{-1}) = y_initial):

    y0[k]  = C_G x_G[k]                              plant output (true angle) [rad]
    d[k]   = ADC(s_k g_theta(y0[k]) + v[k])           Hall signals (s_k: sensor gain, default 1;
                                                     ADC: quantizer and rails, default none)
    y[k]   = f_init(d[k]; y[k-1])                    eq. (fimp) [rad]
    e[k]   = r[k] - y[k]
    u[k]   = C_C x_C[k] + D_C e[k]                   torque command
    x_C[k+1] = A_C x_C[k] + B_C e[k]
    x_G[k+1] = A_G x_G[k] + B_G (u[k] + T_d[k] + T_c(y0[k]))     (T_c: cogging torque)

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
    dw    = du + T_c'(y0) dy0 (+ [cos k y0, sin k y0] for the cogging coefficients)
    S_C+  = A_C S_C - B_C dy
    S_G+  = A_G S_G + B_G dw (+ B_G w for log c, the plant input gain)

The feedback term ``g'(y0) dy0`` is what makes simulation-error minimization converge
(docs/design.md).
The hot loops are compiled with numba; float64 throughout.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, replace

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.sensor.flux import FluxModel
from hallcal.sensor.reconstruction import clarke_matrix
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop_kernel import (
    F64,
    LoopArrays,
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
    simulate,
    unwrap,
)
from hallcal.sim.lti import ContinuousTF, DiscreteTF, StateSpace

__all__ = [
    "ClosedLoop",
    "LoopJacobian",
    "LoopResult",
    "LoopStatus",
    "SensorADC",
    "loop_jacobian",
    "simulate_loop",
]


class LoopStatus(enum.StrEnum):
    """Outcome of a closed-loop simulation or sensitivity pass."""

    OK = "ok"
    #: the states left a sane range or the angle moved half an electrical period in one sample
    DIVERGED = "diverged"

    @property
    def success(self) -> bool:
        return self is LoopStatus.OK


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
    cogging : CoggingTorque or None
        A known cogging torque T_c(y0) at the plant input, part of the plant model (e.g. one
        identified earlier); the simulations and sensitivities include it.
    rails : ndarray (2, 3)
        The ADC rails [Hall signal unit] (row 0 lowest, row 1 highest value per sensor) between
        the sensors and f_init: the model's f_init sees its flux clipped to them, as the drive's
        saw the clipped signals (:mod:`hallcal.fit.censor`); default -inf/+inf (none). Used by
        the model simulations of :mod:`hallcal.fit.gauss_newton`.
    """

    plant: StateSpace
    controller: StateSpace
    pole_pairs: int
    projection: NDArray[np.float64] = field(default_factory=lambda: clarke_matrix()[:2])
    offset: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    cogging: CoggingTorque | None = None
    rails: NDArray[np.float64] = field(
        default_factory=lambda: np.array([[-np.inf] * 3, [np.inf] * 3])
    )

    def __post_init__(self) -> None:
        if self.plant.D != 0.0:
            raise ValueError(
                "the plant has a direct feedthrough (as many zeros as poles and no delay): the "
                "loop through f_init would be algebraic"
            )
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
        """Discretize G(s) exactly (ZOH with delay) and realize C(q) in state space.

        Parameters
        ----------
        plant : ContinuousTF
            G(s) with its input delay (or the BLA's parametric model).
        controller : DiscreteTF
            C(q), eq. (controller).
        sample_time : float
            T_s [s].
        pole_pairs : int
            n_m of f_init in the loop.
        projection : array_like, shape (2, 3), keyword-only, optional
            f_init's projection; default the Clarke rows.
        offset : array_like, shape (3,), keyword-only, optional
            Sensor offsets f_init subtracts; default zero.

        Returns
        -------
        ClosedLoop
            The loop of eq. (state_eq), without cogging torque.
        """
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
        return replace(self, plant=StateSpace(p.A, c * p.B, p.C, p.D, p.dt))

    def with_cogging(self, cogging: CoggingTorque | None) -> ClosedLoop:
        """The loop with a known cogging torque at the plant input (None: without)."""
        return replace(self, cogging=cogging)

    def with_rails(self, low: ArrayLike, high: ArrayLike) -> ClosedLoop:
        """The loop whose f_init sees the sensors clipped to [low, high] (per sensor).

        Parameters
        ----------
        low, high : array_like (3,) or float
            Rails [Hall signal unit], -inf / +inf for none; low < high.

        Returns
        -------
        ClosedLoop
            This loop with :attr:`rails`.
        """
        rails = np.array([np.broadcast_to(low, 3), np.broadcast_to(high, 3)], dtype=np.float64)
        if np.isnan(rails).any() or not (rails[0] < rails[1]).all():
            raise ValueError("rails must satisfy low < high for every sensor")
        return replace(self, rails=rails)

    @property
    def sample_time(self) -> float:
        """T_s [s]: the plant's (and controller's) dt, set for every loop (discrete)."""
        dt = self.plant.dt
        if dt is None:  # refused by __post_init__; here for the type checker
            raise ValueError("plant and controller must be discrete")
        return float(dt)

    def kernel_arrays(self) -> LoopArrays:
        """The kernel arguments of the loop (:data:`hallcal.sim.loop_kernel.LoopArrays`)."""
        p, c = self.plant, self.controller
        return (
            kernel_array(p.A),
            kernel_array(p.B),
            kernel_array(p.C),
            kernel_array(c.A),
            kernel_array(c.B),
            kernel_array(c.C),
            float(c.D),
            kernel_array(self.projection),
            kernel_array(self.offset),
        )


@dataclass(frozen=True)
class SensorADC:
    """The converter between the Hall sensors and f_init: a quantizer, then the rails.

    Per sensor h, the value f_init sees is ``clip(q_h(v), low_h, high_h)`` with
    ``q_h(v) = origin_h + step_h floor((v - origin_h) / step_h + 1/2)`` (a uniform mid-tread
    quantizer; ``step_h = 0``: none). The defaults change nothing (infinite rails, no quantizer).

    Attributes
    ----------
    low, high : ndarray (3,)
        Rails [Hall signal unit]: the lowest and highest value the converter outputs.
    step : ndarray (3,)
        Quantization step (one code) [Hall signal unit]; 0 = no quantization.
    origin : ndarray (3,)
        A value the quantizer represents exactly [Hall signal unit] (the code grid's anchor).
    """

    low: NDArray[np.float64] = field(default_factory=lambda: np.full(3, -np.inf))
    high: NDArray[np.float64] = field(default_factory=lambda: np.full(3, np.inf))
    step: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    origin: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))

    def within(self, rails: ArrayLike) -> SensorADC:
        """This converter with its rails narrowed to ``rails`` (2 x 3: low, high)."""
        r = np.asarray(rails, dtype=np.float64)
        return replace(self, low=np.maximum(self.low, r[0]), high=np.minimum(self.high, r[1]))

    def _arrays(self) -> tuple[F64, F64, F64, F64]:
        lo, hi, step, origin = (
            kernel_array(np.broadcast_to(np.asarray(a, dtype=np.float64), (3,)))
            for a in (self.low, self.high, self.step, self.origin)
        )
        return lo, hi, step, origin


@dataclass(frozen=True)
class LoopResult:
    """Simulated signals, one entry per sample.

    Attributes
    ----------
    y0 : true (simulated) angle [rad]; y : f_init output [rad]; u : torque command;
    d : Hall signals (N, 3) including noise; torque : total plant input u + T_d + T_c(y0);
    status : LoopStatus.OK, or DIVERGED when the loop went unstable: the states left a sane
    range or the angle moved more than half an electrical period in one sample, so that f_init
    aliases (the remaining samples are NaN).
    """

    y0: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    u: NDArray[np.float64] = field(repr=False)
    d: NDArray[np.float64] = field(repr=False)
    torque: NDArray[np.float64] = field(repr=False)
    status: LoopStatus = LoopStatus.OK


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


def _harmonics_of(flux: FluxModel) -> NDArray[np.int64]:
    return np.asarray(flux.basis.harmonics, dtype=np.int64)


def _cogging_arrays(*torques: CoggingTorque | None) -> tuple[NDArray, NDArray]:
    """Orders (float64) and interleaved coefficients of the terms of several cogging torques,
    concatenated in order (the kernels sum all terms; an order may repeat)."""
    ts = [t for t in torques if t is not None and t.size]
    if not ts:
        return np.zeros(0), np.zeros(0)
    orders = np.concatenate([np.asarray(t.orders, dtype=np.float64) for t in ts])
    return orders, np.concatenate([t.coefficients for t in ts])


def simulate_loop(
    loop: ClosedLoop,
    flux: FluxModel,
    r: ArrayLike,
    *,
    noise: ArrayLike | None = None,
    torque_disturbance: ArrayLike | None = None,
    cogging: CoggingTorque | None = None,
    y_initial: float = 0.0,
    initial_angle: float = 0.0,
    sensor_gain: ArrayLike | None = None,
    adc: SensorADC | None = None,
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
    cogging : CoggingTorque, keyword-only, optional
        Position-periodic torque T_c(y0) added to the plant input.
    y_initial : float
        f_init's estimate before the first sample [rad].
    initial_angle : float, keyword-only
        True angle at the first sample [rad]: the plant starts at rest with
        ``y0 = initial_angle + C_G x_G`` (a power-up at an arbitrary rotor position; f_init still
        starts from ``y_initial``). The flux, the cogging torque and the returned ``y0`` are all
        at this true angle. Default 0, the convention of DESIGN.md.
    sensor_gain : array_like (N, 3), keyword-only, optional
        s_k per sample and sensor multiplying the flux before the noise is added (a sensor whose
        sensitivity drifts as it warms up); default 1.
    adc : SensorADC, keyword-only, optional
        Quantizer and rails between the sensors and f_init (the loop runs on the converted
        values, which are also the returned ``d``); default none.

    Returns
    -------
    LoopResult
    """
    r = kernel_array(r)
    N = r.size
    v = np.zeros((N, 3)) if noise is None else kernel_array(noise)
    td = np.zeros(N) if torque_disturbance is None else kernel_array(torque_disturbance)
    sg = np.zeros((0, 3)) if sensor_gain is None else kernel_array(sensor_gain)
    if v.shape != (N, 3) or td.shape != (N,) or sg.shape not in ((N, 3), (0, 3)):
        raise ValueError("noise and sensor_gain must be (N, 3) and torque_disturbance (N,)")
    y0, y, u, d, tq, ok = simulate(
        *loop.kernel_arrays(),
        float(loop.pole_pairs),
        kernel_array(flux.theta),
        _harmonics_of(flux),
        False,
        *_cogging_arrays(loop.cogging, cogging),
        *(adc or SensorADC()).within(loop.rails)._arrays(),
        np.zeros(0),
        r,
        v,
        td,
        sg,
        float(y_initial),
        float(initial_angle),
        False,
    )
    return LoopResult(y0, y, u, d, tq, LoopStatus.OK if ok else LoopStatus.DIVERGED)


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

    The straightforward forward-sensitivity recursion of the module docstring, one dense
    (N, 3, p) array: the reference against which the structured Gauss-Newton system of
    :mod:`hallcal.fit.gauss_newton` is tested (the fit itself never forms it).

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
        _harmonics_of(flux),
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
