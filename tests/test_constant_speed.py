"""Constant-speed calibration on synthetic data with known truth (hallcal.fit.constant_speed).

The synthetic sensors have what the ring-jig recordings have: unequal electrical spacing (0, 101
and 261 degrees), unequal gains, raw-ADC offsets of about 40 000 counts, per-magnet variations
(amplitude and offset modulated at 1-3 cycles per revolution, different per sensor), a third
electrical harmonic, white noise, and both directions of rotation.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hallcal._constants import TWO_PI
from hallcal.fit.constant_speed import (
    GeometryStatus,
    calibrate_constant_speed,
    default_harmonics,
    estimate_sensor_geometry,
    find_constant_speed,
)
from hallcal.sensor.flux import FourierBasis
from hallcal.sensor.reconstruction import clarke_matrix

PHASES = np.radians([0.0, 101.0, 261.0])
AMPS = np.array([3000.0, 2400.0, 3300.0])
OFFSETS = np.array([41000.0, 40500.0, 42000.0])


def hall(y0, n, *, phases=PHASES, amps=AMPS, offsets=OFFSETS, distort=True):
    """True flux g(y0) in ADC counts, shape (N, 3)."""
    y0 = np.asarray(y0, dtype=float)
    out = np.empty((y0.size, 3))
    for h in range(3):
        e = n * y0 - phases[h]
        if distort:
            am = 1.0 + 0.05 * np.cos(y0 + 0.7 * h) + 0.03 * np.sin(2.0 * y0 - 1.1 * h)
            om = 60.0 * np.cos(3.0 * y0 + h)
            third = 0.03 * np.cos(3.0 * e + 0.4)
        else:
            am, om, third = 1.0, 0.0, 0.0
        out[:, h] = offsets[h] + om + amps[h] * am * (np.cos(e) + third)
    return out


def recording(n=7, *, direction=1, revolutions=6.0, samples_per_cycle=40, sigma=10.0, seed=0,
              phase0=0.4, distort=True, burst=None):  # fmt: skip
    """Constant-speed recording; returns d, the true angle y0 and the speed b [rad/sample]."""
    rng = np.random.default_rng(seed)
    b = direction * TWO_PI / (n * samples_per_cycle)
    N = int(round(revolutions * TWO_PI / abs(b)))
    k = np.arange(N)
    y0 = phase0 + b * k
    if burst is not None:  # a decaying oscillation of the rotor (a rig resonance)
        k0, amp, period = burst
        tau = np.maximum(k - k0, 0)
        y0 = y0 + (k >= k0) * amp * np.exp(-tau / (3 * period)) * np.sin(TWO_PI * tau / period)
    d = hall(y0, n, distort=distort) + sigma * rng.standard_normal((N, 3))
    return d, y0, b


def noise_floor(d_clean, d_noisy, lut):
    """RMS angle error [rad] that the noise alone causes through the table (Monte Carlo)."""
    return float(np.std(lut.f_star(d_noisy) - lut.f_star(d_clean)))


def centred_rms(x):
    x = np.asarray(x)
    return float(np.sqrt(np.mean((x - x.mean()) ** 2)))


# --------------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------------


def test_geometry_exact_on_pure_sinusoids():
    n = 7
    y0 = np.linspace(0.0, 3.3, 2000)
    d = hall(y0, n, distort=False)
    g = estimate_sensor_geometry(d, n)
    assert g.status == "ok"
    np.testing.assert_allclose(g.phases, PHASES, atol=1e-9)
    np.testing.assert_allclose(g.amplitudes, AMPS, rtol=1e-9)
    np.testing.assert_allclose(g.offsets, OFFSETS, rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(g.spacing_deg, [101.0, 160.0, 99.0], atol=1e-7)
    assert g.direction == 1
    assert g.revolutions == pytest.approx(3.3 / TWO_PI, rel=1e-6)
    # the projection maps the data onto a circle of the mean amplitude, psi = n y0
    ab = (d - g.offsets) @ g.projection.T
    np.testing.assert_allclose(np.hypot(ab[:, 0], ab[:, 1]), np.mean(AMPS), rtol=1e-9)
    psi = np.arctan2(ab[:, 1], ab[:, 0])
    err = np.angle(np.exp(1j * (psi - n * y0)))
    assert np.max(np.abs(err)) < 1e-9
    # and f_init with it is exact
    np.testing.assert_allclose(g.f_init(d, n), y0, atol=1e-9)


def test_geometry_nominal_is_clarke():
    n = 5
    y0 = np.linspace(0.0, 2.0, 1500)
    ph = np.array([0.0, TWO_PI / 3, 2 * TWO_PI / 3])
    d = hall(y0, n, phases=ph, amps=np.full(3, 2.0), offsets=np.zeros(3), distort=False)
    g = estimate_sensor_geometry(d)
    np.testing.assert_allclose(g.projection, clarke_matrix()[:2], atol=1e-9)
    np.testing.assert_allclose(g.phases_deg, [0.0, 120.0, 240.0], atol=1e-7)
    assert g.revolutions is None


def test_geometry_reversed_wiring_and_direction():
    """Sensor order defines the positive direction; turning backwards gives direction -1."""
    n = 7
    y0 = np.linspace(0.0, -2.5, 1800)  # backwards
    d = hall(y0, n, distort=False)
    g = estimate_sensor_geometry(d, n)
    np.testing.assert_allclose(g.phases, PHASES, atol=1e-9)
    assert g.direction == -1
    assert g.electrical_cycles == pytest.approx(-2.5 * n / TWO_PI, rel=1e-6)
    # swapping sensors 2 and 3 flips the orientation: sensor order 1, 3, 2 is now the positive one
    g2 = estimate_sensor_geometry(d[:, [0, 2, 1]], n)
    np.testing.assert_allclose(g2.spacing_deg, [99.0, 160.0, 101.0], atol=1e-7)
    assert g2.direction == 1


def test_geometry_with_noise_and_distortion():
    d, _, _ = recording(direction=-1, sigma=10.0)
    g = estimate_sensor_geometry(d, 7)
    assert g.status == "ok"
    np.testing.assert_allclose(g.phases_deg, np.degrees(PHASES), atol=0.5)
    np.testing.assert_allclose(g.amplitudes, AMPS, rtol=0.02)
    np.testing.assert_allclose(g.offsets, OFFSETS, atol=20.0)
    assert g.direction == -1


def test_geometry_partial_coverage_and_degenerate():
    n = 7
    d = hall(np.linspace(0.0, 0.5, 300), n, distort=False)  # 0.56 electrical cycles
    assert estimate_sensor_geometry(d, n).status == "partial_coverage"
    still = np.tile([1.0, 2.0, 3.0], (100, 1))  # no plane: the typed status, not a string
    assert estimate_sensor_geometry(still).status is GeometryStatus.DEGENERATE
    with pytest.raises(ValueError, match="cannot calibrate: sensor geometry: .* span a plane"):
        calibrate_constant_speed(still, 1, FourierBasis((1,)), start=0, stop=100)
    with pytest.raises(ValueError):
        estimate_sensor_geometry(np.zeros((10, 2)))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    p2=st.floats(60.0, 170.0),
    p3=st.floats(60.0, 170.0),
    amps=st.lists(st.floats(0.3, 3.0), min_size=3, max_size=3),
    offs=st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3),
    start=st.floats(-10.0, 10.0),
    direction=st.sampled_from([-1, 1]),
)
def test_geometry_property_exact_recovery(p2, p3, amps, offs, start, direction):
    """Any spacing (neighbours 60-170 degrees apart), gains, offsets and direction: exact."""
    n = 4
    ph = np.radians([0.0, p2, p2 + p3])
    y0 = start + direction * np.linspace(0.0, 2.0, 800)
    d = hall(y0, n, phases=ph, amps=np.array(amps), offsets=np.array(offs), distort=False)
    g = estimate_sensor_geometry(d, n)
    np.testing.assert_allclose(g.phases, ph, atol=1e-7)
    np.testing.assert_allclose(g.amplitudes, amps, rtol=1e-7)
    np.testing.assert_allclose(g.offsets, offs, atol=1e-6 * max(1.0, max(np.abs(offs))))
    assert g.direction == direction


# --------------------------------------------------------------------------------------------------
# constant-speed calibration
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("direction", [1, -1])
def test_calibration_recovers_true_angle(direction):
    """Held-out angle error at the noise floor; f_init is an order of magnitude worse."""
    n = 7
    d, y0, b_true = recording(n, direction=direction, sigma=10.0, seed=3)
    N = d.shape[0]
    stop = N // 2  # calibrate on the first 3 revolutions, hold out the last 3
    basis = FourierBasis(default_harmonics(n))
    res = calibrate_constant_speed(d, n, basis, start=0, stop=stop)
    assert res.status == "ok", res.warnings
    assert res.converged and res.iterations < 40
    assert res.b == pytest.approx(b_true, rel=1e-5)
    assert res.direction == direction
    assert res.revolutions == pytest.approx(3.0, rel=1e-3)
    np.testing.assert_allclose(res.geometry.phases_deg, np.degrees(PHASES), atol=0.5)
    assert res.lut.bijective
    # the true angle, up to the unobservable constant (the gauge)
    held = slice(stop, N)
    e_star = res.lut.f_star(d)[held] - y0[held]
    e_init = res.lut.f_init(d)[held] - y0[held]
    # the constant is small: f_star lives in f_init's frame, within an electrical cycle of y0
    assert abs(np.mean(e_star) - np.mean(e_init)) < 0.2 * TWO_PI / n
    clean = hall(y0, n)
    floor = noise_floor(clean[held], d[held], res.lut)
    assert centred_rms(e_init) > 8 * floor
    assert centred_rms(e_star) < 1.2 * floor
    # diagnostics: the noise estimate and the analytic angle floor match the truth
    assert res.noise_std == pytest.approx(10.0, rel=0.1)
    assert res.angle_noise_floor == pytest.approx(floor, rel=0.2)
    assert res.motion_rms < 2 * floor
    np.testing.assert_allclose(res.weights, 1.0)  # clean constant speed: nothing down-weighted
    assert res.residual_rms == pytest.approx(np.full(3, 10.0), rel=0.1)
    diag = json.loads(json.dumps(res.to_dict()))
    assert diag["geometry"]["phases"] == pytest.approx(res.geometry.phases.tolist())
    assert diag["b"] == res.b and diag["status"] == "ok" and diag["downweighted_fraction"] == 0.0


def test_gauge_mean_of_correction_is_zero():
    """a is chosen so that f_init - y0 has zero mean over the segment (documented gauge)."""
    n = 7
    d, _, _ = recording(n, direction=-1, sigma=5.0, seed=4)
    res = calibrate_constant_speed(d, n, FourierBasis(default_harmonics(n)), start=100, stop=1500)
    y = res.lut.f_init(d)[100:1500]
    assert np.mean(y - res.y0()) == pytest.approx(0.0, abs=1e-12)
    # the table's correction averages out over a revolution; f_star follows the fitted line
    assert abs(np.mean(res.lut.eta)) < 1e-3 / n
    ys = res.lut.f_star(d)[100:1500]
    assert centred_rms(ys - res.y0()) < 2.0 * res.angle_noise_floor
    # the model reproduces the data at the fitted angles
    np.testing.assert_allclose(res.model(res.y0()), d[100:1500], atol=6 * 5.0)


def test_noiseless_is_exact():
    n = 5
    d, y0, b = recording(n, revolutions=3.0, sigma=0.0, samples_per_cycle=30, direction=-1)
    basis = FourierBasis(tuple(range(1, 3 * n + 3)))  # all harmonics of the truth
    res = calibrate_constant_speed(d, n, basis, start=0, stop=len(d))
    assert res.b == pytest.approx(b, rel=1e-10)
    e = res.lut.f_star(d) - y0
    assert centred_rms(e) < 1e-6
    assert res.cost < 1e-12 * len(d) * np.mean(AMPS) ** 2


@settings(max_examples=8, deadline=None)
@given(
    phase0=st.floats(-20.0, 20.0),
    spc=st.integers(25, 60),
    direction=st.sampled_from([-1, 1]),
    seed=st.integers(0, 1000),
)
def test_property_speed_and_angle(phase0, spc, direction, seed):
    """Any start angle, speed and direction: b and the held-out angle near the floor."""
    n = 5
    d, y0, b = recording(
        n, direction=direction, revolutions=4.0, samples_per_cycle=spc, sigma=8.0, seed=seed,
        phase0=phase0,
    )  # fmt: skip
    N = len(d)
    res = calibrate_constant_speed(
        d, n, FourierBasis(default_harmonics(n)), start=0, stop=N // 2, robust=False
    )
    assert res.converged
    assert res.b == pytest.approx(b, rel=1e-4)  # statistical error about 1e-5
    e = res.lut.f_star(d)[N // 2 :] - y0[N // 2 :]
    floor = noise_floor(hall(y0[N // 2 :], n), d[N // 2 :], res.lut)
    assert centred_rms(e) < 1.3 * floor


def test_fewer_than_one_revolution_warns():
    n = 7
    d, _, _ = recording(n, revolutions=2.0, sigma=5.0)
    stop = int(0.8 * len(d) / 2.0)  # 0.8 revolution
    res = calibrate_constant_speed(
        d, n, FourierBasis(default_harmonics(n, sidebands=1)), start=0, stop=stop
    )
    assert res.revolutions < 1.0
    assert res.status in ("warning", "not_converged")
    assert any("< 1 revolution" in w for w in res.warnings)


def test_robust_weights_reject_a_resonance_burst():
    """A ringing rotor in the calibration part: the reweighted fit stays near the floor."""
    n = 7
    period = 13  # samples: a resonance at about 3 times the electrical frequency
    d, y0, _ = recording(n, sigma=5.0, seed=7, burst=(300, 0.15 / n, period))
    N = len(d)
    stop = N // 2
    basis = FourierBasis(default_harmonics(n))
    plain = calibrate_constant_speed(d, n, basis, start=0, stop=stop, robust=False)
    robust = calibrate_constant_speed(d, n, basis, start=0, stop=stop)
    held = slice(stop, N)
    e_plain = centred_rms(plain.lut.f_star(d)[held] - y0[held])
    e_robust = centred_rms(robust.lut.f_star(d)[held] - y0[held])
    floor = noise_floor(hall(y0[held], n), d[held], robust.lut)
    assert robust.weights.min() < 0.2  # the burst was found ...
    assert np.mean(robust.weights[600:] == 1.0) > 0.9  # ... and the rest left alone
    assert e_robust < 0.6 * e_plain
    assert e_robust < 2.0 * floor
    assert robust.motion_rms > 2 * robust.angle_noise_floor  # the burst shows in the diagnostic


def test_input_validation():
    n = 7
    d, _, _ = recording(n, revolutions=2.0)
    basis = FourierBasis(default_harmonics(n))
    with pytest.raises(ValueError, match="pole-pair harmonic"):
        calibrate_constant_speed(d, n, FourierBasis((1, 2)), start=0, stop=len(d))
    with pytest.raises(ValueError, match="start"):
        calibrate_constant_speed(d, n, basis, start=10, stop=5)
    with pytest.raises(ValueError, match="too short"):
        calibrate_constant_speed(d, n, basis, start=0, stop=20)
    with pytest.raises(ValueError, match="shape"):
        calibrate_constant_speed(d[:, :2], n, basis, start=0, stop=len(d))
    still = np.tile(d[:1], (400, 1)) + np.random.default_rng(0).standard_normal((400, 3))
    assert estimate_sensor_geometry(still).status is GeometryStatus.DEGENERATE
    with pytest.raises(ValueError, match="ellipse"):
        calibrate_constant_speed(still, n, FourierBasis((7,)), start=0, stop=400)
    crawl = hall(np.linspace(0.0, 0.5, 400) / n, n)  # half an electrical cycle
    with pytest.raises(ValueError, match="electrical cycle"):
        calibrate_constant_speed(crawl, n, FourierBasis((7,)), start=0, stop=400)


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------


def test_find_constant_speed_on_trapezoid():
    """Rest, accelerate, cruise, decelerate, rest: the segment lies inside the cruise."""
    n = 7
    v = TWO_PI / (n * 40)  # rad/sample
    acc = np.concatenate([np.zeros(200), np.linspace(0, v, 300), np.full(2000, v)])
    vel = -np.concatenate([acc, acc[::-1]])  # backwards
    y0 = np.cumsum(vel)
    d = hall(y0, n) + 5.0 * np.random.default_rng(1).standard_normal((y0.size, 3))
    seg = find_constant_speed(d, n)
    assert seg.status == "ok"
    cruise = (500, 4500)
    assert cruise[0] <= seg.start < cruise[0] + 150
    assert cruise[1] - 150 < seg.stop <= cruise[1]
    assert seg.samples_per_cycle == 40
    assert seg.speed == pytest.approx(-v, rel=2e-3)
    assert seg.revolutions == pytest.approx((seg.stop - seg.start) * v / TWO_PI, rel=2e-3)
    s, m, e = seg.split(2.0)
    assert (s, e) == (seg.start, seg.stop)
    assert (m - s) * v == pytest.approx(2 * TWO_PI, abs=v)
    assert find_constant_speed(np.ones((100, 3)), n).status == "not_found"


def test_default_harmonics():
    assert default_harmonics(25) == tuple(range(1, 76))
    assert default_harmonics(11, electrical=1) == tuple(range(1, 12))
    assert default_harmonics(25, electrical=2, sidebands=1) == (1, 24, 25, 26, 49, 50, 51)
    assert default_harmonics(4, electrical=1, sidebands=0) == (4,)
    with pytest.raises(ValueError):
        default_harmonics(0)


# --------------------------------------------------------------------------------------------------
# through the pipeline (the setup's [trajectory] kind = "constant-speed")
# --------------------------------------------------------------------------------------------------


def test_pipeline_constant_speed(tmp_path):
    from hallcal import pipeline
    from hallcal.errors import HallcalInputError
    from hallcal.io import Dataset, read_artifact, setup_from_dict, write_artifact

    n = 7
    d, y0, _ = recording(n, direction=-1, sigma=5.0, seed=11)
    N = len(d)
    ds = Dataset.from_columns({"d1": d[:, 0], "d2": d[:, 1], "d3": d[:, 2], "y_ref": y0})
    setup = setup_from_dict(
        {
            "pole_pairs": n,
            "sample_time": 1.0,
            "trajectory": {"kind": "constant-speed", "start": 0, "stop": N // 2},
        }
    )
    cal = pipeline.calibrate(ds, setup)
    assert cal.status == "ok", cal.messages
    assert cal.model_info["harmonics"] == list(default_harmonics(n))
    assert cal.validation is not None
    art = cal.to_artifact()
    cs = art["diagnostics"]["constant_speed"]
    np.testing.assert_allclose(cs["geometry"]["phases_deg"], np.degrees(PHASES), atol=0.5)
    np.testing.assert_allclose(art["reconstruction"]["projection"], cal.lut.projection)
    write_artifact(tmp_path / "cal.json", art)
    lut = read_artifact(tmp_path / "cal.json").lut()
    e = lut.f_star(d)[N // 2 :] - y0[N // 2 :]
    assert centred_rms(e) < 1.3 * noise_floor(hall(y0[N // 2 :], n), d[N // 2 :], lut)
    # user mistakes are one-line input errors naming the key
    bad = setup_from_dict(
        {
            "pole_pairs": n,
            "sample_time": 1.0,
            "trajectory": {"kind": "constant-speed", "start": 0, "stop": N + 5},
        }
    )
    with pytest.raises(HallcalInputError, match="trajectory"):
        pipeline.calibrate(ds, bad)
    no_n = setup_from_dict(
        {
            "pole_pairs": n,
            "sample_time": 1.0,
            "model": {"harmonics": [1, 2, 3]},
            "trajectory": {"kind": "constant-speed"},
        }
    )
    with pytest.raises(HallcalInputError, match="harmonics"):
        pipeline.calibrate(ds, no_n)
    # a segment that includes the acceleration is flagged
    v = TWO_PI / (n * 40)
    vel = np.concatenate([np.linspace(0, v, 400), np.full(1600, v)])
    y_acc = np.cumsum(vel)
    d_acc = hall(y_acc, n) + 5.0 * np.random.default_rng(2).standard_normal((y_acc.size, 3))
    ds_acc = Dataset.from_columns({"d1": d_acc[:, 0], "d2": d_acc[:, 1], "d3": d_acc[:, 2]})
    cal_acc = pipeline.calibrate(ds_acc, setup)  # start 0: inside the acceleration
    assert cal_acc.status in ("warning", "not_bijective")  # here the table is even unusable
    assert "speed varies" in cal_acc.messages[0].text and "looks like" in cal_acc.messages[0].text
