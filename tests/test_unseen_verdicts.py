"""The misfit check and the power-up lock on conditions found by the audit of unseen inputs
(benchmarks/bench_observer_unseen.py): a transient at the start of a recording must not make
plain ``reconstruct`` refuse a recording that fits (sensor/misfit.py: the restarted test), and a
lock that the rest of the recording refutes must not be accepted (pipeline/powerup.py:
identification_check).

Bench: the paper's 11 pole pairs (magnet set seed 6), its true flux as the model (exact table,
the bench's sigma), open-loop signals truth(y0) + white noise. Seeds fixed: every count is
deterministic.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hallcal._constants import TWO_PI
from hallcal.io import Dataset
from hallcal.pipeline.powerup import SignalStatus, identification_check
from hallcal.sensor import absolute as ab
from hallcal.sensor.lut import build_lut
from hallcal.sensor.misfit import MisfitStatus, model_misfit
from hallcal.sim.bench import BenchConfig

TS = 2.5e-4


@pytest.fixture(scope="module")
def bench():
    cfg = BenchConfig(seed=6)
    truth = cfg.truth()
    loop = cfg.loop()
    lut = build_lut(truth, 11, projection=loop.projection, offset=loop.offset)
    dec = ab.build_decoder(truth, lut, noise_std=math.sqrt(cfg.noise_variance))
    return cfg, truth, lut, dec


def signals(cfg, truth, y0, seed):
    rng = np.random.default_rng(seed)
    return truth(y0) + math.sqrt(cfg.noise_variance) * rng.standard_normal((y0.size, 3))


def rail(truth, d, samples, channel=1):
    """``samples`` readings of one channel at 1.5x its peak (a rail) from the first."""
    out = d.copy()
    g = truth(np.linspace(0.0, TWO_PI, 512, endpoint=False))[:, channel]
    out[:samples, channel] = g.mean() + 1.5 * (g.max() - g.mean())
    return out


@pytest.mark.parametrize("speed", [0.0, 2.0])
def test_a_transient_at_the_start_does_not_condemn_a_recording(bench, speed):
    cfg, truth, _, dec = bench
    y0 = 1.0 + speed * TS * np.arange(4000)
    d = signals(cfg, truth, y0, 11)
    assert model_misfit(dec, d).status is MisfitStatus.FITS
    # 20 samples at the rail / 30 at 10x the noise crossed the plain test's bound (measured:
    # mismatch at sample 10 and 12); the restarted test accepts the 3970 samples after them
    burst = np.where(np.arange(4000)[:, None] < 30, 9.0, 0.0) * math.sqrt(cfg.noise_variance)
    burst = burst * np.random.default_rng(12).standard_normal(d.shape)
    for bad in (rail(truth, d, 20), d + burst):
        res = model_misfit(dec, bad)
        assert res.status is MisfitStatus.FITS
        assert res.transients >= 1
        assert res.to_dict()["transients"] == res.transients


def test_a_persistent_misfit_stays_a_mismatch_at_its_first_crossing(bench):
    cfg, truth, _, dec = bench
    y0 = 1.0 + 2.0 * TS * np.arange(4000)
    d = signals(cfg, truth, y0, 13)
    for changed in (d[:, [1, 0, 2]], d * [1.0, 1.0, 1.05]):
        res = model_misfit(dec, changed)
        assert res.status is MisfitStatus.MISMATCH
        assert res.sample is not None and res.sample < 40  # crosses within ~11 samples
        assert res.transients == 0


def test_without_a_crossing_the_verdict_is_the_plain_tests(bench):
    cfg, truth, _, dec = bench
    d = signals(cfg, truth, 0.3 + 2.0 * TS * np.arange(3000), 14)
    res = model_misfit(dec, d)
    lam = np.cumsum(dec.sample_costs(d), axis=0)
    k = np.cumsum(dec.features(d)["valid"])
    D = dec.misfit.statistic(lam.min(axis=1), k)
    assert res.statistic == D[-1] and res.samples == k[-1] and res.transients == 0
    assert "transients" not in res.to_dict()  # outputs of healthy recordings unchanged


def _columns(d):
    return Dataset.from_columns({f"d{h + 1}": d[:, h] for h in range(3)})


def test_a_lock_refuted_by_the_rest_of_the_recording_is_refused(bench):
    cfg, truth, lut, dec = bench
    rng = np.random.default_rng(900)
    refused = locked = 0
    for i in range(60):
        y0 = rng.uniform(0, TWO_PI) + 2.0 * TS * np.arange(400)
        d = signals(cfg, truth, y0, 900_000 + i)[:, [1, 0, 2]]  # d1 and d2 swapped
        angles = ab.absolute_reconstruction(dec, lut, d)
        if angles.identification.status is ab.PowerUpStatus.IDENTIFIED:
            locked += 1
            check = identification_check(dec, _columns(d), angles)
            refused += check.status in (SignalStatus.MISMATCH, SignalStatus.WIRING)
    # measured: 10 of 60 power-ups locked on the swapped signals within ~10 samples (the lock
    # alone claimed an error below 1e-7); the 390 samples of motion after it refute them all
    assert locked >= 1
    assert refused == locked


def test_a_healthy_lock_keeps_its_verdict_and_message(bench):
    cfg, truth, lut, dec = bench
    d = signals(cfg, truth, 2.0 + 2.0 * TS * np.arange(400), 15)
    angles = ab.absolute_reconstruction(dec, lut, d)
    ident = angles.identification
    assert ident.status is ab.PowerUpStatus.IDENTIFIED
    check = identification_check(dec, _columns(d), angles)
    assert check.status is SignalStatus.FITS
    assert check.message == (
        f"signals fit the calibration's model (misfit {ident.cost_per_dof:.2f} times the "
        f"calibrated noise variance over {ident.samples} samples)"
    )


def test_a_transient_at_power_up_is_named_not_a_changed_calibration(bench):
    cfg, truth, lut, dec = bench
    d = rail(truth, signals(cfg, truth, 2.0 + 0.0 * np.arange(2000), 16), 20)
    angles = ab.absolute_reconstruction(dec, lut, d)
    assert angles.identification.status is ab.PowerUpStatus.MISMATCH
    check = identification_check(dec, _columns(d), angles)
    assert check.status is SignalStatus.MISMATCH  # still refused (exit 3): no lock was made
    assert "transient at power-up" in check.message and "power up again" in check.message


def test_a_misfit_on_part_of_the_turn_is_not_forgiven_as_a_transient(bench):
    """A ring remounted 0.3 electrical degrees off-centre (angle warp and air-gap gain of that
    size per sensor) misfits only on part of the turn (cost about 2x the noise's): the plain
    test crosses early, and restarted without the confirmation at kappa 1.5 it accepted a
    well-fitting stretch (this input, and 3 of 5 such trials on the bench)."""
    cfg, truth, _, dec = bench
    y0 = 2.0 * TS * np.arange(20000)
    w, phi = math.radians(0.3), TWO_PI * np.arange(3) / 33.0
    c = truth.theta[:, 0]
    d = np.empty((y0.size, 3))
    for h in range(3):
        seen = truth(y0 + (w / 11) * np.sin(y0 - phi[h] + 0.4))[:, h]
        d[:, h] = c[h] + (1.0 + w * np.cos(y0 - phi[h] + 0.4)) * (seen - c[h])
    d += math.sqrt(cfg.noise_variance) * np.random.default_rng(1000).standard_normal(d.shape)
    res = model_misfit(dec, d)
    assert res.status is MisfitStatus.MISMATCH
    assert res.sample is not None and res.sample < 2000
