"""Simulation-error minimization (SEM) of the flux model through the closed loop.

Problem (problem) of van Meer et al.: ``min_theta J(theta) = sum_k ||d(t_k) - d_sim_theta(t_k)||^2``
where d_sim comes from the closed loop (state_eq) simulated from the recorded reference with the
plant model, the known controller, f_init and ``g_theta(y0) = psi(y0) theta``, zero initial
conditions. Optionally the parameters also hold the plant input gain c (eq. c_hat, refined
jointly) and a cogging torque ``T_c(y0) = sum_k a_k cos(k y0) + b_k sin(k y0)`` at the plant input
(the cause of the experiment's residual error named in the paper's discussion).

Instead of the paper's interior-point method on finite differences (2 hours), this module uses
Levenberg-Marquardt (More 1978, "The Levenberg-Marquardt algorithm: implementation and theory";
Nocedal & Wright 2006, sec. 10.3) on the exact Gauss-Newton system from forward sensitivities,
including the feedback term d y0_sim / d theta. The system J^T J, J^T e, e^T e is formed without
the dense Jacobian (:mod:`hallcal.fit.gauss_newton`), so time and memory grow gently with the
number of parameters. One iteration costs one sensitivity pass and one or two plain simulations.

Parameter covariance (Ljung 1999, "System Identification", sec. 9.3): for white Hall noise,
``cov(x) ~ sigma^2 (J^T J)^-1`` with ``sigma^2 = J(x*) / (3 N - p)``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.fit.gauss_newton import (
    GaussNewtonSystem,
    ParameterLayout,
    checked_weights,
    gauss_newton_system,
    regression_normal_equations,
    simulate_model,
)
from hallcal.limits import check_hall_scale, check_work_memory, one_blas_thread
from hallcal.messages import Outcome
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.reconstruction import f_init
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "SEMResult",
    "SEMStatus",
    "least_squares_start",
    "default_chunk",
    "angle_error_gradient",
    "predicted_angle_error",
    "solve_sem",
]


class SEMStatus(Outcome):
    """How a SEM solve ended."""

    #: the Gauss-Newton step predicts a relative cost decrease below the tolerance
    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    #: no damped step reduced the cost
    STALLED = "stalled"
    #: the closed loop with the starting model is unstable
    DIVERGED = "diverged"
    #: not known (a result rebuilt from an artifact without the solver's status)
    UNKNOWN = "unknown"


@dataclass(frozen=True)
class SEMResult:
    """Outcome of :func:`solve_sem`.

    Attributes
    ----------
    flux : FluxModel
        g_theta* (theta as 3 x m).
    theta0 : ndarray (3, m)
        Starting point.
    cost_history : ndarray
        J(theta) at the start and after each accepted iteration.
    iterations : int
        Accepted Levenberg-Marquardt steps.
    status : SEMStatus
        CONVERGED, MAX_ITERATIONS, STALLED or DIVERGED (see :class:`SEMStatus`).
    solve_time : float
        Wall time [s], compilation excluded when warm.
    noise_variance : float
        sigma^2 = J(theta*) / (3 N - p), per Hall channel.
    covariance : ndarray (3 m, 3 m)
        Covariance of theta (flattened sensor-major): its block of sigma^2 (J^T J)^-1 over all
        parameters, so it includes the uncertainty that the gain and the cogging torque add.
    n_samples : int
        N.
    d_sim : ndarray (N, 3)
        Simulated Hall signals at the solution (NaN when the loop diverged).
    y0_sim : ndarray (N,)
        Simulated angle at the solution (NaN when the loop diverged).
    gain : float
        Factor c on the plant input matrix found jointly with theta (1 unless ``fit_gain``).
    gain_std : float
        Its standard deviation from the covariance (first order, c * std(log c)).
    cogging : CoggingTorque or None
        The cogging torque identified jointly (with the covariance of its coefficients), None
        when no cogging orders were fitted.
    parameter_covariance : ndarray (p, p) or None
        sigma^2 (J^T J + R)^-1 over all parameters in the layout of ``layout``.
    batch_covariance : ndarray (p, p) or None
        The batch-means (long-run) covariance ``A^-1 M A^-1`` with ``A = J^T J + R`` and M the
        covariance of the scores J^T e summed over batches of consecutive samples, times the
        number of batches: valid when the residual is coloured (unmodelled motion) as long as
        its correlation is shorter than a batch (Ljung 1999, sec. 9.3; the batch-means method
        of simulation output analysis). Its rank is at most ``batches - 1``: use it for a few
        parameters at a time.
    batches : int
        Number of batches B.
    drift : ndarray (3, 2) or None
        With ``fit_drift``: per sensor the gain change gamma_h (relative) and the offset change
        delta_h [Hall signal unit] over the run, identified jointly; theta is then the sensors
        at the run's middle (:class:`~hallcal.fit.gauss_newton.ParameterLayout`).
    drift_std : ndarray (3, 2) or None
        Their standard deviations from the covariance.
    layout : ParameterLayout or None
        What the parameter vector holds.
    message : str
        One line on how the solve ended.
    """

    flux: FluxModel
    theta0: NDArray[np.float64] = field(repr=False)
    cost_history: NDArray[np.float64] = field(repr=False)
    iterations: int
    status: SEMStatus
    solve_time: float
    noise_variance: float
    covariance: NDArray[np.float64] = field(repr=False)
    n_samples: int
    d_sim: NDArray[np.float64] = field(repr=False)
    y0_sim: NDArray[np.float64] = field(repr=False)
    gain: float = 1.0
    gain_std: float = 0.0
    cogging: CoggingTorque | None = field(default=None, repr=False)
    parameter_covariance: NDArray[np.float64] | None = field(default=None, repr=False)
    layout: ParameterLayout | None = field(default=None, repr=False)
    message: str = ""
    batch_covariance: NDArray[np.float64] | None = field(default=None, repr=False)
    batches: int = 0
    drift: NDArray[np.float64] | None = None
    drift_std: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", SEMStatus(self.status))

    @property
    def cost(self) -> float:
        """Final J(theta*)."""
        return float(self.cost_history[-1])

    @property
    def initial_cost(self) -> float:
        return float(self.cost_history[0])

    @property
    def theta(self) -> NDArray[np.float64]:
        return self.flux.theta


def least_squares_start(
    basis: FourierBasis, d: ArrayLike, y: ArrayLike, *, weights: ArrayLike | None = None
) -> NDArray[np.float64]:
    """theta_0 by linear least squares of d on the basis at the f_init output y.

    Treats the measured f_init angle as if it were y0. The resulting model reproduces f_init's
    view of the sensors (its LUT is close to zero) but already carries the harmonic shape of the
    data, which makes the SEM start much closer than pure sinusoids when the flux is distorted.
    The normal equations come from trigonometric moments
    (:func:`hallcal.fit.gauss_newton.regression_normal_equations`: no N x m matrix).

    Parameters
    ----------
    basis : FourierBasis
        The model's basis beta (eq. (basis)).
    d : array_like (N, 3)
        Hall signals.
    y : array_like (N,)
        f_init output recorded in the loop [rad], used in place of y0.
    weights : array_like (N, 3), keyword-only, optional
        Per-sample, per-channel weights (0: censored, :mod:`hallcal.fit.censor`): each
        sensor's row is then a weighted least-squares fit.

    Returns
    -------
    ndarray, shape (3, m)
        theta_0, one row per sensor.
    """
    yy = np.asarray(y, dtype=np.float64)
    dd = np.asarray(d, dtype=np.float64)
    if weights is None:
        G, rhs, _ = regression_normal_equations(yy, dd, basis.harmonics)
        return _normal_solve(basis, G, rhs, yy, dd, None).T.copy()
    w = np.asarray(weights, dtype=np.float64)
    rows = []
    for h in range(3):
        G, rhs, _ = regression_normal_equations(yy, dd[:, h], basis.harmonics, weights=w[:, h])
        rows.append(_normal_solve(basis, G, rhs, yy, dd[:, h : h + 1], w[:, h])[:, 0])
    return np.vstack(rows)


def _normal_solve(
    basis: FourierBasis, G: NDArray, rhs: NDArray, y: NDArray, d: NDArray, w: NDArray | None
) -> NDArray[np.float64]:
    """The solution (m, c) of the normal equations ``G x = rhs`` of d (N, c) on beta(y), with
    sample weights w (None: 1)."""
    # Over whole revolutions the Fourier columns are nearly orthogonal, so G is well conditioned
    # and a Cholesky solve is as accurate as an SVD of the regressors.
    with one_blas_thread():
        try:
            if np.linalg.cond(G) > 1e10:
                raise np.linalg.LinAlgError
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(G), rhs)
        except np.linalg.LinAlgError:  # less than a revolution of data: the SVD of the regressors
            check_work_memory(
                8.0 * y.size * basis.size,
                f"the least-squares start ({y.size} samples x {basis.size} basis functions)",
                "use fewer harmonics or a shorter recording",
            )
            if w is None:
                return np.linalg.lstsq(basis.evaluate(y), d, rcond=None)[0]
            sw = np.sqrt(w)[:, None]
            return np.linalg.lstsq(sw * basis.evaluate(y), sw * d, rcond=None)[0]


# ------------------------------------------------------------------------------------------------
# The problem and its Levenberg-Marquardt iterations
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Problem:
    """Problem (problem) with a diagonal ridge R and sample weights W (0: censored):
    F(x) = sum_k e_k^T W_k e_k + x^T R x, e = d - d_sim(x)."""

    loop: ClosedLoop
    layout: ParameterLayout
    r: NDArray[np.float64] = field(repr=False)
    d: NDArray[np.float64] = field(repr=False)
    ridge: NDArray[np.float64] = field(repr=False)
    stride: int
    threads: int | None
    chunk: int
    weights: NDArray[np.float64] | None = field(default=None, repr=False)

    @property
    def observations(self) -> int:
        """Residual entries that count: 3 N, less the censored ones (weight 0)."""
        return self.d.size if self.weights is None else int(np.count_nonzero(self.weights))

    def system(self, x: NDArray, *, exact: bool = False) -> GaussNewtonSystem:
        return gauss_newton_system(
            self.loop, self.layout, x, self.r, self.d, chunk=self.chunk,
            stride=1 if exact else self.stride, threads=self.threads, weights=self.weights,
        )  # fmt: skip

    def objective(self, system: GaussNewtonSystem, x: NDArray) -> float:
        return float(system.sse + self.ridge @ x**2)

    def cost(self, x: NDArray) -> float:
        """F(x) from one plain simulation (inf when the loop diverges)."""
        sim = simulate_model(self.loop, self.layout, x, self.r)
        if not sim.status.success:
            return math.inf
        e = self.d - sim.d
        if self.weights is not None:
            return float(np.vdot(e, self.weights * e) + self.ridge @ x**2)
        return float(np.vdot(e, e) + self.ridge @ x**2)


@dataclass
class _Iterate:
    x: NDArray[np.float64]
    system: GaussNewtonSystem
    history: list[float]
    iterations: int
    status: SEMStatus
    exact: bool = False  # the system is formed from every sample (stride 1)


def _normal_matrix(problem: _Problem, system: GaussNewtonSystem, x: NDArray):
    """(J^T J + R, J^T e - R x) of the regularized problem."""
    return system.gram + np.diag(problem.ridge), system.gradient - problem.ridge * x


def _decrement(A: NDArray, g: NDArray) -> float:
    """g^T A^-1 g: twice the decrease a full Gauss-Newton step predicts (inf if singular)."""
    try:
        return float(g @ scipy.linalg.cho_solve(scipy.linalg.cho_factor(A), g))
    except (np.linalg.LinAlgError, ValueError):
        try:
            return float(g @ np.linalg.solve(A, g))
        except np.linalg.LinAlgError:
            return math.inf


def _damped_step(problem: _Problem, A: NDArray, g: NDArray, x: NDArray, F: float, lam: float):
    """Raise lambda until ``(A + lam diag(A)) s = g`` reduces F (More 1978, sec. 2).

    Returns (step, F(x + step), lam) or (None, F, lam) when 30 tries fail.
    """
    dA = np.diag(A).copy()
    dA[dA <= 0] = 1.0
    for _ in range(30):
        try:
            step = np.linalg.solve(A + lam * np.diag(dA), g)
        except np.linalg.LinAlgError:
            lam *= 10.0
            continue
        F_new = problem.cost(x + step)
        if F_new < F:
            return step, F_new, lam
        lam *= 4.0
    return None, F, lam


#: Statistical convergence: the full Gauss-Newton step would lower the cost by less than about
#: one noise variance (decrement ``g^T A^-1 g <= 2 sigma^2``), i.e. the iterate lies within
#: about one standard deviation of the optimum in every direction of the parameter space.
_DECREMENT_SIGMAS = 2.0
#: ... or two accepted steps in a row each lowered the cost by less than this many sigma^2.
_STALL_SIGMAS = 0.1
#: Contraction of the decrement assumed over a solve's first step when predicting whether the
#: next iterate passes the test (later steps use the last measured ratio). Measured on 24-28
#: pole-pair zoo motors: 63 -> 0.0 sigma^2 over a first step; 2.2e7, 3.8e6, 3.3e4, 2305, 1.3
#: over four steps of a first fit (ratios 0.17, 0.009, 0.07, 6e-4).
_FIRST_CONTRACTION = 0.02


def _levenberg_marquardt(
    problem: _Problem, x0: NDArray, *, max_iterations: int, tol: float, damping: float,
    exact_next: bool = True,
) -> _Iterate:  # fmt: skip
    """Levenberg-Marquardt iterations from x0 until the decrement test passes.

    Stops when the full Gauss-Newton step predicts a relative decrease below tol (Dennis &
    Schnabel 1996, sec. 7.2): it needs no further simulation. The test is also passed at the
    statistical resolution of the problem, where further steps change the estimate by much
    less than its own standard deviation: when the decrement is below ``2 sigma^2`` (sigma^2 =
    F / (3 N - p)), or when two accepted steps in a row each lowered F by less than
    ``0.1 sigma^2``. The second rule matters with the strided J^T J of large models, whose
    decrement overstates what the exact cost can still give: measured on a 16 kHz, 200 000
    sample run with 465 parameters, 22 of 30 iterations lowered F by 0.01-0.03 sigma^2 each.

    With a stride and ``exact_next``, the system after a step whose next decrement is predicted
    to pass the test (the decrement times its last contraction ratio, or times
    ``_FIRST_CONTRACTION`` after the first step, below ``2 sigma^2``) is the exact one (stride
    1): where the test then passes it is the system of the covariance too
    (:func:`_uncertainty`), one pass over the samples saved; where it does not, the iterations
    go on with the exact Hessian.
    """
    x = np.array(x0, dtype=np.float64)
    system = problem.system(x)
    exact = problem.stride == 1
    if not system.status.success:
        return _Iterate(x, system, [math.inf], 0, SEMStatus.DIVERGED)
    F = problem.objective(system, x)
    history = [F]
    lam = damping
    iterations = 0
    dof = max(problem.observations - problem.layout.size, 1)
    small_steps = 0
    contraction = _FIRST_CONTRACTION
    previous = math.inf
    with one_blas_thread():
        while True:
            A, g = _normal_matrix(problem, system, x)
            sigma2 = F / dof
            decrement = _decrement(A, g)
            if decrement <= max(tol * F, _DECREMENT_SIGMAS * sigma2) or small_steps >= 2:
                return _Iterate(x, system, history, iterations, SEMStatus.CONVERGED, exact)
            if iterations >= max_iterations:
                return _Iterate(x, system, history, iterations, SEMStatus.MAX_ITERATIONS, exact)
            step, F_new, lam = _damped_step(problem, A, g, x, F, lam)
            if step is None:
                return _Iterate(x, system, history, iterations, SEMStatus.STALLED, exact)
            small_steps = small_steps + 1 if F - F_new < _STALL_SIGMAS * sigma2 else 0
            x = x + step
            iterations += 1
            history.append(F_new)
            lam = max(lam / 5.0, 1e-12)
            if math.isfinite(previous) and previous > 0:
                contraction = decrement / previous
            previous = decrement
            exact = problem.stride == 1 or (
                exact_next and contraction * decrement <= _DECREMENT_SIGMAS * sigma2
            )
            system = problem.system(x, exact=exact)
            F = problem.objective(system, x)


def _covariance(system: GaussNewtonSystem, ridge: NDArray, sigma2: float) -> NDArray[np.float64]:
    """sigma^2 (J^T J + R)^-1 (NaN when singular or unavailable)."""
    p = ridge.size
    if not system.status.success:
        return np.full((p, p), math.nan)
    with one_blas_thread():
        try:
            inv = np.linalg.inv(system.gram + np.diag(ridge))
            return (sigma2 * inv).astype(np.float64, copy=False)
        except np.linalg.LinAlgError:
            return np.full((p, p), math.nan)


def _batch_covariance(
    system: GaussNewtonSystem, cov: NDArray, sigma2: float
) -> NDArray[np.float64] | None:
    """``A^-1 M A^-1`` with M the centred batch-score covariance times B/(B-1) (B batches)."""
    S = system.batch_gradients
    B = S.shape[0]
    if B < 3 or not system.status.success or not np.all(np.isfinite(cov)) or not sigma2 > 0:
        return None
    Sc = S - S.mean(axis=0)
    Ainv = cov / sigma2
    with one_blas_thread():
        L = Ainv @ Sc.T  # (p, B)
        return (B / (B - 1)) * (L @ L.T)


def _default_stride(p: int) -> int:
    """Rank-one products from every sample up to 128 parameters, every 4th beyond.

    The exact products cost O(N p^2) against O(N p n^2) for the recursion (n = 8 loop states):
    below about 128 columns they are the smaller part; beyond, every 4th sample keeps the
    Hessian of the iterations within about 4 / N of the exact one (see
    :mod:`hallcal.fit.gauss_newton`) at a quarter of the cost.
    """
    return 1 if p <= 128 else 4


def solve_sem(
    loop: ClosedLoop,
    r: ArrayLike,
    d: ArrayLike,
    basis: FourierBasis,
    *,
    theta0: ArrayLike | None = None,
    y: ArrayLike | None = None,
    max_iterations: int = 50,
    tol: float = 1e-6,
    damping: float = 1e-6,
    regularization: ArrayLike | None = None,
    fit_gain: bool = False,
    gain0: float = 1.0,
    cogging: Sequence[int] | CoggingTorque = (),
    stride: int | None = None,
    threads: int | None = None,
    chunk: int | None = None,
    weights: ArrayLike | None = None,
    fit_drift: bool = False,
    drift0: ArrayLike | None = None,
    covariance: str = "exact",
) -> SEMResult:
    """Solve problem (problem) by Levenberg-Marquardt on exact sensitivities.

    Parameters
    ----------
    loop : ClosedLoop
        Plant model (BLA or known G), controller C(q), n_m and the f_init used in the experiment.
    r : array_like (N,)
        Recorded reference [rad].
    d : array_like (N, 3)
        Recorded Hall signals.
    basis : FourierBasis
        The model's basis beta(y0) (any set of harmonics).
    theta0 : array_like (3, m), keyword-only, optional
        Start. Default: :func:`least_squares_start` at ``y`` (or at f_init(d) when y is None).
    y : array_like (N,), optional
        The f_init output recorded in the loop [rad], used for the default start.
    max_iterations : int
        Maximum accepted steps.
    tol : float
        Stop when the Gauss-Newton step predicts a relative cost decrease below tol.
    damping : float
        Initial Levenberg-Marquardt parameter lambda (relative to diag(J^T J)).
    regularization : array_like (3 m,), optional
        Diagonal Tikhonov weights w on theta: the cost becomes J(theta) + sum_j w_j theta_j^2
        (used by the kernel basis, whose prior is diagonal in the Fourier modes).
    fit_gain : bool
        Also estimate a factor c on the plant's input matrix (parametrized as log c, exact
        sensitivity), refining the gain correction of eq. (c_hat) at the SEM optimum where the
        flux model no longer masks it.
    gain0 : float
        Start of c with ``fit_gain`` (the result's ``gain`` is relative to ``loop`` as well).
    cogging : sequence of int or CoggingTorque
        Orders k of a cogging torque ``T_c(y0) = sum a_k cos(k y0) + b_k sin(k y0)`` at the plant
        input, identified jointly (a CoggingTorque also gives the start of its coefficients;
        default start zero).
    stride : int, optional
        Rank-one part of J^T J from every stride-th sample during the iterations (default:
        :func:`_default_stride`); the covariance always uses the exact system.
    threads : int, optional
        Threads of the sensitivity pass (1 or 2; default 2 on machines with two cores or more).
    chunk : int, optional
        Samples per chunk of the sensitivity pass, also the batch of the batch-means covariance
        (default :func:`default_chunk`: at least :data:`BATCHES` batches).
    weights : array_like (N, 3), optional
        Per-sample, per-channel weights of the cost (0: a censored sample, e.g. at an ADC rail,
        :mod:`hallcal.fit.censor`; the loop's f_init still sees it); the default start is then
        a weighted least-squares fit, and sigma^2 counts the uncensored entries only.
    fit_drift : bool
        Also identify each sensor's gain and offset linear in time over the run (6 parameters,
        :mod:`hallcal.fit.drift`); the loop's f_init sees the drifting signals, and theta is the
        sensors at the run's middle.
    drift0 : array_like (3, 2), optional
        Start of the drift (default zero).
    covariance : {"exact", "moved", "iterations"}
        The system the covariances come from when the iterations use a stride (p > 128):
        "exact" (default) forms it again from every sample at the solution; "iterations" takes
        the iterations' last one (its Hessian within about stride / N, the gradient exact:
        for a caller that uses the parameters only, e.g. a drift estimate); "moved" is
        "exact" once a step was taken and "iterations" when the start already passed the
        convergence test (a joint fit whose added parameters stay at their start, e.g. a
        cogging torque of zero, whose test statistic is then zero whatever the covariance).
        Each saves one pass over the samples with the full rank-one products (the largest
        part of a system at p in the hundreds).

    Returns
    -------
    SEMResult
    """
    if covariance not in _COVARIANCE_SOURCES:
        raise ValueError(f"covariance must be one of {_COVARIANCE_SOURCES}, not {covariance!r}")
    t_start = time.perf_counter()
    r, d = checked_record(r, d)
    cog0: CoggingTorque | None = None
    if isinstance(cogging, CoggingTorque):
        cog0, orders = cogging, cogging.orders
    else:
        orders = tuple(int(k) for k in cogging)
    layout = ParameterLayout(basis, fit_gain=fit_gain, cogging_orders=orders, fit_drift=fit_drift)
    w = None if weights is None else checked_weights(weights, r.size)
    theta_start = _theta_start(loop, basis, d, theta0, y, w)
    problem = _problem(loop, layout, r, d, regularization, stride=stride, threads=threads,
                       chunk=default_chunk(r.size) if chunk is None else chunk,
                       weights=w)  # fmt: skip
    x0 = layout.pack(theta_start, math.log(gain0) if fit_gain else 0.0, cog0, drift0)
    it = _levenberg_marquardt(problem, x0, max_iterations=max_iterations, tol=tol, damping=damping,
                              exact_next=covariance != "iterations")  # fmt: skip
    exact = covariance == "exact" or (covariance == "moved" and it.iterations > 0)
    unc = _uncertainty(problem, it, exact=exact)
    return SEMResult(
        flux=FluxModel(basis, layout.theta(it.x)),
        theta0=theta_start,
        cost_history=np.asarray(it.history),
        iterations=it.iterations,
        status=it.status,
        solve_time=time.perf_counter() - t_start,
        noise_variance=unc.sigma2,
        covariance=unc.parameter[: layout.n_theta, : layout.n_theta].copy(),
        n_samples=r.size,
        d_sim=unc.system.d,
        y0_sim=unc.system.y0,
        gain=unc.gain,
        gain_std=unc.gain_std,
        cogging=layout.cogging(it.x, unc.parameter) if orders else None,
        parameter_covariance=unc.parameter,
        layout=layout,
        message=_message(it, layout.size),
        batch_covariance=unc.batch,
        batches=int(unc.system.batch_gradients.shape[0]),
        drift=layout.drift(it.x) if fit_drift else None,
        drift_std=_drift_std(layout, unc.parameter) if fit_drift else None,
    )


def _drift_std(layout: ParameterLayout, cov: NDArray) -> NDArray[np.float64]:
    """(3, 2) standard deviations of the drift parameters from the parameter covariance."""
    j = layout.drift_start
    return np.sqrt(np.maximum(np.diag(cov)[j : j + 6], 0.0)).reshape(3, 2)


#: Where :func:`solve_sem` takes its covariances from (its ``covariance`` argument).
_COVARIANCE_SOURCES = ("exact", "moved", "iterations")

#: Batches of the batch-means (long-run) covariance the default chunk aims at: its variance of a
#: linear functional of theta has B - 1 degrees of freedom (B = 24: within a factor 0.7-1.5 at
#: 95 %, the calibration band of the predicted error).
BATCHES = 24


def default_chunk(n_samples: int) -> int:
    """Samples per chunk (and batch): ``N / BATCHES`` within [512, 4096].

    4096 keeps the per-chunk overhead of the two-thread sensitivity pass small on long runs;
    512 samples are still many times the correlation time of the scores (the loop's closed-loop
    time constant, 1/(2 pi f_c): at most about 100 samples for a crossover at fs / 600).

    Parameters
    ----------
    n_samples : int
        N, samples of the run.

    Returns
    -------
    int
        Samples per chunk.
    """
    return int(min(4096, max(512, int(n_samples) // BATCHES)))


def checked_record(r: ArrayLike, d: ArrayLike) -> tuple[NDArray, NDArray]:
    """r (N,) and d (N, 3) as contiguous float64 arrays; d within the accepted Hall scale."""
    r = np.ascontiguousarray(r, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    if d.shape != (r.size, 3):
        raise ValueError("d must have shape (N, 3) with N = len(r)")
    check_hall_scale(float(np.max(np.abs(d))) if d.size else 0.0)
    return r, d


def _theta_start(
    loop: ClosedLoop, basis: FourierBasis, d: NDArray, theta0: ArrayLike | None,
    y: ArrayLike | None, weights: NDArray | None = None,
) -> NDArray[np.float64]:  # fmt: skip
    """theta0 as (3, m), by default :func:`least_squares_start` at y (or at f_init(d))."""
    if theta0 is None:
        yy = f_init(d, loop.pole_pairs, projection=loop.projection, offset=loop.offset)
        theta0 = least_squares_start(basis, d, yy if y is None else y, weights=weights)
    return np.array(theta0, dtype=np.float64).reshape(3, basis.size)


def _problem(
    loop: ClosedLoop, layout: ParameterLayout, r: NDArray, d: NDArray,
    regularization: ArrayLike | None, *, stride: int | None, threads: int | None, chunk: int,
    weights: NDArray | None = None,
) -> _Problem:  # fmt: skip
    """Problem (problem) with the Tikhonov ridge on theta (zero on the gain and the cogging).

    The inert b_0 of a cogging order 0 (a constant load torque, whose sine regressor is zero)
    gets a unit ridge: its column of J is zero, so it stays at 0 and J^T J + R stays regular.
    """
    ridge = np.zeros(layout.size)
    if regularization is not None:
        ridge[: layout.n_theta] = np.asarray(regularization, dtype=np.float64)
    ridge[list(layout.inert)] = 1.0
    p = layout.size
    return _Problem(
        loop, layout, r, d, ridge, _default_stride(p) if stride is None else max(1, int(stride)),
        threads, int(chunk), weights,
    )  # fmt: skip


@dataclass(frozen=True)
class _Uncertainty:
    """The exact Gauss-Newton system at the solution and the covariances it gives."""

    system: GaussNewtonSystem
    sigma2: float  # J(x*) / (3 N - p)
    parameter: NDArray[np.float64]  # sigma^2 (J^T J + R)^-1 over all parameters
    batch: NDArray[np.float64] | None  # batch-means covariance
    gain: float
    gain_std: float


def _uncertainty(problem: _Problem, it: _Iterate, *, exact: bool = True) -> _Uncertainty:
    """Parameter covariance ``sigma^2 (J^T J + R)^-1`` (Ljung 1999, sec. 9.3) from the exact
    system (every sample, whatever the iterations' stride; with ``exact=False`` the iterations'
    last system), and the batch-means covariance."""
    layout = problem.layout
    system = it.system
    if exact and not it.exact and system.status.success:
        system = problem.system(it.x, exact=True)  # the exact system for the covariance
    sigma2 = it.history[-1] / max(problem.observations - layout.size, 1)
    cov_all = _covariance(system, problem.ridge, sigma2)
    batch_cov = _batch_covariance(system, cov_all, sigma2)
    gain = math.exp(layout.log_gain(it.x))
    gain_std = (
        gain * math.sqrt(max(cov_all[layout.gain_index, layout.gain_index], 0.0))
        if layout.fit_gain
        else 0.0
    )
    return _Uncertainty(system, sigma2, cov_all, batch_cov, gain, gain_std)


def _message(it: _Iterate, p: int) -> str:
    what = {
        SEMStatus.CONVERGED: "converged",
        SEMStatus.MAX_ITERATIONS: "stopped at the iteration limit",
        SEMStatus.STALLED: "stalled (no damped step reduced the cost)",
        SEMStatus.DIVERGED: "the closed loop with the starting model diverges",
    }.get(it.status, str(it.status))
    return (
        f"SEM {what}: {p} parameters, {it.iterations} iterations, cost "
        f"{it.history[0]:.6g} -> {it.history[-1]:.6g}"
    )


def predicted_angle_error(
    flux: FluxModel,
    covariance: ArrayLike,
    pole_pairs: int,
    *,
    projection: ArrayLike,
    offset: ArrayLike,
    points: int = 512,
    about_mean: bool = False,
) -> NDArray[np.float64]:
    """Standard deviation of the LUT correction eta(y0) implied by cov(theta) [rad].

    First-order propagation through eq. (recon_biject): ``eta = y0 - f_init(g_theta(y0))`` so
    ``d eta / d theta = -(1/n_m) d psi/d d . (I_3 kron beta(y0))``. By default the table's
    constant offset is included: ``reconstruct`` outputs it, a user measures it against an
    encoder, and the calibration run pins the frame of y0 (y0 = 0 at its first sample, the loop
    simulated from rest there) only as well as the loop reveals a constant shift of the angle,
    which cov(theta) says. ``about_mean`` removes the mean over y0 of the derivative (the error
    about its mean, the offset left out).

    Parameters
    ----------
    flux : FluxModel
        The identified g_theta (Fourier basis).
    covariance : array_like (3 m, 3 m)
        cov(theta), theta flattened sensor-major.
    pole_pairs : int
        n_m.
    projection : array_like (2, 3), keyword-only
        f_init's projection P.
    offset : array_like (3,), keyword-only
        Sensor offsets f_init subtracts.
    points : int, keyword-only
        Grid size M over one revolution.
    about_mean : bool, keyword-only
        Leave the table's constant offset out (default False: include it).

    Returns
    -------
    ndarray (points,)
        std of eta on a uniform grid of y0 over one revolution.
    """
    G = angle_error_gradient(flux, pole_pairs, projection=projection, offset=offset,
                             points=points)  # fmt: skip
    if about_mean:
        G -= G.mean(axis=0)
    C = np.asarray(covariance, float)
    var = np.einsum("ij,jk,ik->i", G, C, G)
    return np.sqrt(np.maximum(var, 0.0))


def angle_error_gradient(
    flux: FluxModel,
    pole_pairs: int,
    *,
    projection: ArrayLike,
    offset: ArrayLike,
    points: int = 512,
) -> NDArray[np.float64]:
    """d eta(y0) / d theta on a uniform grid of y0 over one revolution [rad per unit of theta].

    ``eta = y0 - f_init(g_theta(y0))`` (eq. recon_biject), so ``d eta / d theta = -(1/n_m)
    d psi/d d . (I_3 kron beta(y0))``; the rows of :func:`predicted_angle_error`.

    Parameters
    ----------
    flux : FluxModel
        g_theta.
    pole_pairs : int
        n_m.
    projection : array_like (2, 3), keyword-only
        Clarke's projection of f_init.
    offset : array_like (3,), keyword-only
        Sensor offsets removed before it.
    points : int, keyword-only
        Grid points over the revolution.

    Returns
    -------
    ndarray (points, 3 m)
    """
    y0 = TWO_PI * np.arange(points) / points
    B = flux.basis.evaluate(y0)  # (M, m)
    g = flux(y0) - np.asarray(offset, float)
    P = np.asarray(projection, float)
    ab = g @ P.T
    rho2 = ab[:, 0] ** 2 + ab[:, 1] ** 2
    dpsi = (ab[:, [0]] * P[1] - ab[:, [1]] * P[0]) / rho2[:, None]  # (M, 3)
    return -(dpsi[:, :, None] * B[:, None, :]).reshape(points, -1) / pole_pairs  # (M, 3m)
