"""Regressions from the motor zoo (``benchmarks/bench_zoo.py``): motors unlike the paper's bench.

Zoo motor 1: 11 pole pairs at 16 kHz, a per-magnet shape variation of 1.1 % that puts flux
content on every mechanical harmonic up to 77 (weak above 61), cogging at 66 and 132. On its
fast ramp (2.8 revolutions in 25 000 samples) ``harmonics = "auto"`` used to stop at the band
1..61: the warp absorbed the weak top harmonics, the table carried a wrong warp (f_star 21x the
noise floor, f_init 9x) that the covariance did not show (predicted 3.4x), and the missing flux
harmonic 63 was then fitted as a cogging torque of 0.2 (50 times the true one, which is at 66).
Measured now (deterministic seeds): band widened 61 -> 66 -> 77, f_star 4.0x, predicted 5.3x,
no cogging found (at this speed the torque at 66 moves the rotor by less than the noise).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from hallcal.fit.adequacy import assess, estimate_noise_variance
from hallcal.fit.cogging_search import plausible_orders, select_cogging, shift_spectrum
from hallcal.fit.order import restrict_theta, select_harmonics
from hallcal.fit.sem import solve_sem
from hallcal.fit.warp import band_edge
from hallcal.sensor.flux import FourierBasis
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run, simulate_run
from hallcal.sim.lti import ContinuousTF, DiscreteTF

# zoo motor 1 (benchmarks/bench_zoo.py, draw_motor(1)), ramp 8 times faster than the zoo's
MOTOR1 = BenchConfig(
    pole_pairs=11,
    sample_time=6.25e-05,
    plant=ContinuousTF(
        (850145.9041536325,), (1.0, 1750.5394566909263, 5259.644979884063, 0.0),
        7.372131966181021e-06,
    ),
    controller=DiscreteTF(
        (1440.121162601371, -2860.308669449665, 1420.2423119948962),
        (1.0, -1.9129789710669276, 0.9129789710669277),
    ),
    noise_variance=3.155135519430876e-05,
    magnet_variation=0.0433780537372177,
    misalignment_deg=(-1.3837372888687183, 0.7244248230730941, 2.0550823921711947),
    gain_mismatch=(-0.030398637125465068, -0.010891892145286332, 0.011971406918856717),
    offset=(0.012563001915099653, -0.012092443099856687, 0.026798868729080716),
    electrical_harmonics=((3, 0.07061867701105928), (5, 0.023244600469549535)),
    cogging_terms=((66, 0.0042500994578301655, 3.501302046796968),
                   (132, 0.0015409754531674465, 239.5987396072446)),
    shape_variation=0.011411342859213889,
    shape_harmonics=7,
    seed=1,
)  # fmt: skip
END = 17.87771701858863  # rad, 2.85 revolutions


@functools.cache
def motor1_runs():
    """Calibration run (25 000 samples) and a fresh validation run (20 000 samples)."""
    cal = simulate_run(MOTOR1, END * np.arange(25_000) / 25_000, seed=1)
    val = simulate_run(MOTOR1, 0.8 * END * np.arange(20_000) / 20_000, seed=10_001)
    return cal, val


def star_over_floor(flux) -> float:
    _, val = motor1_runs()
    lut = build_lut(flux, 11, projection=MOTOR1.loop().projection, offset=MOTOR1.loop().offset)
    assert lut.bijective
    return angle_error(lut.f_star(val.d), val.y0).rms / MOTOR1.noise_floor


@functools.cache
def motor1_selection():
    run, _ = motor1_runs()
    return select_harmonics(MOTOR1.loop(), run.r, run.d, y=run.y, pole_pairs=11)


def test_a_band_that_leaves_the_shape_off_the_data_is_widened():
    sel = motor1_selection()
    _, val = motor1_runs()
    e_init = angle_error(val.y, val.y0).rms / MOTOR1.noise_floor
    assert e_init > 8.0  # measured 9.07
    # the static band test passes 1..61 (the warp absorbs the weak top harmonics) ...
    assert sel.edge.edge < 66
    # ... the fit then leaves the shape off the data and the band is widened to the truth's
    assert max(sel.harmonics) == 77
    assert any(c.stage == "widened" and c.accepted for c in sel.candidates)
    # bounded work: at most max_fits SEM solves
    assert sum(c.stage != "static" for c in sel.candidates) <= 5
    assert sel.sem.status.success
    # measured 4.03 (21.6 with the band 1..61); the bound leaves room for BLAS rounding across
    # machines, not for the failure, which is 5 times larger
    e_star = star_over_floor(sel.sem.flux)
    assert e_star < 0.6 * e_init, (e_star, e_init)
    # the predicted error is honest (measured 5.34 against 4.03): within a factor 2
    pred = sel.report.predicted_error / MOTOR1.noise_floor
    assert 0.5 * e_star < pred < 2.0 * e_star, (pred, e_star)


def test_a_missing_flux_harmonic_is_not_fitted_as_cogging():
    """The old failure: with the band 1..61 the missing flux harmonic 63 leaves a line in the
    shift spectrum; it is not a plausible cogging order (not a multiple of 2 n_m = 22)."""
    run, _ = motor1_runs()
    noise = estimate_noise_variance(run.d)
    edge = band_edge(run.y, run.d, pole_pairs=11, noise_variance=noise.variance)
    basis = FourierBasis(tuple(range(1, 62)))
    sem61 = solve_sem(MOTOR1.loop(), run.r, run.d, basis, theta0=restrict_theta(edge.flux, basis))
    spec = shift_spectrum(sem61, run.d, max_order=264)
    assert spec.ratio[62] > spec.threshold  # the line at 63 is there (measured 31 vs 26)
    assert 63 not in shift_spectrum(sem61, run.d, max_order=264,
                                    tested=plausible_orders(11, 264)).candidates  # fmt: skip
    sel = select_cogging(MOTOR1.loop(), run.r, run.d, sem61)
    assert all(k % 22 == 0 for k in sel.orders)
    if sel.cogging is not None:  # nothing near the 0.2 of the old failure
        assert max(sel.cogging.amplitude) < 0.02


def test_plausible_orders_are_the_multiples_of_the_pole_count():
    assert plausible_orders(11) == tuple(range(22, 265, 22))
    assert plausible_orders(4, 40) == (8, 16, 24, 32, 40)


def test_a_table_no_better_than_its_uncertainty_is_not_silently_ok():
    """When cov(theta) predicts a table error comparable to the correction the table applies,
    the verdict says that f_star may not beat f_init (warning, never "adequate"; the status
    policy then refuses the worse case, :func:`hallcal.pipeline.verdict.decide`)."""
    cfg = BenchConfig()
    run = ramp_run(cfg, ramp_end=7.0, duration=14.0)
    sem = solve_sem(cfg.loop(), run.r, run.d, FourierBasis(tuple(range(1, 12))), y=run.y)
    ok = assess(sem, run.d, pole_pairs=11)
    assert ok.verdict == "adequate", ok.message
    # the same fit with a covariance 1e4 times larger: the table's own predicted error (about
    # 1.9 mrad, from the larger of the white and the batch-means covariance, the variance of
    # the table's offset included) is more than half the correction (f_init's error about zero,
    # about 3.1 mrad) but less than all of it ...
    poor = assess(inflated(sem, 1e4), run.d, pole_pairs=11)
    assert poor.verdict == "warning"
    assert poor.message.startswith("warning: the improvement over f_init is uncertain")
    # ... 1e8 times larger (about 190 mrad): more than the correction itself
    worse = assess(inflated(sem, 1e8), run.d, pole_pairs=11)
    assert worse.verdict == "warning"
    assert worse.message.startswith("warning: f_star may be worse than f_init"), worse.message
    assert math.isfinite(worse.predicted_error) and worse.predicted_error > worse.correction_rms


def inflated(sem, factor: float):
    """The fit with every covariance it carries multiplied by factor."""
    return dataclasses.replace(
        sem, covariance=sem.covariance * factor,
        parameter_covariance=sem.parameter_covariance * factor,
        batch_covariance=None if sem.batch_covariance is None else sem.batch_covariance * factor,
    )  # fmt: skip


# zoo motor 41 (benchmarks/bench_zoo.py, draw_motor(41)): 5 pole pairs, every magnet's shape its
# own (content at every harmonic up to 35), 25 000 samples at 2 kHz
MOTOR41 = BenchConfig(
    seed=41, noise_variance=2.6080589765401552e-05, magnet_variation=0.04095247475056174,
    shape_variation=0.021427228094975857, shape_harmonics=7,
    misalignment_deg=(0.31101141014181977, -2.649241242527417, -0.5005919185634475),
    gain_mismatch=(-0.04352421441772997, -0.027405545601017968, -0.036642955943215406),
    offset=(0.016997259643282386, 0.012440634153672823, 0.013258551598196056),
    electrical_harmonics=((3, 0.06274863228831382), (5, 0.004964874565500304)),
    pole_pairs=5, sample_time=0.0005,
    plant=ContinuousTF((11928691.235248985,), (1.0, 2501.8921634983053, 137929.21924667733, 0.0),
                       0.0004884972180476677),
    controller=DiscreteTF((1.2329047347348308, -2.4568382400441444, 1.2239464629706616),
                          (1.0, -1.9533799157228677, 0.9533799157228678)),
)  # fmt: skip


def test_no_hole_in_a_shape_motors_band():
    """The evidence within the band kept 1..35 without 16 and 20 on zoo motor 41 (a dense band:
    every magnet's shape puts flux at every harmonic); the SEM then bent the angle to make up
    for them, f_star 3.98x the floor with 1.13x predicted. The short gaps of a dense band are
    filled (:func:`hallcal.fit.order.fill_gaps`): 1..35, measured 1.00x."""
    end, n = 16.664294743791437, 25000
    run = simulate_run(MOTOR41, end * np.arange(n) / n, seed=41)
    val = simulate_run(MOTOR41, 0.8 * end * np.arange(20000) / 20000, seed=10041)
    sel = select_harmonics(MOTOR41.loop(), run.r, run.d, y=run.y, pole_pairs=5)
    assert sel.harmonics == tuple(range(1, 36))
    lut = build_lut(sel.sem.flux, 5, projection=MOTOR41.loop().projection,
                    offset=MOTOR41.loop().offset)  # fmt: skip
    # 1.15x: the "ok" bound of the floor (measured 1.00x; with the holes 3.98x)
    assert angle_error(lut.f_star(val.d), val.y0).rms < 1.15 * MOTOR41.noise_floor
