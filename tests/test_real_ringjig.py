"""Constant-speed calibration proven on measured Hall data: the ring-jig recordings.

Data: ``tests/data/ring-jig/`` (shipped with the repository, MIT; see its README and LICENSE).
Three analog
linear Hall sensors over a 25-pole-pair magnet ring turned open loop by a stepper with a trapezoidal
move; 6000 rows of ``hall1 hall2 hall3`` raw ADC counts per file, no encoder, sample rate not logged
(about 1.95 kHz), so time is in samples (``sample_time = 1.0``).

Protocol (per file)
-------------------
1. Load the rows as integers, convert to the dataset's columns d1, d2, d3 (float64). The files are
   not rewritten.
2. 2. Locate the constant-speed part with :func:`hallcal.fit.constant_speed.find_constant_speed`:
   f_init's angle (with the estimated sensor geometry) is differentiated over sliding windows of
   exactly one electrical cycle (52 samples here), which cancels f_init's electrically periodic
   error; the segment is the longest run of samples whose every one-cycle window is within 10 % of
   the cruise speed, minus half a cycle at each end. Found: samples ~110..~5740, 4.35 revolutions,
   1294 samples per revolution, turning against the sensor order (b < 0) in all three files.
3. Calibrate on the first two whole revolutions of that part (default harmonics 1..75, robust
   weights on), reconstruct the *whole* file with f_star from y = 0 before sample 0 (the frame of
   the calibration), and on the held-out rest of the constant part (2.35 revolutions) fit the best
   straight line to f_init and to f_star separately; report the RMS residuals in electrical
   degrees (mechanical times 25).

Results (electrical degrees RMS on the held-out revolutions; measured on a shared 2-core machine)::

    file  Clarke f_init  f_init (est. geometry)  f_star  noise floor  calibration time
    1         5.39              4.87              0.82      0.09        0.5-2 s
    2        10.67              6.59              0.40      0.10        0.5-2 s
    3        10.79              7.05              0.44      0.10        0.5-2 s

(calibration time: 2600 samples, 75 harmonics = 151 parameters per channel, 5 robust rounds of
3-4 Gauss-Newton steps; 0.5-1.2 s on an idle core, up to 2 s when the machine is shared.)

The estimated sensor spacing alone (f_init with the fitted phases 0/101/261 degrees, gains and
offsets instead of Clarke) takes f_init from 5.4-10.8 to 4.9-7.1 degrees; the calibrated table
brings it to 0.4-0.8, 6-16 times better than f_init. Without the robust weights f_star is
1.16/0.46/0.45; with all harmonics up to 87 it is 1.05/0.42/0.42 (robust) or 1.31/0.50/0.45.

What limits the residual
------------------------
The residual is not sensor noise: the white-noise floor (8 counts per channel from second
differences, i.e. 0.10 electrical degrees through f_init; the spectrum of the held-out residual is
flat at about that level above 150 cycles per revolution) is 4-8 times below it. It is mostly the
rig's own motion, i.e. the "best straight line" is not the true angle:

* The calibration residual lies almost entirely *along* the model curve (its tangential part,
  expressed as an angle, is 0.4-1.5 electrical degrees RMS, ``motion_rms``, against about 8 counts
  orthogonal to it): the ring really moves off the straight line.
* In the held-out f_star residual the largest part is a broad, non-synchronous band at about 45-85
  cycles per revolution (0.69/0.24/0.31 degrees in files 1/2/3), coming in bursts (file 1: around
  samples 1200-1700 and 5300-5700): the torsional resonance of the stepper-driven ring, about
  75-110 Hz if the sample rate is 1.95 kHz. It cannot be calibrated (it is not a function of the
  angle); in the calibration part it would leak into the table, which the robust weights limit
  (file 1: 1.16 -> 0.82).
* Slow deviations below 13 cycles per revolution: 0.19-0.26 degrees.
* Stepper microstep ripple: sharp lines at exactly 100 and 200 cycles per revolution (about 0.10
  and 0.07 degrees RMS each in every file): the stepper has 200 full steps per revolution, 4 full
  steps per electrical cycle of the stepper = 50 cycles per revolution; 100 and 200 are its 2nd and
  4th harmonics (and 200 the full-step rate). Being synchronous with the ring they could be
  "calibrated away" with more harmonics, but that would write the stepper's error into the Hall
  table, so the default basis stops at 75. Conversely, whatever part of f_init's large 50-cycle
  error (about 1 degree; the sensors' 2nd electrical harmonic) is really stepper ripple has been
  absorbed into the table: no constant-speed method (nor the paper's closed loop) can separate
  rotor-angle errors periodic in the angle from sensor errors (paper, section "Discussion").

So on this jig the honest floor of this metric is set by the jig's motion (file 1 rings most);
an encoder, or averaging several runs with the stepper re-indexed relative to the ring, would be
needed to go further.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from motor_support import remount_trials

from hallcal._constants import TWO_PI
from hallcal.fit.constant_speed import (
    calibrate_constant_speed,
    default_harmonics,
    estimate_sensor_geometry,
    find_constant_speed,
)
from hallcal.fit.held_out import held_out_error
from hallcal.io import Dataset, setup_from_dict
from hallcal.messages import MessageCode
from hallcal.sensor.flux import FourierBasis
from hallcal.sensor.reconstruction import f_init


def _data_dir() -> Path:
    """The copy shipped in tests/data/ring-jig; the environment variable HALLCAL_REAL_DATA wins."""
    env = os.environ.get("HALLCAL_REAL_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parent / "data" / "ring-jig"


DATA_DIR = _data_dir()
FILES = [DATA_DIR / f"hall_calibration_one_rotation_{i}.txt" for i in (1, 2, 3)]
POLE_PAIRS = 25
CAL_REVOLUTIONS = 2.0


def test_the_recordings_ship_with_the_repository():
    """No skip: the files, their license and their README are part of the repository."""
    for f in FILES:
        assert f.is_file(), f
    assert "MIT License" in (DATA_DIR / "LICENSE").read_text(encoding="utf-8")
    assert "tomrodinger/servomotor" in (DATA_DIR / "README.md").read_text(encoding="utf-8")


def load_dataset(path: Path) -> Dataset:
    """The file as a dataset with columns d1, d2, d3 (float64); the file itself is untouched."""
    raw = np.loadtxt(path, dtype=np.int64)
    assert raw.shape == (6000, 3)
    return Dataset.from_columns({f"d{h + 1}": raw[:, h] for h in range(3)}, path=path)


def hall_matrix(ds: Dataset) -> np.ndarray:
    return ds.d


def line_residual(y: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Residual of the best straight line through (k, y)."""
    A = np.column_stack([np.ones_like(k, dtype=float), k.astype(float)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return y - A @ coef


def elec_deg_rms(x: np.ndarray) -> float:
    return float(np.degrees(np.sqrt(np.mean(np.square(x)))) * POLE_PAIRS)


def band_rms(x_deg: np.ndarray, revolutions: float, lo: float, hi: float) -> float:
    """RMS of the part of x in [lo, hi) cycles per revolution (periodogram, Parseval)."""
    L = x_deg.size
    F = np.fft.rfft(x_deg - x_deg.mean())
    P = np.abs(F) ** 2 / L**2
    P[1:] *= 2.0
    f = np.arange(F.size) / revolutions
    return float(np.sqrt(np.sum(P[(f >= lo) & (f < hi)])))


@pytest.fixture(scope="module")
def results():
    out = {}
    basis = FourierBasis(default_harmonics(POLE_PAIRS))
    for i, path in enumerate(FILES, start=1):
        d = hall_matrix(load_dataset(path))
        seg = find_constant_speed(d, POLE_PAIRS)
        start, mid, stop = seg.split(CAL_REVOLUTIONS)
        res = calibrate_constant_speed(d, POLE_PAIRS, basis, start=start, stop=mid)
        y_init = res.lut.f_init(d)  # whole file, from y = 0 before the first sample
        y_star = res.lut.f_star(d)
        k = np.arange(mid, stop)
        r_init = line_residual(y_init[mid:stop], k)
        r_star = line_residual(y_star[mid:stop], k)
        clarke = f_init(d - d.mean(axis=0), POLE_PAIRS)  # the plain Clarke f_init of the README
        out[i] = {
            "d": d,
            "seg": seg,
            "split": (start, mid, stop),
            "res": res,
            "r_init": r_init,
            "r_star": r_star,
            "init": elec_deg_rms(r_init),
            "star": elec_deg_rms(r_star),
            "clarke": elec_deg_rms(line_residual(clarke[mid:stop], k)),
            "held_revs": abs(res.b) * (stop - mid) / (2 * math.pi),
        }
    return out


def test_ringjig_sensor_geometry():
    """The README's spacing (about 101, 160 and 98 electrical degrees) from the raw data alone."""
    for path in FILES:
        d = hall_matrix(load_dataset(path))
        g = estimate_sensor_geometry(d, POLE_PAIRS)
        assert g.status == "ok"
        np.testing.assert_allclose(g.spacing_deg, [101.0, 160.0, 98.0], atol=2.0)
        assert g.direction == -1  # the ring turns against the sensor order
        assert g.electrical_cycles == pytest.approx(-112.0, abs=1.0)  # README: about 112
        assert np.all((g.offsets > 40_000) & (g.offsets < 43_000))  # raw ADC offsets
        assert np.all((g.amplitudes > 2_500) & (g.amplitudes < 5_000))


def test_ringjig_constant_speed_part(results):
    for i, r in results.items():
        seg = r["seg"]
        assert seg.status == "ok"
        assert 60 < seg.start < 200, i  # after the acceleration (about 100 samples)
        assert 5650 < seg.stop < 5780, i  # before the deceleration (from about 5760)
        assert seg.revolutions > 4.2
        assert seg.samples_per_cycle == 52
        assert 2 * math.pi / abs(seg.speed) == pytest.approx(1294.0, rel=2e-3)


def test_ringjig_calibration_beats_f_init(results):
    """Held-out f_star < 1.2 electrical degrees RMS and at least 3x better than f_init."""
    print()
    print(
        "file  start   mid  stop  held-revs  Clarke  f_init  f_star  floor  motion  b[rad/sample]"
    )
    for i, r in results.items():
        res = r["res"]
        start, mid, stop = r["split"]
        floor = math.degrees(res.angle_noise_floor) * POLE_PAIRS
        motion = math.degrees(res.motion_rms) * POLE_PAIRS
        print(
            f"{i:4d} {start:6d} {mid:5d} {stop:5d} {r['held_revs']:9.2f} {r['clarke']:7.2f}"
            f" {r['init']:7.2f} {r['star']:7.2f} {floor:6.2f} {motion:7.2f} {res.b:14.7e}"
        )
    for i, r in results.items():
        res = r["res"]
        assert res.status == "ok", (i, res.warnings)
        assert res.lut.bijective
        assert res.revolutions == pytest.approx(CAL_REVOLUTIONS, abs=1e-3)
        assert res.b < 0
        assert 4.0 < r["init"] < 8.0, i
        assert 5.0 < r["clarke"] < 11.5, i
        assert r["star"] < 1.2, i
        assert r["star"] * 3.0 < r["init"], i


def test_ringjig_what_limits_the_residual(results):
    """The residual is rig motion (resonance, drift, microsteps), not sensor noise."""
    print()
    print("file  noise[counts]  floor  f_star  45-85c/rev  <13c/rev  100c/rev  200c/rev  >150c/rev")
    for i, r in results.items():
        res = r["res"]
        x = np.degrees(r["r_star"]) * POLE_PAIRS
        R = r["held_revs"]
        floor = math.degrees(res.angle_noise_floor) * POLE_PAIRS
        resonance = band_rms(x, R, 45.0, 85.0)
        slow = band_rms(x, R, 0.0, 13.0)
        l100 = band_rms(x, R, 99.4, 100.6)
        l200 = band_rms(x, R, 199.4, 200.6)
        white = band_rms(x, R, 150.0, np.inf)
        print(
            f"{i:4d} {res.noise_std:14.1f} {floor:6.2f} {r['star']:7.2f} {resonance:11.2f}"
            f" {slow:9.2f} {l100:9.2f} {l200:9.2f} {white:10.2f}"
        )
        # sensor noise: about 8 counts, 0.1 electrical degrees, several times below f_star
        assert 5.0 < res.noise_std < 12.0
        assert floor < 0.15
        assert r["star"] > 3.0 * floor
        # the fit's residual is motion along the curve, not noise across it
        assert res.motion_rms > 3.0 * res.angle_noise_floor
        # the spectrum above 150 cycles/revolution is at the noise level
        assert white < 1.5 * floor
        # the stepper's microstep lines are there, in every file
        assert 0.04 < l100 < 0.2 and 0.03 < l200 < 0.15
    # the resonance band dominates where the rig rings most (file 1)
    x1 = np.degrees(results[1]["r_star"]) * POLE_PAIRS
    assert band_rms(x1, results[1]["held_revs"], 45.0, 85.0) > 0.7 * results[1]["star"]


def test_ringjig_through_the_pipeline(results):
    """The same calibration from a setup file's point of view (sample_time = 1: time in samples)."""
    from hallcal import pipeline

    r = results[2]
    start, mid, stop = r["split"]
    setup = setup_from_dict(
        {
            "pole_pairs": POLE_PAIRS,
            "sample_time": 1.0,
            "trajectory": {"kind": "constant-speed", "start": start, "stop": mid},
        }
    )
    cal = pipeline.calibrate(load_dataset(FILES[1]), setup)
    # The rig's own motion is 4-16x the noise floor here: the held-out check (fit/held_out.py)
    # predicts the table's error against the straight line at 0.92 deg_el (8.9x the floor), so
    # "ok" (at the floor) cannot be claimed. The prediction is conservative, not low: the table
    # measured on the held-out revolutions after the segment is 0.40 deg_el; within 3x of it.
    assert cal.status == "warning", cal.messages
    # the warning says why (the held-out prediction above the floor), and what it includes
    assert cal.messages[0].code == MessageCode.ABOVE_NOISE_FLOOR, cal.messages
    assert "held-out revolutions" in cal.messages[1].text
    predicted = math.degrees(cal.predicted_error) * POLE_PAIRS
    assert r["star"] <= 1.5 * predicted <= 3.0 * 1.5 * r["star"], (predicted, r["star"])
    y_star = cal.lut.f_star(r["d"])
    np.testing.assert_allclose(y_star, r["res"].lut.f_star(r["d"]), atol=1e-9)
    art = cal.to_artifact()
    geo = art["diagnostics"]["constant_speed"]["geometry"]
    np.testing.assert_allclose(np.diff(geo["phases_deg"]), [101.0, 160.0], atol=2.0)


def test_ringjig_prediction_follows_the_motion_of_the_revolutions_it_calibrates_on(results):
    """Why the held-out prediction is about 2x the check on captures 1 and 2 (1.20 against
    0.57 mrad on capture 1): not a bias of the predictor but the jig's motion, which is not
    stationary. The prediction's held-out part is the rotor's departure from the straight line
    on the calibration revolutions (capture 1: 78 % of the predicted mean square; the rest the
    tables' absorbed motion, the floor 0.3 %), and the ring rings most in its first two
    revolutions (the fit's motion off the line 1.03 mrad there, 0.57 on the last two).
    Calibrating on the last two revolutions instead, the same predictor is optimistic about the
    first ones: the ratio swaps sides of 1, and their geometric mean is 0.83 (measured: 0.48
    and 1.44; over five two-revolution windows of each capture, 0.44-3.09, geometric mean 0.89).
    """
    r = results[1]
    d, seg = r["d"], r["seg"]
    per = int(round(TWO_PI / abs(seg.speed)))  # samples per revolution
    harmonics = default_harmonics(POLE_PAIRS)
    ratios, motion = [], []
    for lo, hi in ((seg.start, seg.start + 2 * per), (seg.stop - 2 * per, seg.stop)):
        res = calibrate_constant_speed(d, POLE_PAIRS, FourierBasis(harmonics), start=lo, stop=hi)
        held = held_out_error(d, POLE_PAIRS, harmonics, start=lo, stop=hi, speed=res.b)
        y = res.lut.f_star(d)
        checked = np.concatenate(
            [line_residual(y[a:b], np.arange(a, b)) for a, b in ((seg.start, lo), (hi, seg.stop))
             if b - a > per // 2]
        )  # fmt: skip
        ratios.append(float(np.sqrt(np.mean(checked**2))) / held.predicted(res))
        motion.append(res.motion_rms)
    # the calm half is the one checked first, the ringing one second (1.03 against 0.57 mrad)
    assert motion[0] > 1.5 * motion[1], motion
    # 0.48 and 1.44 measured; the margins leave room for BLAS rounding in 150-column fits, far
    # below the jig's own effect
    assert ratios[0] < 0.6 and ratios[1] > 1.2, ratios
    assert 0.67 <= math.sqrt(ratios[0] * ratios[1]) <= 1.5, ratios


def test_ringjig_power_up_pole_pair(results):
    """Power-up identification on measured data (sensor/absolute.py).

    Per file: the decoder of the calibration (first two revolutions; noise across the curve
    from the same samples), then 50 random starts in the held-out revolutions, each a fresh
    power-up: f_init from y = 0 at the start, 60 samples (a little more than one electrical
    cycle of 52 samples at this speed). The pole pair it identifies must equal the one that
    continuous tracking from the start of the file gives (the calibration's frame) for >= 95 %
    of the starts (the figure measured before); all of them lock within the 60 samples here.

    Every held-out start is also run through the same test: wrong locks stay below 0.2 % of
    the starts (alpha = 0.1 %, doubled because overlapping windows share the rig's vibration
    bursts, so wrong locks come in clusters).
    """
    from hallcal.sensor import absolute as ab

    n = POLE_PAIRS
    print()
    print("file  status        sigma  white  grid  agree  locked  lock[samples] med/max  wrong/all")
    for i, r in results.items():
        res, d = r["res"], r["d"]
        start, mid, stop = r["split"]
        noise = ab.estimate_normal_noise(res.model, res.lut, d, start=start, stop=mid)
        dec = ab.build_decoder(res.model, res.lut, noise_std=noise.total_std)
        rep = ab.assess_identifiability(
            dec, calibration_samples=mid - start, basis_size=res.model.basis.size, noise=noise
        )
        assert rep.status.success, rep.message
        y_cont = res.lut.f_init(d)  # continuous tracking from the start of the file
        rng = np.random.default_rng(1000 + i)
        W = 60
        agree = locked = 0
        lock_at = []
        for s in rng.integers(mid, stop - W, 50):
            window = d[s : s + W]
            ident = dec.identify(window)
            y0 = res.lut.f_init(window[:1])[0]
            expected = int(np.round((y_cont[s] - y0) * n / (2 * math.pi))) % n
            agree += ident.offset == expected
            if ident.status is ab.PowerUpStatus.IDENTIFIED:
                locked += 1
                lock_at.append(ident.lock_sample)
        # every start: in the continuous frame the right offset is 0 for all of them
        costs = dec.sample_costs(d)
        wrong = total = 0
        for s in range(mid, stop - W):
            lam = np.cumsum(costs[s : s + W], axis=0)
            lam -= lam.min(axis=1, keepdims=True)
            hit = np.flatnonzero(np.sum(np.exp(-0.5 * lam), axis=1) - 1.0 <= dec.lock_threshold)
            total += 1
            if hit.size:
                wrong += int(np.argmin(lam[hit[0]])) != 0
        print(
            f"{i:4d}  {rep.status.value:12s} {noise.total_std:6.1f} {noise.white_std:6.1f}"
            f" {dec.grid:5d} {agree:4d}/50 {locked:5d}/50  {np.median(lock_at):6.0f}/"
            f"{max(lock_at):<6d} {wrong:4d}/{total}"
        )
        assert agree >= 48, i  # >= 95 % of 50
        assert locked == 50, i
        assert wrong <= 0.002 * total, i


def test_ringjig_remounted_ring_is_refused(results):
    """Power-up on a capture the calibration was not made on (the ring remounted: whole pole
    pitches and a once-per-revolution eccentricity of about +-10 electrical degrees apart; the
    signals no longer match the model): for each ordered pair of different captures, 60 random
    starts of 1000 samples in the constant-speed part. Without the misfit test the sequential
    test locked, claiming posterior >= 0.999, on 9-40 of the 60 per pair (printed as "old
    rule"); now none locks, every one is refused ("mismatch", the best pole pair's cost 4-5
    times the calibrated noise's), and so is the whole recording (plain ``reconstruct``)."""
    from hallcal.sensor import absolute as ab
    from hallcal.sensor.misfit import MisfitStatus, model_misfit

    W = 1000
    decoders = {}
    for i, r in results.items():
        start, mid, _ = r["split"]
        res = r["res"]
        decoders[i], _ = ab.analyze_calibration(
            res.model, res.lut, r["d"], start=start, stop=mid, basis_size=res.model.basis.size
        )
    print()
    print("cal  data  old rule: locked  now: identified  mismatch  samples to refuse med/max")
    for ci, dec in decoders.items():
        for di, r in results.items():
            if ci == di:
                continue
            d = r["d"]
            start, _, stop = r["split"]
            old, locked, refused, at = remount_trials(
                dec, d, start, stop, window=W, seed=100 * ci + di
            )
            print(f"{ci:3d} {di:5d} {old:12d}/60 {locked:10d}/60 {refused:8d}/60"
                  f" {np.median(at):10.0f}/{max(at)}")  # fmt: skip
            assert locked == 0, (ci, di)  # 0 of 60 confidently wrong
            assert refused == 60, (ci, di)  # each one says so
            assert model_misfit(dec, d[start:stop]).status is MisfitStatus.MISMATCH
    # the same capture: every start in the held-out revolutions, 200 samples each (the
    # calibration's decoder locks at standstill only after the goodness-of-fit gate's 96
    # samples, sensor/absolute.py step 7): the rig's vibration bursts make a few false
    # "mismatch" (measured 0, 10 and 0 of about 2840 per file, overlapping starts in the same
    # bursts: 0.35 % at most, the misfit test's, the gate adds none; bound 0.5 %); the rest lock
    W = 200
    print("file  every start: false mismatch  locked  undecided")
    for i, dec in decoders.items():
        d = results[i]["d"]
        _, mid, stop = results[i]["split"]
        counts = {s: 0 for s in ab.PowerUpStatus}
        for s in range(mid, stop - W):
            counts[dec.identify(d[s : s + W]).status] += 1
        total = stop - W - mid
        mism, ok = counts[ab.PowerUpStatus.MISMATCH], counts[ab.PowerUpStatus.IDENTIFIED]
        print(f"{i:4d} {mism:20d}/{total} {ok:7d} {counts[ab.PowerUpStatus.UNDECIDED]:9d}")
        assert counts[ab.PowerUpStatus.MISMATCH] <= 0.005 * total, i
        assert counts[ab.PowerUpStatus.IDENTIFIED] >= 0.99 * total, i
