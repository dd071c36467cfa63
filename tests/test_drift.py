"""Sensors drifting during the run (fit/drift.py, solve_sem(fit_drift=True)): found, named,
identified, and the table the one of the run's middle."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hallcal import pipeline
from hallcal.fit.drift import detect_drift, undrifted
from hallcal.fit.sem import solve_sem
from hallcal.io import Dataset, ModelSpec, Setup
from hallcal.messages import MessageCode, Severity
from hallcal.pipeline import sensors
from hallcal.sensor.flux import FourierBasis
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run

# A small bench: 4 pole pairs, 2 revolutions in 6 s (24 000 samples); sensor 1's gain rises
# by 2 % over the run and sensor 3's offset by 0.01, both zero at the middle (3 s).
SMALL = BenchConfig(pole_pairs=4, seed=7)
RAMP = {"ramp_end": 4 * math.pi, "duration": 6.0}
DRIFTING = replace(SMALL, gain_drift=(0.02 / 6, 0.0, 0.0), offset_drift=(0.0, 0.0, 0.01 / 6),
                   drift_reference_time=3.0)  # fmt: skip
SIGMA = math.sqrt(SMALL.noise_variance)


@pytest.fixture(scope="module")
def drifting_run():
    return ramp_run(DRIFTING, **RAMP)


@pytest.fixture(scope="module")
def drifting_fit(drifting_run):
    """The joint fit of flux (harmonics 1..4) and drift on the drifting run."""
    run = drifting_run
    return solve_sem(SMALL.loop(), run.r, run.d, FourierBasis((1, 2, 3, 4)), y=run.y,
                     fit_drift=True)  # fmt: skip


def test_trend_of_the_residual_is_found_and_sized():
    """Synthetic residual: the estimates within 4 of their standard deviations (a 4-sigma
    band: 6e-5 per parameter), nothing named without a drift (5-sigma threshold)."""
    rng = np.random.default_rng(2)
    N = 50_000
    y0 = np.linspace(0, 4 * np.pi, N)
    d_sim = np.column_stack([np.cos(4 * y0 - 2 * np.pi * h / 3) for h in range(3)])
    tau = np.arange(N) / (N - 1) - 0.5
    noise = SIGMA * rng.standard_normal((N, 3))
    clean = detect_drift(d_sim + noise, d_sim, [SIGMA] * 3)
    assert not clean.any and clean.describe() == ""
    d = d_sim * (1 + np.outer(tau, [0.01, 0.0, 0.0])) + np.outer(tau, [0.0, -0.005, 0.0])
    rep = detect_drift(d + noise, d_sim, [SIGMA] * 3)
    assert rep.drifting.tolist() == [True, True, False]
    assert abs(rep.gain[0] - 0.01) < 4 * rep.gain_std[0]
    assert abs(rep.offset[1] + 0.005) < 4 * rep.offset_std[1]
    assert "sensor 1: gain +1 %" in rep.describe() and "sensor 3" not in rep.describe()
    np.testing.assert_allclose(undrifted(d, rep), d_sim, atol=1e-3)  # the estimates' error


def test_joint_drift_identifies_the_sensors_at_mid_run(drifting_run, drifting_fit):
    """With the drift in the SEM: gain and offset changes within 4 std of the truth, the cost
    at the noise level, and the table within 1.15x the floor on a fresh run of the sensors
    frozen at the middle; without it the static model misses by far more."""
    run, sem = drifting_run, drifting_fit
    basis = sem.flux.basis
    assert sem.drift is not None and sem.drift_std is not None
    truth = np.array([[0.02, 0.0], [0.0, 0.0], [0.0, 0.01]])
    assert np.all(np.abs(sem.drift - truth) < 4 * sem.drift_std)
    assert sem.cost / (3 * run.n_samples * SMALL.noise_variance) < 1.05  # chi2: 1 +- 0.005
    val = ramp_run(SMALL, **RAMP, seed=50)
    lut = build_lut(sem.flux, 4, points=4096)
    joint = angle_error(lut.f_star(val.d), val.y0).rms / SMALL.noise_floor
    assert joint < 1.15
    static = solve_sem(SMALL.loop(), run.r, run.d, basis, y=run.y)
    lut0 = build_lut(static.flux, 4, points=4096)
    # measured 1.13 against 1.00: the drift's share of the error, which the joint fit removes
    assert angle_error(lut0.f_star(val.d), val.y0).rms / SMALL.noise_floor > joint + 0.08


def test_calibrate_names_and_identifies_the_drift(drifting_run):
    run = drifting_run
    model = ModelSpec(harmonics=(1, 2, 3, 4), cogging="none")
    setup = Setup(pole_pairs=4, sample_time=SMALL.sample_time, controller=SMALL.controller,
                  plant=SMALL.plant, model=model)  # fmt: skip
    cal = pipeline.calibrate(Dataset.from_columns(run.columns(with_encoder=False)), setup)
    assert str(cal.status) == "warning"
    line = next(m.text for m in cal.messages if m.code is MessageCode.SENSOR_DRIFT)
    assert "sensor 1: gain +2" in line and "run's middle" in line
    info = cal.to_artifact()["diagnostics"]["sensors"]["drift"]
    assert info["identified"] and info["gain_change"][0] == pytest.approx(0.02, abs=5e-4)
    val = ramp_run(SMALL, **RAMP, seed=51)
    assert angle_error(cal.lut.f_star(val.d), val.y0).rms / SMALL.noise_floor < 1.15


@pytest.mark.parametrize("scale", [0.0, 0.5, 4.9, 5.1, 50.0])
def test_a_drift_the_final_fit_does_not_confirm_is_a_note_not_a_warning(
    drifting_run, drifting_fit, scale
):
    """The final fit's drift named (a warning, status ok -> warning) only when one of its six
    parameters reaches the detection's 5 standard deviations; below, a note that f_init's view
    saw a trend the fit does not confirm, the status unchanged (unseen zoo 211: adc12, no
    drift in its truth, largest 1.7 sigma, was told "the sensors drift")."""
    run, sem = drifting_run, drifting_fit
    assert sem.drift_std is not None
    sign = np.where(np.arange(6).reshape(3, 2) % 2 == 0, 1.0, -1.0)
    drift = scale * sem.drift_std * sign  # the largest |z| is exactly `scale`
    assert sensors.confirmed_drift(drift, sem.drift_std) == pytest.approx(scale)
    small = replace(sem, drift=drift)
    found = sensors.examine(run.d, run.y, pole_pairs=4, basis="fourier")
    (status, _, msgs), out = sensors.verdict(run.d, small, found, ("ok", None, ()), ok="ok",
                                             warning="warning")  # fmt: skip
    drift_msgs = [m for m in msgs if m.code is MessageCode.SENSOR_DRIFT]
    assert len(drift_msgs) == 1 and out["drift"]["identified"]
    if scale > 5.0:
        assert status == "warning" and drift_msgs[0].severity is Severity.WARNING
        assert "the sensors drift during the run" in drift_msgs[0].text
    else:
        assert status == "ok" and drift_msgs[0].severity is Severity.NOTE
        assert "not confirmed by the final fit" in drift_msgs[0].text
    nan_std = np.full((3, 2), np.nan)  # no standard deviations: named, as before the test
    assert not sensors.confirmed_drift(drift, nan_std) <= 5.0
