"""The structured Gauss-Newton system (fit/gauss_newton.py) against the dense Jacobian.

The oracle is ``loop_jacobian`` of ``tests/loop_oracle.py``, a separate, straightforward
forward-sensitivity recursion that forms the dense (N, 3, p) Jacobian with direct sines and
cosines; it is itself checked against central differences of the plain simulation in
``tests/test_loop.py``.

Tolerances: the structured system takes its sines and cosines from the angle-addition recursion
(rounding error ~ n eps at harmonic n) and sums in other orders (chunks, threads, trigonometric
moments) than the dense products, and the loop's sensitivity amplifies rounding: the two agree to
about 1e-12 relative (measured); 1e-10 leaves a margin while any missing term (a feedback or
cogging-slope term, a wrong column) is off by 1e-3 or more.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from loop_oracle import loop_jacobian

from hallcal._constants import TWO_PI
from hallcal.fit.gauss_newton import (
    ParameterLayout,
    _moments,
    gauss_newton_system,
    gram_from_moments,
    regression_normal_equations,
    simulate_model,
)
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sim.bench import BenchConfig, ramp_run
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import simulate_loop

RTOL = 1e-10


@pytest.fixture(scope="module")
def short_run():
    """1.5 s of a distorted, cogging bench (6000 samples): rich flux, non-trivial motion."""
    cfg = BenchConfig(
        electrical_harmonics=((3, 0.10), (5, 0.04)),
        pole_modulation=0.02,
        cogging=0.003,
        cogging_periods=66,
        torque_disturbance=2e-3,
        seed=3,
    )
    return cfg, ramp_run(cfg, ramp_end=1.5, duration=1.5, seed=3)


def _theta_near_truth(run, basis: FourierBasis, seed: int = 0) -> np.ndarray:
    yy = TWO_PI * np.arange(2048) / 2048
    th = np.linalg.lstsq(basis.evaluate(yy), run.truth(yy), rcond=None)[0].T
    return th + 1e-3 * np.random.default_rng(seed).standard_normal(th.shape)


def _dense(loop, layout: ParameterLayout, x, r, d):
    """J^T J, J^T e, e^T e and the simulation from the dense oracle."""
    cog = layout.cogging(x)
    lj = loop_jacobian(
        loop.with_plant_gain(math.exp(layout.log_gain(x))),
        FluxModel(layout.basis, layout.theta(x)),
        r,
        fit_gain=layout.fit_gain,
        cogging=cog,
        fit_cogging=bool(layout.cogging_orders),
    )
    J = lj.jac.reshape(-1, layout.size)
    e = (d - lj.d).ravel()
    # the scale of the sums behind each entry of J^T e (its terms cancel in part)
    scale = np.abs(J).T @ np.abs(e)
    return J.T @ J, J.T @ e, float(e @ e), lj, scale


def _assert_matches(gn, dense) -> None:
    JtJ, Jte, ete, lj, scale = dense
    assert gn.status.success and lj.status.success
    np.testing.assert_allclose(gn.gram, JtJ, rtol=0, atol=RTOL * np.abs(JtJ).max())
    np.testing.assert_allclose(gn.gradient, Jte, rtol=0, atol=RTOL * scale.max())
    assert gn.sse == pytest.approx(ete, rel=RTOL)
    np.testing.assert_allclose(gn.d, lj.d, rtol=0, atol=RTOL)  # |d| ~ 1
    np.testing.assert_allclose(gn.y0, lj.y0, rtol=0, atol=RTOL * np.abs(lj.y0).max())


@settings(max_examples=20)
@given(
    harmonics=st.sets(st.integers(1, 40), min_size=1, max_size=14),
    fit_gain=st.booleans(),
    cogging=st.sets(st.integers(1, 140), max_size=3),
    threads=st.sampled_from([1, 2]),
    chunk=st.sampled_from([257, 4096]),
    log_gain=st.floats(-0.1, 0.1),
)
def test_matches_dense_jacobian_for_any_harmonic_set(
    short_run, harmonics, fit_gain, cogging, threads, chunk, log_gain
):
    cfg, run = short_run
    basis = FourierBasis(tuple(sorted(harmonics | {11})))  # n_m keeps f_init meaningful
    orders = tuple(sorted(cogging))
    layout = ParameterLayout(basis, fit_gain=fit_gain, cogging_orders=orders)
    rng = np.random.default_rng(len(harmonics))
    cog = CoggingTorque(orders, 1e-3 * rng.standard_normal(len(orders)),
                        1e-3 * rng.standard_normal(len(orders)))  # fmt: skip
    x = layout.pack(_theta_near_truth(run, basis), log_gain if fit_gain else 0.0, cog)
    loop = cfg.loop()
    gn = gauss_newton_system(loop, layout, x, run.r, run.d, chunk=chunk, threads=threads)
    _assert_matches(gn, _dense(loop, layout, x, run.r, run.d))
    np.testing.assert_allclose(gn.batch_gradients.sum(axis=0), gn.gradient, rtol=0, atol=0)
    assert gn.batch_gradients.shape == (-(-run.n_samples // min(chunk, run.n_samples)), x.size)


def test_threads_and_chunks_agree(short_run):
    """One or two threads give the same system to the bit (the same sums per column, the same
    BLAS calls); the chunking changes only the summation order."""
    cfg, run = short_run
    layout = ParameterLayout(FourierBasis(tuple(range(1, 34))), True, (66,))
    x = layout.pack(_theta_near_truth(run, layout.basis), 0.02, CoggingTorque((66,), [1e-3], [0]))
    a = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, threads=1, chunk=4096)
    a2 = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, threads=2, chunk=4096)
    for name in ("gram", "gradient", "batch_gradients", "d", "y0"):
        np.testing.assert_array_equal(getattr(a2, name), getattr(a, name))
    assert a2.sse == a.sse
    b = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, threads=2, chunk=700)
    np.testing.assert_allclose(b.gram, a.gram, rtol=0, atol=1e-12 * np.abs(a.gram).max())
    np.testing.assert_allclose(
        b.gradient, a.gradient, rtol=0, atol=1e-12 * np.abs(a.gradient).max()
    )
    np.testing.assert_array_equal(b.d, a.d)
    assert np.array_equal(a.gram, a.gram.T) and np.array_equal(b.gram, b.gram.T)


def test_strided_hessian_is_a_close_quadrature(short_run):
    """stride 4: gradient and cost bit-identical (same chunks), J^T J within 5 % (Frobenius).

    The rank-one sum over every 4th sample of smooth sensitivities is a Riemann sum with a
    relative error of order 4 / (samples per loop time constant): about 1 % here."""
    cfg, run = short_run
    layout = ParameterLayout(FourierBasis(tuple(range(1, 14))), True, (66,))
    x = layout.pack(_theta_near_truth(run, layout.basis), 0.0)
    exact = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, chunk=1000)
    quad = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, chunk=1000, stride=4)
    np.testing.assert_array_equal(quad.gradient, exact.gradient)
    assert quad.sse == exact.sse
    assert np.linalg.norm(quad.gram - exact.gram) < 0.05 * np.linalg.norm(exact.gram)
    grad_only = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, chunk=1000, gram=False)
    np.testing.assert_array_equal(grad_only.gradient, exact.gradient)


def test_simulate_model_matches_simulate_loop(short_run):
    cfg, run = short_run
    layout = ParameterLayout(FourierBasis((1, 2, 11, 22, 33, 55)), True, (66, 7))
    cog = CoggingTorque((66, 7), [2e-3, -1e-3], [1e-3, 5e-4])
    th = _theta_near_truth(run, layout.basis)
    x = layout.pack(th, -0.05, cog)
    sim = simulate_model(cfg.loop(), layout, x, run.r)
    ref = simulate_loop(
        cfg.loop().with_plant_gain(math.exp(-0.05)), FluxModel(layout.basis, th), run.r,
        cogging=cog,
    )  # fmt: skip
    assert sim.status.success and ref.status.success
    np.testing.assert_allclose(sim.d, ref.d, rtol=0, atol=RTOL)
    np.testing.assert_allclose(sim.y, ref.y, rtol=0, atol=RTOL)
    np.testing.assert_allclose(sim.u, ref.u, rtol=0, atol=1e-9 * np.abs(ref.u).max())


def test_diverged_pass_is_all_nan(short_run):
    """An unstable loop (plant gain x 30) gives NaN everywhere, never uninitialised memory."""
    cfg, run = short_run
    layout = ParameterLayout(FourierBasis(tuple(range(1, 12))), fit_gain=True)
    x = layout.pack(_theta_near_truth(run, layout.basis), math.log(30.0))
    for threads in (1, 2):
        gn = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, threads=threads, chunk=512)
        assert not gn.status.success and gn.sse == math.inf
        for arr in (gn.gram, gn.gradient, gn.d, gn.y0, gn.batch_gradients):
            assert np.all(np.isnan(arr))
    sim = simulate_model(cfg.loop(), layout, x, run.r)
    assert not sim.status.success
    bad = np.isnan(sim.y0)
    assert bad.any() and np.all(bad[np.argmax(bad) :])  # NaN from the divergence on
    lj = loop_jacobian(cfg.loop().with_plant_gain(30.0), FluxModel(layout.basis, layout.theta(x)),
                       run.r)  # fmt: skip
    k = int(np.argmax(np.isnan(lj.y0)))
    assert not lj.status.success and np.all(np.isnan(lj.jac[k:])) and np.all(np.isnan(lj.d[k:]))


@settings(max_examples=30)
@given(harmonics=st.sets(st.integers(1, 30), min_size=1, max_size=10), seed=st.integers(0, 99))
def testgram_from_moments_matches_dense_products(harmonics, seed):
    """sum_k w_k beta_k beta_k^T from moments equals the dense sum (rounding only: 1e-12)."""
    rng = np.random.default_rng(seed)
    y = np.sort(rng.uniform(-3.0, 15.0, 500))
    w = rng.standard_normal(500)
    basis = FourierBasis(tuple(sorted(harmonics)))
    C, S = _moments(y, np.ascontiguousarray(w[:, None]), 2 * max(harmonics))
    M = gram_from_moments(C[0], S[0], basis.harmonics)
    B = basis.evaluate(y)
    dense = (B * w[:, None]).T @ B
    np.testing.assert_allclose(M, dense, rtol=0, atol=1e-12 * np.abs(dense).max())


def test_regression_normal_equations_match_dense():
    rng = np.random.default_rng(5)
    y = np.linspace(0.0, 14.0, 3000)
    d = rng.standard_normal((3000, 3))
    basis = FourierBasis((1, 3, 11, 12, 40))
    G, rhs, dd = regression_normal_equations(y, d, basis.harmonics)
    B = basis.evaluate(y)
    np.testing.assert_allclose(G, B.T @ B, rtol=0, atol=1e-10 * 3000)
    np.testing.assert_allclose(rhs, B.T @ d, rtol=0, atol=1e-10 * 3000)
    assert dd == pytest.approx(float(np.sum(d * d)), rel=1e-13)


def test_layout_round_trip():
    layout = ParameterLayout(FourierBasis((1, 11)), fit_gain=True, cogging_orders=(66, 132))
    th = np.arange(15.0).reshape(3, 5)
    cog = CoggingTorque((132,), [0.5], [-0.25])
    x = layout.pack(th, 0.3, cog)
    assert layout.size == 15 + 1 + 4 and layout.gain_index == 15 and layout.cogging_start == 16
    np.testing.assert_array_equal(layout.theta(x), th)
    assert layout.log_gain(x) == 0.3
    back = layout.cogging(x)
    assert back.orders == (66, 132)
    np.testing.assert_array_equal(back.a, [0.0, 0.5])
    np.testing.assert_array_equal(back.b, [0.0, -0.25])
    with pytest.raises(ValueError):
        ParameterLayout(FourierBasis((1,)), cogging_orders=(3, 3))
    with pytest.raises(ValueError, match="entries"):
        simulate_model(BenchConfig().loop(), layout, np.zeros(3), np.zeros(10))


def test_known_cogging_of_the_loop_is_simulated_not_fitted(short_run):
    """A cogging torque carried by the loop (known) adds to the fitted orders, same order too."""
    cfg, run = short_run
    known = CoggingTorque((66, 132), [2e-3, 0.0], [1e-3, 5e-4])
    loop = cfg.loop().with_cogging(known)
    layout = ParameterLayout(FourierBasis(tuple(range(1, 12))), True, (66, 7))
    x = layout.pack(_theta_near_truth(run, layout.basis), 0.01,
                    CoggingTorque((66, 7), [1e-3, 1e-3], [0.0, -1e-3]))  # fmt: skip
    gn = gauss_newton_system(loop, layout, x, run.r, run.d, chunk=1000)
    _assert_matches(gn, _dense(loop, layout, x, run.r, run.d))
    # the same motion as one torque with the sum of the coefficients, simulated directly
    total = CoggingTorque((66, 132, 7), [3e-3, 0.0, 1e-3], [1e-3, 5e-4, -1e-3])
    ref = simulate_loop(cfg.loop().with_plant_gain(math.exp(0.01)),
                        FluxModel(layout.basis, layout.theta(x)), run.r, cogging=total)  # fmt: skip
    np.testing.assert_allclose(gn.d, ref.d, rtol=0, atol=RTOL)


def test_weights_give_the_weighted_system(short_run):
    """Per-sample, per-channel weights (0 = censored): J^T W J, J^T W e, e^T W e of the dense
    oracle, one or two threads; the default (no weights) equals weights of 1 to the bit."""
    cfg, run = short_run
    layout = ParameterLayout(FourierBasis(tuple(range(1, 14))), True, (66,))
    x = layout.pack(_theta_near_truth(run, layout.basis), 0.01, CoggingTorque((66,), [1e-3], [0]))
    w = np.random.default_rng(5).choice([0.0, 0.5, 1.0], size=run.d.shape)
    JtJ, _, _, lj, _ = _dense(cfg.loop(), layout, x, run.r, run.d)
    J = lj.jac.reshape(-1, layout.size)
    e = (run.d - lj.d).ravel()
    wf = w.ravel()
    dense = (J.T @ (wf[:, None] * J), J.T @ (wf * e), float(e @ (wf * e)), lj,
             np.abs(J).T @ np.abs(wf * e))  # fmt: skip
    for threads in (1, 2):
        gn = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, weights=w, threads=threads)
        _assert_matches(gn, dense)
    ones = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, weights=np.ones_like(w))
    plain = gauss_newton_system(cfg.loop(), layout, x, run.r, run.d)
    np.testing.assert_array_equal(ones.gradient, plain.gradient)
    np.testing.assert_allclose(ones.gram, JtJ, rtol=0, atol=RTOL * np.abs(JtJ).max())
    with pytest.raises(ValueError):
        gauss_newton_system(cfg.loop(), layout, x, run.r, run.d, weights=-w)


def _assert_matches_central_differences(gn, loop, layout, x, run, sim, w) -> None:
    """J^T W J and J^T W e of `gn` against a Jacobian of central differences of
    simulate_model: the oracle where the dense one has no columns (ADC rails, drift).

    Step 1e-6: truncation O(h^2) ~ 1e-12 and rounding O(eps / h) ~ 1e-10 per entry, far below
    the 1e-5 relative tolerance of the sums."""
    h = 1e-6
    cols = []
    for j in range(layout.size):
        dx = np.zeros(layout.size)
        dx[j] = h
        up = simulate_model(loop, layout, x + dx, run.r).d
        dn = simulate_model(loop, layout, x - dx, run.r).d
        cols.append(((up - dn) / (2 * h)).ravel())
    J = np.column_stack(cols)
    e = (run.d - sim.d).ravel()
    wf = w.ravel()
    JtWJ = J.T @ (wf[:, None] * J)
    np.testing.assert_allclose(gn.gram, JtWJ, rtol=0, atol=1e-5 * np.abs(JtWJ).max())
    np.testing.assert_allclose(gn.gradient, J.T @ (wf * e), rtol=0,
                               atol=1e-5 * (np.abs(J).T @ np.abs(wf * e)).max())  # fmt: skip


def test_rails_clip_what_the_model_f_init_sees(short_run):
    """With rails in the loop, f_init sees the model flux clipped (as the drive saw the clipped
    signals) while d_sim stays the flux: the simulation equals the bench loop with those rails,
    and J^T W J, J^T W e equal the products of a central-difference Jacobian.

    Differences with h = 1e-6 on a cost whose kinks (a sample crossing a rail) are isolated:
    truncation and rounding ~1e-8 relative; 1e-5 leaves a margin while a missing rail term
    (f_init differentiated through a clipped channel) is off by several percent."""
    cfg, run = short_run
    loop = cfg.loop().with_rails([-0.97, -np.inf, -0.98], [0.96, 0.99, np.inf])
    layout = ParameterLayout(FourierBasis((1, 11, 22)))
    x = layout.pack(_theta_near_truth(run, layout.basis))
    sim = simulate_model(loop, layout, x, run.r)
    ref = simulate_loop(loop, FluxModel(layout.basis, layout.theta(x)), run.r)
    np.testing.assert_allclose(sim.y, ref.y, rtol=0, atol=RTOL)
    assert ref.d[:, 0].max() == 0.96 and sim.d[:, 0].max() > 0.96  # d_sim: the unclipped flux
    w = (np.abs(run.d) < 0.95).astype(float)
    gn = gauss_newton_system(loop, layout, x, run.r, run.d, weights=w)
    _assert_matches_central_differences(gn, loop, layout, x, run, sim, w)
    plain = simulate_model(cfg.loop(), layout, x, run.r)
    assert np.abs(plain.y0 - sim.y0).max() > 1e-5  # the rails moved the simulated motor


def test_drift_columns_match_central_differences(short_run):
    """Sensor gain and offset linear in time (``fit_drift``): the simulation carries the drift
    (f_init sees the drifting signals), and J^T W J, J^T W e equal the products of a
    central-difference Jacobian over theta, the gain, a cogging order and the six drift
    parameters, with weights and rails (tolerance as for the rails)."""
    cfg, run = short_run
    loop = cfg.loop().with_rails([-0.97, -np.inf, -np.inf], [0.96, np.inf, np.inf])
    layout = ParameterLayout(FourierBasis((1, 11)), True, (66,), fit_drift=True)
    drift = [[0.02, 0.001], [-0.01, 0.0], [0.0, -0.002]]
    x = layout.pack(_theta_near_truth(run, layout.basis), 0.01, CoggingTorque((66,), [1e-3], [0]),
                    drift)  # fmt: skip
    np.testing.assert_array_equal(layout.drift(x), drift)
    sim = simulate_model(loop, layout, x, run.r)
    tau = np.arange(run.n_samples) / (run.n_samples - 1) - 0.5
    g = FluxModel(layout.basis, layout.theta(x))(sim.y0)
    dr = np.asarray(drift)
    np.testing.assert_allclose(sim.d, (1 + np.outer(tau, dr[:, 0])) * g + np.outer(tau, dr[:, 1]),
                               rtol=0, atol=1e-12)  # fmt: skip
    flat = ParameterLayout(FourierBasis((1, 11)), True, (66,))
    assert np.abs(simulate_model(loop, flat, x[: flat.size], run.r).y - sim.y).max() > 1e-5
    w = (np.abs(run.d) < 0.95).astype(float)
    gn = gauss_newton_system(loop, layout, x, run.r, run.d, weights=w, stride=3)
    exact = gauss_newton_system(loop, layout, x, run.r, run.d, weights=w)
    _assert_matches_central_differences(exact, loop, layout, x, run, sim, w)
    np.testing.assert_array_equal(gn.gradient, exact.gradient)  # the stride: J^T J only
    assert np.linalg.norm(gn.gram - exact.gram) < 0.05 * np.linalg.norm(exact.gram)
