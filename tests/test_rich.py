"""Every magnet different: automatic model choice and the kernel model reach the noise floor.

The rich-shape bench (benchmarks/bench_rich.py), smaller for a test: 5 pole pairs (truth on
mechanical harmonics 1..25, every sideband 5k +- j), trapezoidal flux (electrical harmonics
3 and 5 at 10 % and 4 %),
2 degrees misalignment, per-magnet shape variation 0.075, 40 000 samples (0 -> 13 rad in 10 s,
two revolutions); validation on a fresh run of the same motor. The full-size benchmark
(11 pole pairs, 160 000 samples, 5 seeds at two strengths) is ``benchmarks/bench_rich.py``.

Measured here (seeds 1, 2): f_init 25-28x the noise floor; ``harmonics = "auto"`` 1.027 and
1.063x, the kernel 1.030 and 1.063x; a Fourier model one harmonic wider than the flux (1..26)
lets a slow warp of the angle float (1.108x against 1.027x with 1..25).
"""

from __future__ import annotations

import functools

import pytest

from hallcal.fit.kernel import solve_kernel_sem
from hallcal.fit.order import select_harmonics
from hallcal.fit.sem import solve_sem
from hallcal.sensor.flux import FourierBasis
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run

N_M = 5


def config(seed: int) -> BenchConfig:
    return BenchConfig(
        pole_pairs=N_M,
        electrical_harmonics=((3, 0.10), (5, 0.04)),
        magnet_variation=0.0,
        misalignment_deg=(0.0, 2.0, 0.0),
        shape_variation=0.075,
        seed=seed,
    )


@functools.cache
def runs(seed: int):
    cfg = config(seed)
    return (
        ramp_run(cfg, ramp_end=13.0, duration=10.0, seed=seed),
        ramp_run(cfg, ramp_end=12.0, duration=10.0, seed=seed + 100),
    )


def ratio(flux, seed: int) -> float:
    """f_star's RMS error on the validation run over the noise floor."""
    _, val = runs(seed)
    lut = build_lut(flux, N_M)
    assert lut.bijective
    return angle_error(lut.f_star(val.d), val.y0).rms / config(seed).noise_floor


@pytest.mark.parametrize("seed", [1, 2])
def test_auto_and_kernel_reach_the_noise_floor(seed):
    cfg = config(seed)
    run, val = runs(seed)
    e_init = angle_error(val.y, val.y0).rms / cfg.noise_floor
    assert e_init > 20
    sel = select_harmonics(cfg.loop(), run.r, run.d, y=run.y)
    assert sel.edge.edge == 5 * N_M and sel.edge.status.success  # the truth's band, 1..25
    assert sel.report.verdict == "adequate", sel.report.message
    assert ratio(sel.sem.flux, seed) < 1.10  # the acceptance target
    ker = solve_kernel_sem(cfg.loop(), run.r, run.d, y=run.y, points=128)
    assert ker.harmonics == 5 * N_M and ker.status == "converged"
    assert ratio(ker.flux, seed) < 1.10
    # the predicted error (covariance of theta, adequacy report) is honest within 10 %
    assert sel.report.predicted_error / cfg.noise_floor == pytest.approx(
        ratio(sel.sem.flux, seed), rel=0.1
    )


def test_one_harmonic_too_many_lets_the_warp_float():
    """The mechanism behind the band: with harmonic 26 in the model, a once-per-revolution warp
    of the angle moves content 25 -> 26 freely, and the loop barely sees it."""
    seed = 1
    cfg = config(seed)
    run, _ = runs(seed)
    wide = solve_sem(cfg.loop(), run.r, run.d, FourierBasis(tuple(range(1, 27))), y=run.y)
    band = solve_sem(cfg.loop(), run.r, run.d, FourierBasis(tuple(range(1, 26))), y=run.y)
    # measured 1.027 (band) against 1.108 (one harmonic more): deterministic seeds; on the
    # 11-pole-pair bench of the benchmark the difference is 1.03 against 3.7
    assert ratio(band.flux, seed) < 1.05
    assert ratio(wide.flux, seed) > 1.05 * ratio(band.flux, seed)
