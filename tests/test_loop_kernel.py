"""The closed loop's forms against each other on random small loops (sim/loop_kernel.py).

The loop's steps are written once (:mod:`hallcal.sim.loop_kernel`) and driven by two kernels
of the package: the one simulation (the bench's :func:`~hallcal.sim.loop.simulate_loop`, direct
sines per harmonic, and the solver's :func:`~hallcal.fit.gauss_newton.simulate_model`, the
trigonometric recursion) and the structured Gauss-Newton pass
(:func:`~hallcal.fit.gauss_newton.gauss_newton_system`: column blocks, weights, rails, drift);
the tests' dense Jacobian (``tests/loop_oracle.py``) is a third, independent form.
On random stable loops (plant, controller, n_m, flux harmonics, cogging orders, gain, rails,
drift, a loop's own known cogging torque) they must agree with each other, and the
sensitivities with central differences of the simulation (an oracle that shares no sensitivity
code).
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from loop_oracle import loop_jacobian

from hallcal.fit.gauss_newton import ParameterLayout, gauss_newton_system, simulate_model
from hallcal.sensor.flux import FluxModel, FourierBasis, sinusoidal_theta
from hallcal.sim.bench import PAPER_CONTROLLER, PAPER_PLANT
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import ClosedLoop, simulate_loop
from hallcal.sim.lti import ContinuousTF, DiscreteTF

#: samples of each random run (0.15 s at 4 kHz): short, yet the loop's transient and a few
#: electrical periods
N = 600
SAMPLE_TIME = 2.5e-4


@st.composite
def random_loops(draw):
    """A random stable loop, model and run: (loop, layout, x, r, d)."""
    k_gain = draw(st.floats(0.6, 1.4))
    damping = draw(st.floats(0.8, 1.25))
    delay = draw(st.floats(0.5, 1.5))
    c_gain = draw(st.floats(0.6, 1.1))
    n_m = draw(st.integers(1, 4))
    plant = ContinuousTF(
        (PAPER_PLANT.num[0] * k_gain,),
        (1.0, PAPER_PLANT.den[1] * damping, PAPER_PLANT.den[2] * damping, 0.0),
        PAPER_PLANT.delay * delay,
    )
    controller = DiscreteTF(tuple(c_gain * v for v in PAPER_CONTROLLER.num), PAPER_CONTROLLER.den)
    loop = ClosedLoop.from_transfer_functions(plant, controller, SAMPLE_TIME, n_m)
    if draw(st.booleans()):  # a known cogging torque of the loop itself, never fitted
        loop = loop.with_cogging(CoggingTorque((draw(st.integers(1, 12)),), [2e-3], [-1e-3]))
    if draw(st.booleans()):  # ADC rails that clip the peaks of the flux
        loop = loop.with_rails(-0.97, 0.97)
    harmonics = draw(st.sets(st.integers(1, 9), max_size=4)) | {n_m}
    basis = FourierBasis(tuple(sorted(harmonics)))
    layout = ParameterLayout(
        basis,
        fit_gain=draw(st.booleans()),
        cogging_orders=tuple(sorted(draw(st.sets(st.integers(0, 12), max_size=3)))),
        fit_drift=draw(st.booleans()),
    )
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    theta = sinusoidal_theta(basis, n_m, amplitude=np.ones(3), offset=np.zeros(3))
    theta = theta + 0.03 * rng.standard_normal(theta.shape)
    n_cog = len(layout.cogging_orders)
    cog = CoggingTorque(layout.cogging_orders, 2e-3 * rng.standard_normal(n_cog),
                        2e-3 * rng.standard_normal(n_cog))  # fmt: skip
    drift = 0.02 * rng.standard_normal((3, 2)) if layout.fit_drift else None
    x = layout.pack(theta, draw(st.floats(-0.1, 0.1)) if layout.fit_gain else 0.0, cog, drift=drift)
    speed = draw(st.floats(-20.0, 20.0))  # mechanical [rad/s]
    r = speed * SAMPLE_TIME * np.arange(N)
    sim = simulate_model(loop, layout, x, r)
    assume(sim.status.success and np.abs(sim.y0 - r).max() < 0.5)  # stable and tracking
    d = sim.d + 0.01 * rng.standard_normal((N, 3))  # a recording: the model plus noise
    return loop, layout, x, r, d


def _bench_loop(loop: ClosedLoop, layout: ParameterLayout, x: np.ndarray) -> ClosedLoop:
    """The loop as the bench simulates the model x: plant gain c applied, fitted cogging added
    (the loop's own cogging torque stays)."""
    return loop.with_plant_gain(math.exp(layout.log_gain(x)))


def _dense(loop, layout, x, r):
    """loop_jacobian of the model x (no drift: the dense form has no drift columns)."""
    return loop_jacobian(
        _bench_loop(loop, layout, x),
        FluxModel(layout.basis, layout.theta(x)),
        r,
        fit_gain=layout.fit_gain,
        cogging=layout.cogging(x),
        fit_cogging=bool(layout.cogging_orders),
    )


def _central_differences(loop, layout, x, r) -> np.ndarray:
    """d d_sim / d x (3 N, p) by central differences of simulate_model, step 1e-4.

    The simulation's own rounding is ~1e-13 (y0 = C_G x_G sums terms of C_G ~ 1e5), so the
    rounding part of a difference quotient is ~1e-13 / h; measured on one of these loops, the
    largest error per column relative to the column was 1e-8, 3e-8, 3e-7, 3e-6 at h = 1e-4,
    1e-5, 1e-6, 1e-7 (rounding-dominated down to 1e-4, truncation O(h^2) still below)."""
    h = 1e-4
    cols = []
    for j in range(layout.size):
        dx = np.zeros(layout.size)
        dx[j] = h
        up = simulate_model(loop, layout, x + dx, r).d
        dn = simulate_model(loop, layout, x - dx, r).d
        cols.append(((up - dn) / (2 * h)).ravel())
    return np.column_stack(cols)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(case=random_loops())
def test_simulator_and_solver_simulate_the_same_loop(case):
    """simulate_loop's y0 equals simulate_model's: the same kernel, the basis by direct sines
    against the angle-addition recursion, whose rounding (~n eps at harmonic n, below 1e-14)
    the stable loop carries on without growth: 1e-11 rad is a thousand times that."""
    loop, layout, x, r, _ = case
    model = simulate_model(loop, layout, x, r)
    bench_loop = _bench_loop(loop, layout, x)
    if layout.fit_drift:  # the bench has no drift; the model's y0 without it
        layout = ParameterLayout(layout.basis, layout.fit_gain, layout.cogging_orders)
        x = x[: layout.size]
        model = simulate_model(loop, layout, x, r)
    bench = simulate_loop(bench_loop, FluxModel(layout.basis, layout.theta(x)), r,
                          cogging=layout.cogging(x))  # fmt: skip
    assert bench.status.success and model.status.success
    np.testing.assert_allclose(bench.y0, model.y0, rtol=0, atol=1e-11)
    np.testing.assert_allclose(bench.y, model.y, rtol=0, atol=1e-11)
    # d: the bench's is what f_init saw (clipped at the rails), the model's the flux
    np.testing.assert_allclose(np.clip(model.d, *loop.rails), bench.d, rtol=0, atol=1e-11)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(case=random_loops(), threads=st.sampled_from([1, 2]), chunk=st.sampled_from([97, 4096]))
def test_solver_sensitivities_equal_the_dense_jacobian_and_central_differences(
    case, threads, chunk
):
    """J^T W J and J^T W e of the structured pass against the dense Jacobian (same equations;
    other summation order, trigonometric moments, recursion: 1e-9 of the largest entry; the
    dense form has neither drift nor rails) and against central differences
    (:func:`_central_differences`: ~1e-8 per entry; 1e-5 of the largest entry of the sums, as
    in tests/test_gauss_newton.py; with rails 1e-3, because d_sim has a kink each time a sensor
    reaches a rail and a difference quotient across one is no derivative: 4e-5 off on one drawn
    loop), with random weights (0: censored)."""
    loop, layout, x, r, d = case
    w = np.random.default_rng(len(x)).uniform(0.0, 2.0, (N, 3))
    w[::5, 0] = 0.0
    gn = gauss_newton_system(loop, layout, x, r, d, weights=w, threads=threads, chunk=chunk)
    assert gn.status.success
    e = (d - gn.d).ravel()
    wf = w.ravel()
    smooth = bool(np.isinf(loop.rails).all())
    forms = [(_central_differences(loop, layout, x, r), 1e-5 if smooth else 1e-3)]
    if smooth and not layout.fit_drift:
        forms.append((_dense(loop, layout, x, r).jac.reshape(3 * N, layout.size), 1e-9))
    for J, tol in forms:
        JtWJ = J.T @ (wf[:, None] * J)
        np.testing.assert_allclose(gn.gram, JtWJ, rtol=0, atol=tol * np.abs(JtWJ).max())
        scale = (np.abs(J).T @ np.abs(wf * e)).max()  # the size of the terms of J^T W e
        np.testing.assert_allclose(gn.gradient, J.T @ (wf * e), rtol=0, atol=tol * scale)


@settings(max_examples=30, deadline=None, derandomize=True)
@given(case=random_loops())
def test_dense_jacobian_equals_central_differences(case):
    """Each entry of loop_jacobian against central differences of simulate_model
    (:func:`_central_differences`: ~1e-8 of the column's scale; 1e-6 of the largest entry) and
    its d, y0 against the model simulation (1e-11, the basis recursion's rounding as above)."""
    loop, layout, x, r, _ = case
    loop = loop.with_rails(-np.inf, np.inf)  # smooth (see the test above)
    if layout.fit_drift:  # the dense form has no drift columns: the model without drift
        layout = ParameterLayout(layout.basis, layout.fit_gain, layout.cogging_orders)
        x = x[: layout.size]
    lj = _dense(loop, layout, x, r)
    assert lj.status.success
    J = lj.jac.reshape(3 * N, layout.size)
    J_fd = _central_differences(loop, layout, x, r)
    np.testing.assert_allclose(J, J_fd, rtol=0, atol=1e-6 * np.abs(J).max())
    model = simulate_model(loop, layout, x, r)
    np.testing.assert_allclose(lj.d, model.d, rtol=0, atol=1e-11)
    np.testing.assert_allclose(lj.y0, model.y0, rtol=0, atol=1e-11)
