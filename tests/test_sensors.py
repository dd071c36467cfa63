"""The sensor steps of the closed-loop calibration (pipeline/sensors.py): skewed sensors are
named and the model choice looks through their spacing; healthy sensors change nothing."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hallcal import pipeline
from hallcal.io import Dataset, ModelSpec, Setup
from hallcal.messages import MessageCode
from hallcal.pipeline import sensors
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run

# A small bench: 4 pole pairs, 2 revolutions in 6 s (24 000 samples).
SMALL = BenchConfig(pole_pairs=4, seed=7)
RAMP = {"ramp_end": 4 * math.pi, "duration": 6.0}


@pytest.mark.parametrize("misalignment", [(0.0, 0.0, 0.0), (0.0, -20.0, -10.0)])
def test_skewed_sensors_are_named_and_calibrated(misalignment):
    """Sensors at 0/100/230 electrical degrees: one line names them, and the automatic choice
    reaches 1.15x the floor (the truth's 4 harmonics); nominal sensors get no such line."""
    cfg = replace(SMALL, misalignment_deg=misalignment)
    run = ramp_run(cfg, **RAMP)
    setup = Setup(pole_pairs=4, sample_time=cfg.sample_time, controller=cfg.controller,
                  plant=cfg.plant, model=ModelSpec(harmonics="auto", cogging="none"))  # fmt: skip
    cal = pipeline.calibrate(Dataset.from_columns(run.columns(with_encoder=False)), setup)
    skew = [m.text for m in cal.messages if m.code is MessageCode.SKEWED_SENSORS]
    assert len(skew) == (1 if any(misalignment) else 0)
    if skew:
        assert "0/100/230 electrical degrees" in skew[0]
    assert cal.model_info["harmonics"] == [1, 2, 3, 4]
    val = ramp_run(cfg, **RAMP, seed=99)
    assert angle_error(cal.lut.f_star(val.d), val.y0).rms / cfg.noise_floor < 1.15


def test_healthy_sensors_leave_the_data_alone():
    """No rail, no drift, no skew: the loop, the signals and the choice's view are the inputs."""
    run = ramp_run(SMALL, **RAMP)
    found = sensors.examine(run.d, run.y, pole_pairs=4, basis="fourier")
    assert not found.censoring.any and not found.drifting and found.geometry is None
    assert found.notes == () and found.weights is None
    loop, d, y, dc, yc = sensors.for_choice(SMALL.loop(), run.r, run.d, run.y, found,
                                            pole_pairs=4)  # fmt: skip
    assert not np.isfinite(loop.rails).any()  # no rail
    for a, b in ((d, run.d), (y, run.y), (dc, run.d), (yc, run.y)):
        np.testing.assert_array_equal(a, b)
