"""The model-based observer (hallcal.sensor.observer) and ``reconstruct --observer``.

Small benches (4 pole pairs, a few seconds of ramp) with the bench's true flux as the model, so
that each test isolates the observer; the end-to-end test calibrates a folding map through the
command line. The measured figures on the paper's bench are in benchmarks/bench_observer.txt.
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import tomllib
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
from cli_support import PAPER_LOOP_TOML, run_cli
from hypothesis import given
from hypothesis import strategies as st

from hallcal._constants import TWO_PI
from hallcal.io import read_dataset, write_dataset
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sensor.observer import (
    ObserverSettings,
    ObserverState,
    chi_square_quantile,
    observer_model,
    run_observer,
)
from hallcal.sim.bench import BenchConfig, ramp_run, simulate_run

N_M = 4
BENCH = BenchConfig(pole_pairs=N_M, seed=3)
#: a bench whose map y0 -> f_init(g(y0)) folds (min slope -0.26) while g(y) is injective
FOLDING = BenchConfig(pole_pairs=N_M, shape_variation=0.25, seed=1)
#: 60 K warmer than BENCH: NdFeB remanence -7.2 %, sensitivities +-1 %, offsets ~1 % of A
WARM = dataclasses.replace(
    BENCH, amplitude=0.928, gain_mismatch=(0.01, -0.008, 0.004), offset=(0.01, -0.01, 0.005)
)
TWO_S = 8000  # samples in 2 s at the bench's 4 kHz


def _model(cfg: BenchConfig):
    return observer_model(cfg.truth(), cfg.pole_pairs, cfg.noise_variance)


@pytest.fixture(scope="module")
def healthy():
    return ramp_run(BENCH, ramp_end=4.0, duration=4.0, seed=11)


def test_tables_interpolate_the_flux_model_to_far_below_the_noise():
    m = _model(BENCH)
    flux = BENCH.truth()
    y = np.linspace(0.0, 2 * math.pi, 997)
    g, dg = flux.value_and_derivative(y)
    # the kernel's Hermite interpolation, evaluated through one Gauss-Newton step per sample on
    # noise-free data: y_obs must return y itself once the speed is tracked (the step's error
    # is second order in the prediction's, which decays by 0.95 per sample from the start at a
    # table node); the adaptation held at the model (a prior of 1e12 samples), so that its
    # start-up transient (2.6e-6 rad here, decaying) does not hide the interpolation's error
    run = run_observer(m, g, settings=ObserverSettings(prior_samples=1e12))
    assert np.max(np.abs(run.y_obs[300:] - y[300:])) < 1e-7  # far below sigma / |g'| ~ 1e-3 rad
    assert m.points >= 256 and dg.shape == (997, 3)


def test_healthy_run_is_at_the_noise_floor_and_at_or_below_the_table(healthy):
    m = _model(BENCH)
    run = run_observer(m, healthy.d)
    floor = BENCH.noise_floor
    obs = angle_error(run.y_obs, healthy.y0).rms
    lut = build_lut(BENCH.truth(), N_M)
    star = angle_error(lut.f_star(healthy.d), healthy.y0).rms
    # 16 000 samples: the RMS of the ML angle is within 3 % of its floor (sampling spread ~1 %)
    assert obs < 1.03 * floor
    assert obs <= 1.01 * star  # the ML angle is never noisier than the table's (1 % spread)
    assert set(run.state) == {ObserverState.OK.value}
    # misfit per degree of freedom about 1 once the window is full (256 samples x 2 dof)
    assert abs(float(np.mean(run.misfit[512:])) - 1.0) < 0.05
    assert run.excluded == -1


def test_warm_motor_adapts_to_the_floor_within_two_seconds_where_the_table_does_not():
    warm = ramp_run(WARM, ramp_end=4.0, duration=4.0, seed=12)
    run = run_observer(_model(BENCH), warm.d)
    floor = WARM.noise_floor
    obs = angle_error(run.y_obs[TWO_S:], warm.y0[TWO_S:]).rms
    star = angle_error(build_lut(BENCH.truth(), N_M).f_star(warm.d)[TWO_S:], warm.y0[TWO_S:]).rms
    assert obs < 1.2 * floor  # the acceptance bound
    assert star > 2.0 * floor  # the static table is far off (the reason for the adaptation)
    states = set(run.state[:TWO_S])
    assert ObserverState.ADAPTING.value in states and run.state[-1] == "ok"
    # adapted gains: the common -7.2 % and the per-sensor 1 % (to 0.2 %: noise and prior)
    assert np.allclose(run.gain, 0.928 * (1 + np.array(WARM.gain_mismatch)), atol=2e-3)
    assert run.excluded == -1


@pytest.mark.parametrize("speed", [0.2, 0.47, 1.1])
def test_a_rotor_already_spinning_at_the_first_sample_is_not_learned_as_drift(speed):
    """A recording cut from a run (or a power-up while coasting): the first sample is acquired
    with the speed at 0, so the first predictions lag by up to ``speed`` electrical rad per
    sample until the speed is tracked. The adaptation must not learn that lag as gains and
    levels (it did: gains 2 % off, then stale for good with y_obs at 4-27x the floor)."""
    m = _model(BENCH)
    n = 8000
    y0 = speed / N_M * np.arange(n)  # electrical rad per sample -> mechanical
    g, _ = BENCH.truth().value_and_derivative(y0)
    rng = np.random.default_rng(7)
    d = g + rng.normal(0.0, math.sqrt(BENCH.noise_variance), g.shape)
    run = run_observer(m, d)
    obs = angle_error(run.y_obs[1000:], y0[1000:]).rms
    assert obs < 1.1 * BENCH.noise_floor  # the floor's 7 000-sample spread is ~1 %
    # at most a short alarm while the speed is caught (the window's first 256 samples)
    assert np.mean(run.state[1000:] == ObserverState.OK.value) > 0.99
    assert np.allclose(run.gain, 1.0, atol=5e-3)  # the adaptation's noise with its prior


@pytest.mark.parametrize(
    ("peak_speed", "frequency"),
    [(200.0, 8.0), (600.0, 26.5), (2230.0, 18.0)],  # peak accelerations 1.0e4, 1.0e5, 2.5e5 rad/s^2
)
def test_servo_motion_is_tracked_without_calling_the_model_stale(peak_speed, frequency):
    """A servo's reversing motion, v = V sin(2 pi f t) (4 pole pairs, 4 kHz; the last case
    reaches 0.71 of the Nyquist speed): the prediction must follow the acceleration, or the misfit
    taken on the model linearized at a lagging prediction reads as a model that no longer fits.
    With the speed-only tracker: 100 % `stale` from 1e4 rad/s^2 (n_m 11), the angle lost at 1e5
    (468x the floor, benchmarks/bench_observer_unseen.txt)."""
    m = _model(BENCH)
    n = 8000
    t = np.arange(n) * 2.5e-4
    w = 2.0 * math.pi * frequency
    y0 = peak_speed / w * (1.0 - np.cos(w * t))
    g, _ = BENCH.truth().value_and_derivative(y0)
    d = g + np.random.default_rng(17).normal(0.0, math.sqrt(BENCH.noise_variance), g.shape)
    run = run_observer(m, d)
    err = angle_error(run.y_obs[500:], y0[500:]).rms
    assert err < 1.15 * BENCH.noise_floor  # measured 1.02-1.06x; the floor's spread is ~1 %
    assert np.mean(run.state[500:] == ObserverState.OK.value) > 0.99  # 1e-9 per sample
    assert np.max(np.abs(run.y_obs - y0)) < math.pi / (4 * N_M)  # never near a pole pitch


def test_an_angle_lost_with_a_channel_out_is_stale_not_degraded(healthy):
    """Garbage readings (600 random samples) lose the angle; a channel reading NaN now and then
    stays excluded. When the signals are healthy again the two channels left do not fit the
    model at the lost angle (misfit at its cap): that is `stale`, not `degraded` (which says the
    angle from two channels is trustworthy). Before: `degraded` throughout, 3.1 rad off."""
    m = _model(BENCH)
    d = healthy.d[:8000].copy()
    d[1000:1600] = np.random.default_rng(0).uniform(-2.0, 2.0, (600, 3))
    d[::13, 1] = np.nan
    run = run_observer(m, d)
    tail = slice(6000, 8000)
    off = np.abs((run.y_obs[tail] - healthy.y0[tail] + np.pi) % TWO_PI - np.pi)
    lost = off > math.pi / (4 * N_M)  # a quarter pole pitch: not the two-channel ML angle
    assert lost.any()  # the garbage does lose the angle here (measured: 3.1 rad off)
    assert set(run.state[tail][lost]) <= {"stale", "fault"}


@pytest.mark.parametrize(
    ("kind", "channel"), [("zero-field", 0), ("rail", 1), ("clipped", 2), ("disconnected", 1)]
)
def test_a_failed_channel_is_excluded_quickly_and_the_angle_never_slips(healthy, kind, channel):
    m = _model(BENCH)
    d = healthy.d.copy()
    k0 = 9000
    if kind == "zero-field":
        d[k0:, channel] = m.center[channel]
    elif kind == "rail":
        d[k0:, channel] = 1.4
    elif kind == "clipped":
        d[k0:, channel] = np.clip(d[k0:, channel], -0.75, 0.75)
    else:
        d[k0:, channel] = np.nan
    run = run_observer(m, d)
    changed = np.flatnonzero(~(np.abs(d[:, channel] - healthy.d[:, channel]) < 0.05))
    first_bad = int(changed[changed >= k0][0])  # first sample off by 5 % of the amplitude
    assert run.excluded == channel
    assert 0 <= run.first_exclusion - first_bad < 100  # the acceptance bound
    err = run.y_obs - healthy.y0
    assert np.max(np.abs(err)) < math.pi / (2 * N_M)  # never half a pole pitch off
    floor = BENCH.noise_floor
    assert angle_error(run.y_obs[:k0], healthy.y0[:k0]).rms < 1.10 * floor
    after = angle_error(run.y_obs[run.first_exclusion + 1 :], healthy.y0[run.first_exclusion + 1 :])
    assert after.rms < 1.6 * floor  # two-sensor ML bound about 1.32x
    assert set(run.state[run.first_exclusion + 1 :]) == {ObserverState.DEGRADED.value}


def test_folding_map_is_tracked_at_the_floor_where_no_table_exists():
    lut = build_lut(FOLDING.truth(), N_M)
    m = _model(FOLDING)
    assert not lut.bijective and m.injectivity.injective
    run_ = ramp_run(FOLDING, ramp_end=4.0, duration=4.0, seed=13)
    run = run_observer(m, run_.d)
    # against the configured floor and the ML angle's own per-sample bound (1.10x it here)
    assert angle_error(run.y_obs, run_.y0).rms < 1.2 * FOLDING.noise_floor
    assert set(run.state) == {"ok"}


def test_a_curve_that_is_not_injective_fails_the_check():
    flux = BENCH.truth()
    theta = flux.theta.copy()
    theta[1] = theta[0]  # two sensors at the same place: the curve retraces itself
    theta[2] = theta[0]
    inj = observer_model(FluxModel(flux.basis, theta), N_M, BENCH.noise_variance).injectivity
    assert not inj.injective and inj.separation < inj.margin


@pytest.mark.parametrize("offset", [0.01, 0.3])
def test_a_glitch_is_blamed_on_its_channel_and_the_step_comes_from_the_two_others(offset):
    """An outlier sample on the linearized model (no noise): the prediction ``offset`` rad short
    of the angle and channel 1 off by 0.5. The fits without one channel are chosen by their
    chi-square without the step bound, so channel 1 is blamed also where the two others' fit
    needs more than the bound (0.3 rad against max_step 0.2); only the chosen step is bounded."""
    from hallcal.sensor.observer import _robust, _step

    y = 0.7
    f = np.cos(y - 2.0 * np.pi / 3.0 * np.arange(3))
    dg = -np.sin(y - 2.0 * np.pi / 3.0 * np.arange(3))
    a, w = np.ones(3), np.full(3, 1e4)  # sigma 0.01
    r = dg * offset  # the residuals of a prediction `offset` short, linearized
    r[1] += 0.5  # the glitch: 50 sigma
    srr, num, den = np.sum(w * r * r), np.sum(w * dg * r), np.sum(w * dg * dg)
    max_step = 0.2
    chi = _step(srr, num, den, max_step)[1]
    gross = np.full(3, 0.05)
    step, _, blamed, mark, outlier = _robust(f, dg, r, a, w, srr, num, den, chi, max_step, 12.0,
                                             gross)  # fmt: skip
    assert (blamed, mark, outlier) == (1, 1, True)
    # the two others' fit is exact here (no noise, linear); bounded at max_step beyond it
    assert step == pytest.approx(min(offset, max_step), rel=1e-9)


def test_a_ring_remounted_one_pole_pitch_off_goes_stale_within_one_revolution(healthy):
    # the ring turned by one pole pitch relative to the sensors: each sample now shows the
    # neighbouring magnet's signature
    pitch = 2 * math.pi / N_M
    flux = BENCH.truth()
    rng = np.random.default_rng(4)
    d = flux(healthy.y0 + pitch) + math.sqrt(BENCH.noise_variance) * rng.standard_normal(
        (healthy.y0.size, 3)
    )
    run = run_observer(_model(BENCH), d, y_initial=0.0)
    stale = np.flatnonzero(run.state == "stale")
    assert stale.size
    travelled = healthy.y0[stale[0]] - healthy.y0[0]
    assert travelled < 2 * math.pi  # within one revolution
    assert float(np.median(run.misfit[stale])) > 2 * run.threshold


@given(k=st.floats(1.0, 5000.0), p=st.floats(1e-12, 1e-3))
def test_wilson_hilferty_threshold_is_never_below_the_chi_square_quantile(k, p):
    z = float(scipy.stats.norm.isf(p))
    exact = float(scipy.stats.chi2.isf(p, k))
    ratio = chi_square_quantile(k, z) / exact
    # conservative (the stated false-alarm rate is an upper bound) down to k = 1, p = 1e-12
    # (ratio 1.35 there), and within 1 % from k = 64 (a quarter of the window) on
    assert ratio >= 1.0 - 1e-9
    if k >= 64:
        assert ratio < 1.01


def test_settings_are_checked():
    from hallcal.sensor.observer import ObserverSettings

    with pytest.raises(ValueError, match="fault_count"):
        ObserverSettings(fault_count=100, fault_window=10)
    with pytest.raises(ValueError, match="gain_bounds"):
        ObserverSettings(gain_bounds=(1.1, 1.3))


# ------------------------------------------------------------------ the command line, end to end

SETUP = (
    """\
