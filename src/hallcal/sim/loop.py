"""Closed-loop simulation of Fig. cl_scheme / eq. (state_eq); the equations of its sensitivities.

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
(docs/design.md); :mod:`hallcal.fit.gauss_newton` runs this recursion. The hot loops are
compiled with numba; float64 throughout.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.messages import Outcome
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.reconstruction import clarke_matrix, projection_and_offset
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop_kernel import F64, LoopArrays, kernel_array, simulate
from hallcal.sim.lti import ContinuousTF, DiscreteTF, StateSpace

__all__ = [
    "ClosedLoop",
    "LoopResult",
    "LoopStatus",
    "SensorADC",
    "simulate_loop",
]


class LoopStatus(Outcome):
    """Outcome of a closed-loop simulation or sensitivity pass."""

    OK = "ok"
    #: the states left a sane range or the angle moved half an electrical period in one sample
    DIVERGED = "diverged"


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
            *projection_and_offset(projection, offset),
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
        np.asarray(flux.basis.harmonics, dtype=np.int64),
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
