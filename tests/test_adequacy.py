"""Model adequacy: noise level from the data, residual analysis and the verdict.

Acceptance on the virtual bench: the trapezoidal flux fitted with the paper's harmonics 1..11 is
refused with a message naming the missing harmonics; the paper's bench is adequate; and no fit in
this file gives an f_star worse than f_init (against the bench's true angle, on a fresh run)
without a "warning" or "inadequate" verdict.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math

import numpy as np
import pytest
import scipy.signal

from hallcal.fit.adequacy import (
    assess,
    chi2_isf_even,
    curve_projection,
    estimate_noise_variance,
    harmonic_content,
)
from hallcal.fit.sem import solve_sem
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run

H11 = tuple(range(1, 12))
TRAP = ((3, 0.10), (5, 0.04))
BENCHES = {
    "paper": BenchConfig(),
    "trapezoid": BenchConfig(electrical_harmonics=TRAP, seed=7),
    "cogging 2e-3": BenchConfig(cogging=2e-3),
    "cogging 2e-2": BenchConfig(cogging=2e-2),
    "disturbance 2e-3": BenchConfig(torque_disturbance=2e-3),
    "disturbance 2e-2": BenchConfig(torque_disturbance=2e-2),
    "pole modulation": BenchConfig(pole_modulation=0.05, seed=3),
}


@functools.cache
def runs(name: str):
    cfg = BENCHES[name]
    return ramp_run(cfg), ramp_run(cfg, ramp_end=12.0, duration=24.0, seed=1234)


@functools.cache
def calibration(name: str, harmonics: tuple[int, ...], plant_gain: float):
    """SEM with the given harmonics, its report, and f_init / f_star on the validation run."""
    cfg = BENCHES[name]
    run, val = runs(name)
    loop = cfg.loop().with_plant_gain(plant_gain)
    sem = solve_sem(loop, run.r, run.d, FourierBasis(harmonics), y=run.y, max_iterations=30)
    rep = assess(sem, run.d, pole_pairs=cfg.pole_pairs)
    lut = build_lut(sem.flux, cfg.pole_pairs)
    e_init = angle_error(lut.f_init(val.d), val.y0).rms
    e_star = angle_error(lut.f_star(val.d), val.y0).rms if lut.bijective else math.inf
    return sem, rep, e_init, e_star


# ------------------------------------------------------------------------------------------
# noise level from the data alone
# ------------------------------------------------------------------------------------------


def test_noise_variance_on_the_paper_bench():
    run, _ = runs("paper")
    est = estimate_noise_variance(run.d)
    s2 = BENCHES["paper"].noise_variance
    assert est.status == "ok"
    assert est.per_channel.shape == (3,)
    np.testing.assert_allclose(est.per_channel, s2, rtol=0.05)
    assert abs(est.variance / s2 - 1) < 0.03
    # the stated standard error is the actual spread (0.4 % pooled for N = 1e5)
    assert 0.002 < est.std_error / s2 < 0.006
    assert abs(est.variance - s2) < 4 * est.std_error


def test_noise_variance_faster_motion_and_other_level():
    cfg = BenchConfig(noise_variance=3e-5, seed=11)
    run = ramp_run(cfg, ramp_end=40.0, duration=10.0)  # 4 rad/s, 8x the paper's speed
    est = estimate_noise_variance(run.d)
    assert abs(est.variance / 3e-5 - 1) < 0.1


def test_noise_variance_bias_for_slow_signals_follows_the_formula():
    rng = np.random.default_rng(0)
    N = 200_000
    omega, a, s2 = 0.05, 1.0, 1e-4
    x = a * np.cos(omega * np.arange(N)) + math.sqrt(s2) * rng.standard_normal(N)
    for k in (1, 2, 3):
        bias = a**2 / 2 * (2 * math.sin(omega / 2)) ** (2 * k) / math.comb(2 * k, k)
        est = estimate_noise_variance(x, order=k)
        assert abs(est.variance - (s2 + bias)) < 5 * est.std_error + 1e-3 * bias
    assert estimate_noise_variance(x, order=1).variance > 1.5 * s2  # order 1 is biased here
    assert abs(estimate_noise_variance(x, order=3).variance / s2 - 1) < 0.02


def test_coloured_noise_is_flagged_and_robust_estimate_ignores_glitches():
    rng = np.random.default_rng(1)
    w = rng.standard_normal((100_000, 3))
    assert estimate_noise_variance(w).status == "ok"
    coloured = scipy.signal.lfilter([1.0], [1.0, -0.5], w, axis=0)
    est = estimate_noise_variance(coloured)
    assert est.status == "coloured"
    glitchy = w.copy()
    glitchy[rng.choice(w.shape[0], 100, replace=False)] += 50.0
    assert estimate_noise_variance(glitchy).variance > 2.0
    assert abs(estimate_noise_variance(glitchy, robust=True).variance - 1.0) < 0.05


def test_noise_variance_short_record():
    est = estimate_noise_variance(np.zeros((5, 3)))
    assert est.status == "too_short" and math.isnan(est.variance)


# ------------------------------------------------------------------------------------------
# harmonic content and the curve projection
# ------------------------------------------------------------------------------------------


def test_harmonic_content_equals_least_squares_and_finds_the_harmonics():
    rng = np.random.default_rng(2)
    N = 30_000
    x = np.linspace(0.0, 2.37 * 2 * math.pi, N) + 1e-3 * rng.standard_normal(N)
    true_h = (2, 11, 33)
    basis = FourierBasis(true_h)
    theta = rng.standard_normal((3, basis.size)) * 0.1
    d = FluxModel(basis, theta)(x) + 0.01 * rng.standard_normal((N, 3))
    K = np.arange(1, 41)
    hc = harmonic_content(x, d, harmonics=K)
    Phi = FourierBasis(tuple(int(h) for h in K)).evaluate(x)
    ref = np.linalg.lstsq(Phi, d, rcond=None)[0].T
    np.testing.assert_allclose(hc.coefficients, ref, atol=1e-9)
    assert tuple(int(h) for h in hc.harmonics[hc.significant]) == true_h
    for j, h in enumerate(true_h):
        s, c = theta[:, 1 + 2 * j], theta[:, 2 + 2 * j]
        expected = math.sqrt(np.mean(s**2 + c**2) / 2)
        assert abs(hc.amplitude_of(h) / expected - 1) < 0.02
    assert hc.status == "ok" and hc.revolutions > 2


def test_curve_projection_recovers_a_shift_along_the_curve():
    truth = BenchConfig(electrical_harmonics=TRAP, seed=7).truth()
    y0 = np.linspace(0.0, 2 * math.pi, 5000, endpoint=False)
    shift = 2e-3 * np.sin(5 * y0) + 1e-3
    delta, resid, speed2 = curve_projection(truth, y0, truth(y0 + shift))
    np.testing.assert_allclose(delta, shift, atol=1e-10)
    assert np.max(np.abs(resid)) < 1e-10
    np.testing.assert_allclose(speed2, np.sum(truth.derivative(y0 + shift) ** 2, axis=1))


# ------------------------------------------------------------------------------------------
# acceptance: verdicts on the virtual bench
# ------------------------------------------------------------------------------------------


def test_trapezoid_with_the_papers_harmonics_is_refused_naming_33_and_55():
    sem, rep, e_init, e_star = calibration("trapezoid", H11, 1.0)
    assert rep.verdict == "inadequate" and rep.refused
    assert {33, 55} <= set(rep.suggested_harmonics)
    assert "33" in rep.message and "55" in rep.message and "auto" in rep.message
    assert rep.ratio > 100 and rep.shape_ratio > 100
    assert rep.periodic_fraction > 0.9
    d = rep.to_dict()
    json.dumps(d)
    assert d["verdict"] == "inadequate" and 33 in d["suggested_harmonics"]
    assert e_star > 5 * BENCHES["trapezoid"].noise_floor  # the refusal is deserved


def test_paper_bench_with_its_harmonics_is_adequate_and_predicts_its_error():
    sem, rep, e_init, e_star = calibration("paper", H11, 1.0)
    cfg = BENCHES["paper"]
    assert rep.verdict == "adequate", rep.message
    assert abs(rep.ratio - 1) < 0.03 and abs(rep.shape_ratio - 1) < 0.03
    assert rep.ratio_std < 0.01
    assert rep.suggested_harmonics == () and rep.unexplained_harmonics == ()
    assert abs(rep.noise_floor / cfg.noise_floor - 1) < 0.03
    assert abs(rep.predicted_error / e_star - 1) < 0.05
    assert rep.bijective and rep.correction_rms > 10 * rep.noise_floor
    json.dumps(rep.to_dict())


@pytest.mark.parametrize("name", ["cogging 2e-2", "disturbance 2e-2"])
def test_unmodelled_motion_is_reported_as_such(name):
    """Cogging and load torque are not in the model: the cost rises, the flux shape still fits.

    Measured: cogging 2e-2 gives a ratio of 15.5 and disturbance 2e-2 a ratio of 34 (position
    mismatch 1.3 and 2 mrad RMS), while f_star stays at the noise floor: a warning that names the
    cause, not a refusal.
    """
    sem, rep, e_init, e_star = calibration(name, H11, 1.0)
    assert rep.verdict == "warning", rep.message
    assert rep.ratio > 5 and rep.shape_ratio < 1.1
    assert "motion" in rep.message and "mrad" in rep.message
    assert rep.position_mismatch_rms > 3 * rep.noise_floor
    assert rep.suggested_harmonics == ()
    assert e_star < 1.1 * BENCHES[name].noise_floor
    if name.startswith("cogging"):
        # cogging at 6 n_m = 66 periods shows as sidebands 55 and 77 of the pole-pair harmonic
        assert {55, 77} <= set(rep.dynamics_harmonics) and rep.periodic_fraction > 0.5
        assert "cogging" in rep.message


#: (bench, harmonics, plant gain, verdict). Adequate only where the model is right; a warning
#: where the flux fits but the motion does not (plant gain off, cogging, load torque): f_star is
#: still at the noise floor; refused where the flux model is wrong: f_star far from the floor.
NEVER_WORSE = [
    ("paper", H11, 1.0, "adequate"),
    ("paper", (11,), 1.0, "inadequate"),  # the table barely changes f_init: here slightly worse
    ("paper", H11, 0.7, "warning"),  # plant model gain 30 % off
    ("trapezoid", H11, 1.0, "inadequate"),
    ("cogging 2e-3", H11, 1.0, "warning"),
    ("cogging 2e-2", H11, 1.0, "warning"),
    ("disturbance 2e-3", H11, 1.0, "warning"),
    ("disturbance 2e-2", H11, 1.0, "warning"),
    ("pole modulation", H11, 1.0, "inadequate"),
]


@pytest.mark.parametrize(("name", "harmonics", "gain", "verdict"), NEVER_WORSE)
def test_never_worse_than_f_init_without_a_warning(name, harmonics, gain, verdict):
    """Every case has its verdict, and f_star agrees with it (measured against the true angle):
    at the noise floor and better than f_init unless refused, far from the floor when refused.

    Measured: f_star 1.00-1.01 x the floor for the adequate and warning cases (f_init 15 x),
    12-18 x for the refused ones (with 11 alone slightly worse than f_init).
    """
    sem, rep, e_init, e_star = calibration(name, harmonics, gain)
    floor = BENCHES[name].noise_floor
    assert rep.verdict == verdict, (name, e_init, e_star, rep.message)
    assert rep.bijective
    if verdict == "inadequate":
        assert e_star > 5 * floor, (e_star, floor)  # the refusal is warranted
    else:
        assert e_star < 1.1 * floor < e_init, (e_star, floor, e_init)
        assert e_star < 1.1 * rep.predicted_error


def test_a_non_bijective_table_is_refused():
    sem, _, _, _ = calibration("paper", H11, 1.0)
    run, _ = runs("paper")
    theta = np.array(sem.theta)
    js, jc = sem.flux.basis.index(10)
    theta[:, [js, jc]] *= 80  # harmonic 10 twice the fundamental: the table folds back
    bad = dataclasses.replace(sem, flux=FluxModel(sem.flux.basis, theta))
    rep = assess(bad, run.d, pole_pairs=11)
    assert not rep.bijective and rep.min_slope < 0
    assert rep.verdict == "inadequate" and "bijective" in rep.message


def test_a_failed_fit_is_refused():
    sem, _, _, _ = calibration("paper", H11, 1.0)
    run, _ = runs("paper")
    failed = dataclasses.replace(sem, cost_history=np.array([np.inf]), status="diverged")
    rep = assess(failed, run.d, pole_pairs=11)
    assert rep.verdict == "inadequate" and rep.status == "failed"
    json.dumps(rep.to_dict())


@pytest.mark.parametrize("df", [2, 4, 6, 8, 12, 40, 1352, 4000])
def test_chi2_quantile_matches_scipy_stats(df):
    """The few lines of Newton's method give scipy.stats.chi2.isf (the oracle) to rounding,
    also for the degrees of freedom of the band test (1352: the Poisson sum's terms would
    overflow a double without logarithms)."""
    import scipy.stats

    for q in np.logspace(-300, np.log10(0.9), 120):
        expected = scipy.stats.chi2.isf(q, df)
        # rounding of the k = df / 2 terms of the Poisson sum: about k eps relative in the sum
        assert chi2_isf_even(q, df) == pytest.approx(expected, rel=max(1e-14, df * 1e-16))
    with pytest.raises(ValueError, match="even"):
        chi2_isf_even(0.01, 3)
    with pytest.raises(ValueError, match="q must"):
        chi2_isf_even(1.0, 2)
