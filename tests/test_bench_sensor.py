"""The virtual bench's sensor imperfections (rails, quantization, drift, spikes): each knob does
what its docstring says, inside the loop, and the defaults change nothing."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hallcal.sensor.reconstruction import f_init
from hallcal.sim.bench import BenchConfig, ramp_run
from hallcal.sim.loop import SensorADC, simulate_loop

# A small, fast bench: 4 pole pairs, 1.5 s of ramp (6000 samples).
SMALL = BenchConfig(pole_pairs=4, seed=5)
RAMP = {"ramp_end": 2.0, "duration": 1.5}


def _quiet(**changes) -> BenchConfig:
    """The small bench without noise, so that each knob's effect is exact."""
    return replace(SMALL, noise_variance=0.0, **changes)


def test_defaults_change_nothing():
    """Explicit neutral knobs (gain 1, an ideal ADC) give bit-identical runs: the kernel's extra
    branches multiply by 1.0, add 0.0 and compare against infinite rails, all exact."""
    cfg = SMALL
    assert cfg.adc() is None
    assert not cfg.quantization_step.any()
    r = np.linspace(0.0, 2.0, 6000, endpoint=False)
    noise = 0.01 * np.random.default_rng(1).standard_normal((r.size, 3))
    plain = simulate_loop(cfg.loop(), cfg.truth(), r, noise=noise)
    neutral = simulate_loop(
        cfg.loop(), cfg.truth(), r, noise=noise, sensor_gain=np.ones((r.size, 3)), adc=SensorADC()
    )
    for a, b in ((plain.d, neutral.d), (plain.y, neutral.y), (plain.y0, neutral.y0)):
        np.testing.assert_array_equal(a, b)


def test_rails_clip_one_sensor_and_the_loop_sees_the_clipped_values():
    cfg = replace(SMALL, adc_high=(0.9, math.inf, math.inf), adc_low=(-math.inf, -0.95, -5.0))
    run = ramp_run(cfg, **RAMP)
    at_top = np.mean(run.d[:, 0] == 0.9)
    assert run.d[:, 0].max() == 0.9 and 0.05 < at_top < 0.3  # the peaks of a unit cosine
    assert run.d[:, 1].min() == -0.95 and run.d[:, 2].min() > -5.0
    # the loop's y is f_init of the recorded (clipped) d, to f_init's rounding (1e-13 rad)
    np.testing.assert_allclose(run.y, f_init(run.d, cfg.pole_pairs), atol=1e-12)
    # and differs from the unclipped run's (the clipping moved the motor)
    assert np.abs(run.y - ramp_run(SMALL, **RAMP).y).max() > 1e-4


def test_quantization_puts_every_sample_on_a_code():
    cfg = replace(SMALL, adc_low=(-1.2,) * 3, adc_high=(1.3,) * 3, adc_bits=10)
    step = 2.5 / 1023
    np.testing.assert_allclose(cfg.quantization_step, step, rtol=1e-15)
    run = ramp_run(cfg, **RAMP)
    codes = (run.d + 1.2) / step
    # codes are integers to the rounding of (d + 1.2) / step (a few ulp of 1023)
    np.testing.assert_allclose(codes, np.round(codes), atol=1e-9)
    np.testing.assert_allclose(run.y, f_init(run.d, cfg.pole_pairs), atol=1e-12)
    stepped = replace(SMALL, adc_step=0.01)
    d = ramp_run(stepped, **RAMP).d
    np.testing.assert_allclose(d / 0.01, np.round(d / 0.01), atol=1e-9)  # grid through 0


def test_gain_and_offset_drift_are_linear_in_time_around_the_reference_time():
    gd, od, tref = (0.02, -0.01, 0.0), (0.0, 0.003, -0.004), 0.75
    cfg = _quiet(gain_drift=gd, offset_drift=od, drift_reference_time=tref)
    run = ramp_run(cfg, **RAMP)
    g = cfg.truth()(run.y0)
    t = run.t - tref
    expected = g * (1.0 + np.outer(t, gd)) + np.outer(t, od)
    np.testing.assert_allclose(run.d, expected, rtol=0, atol=1e-12)  # float64 rounding
    # at the reference time the sensors are the static truth
    k = int(round(tref / cfg.sample_time))
    np.testing.assert_allclose(run.d[k], g[k], atol=1e-15)


def test_spikes_are_seeded_outliers_of_the_set_size_and_rate():
    cfg = _quiet(spike_rate=0.01, spike_size=0.4)
    run = ramp_run(cfg, **RAMP)
    dev = run.d - cfg.truth()(run.y0)
    hit = np.abs(dev) > 1e-9
    np.testing.assert_allclose(np.abs(dev[hit]), 0.4, atol=1e-12)
    # 18 000 draws at p = 0.01: 180 +- 13 (1 sigma); 5 sigma either way
    assert 115 < hit.sum() < 245
    assert 0.3 < np.mean(dev[hit] > 0) < 0.7
    again = ramp_run(cfg, **RAMP)
    np.testing.assert_array_equal(again.d, run.d)  # seeded
    other = ramp_run(cfg, **RAMP, seed=6)
    assert not np.array_equal(np.abs(other.d - cfg.truth()(other.y0)) > 1e-9, hit)


@pytest.mark.parametrize(
    "changes",
    [
        {"adc_low": (0.0, 0.0, 0.0), "adc_high": (0.0, 1.0, 1.0)},
        {"adc_step": -0.1},
        {"adc_bits": 12},  # infinite rails
        {"adc_bits": 12, "adc_low": (-1.0,) * 3, "adc_high": (1.0,) * 3, "adc_step": 0.1},
        {"spike_rate": 1.5},
        {"gain_drift": (0.0, math.nan, 0.0)},
    ],
)
def test_invalid_sensor_knobs_are_refused(changes):
    with pytest.raises(ValueError):
        replace(SMALL, **changes)
