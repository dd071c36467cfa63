"""Censored Hall samples (fit/censor.py): rails and quantization found from the data, the
E-step imputation, and a clipping motor calibrated to its floor from the rest of its samples."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hallcal import pipeline
from hallcal.fit.censor import (
    detect_censoring,
    impute,
    quantization_step,
)
from hallcal.io import Dataset, ModelSpec, Setup
from hallcal.messages import MessageCode
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run

INF = math.inf
# A small bench: 4 pole pairs, 2 revolutions in 6 s (24 000 samples).
SMALL = BenchConfig(pole_pairs=4, seed=7)
RAMP = {"ramp_end": 4 * math.pi, "duration": 6.0}


@pytest.fixture(scope="module")
def clipped():
    """Sensor 2 clipped at 0.97 (its peaks: a few % of its samples), sensor 3 at -0.98."""
    cfg = replace(SMALL, adc_high=(INF, 0.97, INF), adc_low=(-INF, -INF, -0.98))
    return cfg, ramp_run(cfg, **RAMP)


def test_rails_are_found_on_the_clipped_sensors_only(clipped):
    cfg, run = clipped
    c = detect_censoring(run.d)
    assert c.high.tolist() == [INF, 0.97, INF] and c.low.tolist() == [-INF, -INF, -0.98]
    np.testing.assert_array_equal(c.at_high[:, 1], run.d[:, 1] == 0.97)
    np.testing.assert_array_equal(c.at_low[:, 2], run.d[:, 2] == -0.98)
    assert c.counts[0] == 0 and c.counts[1] > 0.01 * run.n_samples and c.counts[2] > 0
    assert "sensor 2" in c.describe() and "sensor 1" not in c.describe()
    assert c.to_dict()["censored_samples"] == c.counts.tolist()
    np.testing.assert_array_equal(c.weights, (~c.mask).astype(float))


def test_no_rail_on_clean_or_finely_quantized_signals():
    """Continuous values never tie at their extremes; a quantized peak puts at most ~2.4x the
    next code's count on its top code (the arcsine law), below the factor 4 of a rail."""
    assert not detect_censoring(ramp_run(SMALL, **RAMP).d).any
    for bits, var in ((12, 1e-8), (10, 1e-6), (8, 1e-5)):
        cfg = replace(SMALL, noise_variance=var, adc_low=(-1.3,) * 3, adc_high=(1.3,) * 3,
                      adc_bits=bits)  # fmt: skip
        c = detect_censoring(ramp_run(cfg, **RAMP).d)
        assert not c.any, bits
        np.testing.assert_allclose(c.step, cfg.quantization_step, rtol=1e-9)
    # the same ADC with its rail inside the signal's range: found
    cfg = replace(SMALL, noise_variance=1e-8, adc_low=(-0.99,) * 3, adc_high=(0.99,) * 3,
                  adc_bits=12)  # fmt: skip
    c = detect_censoring(ramp_run(cfg, **RAMP).d)
    assert c.high.tolist() == [0.99] * 3 and c.low.tolist() == [-0.99] * 3


def test_quantization_step_and_its_variance():
    rng = np.random.default_rng(1)
    codes = rng.integers(-500, 500, 20_000)
    assert quantization_step(0.25 + codes * 0.001) == pytest.approx(0.001, rel=1e-9)
    # codes written with 6 decimals: still a grid (spacings whole multiples within 0.02 q)
    assert quantization_step(np.round(codes * (2.4 / 4095), 6)) == pytest.approx(
        2.4 / 4095, rel=2e-3
    )
    assert quantization_step(rng.standard_normal(20_000)) == 0.0


def test_imputation_is_unbiased_where_the_uncensored_samples_are_not():
    """Clip mu + v (v ~ N(0, sigma^2)) at c: the uncensored samples alone are biased low near
    c; with the censored ones replaced by E[mu + v | mu + v >= c] the mean is mu again.

    200 000 samples per level: the mean's standard error is sigma / 450; 0.01 sigma is 4.5 of
    them, while dropping the censored samples is off by 0.29-0.62 sigma at these levels."""
    sigma, c = 0.1, 1.0
    rng = np.random.default_rng(3)
    for mu in (0.9, 0.95, 0.97):  # at most half of the samples at the rail (else: a stuck sensor)
        x = mu + sigma * rng.standard_normal(200_000)
        d = np.column_stack([np.minimum(x, c), x, x])
        cen = detect_censoring(d)
        assert cen.counts.tolist() == [int(np.sum(x >= c)), 0, 0]
        out = impute(d, cen, np.full_like(d, mu), [sigma, 0.0, 0.0])
        assert abs(out[:, 0].mean() - mu) < 0.01 * sigma
        assert d[~cen.mask[:, 0], 0].mean() < mu - 0.2 * sigma
        np.testing.assert_array_equal(out[:, 1:], d[:, 1:])


