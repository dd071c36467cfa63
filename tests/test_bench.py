"""The virtual bench: paper defaults and that every knob does what it says."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hallcal.sensor.lut import build_lut
from hallcal.sim.bench import (
    BenchConfig,
    noise_floor,
    ramp_run,
    shape_deformation,
    simulate_run,
)


@pytest.fixture(scope="module")
def paper_run():
    return ramp_run(BenchConfig(seed=3))


def test_paper_defaults(paper_run):
    cfg = paper_run.config
    assert (cfg.pole_pairs, cfg.sample_time, cfg.noise_variance) == (11, 2.5e-4, 7.5e-6)
    assert paper_run.n_samples == 104_000
    assert paper_run.truth.basis.harmonics == tuple(range(1, 12))
    assert cfg.noise_floor == pytest.approx(math.sqrt(7.5e-6) * math.sqrt(2 / 3) / 11)
    assert cfg.noise_floor == pytest.approx(2.03e-4, rel=0.01)
    e = paper_run.y - paper_run.y0
    # "f_init gives about 3 mrad"; the magnet variations are random: 2-4.5 mrad
    assert 2e-3 < np.std(e) < 4.5e-3
    assert paper_run.status == "ok"
    assert paper_run.y0[0] == 0.0  # y0 = 0 at the first sample (paper's convention)
    assert abs(paper_run.y0[-1] - 13.0) < 0.05  # the loop tracks the ramp


def test_noise_is_white_with_the_set_variance(paper_run):
    """d - g(y0) is the added noise: sample variance within 2% (3 x 104 000 samples: the
    relative std of the estimate is sqrt(2 / 312 000) = 0.25%)."""
    v = paper_run.d - paper_run.truth(paper_run.y0)
    assert np.var(v) == pytest.approx(7.5e-6, rel=0.02)
    lag1 = np.mean(v[1:] * v[:-1]) / np.var(v)
    assert abs(lag1) < 0.02


def test_same_seed_same_motor_other_noise():
    cfg = BenchConfig(seed=8)
    r = np.linspace(0, 1, 4000)
    a, b, c = simulate_run(cfg, r), simulate_run(cfg, r), simulate_run(cfg, r, seed=9)
    np.testing.assert_array_equal(a.d, b.d)
    np.testing.assert_array_equal(a.truth.theta, c.truth.theta)
    assert not np.array_equal(a.d, c.d)
    other = BenchConfig(seed=10).truth()
    assert not np.allclose(other.theta, a.truth.theta)


@settings(max_examples=15)
@given(
    n=st.integers(1, 30),
    mis=st.floats(-10, 10),
    gain=st.floats(-0.2, 0.2),
    off=st.floats(-1, 1),
    k=st.integers(2, 7),
    ck=st.floats(-0.2, 0.2),
)
def test_truth_is_the_physical_formula(n, mis, gain, off, k, ck):
    """The Fourier truth equals d_2 = o + A (1 + gain) s(n y0 - phi_2) where
    s(psi) = cos psi + c_k cos(k psi) (no per-magnet variation): the fit is exact."""
    cfg = BenchConfig(
        pole_pairs=n,
        magnet_variation=0.0,
        misalignment_deg=(0.0, mis, 0.0),
        gain_mismatch=(0.0, gain, 0.0),
        offset=(0.0, off, 0.0),
        electrical_harmonics=((k, ck),),
        amplitude=2.0,
    )
    y0 = np.linspace(0, 2 * np.pi, 777)
    psi = n * y0 - (2 * np.pi / 3 + math.radians(mis))
    expect = off + 2.0 * (1 + gain) * (np.cos(psi) + ck * np.cos(k * psi))
    np.testing.assert_allclose(cfg.truth()(y0)[:, 1], expect, atol=1e-10)


def test_magnet_variation_and_pole_modulation_break_the_pole_periodicity():
    y0 = np.linspace(0, 2 * np.pi, 1000, endpoint=False)
    for knob in ({"magnet_variation": 0.05}, {"pole_modulation": 0.05, "magnet_variation": 0}):
        g = BenchConfig(pole_pairs=5, **knob).truth()
        shifted = g(y0 + 2 * np.pi / 5)
        assert np.max(np.abs(shifted - g(y0))) > 0.01  # magnets differ
    g = BenchConfig(pole_pairs=5, magnet_variation=0.0).truth()
    np.testing.assert_allclose(g(y0 + 2 * np.pi / 5), g(y0), atol=1e-12)


def test_disturbances_move_the_motor():
    r = np.linspace(0, 2, 8000)
    base = simulate_run(BenchConfig(noise_variance=0.0), r)
    td = simulate_run(BenchConfig(noise_variance=0.0, torque_disturbance=2e-3), r)
    cog = simulate_run(BenchConfig(noise_variance=0.0, cogging=2e-3), r)
    assert np.std(td.y0 - base.y0) > 1e-4
    assert np.std(cog.y0 - base.y0) > 1e-5
    assert td.status == cog.status == "ok"


def test_noise_floor_formula_matches_monte_carlo():
    """f_star with the true table on noisy data is at sigma sqrt(2/3) / (A n_m) within 3%."""
    from hallcal.sensor.lut import build_lut

    cfg = BenchConfig(seed=1, noise_variance=2e-5)
    run = ramp_run(cfg, ramp_end=7.0, duration=14.0)
    lut = build_lut(run.truth, cfg.pole_pairs)
    e = lut.f_star(run.d) - run.y0
    assert np.std(e) == pytest.approx(noise_floor(2e-5, 11), rel=0.03)


@settings(max_examples=12, deadline=None)
@given(
    n=st.integers(1, 13),
    K=st.integers(1, 6),
    s=st.floats(0.001, 0.2),
    seed=st.integers(0, 1000),
    mis=st.floats(-5, 5),
    gain=st.floats(-0.2, 0.2),
)
def test_shape_variation_is_one_rotor_pattern_seen_by_each_sensor(n, K, s, seed, mis, gain):
    """The truth equals the formula of the module docstring: ``A (1 + gain_h) (s(psi) +
    delta(y0 - phi_h / n))`` with the deformation of :func:`shape_deformation`, exactly, on the
    harmonics 1..K n (and the nominal ones)."""
    cfg = BenchConfig(pole_pairs=n, magnet_variation=0.0, misalignment_deg=(0.0, mis, 0.0),
                      gain_mismatch=(0.0, gain, 0.0), shape_variation=s, shape_harmonics=K,
                      seed=seed)  # fmt: skip
    m, a, b = shape_deformation(n, s, electrical_harmonics=K,
                                rng=np.random.default_rng([seed, 2]))  # fmt: skip
    assert tuple(m) == tuple(range(1, K * n + 1))
    g = cfg.truth()
    assert set(range(1, K * n + 1)) <= set(g.basis.harmonics)
    y0 = np.linspace(0, 2 * np.pi, 613)
    for h in range(3):
        phi = 2 * np.pi * h / 3 + (math.radians(mis) if h == 1 else 0.0)
        x = np.outer(m, y0 - phi / n)
        delta = a @ np.cos(x) + b @ np.sin(x)
        expect = (1 + (gain if h == 1 else 0.0)) * (np.cos(n * y0 - phi) + delta)
        np.testing.assert_allclose(g(y0)[:, h], expect, atol=1e-10)


def test_shape_variation_strength_and_default():
    """E[delta^2] = s^2 (RMS over 40 rotors within 10 %: the mean of 40 chi-square-like draws
    with 2 K n = 110 degrees of freedom each); s = 0 leaves the truth bit-identical; switching
    it on does not change the other knobs' draws; f_init's error grows with s."""
    s = 0.05
    rms = []
    for seed in range(40):
        _, a, b = shape_deformation(11, s, rng=np.random.default_rng([seed, 2]))
        rms.append(np.sum(a**2 + b**2) / 2)
    assert math.sqrt(np.mean(rms)) == pytest.approx(s, rel=0.1)
    base = BenchConfig(seed=4, magnet_variation=0.03)
    off = base.truth()
    np.testing.assert_array_equal(off.theta, replace(base, shape_variation=0.0).truth().theta)
    on = replace(base, shape_variation=0.02).truth()
    m, a, b = shape_deformation(11, 0.02, rng=np.random.default_rng([4, 2]))
    y0 = np.linspace(0, 2 * np.pi, 500)
    for h in range(3):  # the magnet_variation draws are unchanged: the difference is delta
        x = np.outer(m, y0 - 2 * np.pi * h / 33)
        np.testing.assert_allclose(on(y0)[:, h] - off(y0)[:, h],
                                   a @ np.cos(x) + b @ np.sin(x), atol=1e-10)  # fmt: skip
    errs = []
    for strength in (0.0, 0.03, 0.1):
        cfg = BenchConfig(magnet_variation=0.0, shape_variation=strength, seed=2)
        lut = build_lut(cfg.truth(), 11, points=2048)
        errs.append(float(np.std(lut.eta)))
    assert errs[0] < 1e-9 < errs[1] < errs[2]
    with pytest.raises(ValueError):
        BenchConfig(shape_variation=-0.1)
    with pytest.raises(ValueError):
        BenchConfig(shape_harmonics=0)


def test_simulate_setup_key_reaches_the_bench():
    """``[bench] shape_variation`` / ``shape_harmonics`` of the setup file set the knob."""
    from hallcal.io.setup import default_setup
    from hallcal.pipeline.simulate import bench_config

    s = default_setup()
    s = replace(s, bench=replace(s.bench, shape_variation=0.03, shape_harmonics=2))
    cfg = bench_config(s)
    assert cfg.shape_variation == 0.03 and cfg.shape_harmonics == 2
    assert set(range(1, 23)) <= set(cfg.truth().basis.harmonics)
