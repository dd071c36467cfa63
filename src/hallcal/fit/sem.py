"""Simulation-error minimization (SEM) of the flux model through the closed loop.

Problem (problem) of van Meer et al.: ``min_theta J(theta) = sum_k ||d(t_k) - d_sim_theta(t_k)||^2``
where d_sim comes from the closed loop (state_eq) simulated from the recorded reference with the
plant model, the known controller, f_init and ``g_theta(y0) = psi(y0) theta``, zero initial
conditions.

Instead of the paper's interior-point method on finite differences (2 hours), this module uses
Levenberg-Marquardt (More 1978, "The Levenberg-Marquardt algorithm: implementation and theory") on
the exact Jacobian from forward sensitivities (:func:`hallcal.sim.loop.loop_jacobian`), including
the feedback term d y0_sim / d theta. One iteration costs one sensitivity pass, one Gram product
J^T J (BLAS, pinned to one thread, see docs/design.md) and one or two plain simulations.

Parameter covariance (Ljung 1999, "System Identification", sec. 9.3): for white Hall noise,
``cov(theta) ~ sigma^2 (J^T J)^-1`` with ``sigma^2 = J(theta*) / (3 N - p)``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.reconstruction import f_init
from hallcal.sim.loop import ClosedLoop, loop_jacobian, simulate_loop

__all__ = ["SEMResult", "least_squares_start", "predicted_angle_error", "solve_sem"]

TWO_PI = 2.0 * math.pi


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
    status : str
        "converged" (predicted relative decrease below ``tol``), "max_iterations", "stalled"
        (no step reduced the cost) or "diverged" (the loop is unstable at the start).
    solve_time : float
        Wall time [s], compilation excluded when warm.
    noise_variance : float
        sigma^2 = J(theta*) / (3 N - p), per Hall channel.
    covariance : ndarray (p, p)
        sigma^2 (J^T J)^-1, theta flattened sensor-major.
    n_samples : int
        N.
    d_sim : ndarray (N, 3)
        Simulated Hall signals at theta*.
    y0_sim : ndarray (N,)
        Simulated angle at theta*.
    gain : float
        Factor c on the plant input matrix found jointly with theta (1 unless ``fit_gain``).
    gain_std : float
        Its standard deviation from the covariance (first order, c * std(log c)).
    """

    flux: FluxModel
    theta0: NDArray[np.float64] = field(repr=False)
    cost_history: NDArray[np.float64] = field(repr=False)
    iterations: int
    status: str
    solve_time: float
    noise_variance: float
    covariance: NDArray[np.float64] = field(repr=False)
    n_samples: int
    d_sim: NDArray[np.float64] = field(repr=False)
    y0_sim: NDArray[np.float64] = field(repr=False)
    gain: float = 1.0
    gain_std: float = 0.0

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