def test_a_clipping_motor_reaches_its_floor_from_the_rest_of_its_samples(clipped):
    """Calibrated on the clipped run (given harmonics: the truth's 1..4), validated on a fresh
    run of the same motor without rails: within 1.15x the noise floor (the acceptance bar);
    the message names the sensors and counts."""
    cfg, run = clipped
    model = ModelSpec(harmonics=(1, 2, 3, 4), cogging="none")
    setup = Setup(pole_pairs=4, sample_time=cfg.sample_time, controller=cfg.controller,
                  plant=cfg.plant, model=model)  # fmt: skip
    cal = pipeline.calibrate(Dataset.from_columns(run.columns(with_encoder=False)), setup)
    note = next(m.text for m in cal.messages if m.code is MessageCode.CENSORED_SAMPLES)
    c = detect_censoring(run.d)
    assert f"sensor 2: {c.counts[1]} " in note and f"sensor 3: {c.counts[2]} " in note
    assert cal.to_artifact()["diagnostics"]["sensors"]["censoring"]["censored_samples"] == (
        c.counts.tolist()
    )
    val = ramp_run(SMALL, **RAMP, seed=99)
    ratio = angle_error(cal.lut.f_star(val.d), val.y0).rms / SMALL.noise_floor
    assert ratio < 1.15


def test_quantization_is_a_lower_bound_on_the_noise():
    """A slow, noise-free quantized signal: its differences see little of the rounding error
    (a slow sawtooth of the angle), so the floor's variance is raised to q^2 / 12; a signal
    crossing many codes per sample already shows it (left unchanged)."""
    from hallcal.fit.adequacy import estimate_noise_variance
    from hallcal.fit.censor import with_quantization

    q = 1e-3
    t = np.arange(50_000)
    slow = np.round(np.column_stack([np.cos(2e-4 * t + p) for p in (0, 2.1, 4.2)]) / q) * q
    est = estimate_noise_variance(slow)
    assert np.all(est.per_channel < 0.5 * q * q / 12)
    up = with_quantization(est, [q, q, q])
    np.testing.assert_allclose(up.per_channel, q * q / 12)
    assert up.variance == pytest.approx(q * q / 12)
    rng = np.random.default_rng(4)
    fast = np.round(rng.standard_normal((50_000, 3)) * 0.05 / q) * q
    est = estimate_noise_variance(fast)
    assert with_quantization(est, [q, q, q]) is est


def test_calibrate_command_names_the_censored_samples(clipped, tmp_path):
    """As a user runs it: a recording whose sensors 2 and 3 clip, ``hallcal calibrate`` exits 0
    and its output names the censored samples per sensor."""
    import subprocess
    import sys

    from hallcal.io.dataset import write_dataset

    cfg, run = clipped
    write_dataset(tmp_path / "cal.csv", run.columns(with_encoder=False))
    (tmp_path / "s.toml").write_text(
        "pole_pairs = 4\nsample_time = 2.5e-4\n"
        "[controller]\nnum = [2.94, -3.29, -2.10, 2.45]\nden = [1, -3.45, 4.52, -2.68, 0.61]\n"
        "[plant]\nnum = [1.663e5]\nden = [1, 632.6, 2702, 0]\ndelay = 1.2e-4\n"
        '[model]\nharmonics = [1, 2, 3, 4]\ncogging = "none"\n'
    )
    res = subprocess.run(
        [sys.executable, "-m", "hallcal.cli", "calibrate", "cal.csv", "--setup", "s.toml",
         "--out", "cal.json"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    out = res.stdout + res.stderr
    counts = detect_censoring(run.d).counts
    assert "censored samples (ADC rail)" in out
    assert f"sensor 2: {counts[1]} " in out and f"sensor 3: {counts[2]} " in out


@pytest.mark.parametrize(("shape", "bands"), [(0.0, 3), (0.03, 5)])
def test_the_imputing_band_follows_the_flux(shape, bands):
    """The flanks of the gaps choose the imputing model's band: 3 n_m for a flux within n_m,
    5 n_m when every magnet has its own shape up to the 6th electrical harmonic."""
    from hallcal.fit.censor import imputation_bands, noise_std

    cfg = replace(SMALL, shape_variation=shape, shape_harmonics=6, adc_high=(INF, 0.97, INF),
                  adc_low=(-INF, -INF, -0.98))  # fmt: skip
    run = ramp_run(cfg, **RAMP)
    c = detect_censoring(run.d)
    assert imputation_bands(run.d, run.y, c, noise_std(run.d, c), pole_pairs=4) == bands
