"""Closed-loop simulation (eq. state_eq) against an independent oracle, and its exact Jacobian.

The oracle integrates the continuous plant with an adaptive ODE solver across each sample
interval (the delayed ZOH input switches at t_k + tau_f), runs the controller as a difference
equation and f_init sample by sample: it shares no code with the ZOH formulas or the numba kernel.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.integrate
import scipy.signal
from loop_oracle import loop_jacobian

from hallcal.sensor.flux import FluxModel, FourierBasis, sinusoidal_theta
from hallcal.sensor.reconstruction import InitReconstructor
from hallcal.sim.bench import PAPER_CONTROLLER, PAPER_PLANT, BenchConfig
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import ClosedLoop, simulate_loop

TS = 2.5e-4
N_ORACLE = 300


def oracle(flux: FluxModel, r: np.ndarray, n_m: int):
    A, B, C, _ = scipy.signal.tf2ss(PAPER_PLANT.num, PAPER_PLANT.den)
    B = B[:, 0]
    C = C[0]
    tau = PAPER_PLANT.delay
    num = np.r_[
        np.zeros(len(PAPER_CONTROLLER.den) - len(PAPER_CONTROLLER.num)), PAPER_CONTROLLER.num
    ]
    den = np.asarray(PAPER_CONTROLLER.den)
    x = np.zeros(A.shape[0])
    rec = InitReconstructor(n_m)
    e_hist = np.zeros(len(den))
    u_hist = np.zeros(len(den))
    u_applied = {}  # sample index -> torque, for the delayed input
    y0s, ys, us = [], [], []
    for k in range(r.size):
        y0 = C @ x
        d = flux(np.array([y0]))[0]
        y = rec.update(*d)
        e = r[k] - y
        e_hist = np.r_[e, e_hist[:-1]]
        # den[0] u[k] = sum num[i] e[k-i] - sum_{i>=1} den[i] u[k-i]
        u = (num @ e_hist - den[1:] @ u_hist[:-1]) / den[0]
        u_hist = np.r_[u, u_hist[:-1]]
        u_applied[k] = u
        y0s.append(y0)
        ys.append(y)
        us.append(u)

        def w(t, k=k):  # delayed held input at time t in [k Ts, (k+1) Ts]
            j = math.floor((t - tau) / TS + 1e-12)
            return u_applied.get(j, 0.0) if j >= 0 else 0.0

        t0, t1 = k * TS, (k + 1) * TS
        switch = t0 + tau - math.floor(tau / TS) * TS
        for a, b in ((t0, switch), (switch, t1)):
            if b - a <= 0:
                continue
            uc = w(0.5 * (a + b))
            sol = scipy.integrate.solve_ivp(
                lambda t, xx, uc=uc: A @ xx + B * uc,
                (a, b),
                x,
                rtol=1e-12,
                atol=1e-15,
                method="DOP853",
            )
            x = sol.y[:, -1]
    return np.array(y0s), np.array(ys), np.array(us)


@pytest.fixture(scope="module")
def paper_flux():
    cfg = BenchConfig(seed=11)
    return cfg.truth(), cfg.loop()


def test_simulation_matches_independent_oracle(paper_flux):
    """Same trajectory to 1e-9 rad: ODE tolerances 1e-12 over 300 samples of an unstable-open-loop
    (integrating) plant amplify to about 1e-10."""
    flux, loop = paper_flux
    r = np.linspace(0, 0.3, N_ORACLE)
    res = simulate_loop(loop, flux, r)
    y0, y, u = oracle(flux, r, 11)
    np.testing.assert_allclose(res.y0, y0, atol=1e-9)
    np.testing.assert_allclose(res.y, y, atol=1e-9)
    np.testing.assert_allclose(res.u, u, atol=1e-9 * max(1.0, np.abs(u).max()))


def test_jacobian_matches_central_differences(paper_flux):
    """Exact sensitivities versus central differences on a short run.

    With h = 1e-5 the truncation error is O(h^2 |d'''|) ~ 1e-10 and the rounding error
    eps * |d| / h ~ 1e-11 amplified by the loop; 1e-7 relative leaves a wide margin while a
    missing feedback term would be off by O(1).
    """
    flux, loop = paper_flux
    r = np.linspace(0, 1.0, 4000)
    lj = loop_jacobian(loop, flux, r)
    assert lj.status == "ok"
    rng = np.random.default_rng(3)
    th = flux.theta.ravel()
    h = 1e-5
    for j in rng.choice(th.size, 8, replace=False):
        tp, tm = th.copy(), th.copy()
        tp[j] += h
        tm[j] -= h
        dp = simulate_loop(loop, FluxModel(flux.basis, tp.reshape(3, -1)), r).d
        dm = simulate_loop(loop, FluxModel(flux.basis, tm.reshape(3, -1)), r).d
        fd = (dp - dm) / (2 * h)
        np.testing.assert_allclose(lj.jac[:, :, j], fd, atol=1e-7 * max(1.0, np.abs(fd).max()))
    # the noise-free simulation inside the Jacobian pass equals the plain simulation
    np.testing.assert_allclose(lj.d, simulate_loop(loop, flux, r).d, atol=1e-13)


def test_gain_and_cogging_columns_match_central_differences(paper_flux):
    """The columns of log c and of the cogging coefficients (oracle for the structured system).

    They act through the plant input only, and the cogging torque feeds back through its slope
    dT_c/dy0. Central differences with h = 1e-4 have a truncation error O(h^2) ~ 1e-8 relative
    (measured 1e-7 at most; 1e-6 allows for it), while leaving out the slope term changes the
    cogging columns by about 1e-3.
    """
    flux, loop = paper_flux
    r = np.linspace(0, 1.0, 4000)
    cog = CoggingTorque((66, 7), [0.01, -0.02], [0.02, 0.005])
    lg = 0.05
    lj = loop_jacobian(loop.with_plant_gain(np.exp(lg)), flux, r, fit_gain=True, cogging=cog,
                       fit_cogging=True)  # fmt: skip
    assert lj.status == "ok" and lj.jac.shape == (r.size, 3, flux.theta.size + 5)

    def d_of(log_gain: float, coef: np.ndarray) -> np.ndarray:
        c = CoggingTorque.from_coefficients(cog.orders, coef)
        return simulate_loop(loop.with_plant_gain(np.exp(log_gain)), flux, r, cogging=c).d

    h = 1e-4
    x = cog.coefficients
    fd = [(d_of(lg + h, x) - d_of(lg - h, x)) / (2 * h)]
    for i in range(x.size):
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        fd.append((d_of(lg, xp) - d_of(lg, xm)) / (2 * h))
    for i, col in enumerate(fd):
        got = lj.jac[:, :, flux.theta.size + i]
        np.testing.assert_allclose(got, col, rtol=0, atol=1e-6 * np.abs(col).max())


def test_feedback_term_matters(paper_flux):
    """Dropping d y0 / d theta (the open-loop 'regression' Jacobian) is far from the truth."""
    flux, loop = paper_flux
    r = np.linspace(0, 1.0, 4000)
    lj = loop_jacobian(loop, flux, r)
    B = flux.basis.evaluate(lj.y0)
    direct = np.zeros_like(lj.jac)
    m = flux.basis.size
    for h in range(3):
        direct[:, h, h * m : (h + 1) * m] = B
    rel = np.linalg.norm(lj.jac - direct) / np.linalg.norm(lj.jac)
    assert rel > 0.1


def test_noise_disturbance_and_divergence_flags():
    cfg = BenchConfig()
    basis = FourierBasis((11,))
    flux = FluxModel(basis, sinusoidal_theta(basis, 11))
    r = np.linspace(0, 2, 8000)
    clean = simulate_loop(cfg.loop(), flux, r)
    assert clean.status == "ok"
    assert np.max(np.abs(clean.y - clean.y0)) < 1e-12  # ideal sensors: f_init is exact
    # A destabilizing controller (gain x 50) is reported as diverged, never as silent NaN.
    bad = ClosedLoop.from_transfer_functions(
        PAPER_PLANT,
        type(PAPER_CONTROLLER)(tuple(50 * c for c in PAPER_CONTROLLER.num), PAPER_CONTROLLER.den),
        TS,
        11,
    )
    res = simulate_loop(bad, flux, r)
    assert res.status == "diverged"
    # Torque disturbance moves the angle; cogging too.
    td = simulate_loop(cfg.loop(), flux, r, torque_disturbance=np.full(r.size, 1e-3))
    assert np.max(np.abs(td.y0 - clean.y0)) > 1e-4
    cg = simulate_loop(cfg.loop(), flux, r, cogging=CoggingTorque((66,), [0.0], [1e-3]))
    assert np.max(np.abs(cg.y0 - clean.y0)) > 1e-6
