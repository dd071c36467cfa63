"""The status policy and the predicted error.

- A constant load torque is a cogging torque of order 0: found when significant, carried in the
  SEM, and the table's constant offset is then right and predicted.
- The oracle noise floor (:mod:`hallcal.sim.oracle`) is the scale of the zoo.
- One status policy (:func:`hallcal.pipeline.verdict.decide`): "ok" only within 1.15x the floor;
  a table predicted worse than f_init is refused, exit status 3 from the CLI with one line.
"""

from __future__ import annotations

import functools
import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hallcal import pipeline
from hallcal.io import Dataset, ModelSpec, Setup, write_dataset
from hallcal.messages import MessageCode
from hallcal.pipeline.calibration import CalibrationStatus
from hallcal.pipeline.verdict import OK_RATIO, WORSE_FRACTION, decide
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run
from hallcal.sim.oracle import oracle_floor

LOAD = 0.003  # plant input units: shifts the paper's loop by about 0.8x the noise floor


@functools.cache
def load_bench():
    """The paper's bench with a constant load torque: calibration and validation runs."""
    cfg = BenchConfig(cogging_terms=((0, LOAD, 0.0),))
    run = ramp_run(cfg, ramp_end=7.0, duration=14.0, seed=1)
    val = ramp_run(cfg, ramp_end=4.0, duration=8.0, seed=2)
    return cfg, run, val


def _setup(cfg: BenchConfig, **model) -> Setup:
    return Setup(
        pole_pairs=cfg.pole_pairs, sample_time=cfg.sample_time, controller=cfg.controller,
        plant=cfg.plant, model=ModelSpec(harmonics=tuple(range(1, 12)), **model),
    )  # fmt: skip


def test_oracle_floor_is_the_gaussian_floor_and_includes_quantization():
    cfg, _, val = load_bench()
    # DESIGN.md: within 3 % of sigma sqrt(2/3) / n_m for Gaussian noise
    assert oracle_floor(val) == pytest.approx(cfg.noise_floor, rel=0.03)
    # a 12-bit ADC over +-1.5 (one code 7.3e-4) with analog noise of a fifth of a code: the
    # floor is the quantization's, code / sqrt(12) per channel, far above the analog noise's
    code = 3.0 / 4095
    adc = BenchConfig(adc_low=(-1.5,) * 3, adc_high=(1.5,) * 3, adc_bits=12,
                      noise_variance=(0.2 * code) ** 2)  # fmt: skip
    run = ramp_run(adc, ramp_end=4.0, duration=8.0, seed=2)
    gaussian = adc.noise_floor
    quantized = math.sqrt(2 / 3) * math.hypot(0.2 * code, code / math.sqrt(12)) / 11
    assert oracle_floor(run) > 1.5 * gaussian  # measured 1.75x
    # measured within 1.5 %; the quantization error is not exactly uniform and white on a
    # slow ramp, hence 10 %
    assert oracle_floor(run) == pytest.approx(quantized, rel=0.1)


def test_a_constant_load_torque_is_found_as_order_0_and_its_offset_carried():
    cfg, run, val = load_bench()
    floor = oracle_floor(val)
    none = pipeline.calibrate(Dataset.from_columns(run.columns()), _setup(cfg, cogging="none"))
    auto = pipeline.calibrate(Dataset.from_columns(run.columns()), _setup(cfg))
    assert auto.cogging is not None and auto.cogging.orders == (0,)
    # the load found within 1 % (measured 0.0030006 +- 1.2e-5 on a longer run)
    assert auto.cogging.a[0] == pytest.approx(LOAD, rel=0.01)
    assert any("constant load" in m.text for m in auto.messages)
    e_none = angle_error(none.lut.f_star(val.d), val.y0)
    e_auto = angle_error(auto.lut.f_star(val.d), val.y0)
    # without the load in the model the table carries an offset of the order of the floor
    # (measured 0.79x on the longer run); with it, a fraction of that
    assert abs(e_none.mean) > 0.5 * floor
    assert abs(e_auto.mean) < 0.5 * abs(e_none.mean)
    assert e_auto.rms_raw < 1.05 * floor < e_none.rms_raw
    # the prediction speaks of the RMS about zero and is calibrated: within [0.67, 1.5]
    assert 0.67 <= e_auto.rms_raw / auto.predicted_error <= 1.5
    assert auto.status is CalibrationStatus.OK


