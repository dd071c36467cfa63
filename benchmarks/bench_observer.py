"""The model-based observer: the figures behind tests/test_observer.py, full size.

Every case runs the observer of :mod:`hallcal.sensor.observer` on a model identified by the
usual calibration (not the bench's truth), except where said.

1. Paper bench (11 pole pairs, harmonics 1..11, the 26 s ramp 0 -> 13 rad), calibrated cold.
   - healthy validation runs: y_obs and y_star against the noise floor, the misfit, the states;
   - warm validation (the same motor 60 K warmer: NdFeB remanence -7.2 %, per-sensor
     sensitivities +1.0/-0.8/+0.4 %, offsets +1.0/-1.0/+0.5 % of A): y_obs after 2 s against
     the warm floor, the static table beside it;
   - failed channel mid-run (stuck at its zero-field level, at a rail, clipped at 75 % of its
     peak, disconnected = NaN): 40 trials each at random channels and instants: samples from
     the first sample off by 5 % of the amplitude to the exclusion, slips (error above half a
     pole pitch), y_obs before (against the three-sensor floor) and after;
   - changed mount: the ring one pole pitch off (the neighbouring magnet's signature), a
     once-per-revolution warp of +-10 electrical degrees common to the three sensors, and
     both: travel until the state is ``stale``.
2. False alarms: healthy runs of the paper bench (3 magnet sets) and of zoo-like benches (4 and
   7 pole pairs, rich shapes, 8 kHz), truth models: alarm events (leaving ``ok``) per hour of
   run, against the design bound (false_alarm 1e-9 per sample).
3. A folding map (4 pole pairs, shape variation 0.25, seed 1): calibrated, the table refused,
   y_obs against the floor and the ML angle's own per-sample bound.
4. Real ring-jig captures (tests/data/ring-jig, 25 pole pairs, three captures of one ring,
   remounted between them): model from capture 1 (constant-speed calibration on its first two
   revolutions), the observer on each capture: misfit, travel until ``stale``.
5. Cost: Python seconds per sample; table bytes of a float C port.

Run: ``python benchmarks/bench_observer.py``; output committed beside it (bench_observer.txt).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path

import numpy as np

import hallcal
from hallcal._constants import TWO_PI
from hallcal.fit.constant_speed import (
    calibrate_constant_speed,
    default_harmonics,
    find_constant_speed,
)
from hallcal.io import Setup
from hallcal.io.setup import ModelSpec
from hallcal.pipeline.observe import calibrated_noise, observer_for
from hallcal.sensor.flux import FourierBasis
from hallcal.sensor.metrics import angle_error
from hallcal.sensor.observer import observer_model, run_observer
from hallcal.sim.bench import BenchConfig, simulate_run

WARM = {"amplitude": 0.928, "gain_mismatch": (0.01, -0.008, 0.004),
        "offset": (0.01, -0.01, 0.005)}  # fmt: skip


def ramp(cfg: BenchConfig, end: float, seconds: float, seed: int):
    n = int(round(seconds / cfg.sample_time))
    return simulate_run(cfg, end * np.arange(n) / n, seed=seed)


def setup_for(cfg: BenchConfig, harmonics) -> Setup:
    return Setup(
        pole_pairs=cfg.pole_pairs,
        sample_time=cfg.sample_time,
        controller=cfg.controller,
        plant=cfg.plant,
        model=ModelSpec(harmonics=tuple(harmonics)),
    )


def states(run) -> str:
    names, counts = np.unique(run.state, return_counts=True)
    return ", ".join(f"{n} {c / len(run):.1%}" for n, c in zip(names, counts, strict=True))


def paper_bench():
    print("1. paper bench (11 pole pairs), calibrated cold on the 26 s ramp, harmonics 1..11")
    cfg = BenchConfig(seed=0)
    cal_run = ramp(cfg, 13.0, 26.0, seed=1)
    t0 = time.perf_counter()
    cal = hallcal.calibrate(cal_run.columns(), setup_for(cfg, range(1, 12)))
    print(f"   calibration {time.perf_counter() - t0:.1f} s, status {cal.status}")
    model = observer_for(cal)
    inj = model.injectivity
    print(f"   table {model.points} points/rev; curve separation {inj.separation:.0f} sigma "
          f"(margin {inj.margin:.0f}); ML per-sample bound {inj.rms_std / cfg.noise_floor:.3f}"
          "x the floor")  # fmt: skip
    floor = cfg.noise_floor
    print("   healthy validation runs (0 -> 10 rad in 20 s):")
    for seed in (21, 22, 23):
        val = ramp(cfg, 10.0, 20.0, seed)
        t0 = time.perf_counter()
        obs = run_observer(model, val.d)
        dt = time.perf_counter() - t0
        e_obs = angle_error(obs.y_obs, val.y0).rms / floor
        e_star = angle_error(cal.lut.f_star(val.d), val.y0).rms / floor
        print(f"     seed {seed}: y_obs {e_obs:.3f}x floor, y_star {e_star:.3f}x; misfit mean "
              f"{np.mean(obs.misfit[512:]):.3f}, max {np.max(obs.misfit[512:]):.3f} "
              f"(threshold {obs.threshold:.3f}); {states(obs)}; "
              f"{1e6 * dt / len(obs):.2f} us/sample")  # fmt: skip

    warm = dataclasses.replace(cfg, **WARM)
    wfloor = warm.noise_floor
    two_s = int(round(2.0 / cfg.sample_time))
    print("   warm validation (60 K: remanence -7.2 %, sensitivities +1.0/-0.8/+0.4 %, offsets "
          "+1.0/-1.0/+0.5 % of A), after 2 s:")  # fmt: skip
    for seed in (31, 32, 33):
        val = ramp(warm, 10.0, 20.0, seed)
        obs = run_observer(model, val.d)
        e_obs = angle_error(obs.y_obs[two_s:], val.y0[two_s:]).rms / wfloor
        e_star = angle_error(cal.lut.f_star(val.d)[two_s:], val.y0[two_s:]).rms / wfloor
        e_1s = angle_error(obs.y_obs[two_s // 2 : two_s], val.y0[two_s // 2 : two_s]).rms
        settle = int(np.flatnonzero(obs.state != "ok")[-1]) + 1 if np.any(obs.state != "ok") else 0
        print(f"     seed {seed}: y_obs {e_obs:.3f}x warm floor (1-2 s: {e_1s / wfloor:.2f}x), "
              f"static table y_star {e_star:.3f}x; state ok from {settle * cfg.sample_time:.2f} s; "
              f"gains {np.round(obs.gain, 4).tolist()}, offsets "
              f"{np.round(obs.offset, 4).tolist()}")  # fmt: skip

    print("   one channel failing mid-run (40 trials per kind; delay from the first sample off by "
          "5 % of A):")  # fmt: skip
    val = ramp(cfg, 10.0, 20.0, 41)
    rng = np.random.default_rng(7)
    for kind in ("zero-field", "rail", "clipped 75 %", "disconnected"):
        delays, slips, wrong, before, after = [], 0, 0, [], []
        for _ in range(40):
            k0 = int(rng.integers(8000, 70000))
            ch = int(rng.integers(3))
            d = val.d.copy()
            if kind == "zero-field":
                d[k0:, ch] = model.center[ch]
            elif kind == "rail":
                d[k0:, ch] = model.center[ch] + 1.5 * math.sqrt(2) * model.amplitude[ch]
            elif kind == "clipped 75 %":
                peak = model.center[ch] + 0.75 * math.sqrt(2) * model.amplitude[ch]
                low = model.center[ch] - 0.75 * math.sqrt(2) * model.amplitude[ch]
                d[k0:, ch] = np.clip(d[k0:, ch], low, peak)
            else:
                d[k0:, ch] = np.nan
            obs = run_observer(model, d)
            off = ~(np.abs(d[:, ch] - val.d[:, ch]) < 0.05 * math.sqrt(2) * model.amplitude[ch])
            first_bad = int(np.flatnonzero(off[k0:])[0]) + k0
            if obs.excluded != ch:
                wrong += 1
                continue
            delays.append(obs.first_exclusion - first_bad)
            err = obs.y_obs - val.y0
            slips += int(np.max(np.abs(err)) > math.pi / cfg.pole_pairs)
            before.append(angle_error(obs.y_obs[:k0], val.y0[:k0]).rms / floor)
            a = obs.first_exclusion + 1
            after.append(angle_error(obs.y_obs[a:], val.y0[a:]).rms / floor)
        dl = np.array(delays)
        print(f"     {kind:13s}: excluded the right channel {40 - wrong}/40, delay median "
              f"{np.median(dl):.0f}, max {np.max(dl)} samples; slips {slips}; y_obs before "
              f"{np.max(before):.3f}x (worst), after median {np.median(after):.3f}x, worst "
              f"{np.max(after):.3f}x the three-sensor floor")  # fmt: skip

    print("   changed mount (validation run 0 -> 10 rad; travel until 'stale'):")
    pitch = TWO_PI / cfg.pole_pairs
    truth = cfg.truth()
    sig = math.sqrt(cfg.noise_variance)
    y0 = val.y0
    noise = sig * np.random.default_rng(9).standard_normal((y0.size, 3))
    warp = math.radians(10.0) / cfg.pole_pairs * np.sin(y0 + 0.7)
    cases = {
        "one pole pitch off": y0 + pitch,
        "+-10 deg_el warp, common": y0 + warp,
        "pitch off + warp": y0 + pitch + warp,
    }
    for name, seen in cases.items():
        d = truth(seen) + noise
        obs = run_observer(model, d)
        stale = np.flatnonzero(obs.state == "stale")
        when = f"{(y0[stale[0]] - y0[0]) / TWO_PI:.2f} rev" if stale.size else "never"
        print(f"     {name:26s}: misfit median {np.median(obs.misfit[512:]):.2f}; stale after "
              f"{when}; {states(obs)}")  # fmt: skip
    return model


def _hour_of_motion(model, cfg: BenchConfig, seed: int) -> tuple[int, float]:
    """Alarm events (samples leaving 'ok' after the first window of each chunk) in one hour of
    noisy Hall signals of the model's truth at a varying speed (0.5-3.5 rad/s, changing
    direction never), in chunks of 2^21 samples (the observer restarted on each)."""
    truth = cfg.truth()
    rng = np.random.default_rng(seed)
    n_total = int(round(3600.0 / cfg.sample_time))
    chunk = 1 << 21
    events = 0
    y = 0.0
    for start in range(0, n_total, chunk):
        n = min(chunk, n_total - start)
        t = (start + np.arange(n)) * cfg.sample_time
        speed = 2.0 + 1.5 * np.sin(TWO_PI * t / 37.0)
        y0 = y + np.cumsum(speed) * cfg.sample_time
        y = float(y0[-1])
        y0 = y0 - y0[0]
        d = truth(y0) + math.sqrt(cfg.noise_variance) * rng.standard_normal((n, 3))
        obs = run_observer(model, d)
        ok = obs.state[512:] == "ok"
        events += int(np.sum(ok[:-1] & ~ok[1:]) + (0 if ok[0] else 1))
    return events, 1.0


def false_alarms(paper_model) -> None:
    print("2. false alarms: one hour of healthy signals per case (noise of the bench, speed "
          "0.5-3.5 rad/s); alarm = a sample leaving 'ok'")  # fmt: skip
    cases = [
        ("paper bench, calibrated model", BenchConfig(seed=0), paper_model),
    ]
    for cfg in (
        BenchConfig(seed=1),
        BenchConfig(pole_pairs=4, shape_variation=0.05, seed=3),
        BenchConfig(
            pole_pairs=7,
            shape_variation=0.05,
            electrical_harmonics=((3, 0.08),),
            sample_time=1.25e-4,
            seed=4,
        ),  # fmt: skip
    ):
        name = f"n_m {cfg.pole_pairs}, {1 / cfg.sample_time / 1000:.0f} kHz, truth model"
        cases.append((name, cfg, observer_model(cfg.truth(), cfg.pole_pairs,
                                                cfg.noise_variance)))  # fmt: skip
    total, hours = 0, 0.0
    for name, cfg, model in cases:
        t0 = time.perf_counter()
        ev, h = _hour_of_motion(model, cfg, 101)
        total += ev
        hours += h
        print(f"   {name:34s}: {ev} alarm events in 1 h ({time.perf_counter() - t0:.0f} s)")
    upper = f"{3.0 / hours:.2g}" if total == 0 else "-"
    print(f"   total {total} in {hours:.0f} h (95 % upper bound {upper} per hour when none); "
          "design: false_alarm 1e-9 per sample bounds the window's alarms by 0.014 per hour "
          "at 4 kHz (union bound)")  # fmt: skip


def folding() -> None:
    print("3. folding map (4 pole pairs, shape variation 0.25, harmonics 1..20)")
    cfg = BenchConfig(pole_pairs=4, shape_variation=0.25, seed=1)
    truth_model = observer_model(cfg.truth(), 4, cfg.noise_variance)
    bound = truth_model.injectivity.rms_std
    print(
        f"   ML per-sample bound {bound / cfg.noise_floor:.3f}x the floor (the curve's speed "
        "varies where Clarke's angle folds)"
    )
    for seconds in (6.5, 13.0):
        cal_run = ramp(cfg, 13.0, seconds, seed=1)
        cal = hallcal.calibrate(cal_run.columns(), setup_for(cfg, range(1, 21)))
        print(f"   calibrated on 13 rad in {seconds:g} s: status {cal.status}, table min slope "
              f"{cal.lut.min_slope:.3f}, observer only {cal.observer_only}, predicted table "
              f"error {cal.predicted_error / cfg.noise_floor:.2f}x the floor")  # fmt: skip
        model = observer_for(cal)
        for seed in (61, 62, 63):
            val = ramp(cfg, 10.0, 10.0, seed)
            obs = run_observer(model, val.d)
            e = angle_error(obs.y_obs, val.y0).rms
            et = angle_error(run_observer(truth_model, val.d).y_obs, val.y0).rms
            print(f"     seed {seed}: y_obs {e / cfg.noise_floor:.3f}x the floor (with the "
                  f"true model {et / cfg.noise_floor:.3f}x); {states(obs)}")  # fmt: skip


def ring_jig() -> None:
    print("4. real ring-jig captures (25 pole pairs), model from capture 1's first 2 revolutions")
    root = Path(__file__).resolve().parents[1] / "tests" / "data" / "ring-jig"
    files = [root / f"hall_calibration_one_rotation_{i}.txt" for i in (1, 2, 3)]
    data = [np.loadtxt(f, dtype=np.int64).astype(np.float64) for f in files]
    n = 25
    seg = find_constant_speed(data[0], n)
    start, mid, stop = seg.split(2.0)
    res = calibrate_constant_speed(data[0], n, FourierBasis(default_harmonics(n)), start=start,
                                   stop=mid)  # fmt: skip
    # the level the monitor measures against: the calibration segment's own orthogonal residual
    # (the model-free noise, 7.9 counts, misses the model's error: misfit 5 on held-out data)
    var = calibrated_noise(res.model, n, data[0], res.noise_std**2, start=start, stop=mid)
    model = observer_model(res.model, n, var)
    samples_per_rev = TWO_PI / abs(res.b)
    print(
        f"   noise {res.noise_std:.1f} counts (model-free), monitor level "
        f"{math.sqrt(var[0]):.1f} counts per channel; curve separation "
        f"{model.injectivity.separation:.0f} sigma; {samples_per_rev:.0f} samples/rev"
    )
    for i, d in enumerate(data, start=1):
        obs = run_observer(model, d)
        stale = np.flatnonzero(obs.state == "stale")
        when = f"{(stale[0] - 110) / samples_per_rev:.2f} rev of motion" if stale.size else "never"
        part = obs.misfit[mid:stop] if i == 1 else obs.misfit[600:]
        print(
            f"   capture {i}: misfit median {np.median(part):.2f} "
            f"{'(held-out revolutions)' if i == 1 else ''}; stale after {when}; {states(obs)}"
        )


def cost() -> None:
    print("5. cost")
    cfg = BenchConfig(seed=0)
    model = observer_model(cfg.truth(), 11, cfg.noise_variance)
    val = ramp(cfg, 10.0, 20.0, 71)
    run_observer(model, val.d[:100])
    t0 = time.perf_counter()
    for _ in range(3):
        run_observer(model, val.d)
    dt = (time.perf_counter() - t0) / (3 * val.n_samples)
    print(f"   Python (numba): {1e6 * dt:.2f} us per sample (healthy run, shared 2-core machine)")
    print(
        f"   float C table: {model.points} intervals x 3 channels x 4 cubic coefficients x 4 "
        f"bytes = {model.points * 3 * 4 * 4} bytes (11 pole pairs, harmonics up to 44; "
        "bench_observer_c.txt)"
    )
    print(f"   (run at load average {os.getloadavg()[0]:.1f} on 2 shared cores: the timings "
          "above depend on it, the figures do not)")  # fmt: skip


if __name__ == "__main__":
    paper_model = paper_bench()
    false_alarms(paper_model)
    folding()
    ring_jig()
    cost()