def least_squares_start(basis: FourierBasis, d: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
    """theta_0 by linear least squares of d on the basis at the f_init output y.

    Treats the measured f_init angle as if it were y0. The resulting model reproduces f_init's
    view of the sensors (its LUT is close to zero) but already carries the harmonic shape of the
    data, which makes the SEM start much closer than pure sinusoids when the flux is distorted.
    """
    Phi = basis.evaluate(np.asarray(y, dtype=np.float64))
    dd = np.asarray(d, dtype=np.float64)
    # Normal equations: over whole revolutions the Fourier columns are nearly orthogonal, so
    # Phi^T Phi is well conditioned and a Cholesky solve is as accurate as an SVD, 30x faster.
    with threadpool_limits(limits=1, user_api="blas"):
        G = Phi.T @ Phi
        rhs = Phi.T @ dd
    try:
        cho = scipy.linalg.cho_factor(G)
        if np.linalg.cond(G) > 1e10:
            raise np.linalg.LinAlgError
        sol = scipy.linalg.cho_solve(cho, rhs)
    except np.linalg.LinAlgError:  # less than a revolution of data: fall back to the SVD
        sol = np.linalg.lstsq(Phi, dd, rcond=None)[0]
    return sol.T.copy()


def _gram(J: NDArray, e: NDArray) -> tuple[NDArray, NDArray]:
    with threadpool_limits(limits=1, user_api="blas"):
        JtJ = J.T @ J
        g = J.T @ e
    return JtJ, g


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
        The model's basis beta(y0).
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
    regularization : array_like (p,), optional
        Diagonal Tikhonov weights w: the cost becomes J(theta) + sum_j w_j theta_j^2 (used by the
        kernel basis, whose prior is diagonal in the Fourier modes).
    fit_gain : bool
        Also estimate a factor c on the plant's input matrix (parametrized as log c, exact
        sensitivity), refining the gain correction of eq. (c_hat) at the SEM optimum where the
        flux model no longer masks it.

    Returns
    -------
    SEMResult
    """
    t_start = time.perf_counter()
    r = np.ascontiguousarray(r, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    N = r.size
    if d.shape != (N, 3):
        raise ValueError("d must have shape (N, 3) with N = len(r)")
    if theta0 is None:
        yy = f_init(d, loop.pole_pairs, projection=loop.projection, offset=loop.offset)
        theta0 = least_squares_start(basis, d, yy if y is None else y)
    theta = np.array(theta0, dtype=np.float64).reshape(3, basis.size)
    ng = 1 if fit_gain else 0
    p = theta.size + ng
    wreg = np.zeros(theta.size) if regularization is None else np.asarray(regularization, float)
    wreg = np.r_[wreg, np.zeros(ng)]
    jac = np.empty((N, 3, p))
    log_gain = 0.0

    def loop_at(lg: float) -> ClosedLoop:
        return loop.with_plant_gain(math.exp(lg)) if fit_gain else loop

    def jacobian_at(th: NDArray, lg: float):
        return loop_jacobian(loop_at(lg), FluxModel(basis, th), r, out=jac, fit_gain=fit_gain)

    def cost_of(th: NDArray, lg: float) -> float:
        res = simulate_loop(loop_at(lg), FluxModel(basis, th), r)
        if res.status != "ok":
            return math.inf
        e = d - res.d
        return float(np.vdot(e, e) + wreg[: th.size] @ (th.ravel() ** 2))

    lam = damping
    history = []
    status = "max_iterations"
    iterations = 0
    lj = jacobian_at(theta, log_gain)
    if lj.status != "ok":
        status = "diverged"
    JtJ = np.eye(p)
    while status not in ("diverged",):
        e = (d - lj.d).ravel()
        th = np.r_[theta.ravel(), [log_gain] * ng]
        cost = float(e @ e + wreg @ th**2)
        if not history:
            history.append(cost)
        J2 = jac.reshape(3 * N, p)
        JtJ, g = _gram(J2, e)
        JtJ_reg = JtJ + np.diag(wreg)
        g = g - wreg * th
        # Stop when the full Gauss-Newton step predicts a relative decrease below tol
        # (Dennis & Schnabel 1996, sec. 7.2): it needs no further simulation.
        try:
            predicted = float(g @ np.linalg.solve(JtJ_reg, g))
        except np.linalg.LinAlgError:
            predicted = math.inf
        if predicted <= tol * cost:
            status = "converged"
            break
        if iterations >= max_iterations:
            break
        diag = np.diag(JtJ_reg).copy()
        diag[diag <= 0] = 1.0
        accepted = False
        for _ in range(30):
            A = JtJ_reg + lam * np.diag(diag)
            try:
                step = np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            new_theta = theta + step[: theta.size].reshape(theta.shape)
            new_log_gain = log_gain + (float(step[-1]) if fit_gain else 0.0)
            new_cost = cost_of(new_theta, new_log_gain)
            if new_cost < cost:
                accepted = True
                break
            lam *= 4.0
        if not accepted:
            status = "stalled"
            break
        theta, log_gain = new_theta, new_log_gain
        iterations += 1
        history.append(new_cost)
        lam = max(lam / 5.0, 1e-12)
        lj = jacobian_at(theta, log_gain)
    final_flux = FluxModel(basis, theta)
    sigma2 = history[-1] / max(3 * N - p, 1) if history else math.nan
    try:
        cov_all = sigma2 * np.linalg.inv(JtJ + np.diag(wreg))
    except np.linalg.LinAlgError:
        cov_all = np.full((p, p), np.nan)
    cov = cov_all[: theta.size, : theta.size]
    gain = math.exp(log_gain)
    gain_std = gain * math.sqrt(max(cov_all[-1, -1], 0.0)) if fit_gain else 0.0
    return SEMResult(
        flux=final_flux,
        theta0=np.asarray(theta0, float).reshape(3, -1),
        cost_history=np.asarray(history if history else [math.inf]),
        iterations=iterations,
        status=status,
        solve_time=time.perf_counter() - t_start,
        noise_variance=sigma2,
        covariance=cov,
        n_samples=N,
        d_sim=lj.d,
        y0_sim=lj.y0,
        gain=gain,
        gain_std=gain_std,
    )


def predicted_angle_error(
    flux: FluxModel,
    covariance: ArrayLike,
    pole_pairs: int,
    *,
    projection: ArrayLike,
    offset: ArrayLike,
    points: int = 512,
) -> NDArray[np.float64]:
    """Standard deviation of the LUT correction eta(y0) implied by cov(theta) [rad].

    First-order propagation through eq. (recon_biject): ``eta = y0 - f_init(g_theta(y0))`` so
    ``d eta / d theta = -(1/n_m) d psi/d d . (I_3 kron beta(y0))``.

    Returns
    -------
    ndarray (points,)
        std of eta on a uniform grid of y0 over one revolution.
    """
    y0 = TWO_PI * np.arange(points) / points
    B = flux.basis.evaluate(y0)  # (M, m)
    g = flux(y0) - np.asarray(offset, float)
    P = np.asarray(projection, float)
    ab = g @ P.T
    rho2 = ab[:, 0] ** 2 + ab[:, 1] ** 2
    dpsi = (ab[:, [0]] * P[1] - ab[:, [1]] * P[0]) / rho2[:, None]  # (M, 3)
    G = -(dpsi[:, :, None] * B[:, None, :]).reshape(points, -1) / pole_pairs  # (M, 3m)
    C = np.asarray(covariance, float)
    var = np.einsum("ij,jk,ik->i", G, C, G)
    return np.sqrt(np.maximum(var, 0.0))