def test_the_predicted_error_includes_the_variance_of_the_offset():
    from hallcal.fit.sem import predicted_angle_error

    cfg, run, _ = load_bench()
    cal = pipeline.calibrate(Dataset.from_columns(run.columns()), _setup(cfg))
    kw = dict(projection=cal.lut.projection, offset=cal.lut.offset)
    cov = cal.sem.covariance
    about_zero = predicted_angle_error(cal.flux, cov, 11, **kw)
    about_mean = predicted_angle_error(cal.flux, cov, 11, about_mean=True, **kw)
    # var about zero = var about the mean + var of the offset (the cross term averages out)
    assert np.mean(about_zero**2) > np.mean(about_mean**2)
    floor = cal.noise_floor
    assert cal.predicted_error**2 >= floor**2 + 0.999 * np.mean(about_zero**2)


@given(
    predicted=st.floats(1e-6, 1.0),
    floor=st.floats(1e-6, 1.0),
    correction=st.floats(0.0, 1.0),
    adequacy=st.sampled_from(["adequate", "warning", "inadequate"]),
    bijective=st.booleans(),
    checks=st.booleans(),
)
def test_ok_only_within_1_15x_the_floor_and_never_predicted_worse_than_f_init(
    predicted, floor, correction, adequacy, bijective, checks
):
    v = decide(bijective=bijective, predicted=predicted, floor=floor,
               correction_rms=correction, adequacy=adequacy,
               adequacy_message="inadequate: x", checks_passed=checks)  # fmt: skip
    f_init = math.hypot(floor, correction)
    if v.status is CalibrationStatus.OK:
        assert predicted <= OK_RATIO * floor
        assert bijective and checks and adequacy == "adequate"
    if v.status.success:  # a table is written with exit 0 only when predicted better than f_init
        assert predicted < f_init
    else:
        assert v.refusal
    own = math.sqrt(max(predicted**2 - floor**2, 0.0))
    if (
        bijective
        and adequacy != "inadequate"
        and (predicted >= f_init or (own >= WORSE_FRACTION * correction and own > 0.5 * floor))
    ):
        assert v.status is CalibrationStatus.INADEQUATE
        assert "worse than f_init" in v.refusal


def test_no_predicted_error_is_not_ok():
    v = decide(bijective=True, predicted=math.nan, floor=1e-4, correction_rms=1e-3)
    assert v.status is CalibrationStatus.WARNING
    assert v.leading[0].code is MessageCode.NO_PREDICTION and v.leading[0].is_warning
    assert v.leading[0].line().startswith("warning: no predicted error")


@functools.cache
def perfect_sensor_run():
    """Ideal sensors (no magnet variation): f_init is at the floor, and a table with 40
    harmonics from a short ramp is predicted worse than f_init (seeded: measured at this seed)."""
    cfg = BenchConfig(magnet_variation=0.0, seed=3)
    return cfg, ramp_run(cfg, ramp_end=7.0, duration=7.0, seed=3)


def test_a_table_predicted_worse_than_f_init_is_refused_exit_3(tmp_path):
    cfg, run = perfect_sensor_run()
    data = tmp_path / "cal.csv"
    write_dataset(data, run.columns(with_encoder=False))
    (tmp_path / "setup.toml").write_text(
        "pole_pairs = 11\nsample_time = 2.5e-4\n"
        "[controller]\nnum = [2.94, -3.29, -2.10, 2.45]\nden = [1, -3.45, 4.52, -2.68, 0.61]\n"
        "[plant]\nnum = [1.663e5]\nden = [1, 632.6, 2702, 0]\ndelay = 1.2e-4\n"
        "[model]\nharmonics = [" + ", ".join(str(h) for h in range(1, 41)) + ']\ncogging = "none"\n'
    )
    out = tmp_path / "cal.json"
    proc = subprocess.run(
        [sys.executable, "-m", "hallcal.cli", "calibrate", str(data), "--setup",
         str(tmp_path / "setup.toml"), "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 3, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("hallcal:")]  # no progress
    assert len(lines) == 1 and lines[0].startswith("hallcal: refused:")
    assert "worse than f_init" in lines[0]
    assert not out.exists()


def test_the_anticogging_table_carries_a_constant_load():
    """The C feed-forward's table of T_c(y0): order 0 is the constant a_0 (the DC bin of the
    inverse FFT holds n a_0, not n a_0 / 2)."""
    from hallcal.output.firmware import _uniform, cogging_map

    k, a, b = np.array([0, 3]), np.array([0.5, 0.1]), np.array([0.0, 0.2])
    y0 = 2 * np.pi * np.arange(64) / 64
    np.testing.assert_allclose(_uniform(k, a, b, 64), cogging_map(k, a, b, y0), atol=1e-12)