pole_pairs = 4
sample_time = 2.5e-4
"""
    + PAPER_LOOP_TOML
    + """\
[model]
basis = "fourier"
harmonics = [1,2,3,4,5,6,7,8,9,10,11,12,13,14,15,16,17,18,19,20]
"""
)


@pytest.fixture(scope="module")
def folding_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fold")
    (d / "s.toml").write_text(SETUP)
    n = 32000
    cal = simulate_run(FOLDING, 8.0 * np.arange(n) / n, seed=1)
    write_dataset(d / "cal.csv", cal.columns())
    val = simulate_run(FOLDING, 6.0 * np.arange(n) / n, seed=2)
    write_dataset(d / "val.csv", val.columns())
    res = run_cli("calibrate", "cal.csv", "--setup", "s.toml", "--out", "cal.json", cwd=d)
    return d, res


def test_calibrate_keeps_a_folding_maps_model_for_the_observer(folding_dir):
    d, res = folding_dir
    assert res.returncode == 0, res.stderr
    assert "use 'hallcal reconstruct --observer'" in res.stderr  # the notes go to stderr
    art = json.loads((d / "cal.json").read_text())
    assert art["diagnostics"]["status"] == "not_bijective"
    assert art["observer"]["injective"] is True


def test_plain_reconstruct_and_export_refuse_naming_the_observer(folding_dir):
    d, _ = folding_dir
    res = run_cli("reconstruct", "cal.json", "val.csv", "--out", "a.csv", cwd=d)
    assert res.returncode == 3
    assert "--observer" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    res = run_cli("export-c", "cal.json", "--out", "c", cwd=d)
    assert res.returncode == 3 and "--observer" in res.stderr


def test_reconstruct_observer_writes_y_obs_misfit_and_state(folding_dir):
    d, _ = folding_dir
    res = run_cli("reconstruct", "cal.json", "val.csv", "--observer", "--out", "a.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    assert "observer:" in res.stdout and "y_obs RMS" in res.stdout
    text = (d / "a.csv").read_text().splitlines()
    assert text[0] == "y_init,y_obs,misfit,state"  # no y_star: no table can exist
    assert text[-1].rsplit(",", 1)[1] in {s.value for s in ObserverState}
    numbers = read_dataset(d / "val.csv")
    rows = np.loadtxt(d / "a.csv", delimiter=",", skiprows=1, usecols=(1,))
    # the identified model, not the truth: within 1.2x the floor (the acceptance bound)
    assert angle_error(rows, numbers["y_ref"]).rms < 1.2 * FOLDING.noise_floor


def test_api_reconstruct_observer_gives_the_same_numbers_as_the_cli(folding_dir):
    import hallcal

    d, _ = folding_dir
    res = run_cli("reconstruct", "cal.json", "val.csv", "--observer", "--out", "c.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    cal = hallcal.load(d / "cal.json")
    assert cal.observer_only
    rec = cal.reconstruct(d / "val.csv", observer=True)
    assert list(rec.columns) == ["y_init", "y_obs", "misfit", "state"]
    cli = np.loadtxt(d / "c.csv", delimiter=",", skiprows=1, usecols=(1, 2))
    assert np.array_equal(cli[:, 0], rec["y_obs"])  # CSV keeps the shortest round-trip digits
    assert np.array_equal(cli[:, 1], rec["misfit"])


def test_a_non_bijective_artifact_without_the_observer_entry_is_still_invalid(folding_dir):
    d, _ = folding_dir
    art = json.loads((d / "cal.json").read_text())
    del art["observer"]
    (d / "bad.json").write_text(json.dumps(art))
    res = run_cli("reconstruct", "bad.json", "val.csv", "--observer", "--out", "b.csv", cwd=d)
    assert res.returncode == 2 and "not bijective" in res.stderr


def test_real_ring_remounted_between_captures_goes_stale_and_its_own_capture_does_not():
    """tests/data/ring-jig: three captures of one ring, remounted between them (whole pole
    pitches and eccentricity, DESIGN.md). Model from capture 1's first two revolutions of its
    constant-speed part, through the front door; the observer on the whole of each capture."""
    import hallcal
    from hallcal.fit.constant_speed import find_constant_speed

    root = Path(__file__).resolve().parent / "data" / "ring-jig"
    caps = [
        np.loadtxt(root / f"hall_calibration_one_rotation_{i}.txt").astype(np.float64)
        for i in (1, 2, 3)
    ]
    seg = find_constant_speed(caps[0], 25)
    start, mid, stop = seg.split(2.0)
    setup = {
        "pole_pairs": 25,
        "sample_time": 1.0,
        "trajectory": {"kind": "constant-speed", "start": int(start), "stop": int(mid)},
    }
    cols = [{f"d{h + 1}": c[:, h] for h in range(3)} for c in caps]
    cal = hallcal.calibrate(cols[0], setup)
    assert cal.observer is not None and cal.observer["injective"]
    own = cal.reconstruct(cols[0], observer=True)
    # its own capture, held-out revolutions included: no alarm (the monitor's level is the
    # calibration part's own worst windowed residual)
    assert set(own["state"][start:]) == {"ok"}
    per_rev = 2 * math.pi / abs(seg.speed)
    for other in cols[1:]:
        rec = cal.reconstruct(other, observer=True)
        stale = np.flatnonzero(rec["state"] == "stale")
        assert stale.size and stale[0] - start < 0.25 * per_rev  # measured 0.07-0.08 rev
        assert np.median(rec["misfit"][stale]) > 10.0  # measured about 45


HARNESS = r"""
#include "hallcal_obs.h"
void run(int n, const float *d, double *y, float *misfit, unsigned char *st)
{
    static hallcal_obs_state s;
    hallcal_obs_reading r;
    int k;
    hallcal_obs_init(&s);
    for (k = 0; k < n; k++) {
        st[k] = hallcal_obs_update(&s, d[3 * k], d[3 * k + 1], d[3 * k + 2]);
        hallcal_obs_read(&s, &r);
        y[k] = 6.283185307179586 * (double)r.revolutions + (double)r.angle;
        misfit[k] = r.misfit;
    }
}
"""


def test_export_c_observer_agrees_with_python_within_1e_5_rad(folding_dir):
    """The C observer (float) on the folding map's validation run, healthy and with a channel
    stuck at its zero-field level: y_obs within 1e-5 rad of Python's on the same (float32)
    inputs, the same state at every sample. Compiled with the strict flags of the lean export."""
    import ctypes

    from firmware_support import CC, STRICT

    import hallcal
    from hallcal.pipeline.observe import run_on

    if CC is None:
        pytest.skip("no C compiler on this machine")
    d, _ = folding_dir
    res = run_cli("export-c", "cal.json", "--observer", "--out", "obs", cwd=d)
    assert res.returncode == 0, res.stderr
    (d / "obs" / "harness.c").write_text(HARNESS)
    lib = d / "obs" / "libobs.so"
    cc = subprocess.run(
        [CC, *STRICT, "-O2", "-fPIC", "-shared", "-o", str(lib), "hallcal_obs.c", "harness.c"],
        cwd=d / "obs", capture_output=True, text=True,
    )  # fmt: skip
    assert cc.returncode == 0, cc.stderr
    so = ctypes.CDLL(str(lib))
    cal = hallcal.load(d / "cal.json")
    val = read_dataset(d / "val.csv")
    d32 = val.d.astype(np.float32)
    stuck = d32.copy()
    stuck[20000:, 1] = np.float32(cal.flux.theta[1, 0])
    # a rotor already spinning at the first sample, 0.47 electrical rad per sample (the
    # adaptation waits for settled steps, in C as in Python)
    y0 = 0.47 / N_M * np.arange(4000)
    g, _ = cal.flux.value_and_derivative(y0)
    noise = np.random.default_rng(3).normal(0.0, math.sqrt(FOLDING.noise_variance), g.shape)
    spinning = np.ascontiguousarray(g + noise, dtype=np.float32)
    for x in (spinning, d32, stuck):
        n = x.shape[0]
        y, m, st = np.zeros(n), np.zeros(n, np.float32), np.zeros(n, np.uint8)
        so.run(ctypes.c_int(n), *(a.ctypes.data_as(ctypes.c_void_p) for a in (x, y, m, st)))
        py = run_on(cal, x.astype(np.float64))
        assert np.max(np.abs(y - py.y_obs)) < 1e-5  # the acceptance bound (measured 1e-6)
        assert np.array_equal(st, py.state_code)
        # the misfit in float: a relative 1e-4 of a sum over 256 samples
        assert np.max(np.abs(m - py.misfit) / np.maximum(py.misfit, 1.0)) < 1e-3
    assert set(py.state[20100:]) == {"degraded"}


def test_api_observer_columns_beside_the_table_on_a_bijective_calibration():
    import hallcal

    n = 24000
    cal_run = simulate_run(BENCH, 8.0 * np.arange(n) / n, seed=21)
    setup = tomllib.loads(SETUP)
    setup["model"]["harmonics"] = [1, 2, 3, 4]  # the bench's truth: magnets 1..3, n_m = 4
    cal = hallcal.calibrate(cal_run.columns(), setup)
    assert cal.status.success and not cal.observer_only
    val = simulate_run(BENCH, 5.0 * np.arange(n) / n, seed=22)
    rec = cal.reconstruct(val.columns(), observer=True)
    assert list(rec.columns) == ["y_init", "y_star", "y_obs", "misfit", "state"]
    star = angle_error(rec["y_star"], val.y0).rms
    # the ML angle is at or below the table's (2 % for the sampling spread of 24 000 samples)
    assert rec.observer_error.rms <= 1.02 * star
    assert rec.validation is not None and set(rec["state"]) == {"ok"}
