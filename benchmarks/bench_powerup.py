"""Absolute angle at power-up: the full-size figures behind tests/test_absolute.py.

1. Paper bench (11 pole pairs, default magnet variation 0.04; magnet sets seed 0, 1, 2),
   calibrated as usual (front door, known plant, the 26 s ramp). 500 closed-loop power-ups at
   random rotor angles per case:
   - at rest, 200 samples: the pole pair chosen (locked, or maximum likelihood after 200);
   - moving at 0.5 rad/s (the calibration ramp's speed) and at 5 rad/s for exactly one
     electrical revolution: right means the sequential test locked within it, on the right
     pole pair;
   - f_star after the lock on the 0.5 rad/s runs (pooled RMS against the true angle, modulo
     one revolution) against the noise floor.
2. Weak bench (7 pole pairs, magnet variation 0.01): the identifiability analysis's predicted
   standstill error rate against the observed one (2000 power-ups), the stated posterior
   against the observed error frequency (binned), and the sequential test's wrong locks. Its
   lock breaks under a plausible sensor drift, so calibrate gives it the common-gain profile
   and a lock after one electrical revolution of motion: at rest that lock never comes, so the
   same decoder locking at once is also shown (the sequential test's own error rate).
3. Ring-jig recordings (25 pole pairs, open loop): 50 random starts in the held-out
   revolutions per file, and every start (wrong locks, false "mismatch"), 200 samples each
   (60 before the goodness-of-fit gate at the lock: the gated lock comes after 96).
4. The ring remounted: the calibration of one capture, 60 random power-ups of 1000 samples on
   each other capture (every ordered pair): locked (confidently wrong) by the lock rule alone,
   and now (identified / refused as "mismatch").
5. Changed sensors on the paper bench (its true flux as the model): one sensor's gain or all
   three off by a little (temperature, a replaced sensor), 100 power-ups each: the lock rule
   alone against the lock with the misfit test (refused, locked right, locked wrong).
6. Ideal sensors (no magnet variation): the verdict and the refusal.

Every healthy power-up is also counted for a false "mismatch" (the misfit test,
hallcal.sensor.misfit: no pole pair fits).

Run: ``python benchmarks/bench_powerup.py``; output committed beside it (bench_powerup.txt).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from motor_support import remount_trials  # noqa: E402

import hallcal  # noqa: E402
from hallcal._constants import TWO_PI  # noqa: E402
from hallcal.errors import CalibrationRefused  # noqa: E402
from hallcal.io import Dataset, default_setup  # noqa: E402
from hallcal.pipeline import simulate  # noqa: E402
from hallcal.sensor import absolute as ab  # noqa: E402
from hallcal.sensor.misfit import model_misfit  # noqa: E402
from hallcal.sim.bench import BenchConfig  # noqa: E402
from hallcal.sim.loop import simulate_loop  # noqa: E402


def wrap(x):
    return np.mod(x + math.pi, TWO_PI) - math.pi


class PowerUps:
    """Closed-loop power-ups on one bench motor (truth and loop built once)."""

    def __init__(self, cfg: BenchConfig) -> None:
        self.cfg = cfg
        self.truth = cfg.truth()
        self.loop = cfg.loop()
        self.n = cfg.pole_pairs
        self.sigma = math.sqrt(cfg.noise_variance)

    def run(self, angle: float, samples: int, speed: float, seed: int):
        g = self.truth(np.array([angle]))[0] - self.loop.offset
        a, b = self.loop.projection @ g
        y_start = wrap(np.array([math.atan2(b, a)]))[0] / self.n
        r = y_start + speed * self.cfg.sample_time * np.arange(samples)
        noise = self.sigma * np.random.default_rng([seed, 1]).standard_normal((samples, 3))
        res = simulate_loop(self.loop, self.truth, r, noise=noise, initial_angle=angle)
        assert res.status == "ok"
        j = int(np.round((res.y0[0] - res.y[0]) * self.n / TWO_PI)) % self.n
        return res, j


def calibrate_bench(setup):
    run = simulate(setup)
    ds = Dataset.from_columns(run.columns(with_encoder=False))
    t0 = time.perf_counter()
    cal = hallcal.calibrate(ds, setup)
    return cal, time.perf_counter() - t0


def paper_bench(seed: int) -> None:
    s = default_setup()
    setup = dataclasses.replace(s, bench=dataclasses.replace(s.bench, seed=seed))
    cal, took = calibrate_bench(setup)
    rep = cal.identifiability
    dec = rep.decoder(cal.flux, cal.lut)
    cfg = BenchConfig(seed=seed)
    pu = PowerUps(cfg)
    floor = cfg.noise_floor
    print(f"\n-- paper bench, magnet set seed {seed} (calibration {took:.1f} s, {cal.status}) --")
    print(f"   {rep.message}")
    print(
        f"   sigma {rep.noise_std:.3e} (bench {pu.sigma:.3e}), table {dec.grid} x {dec.pole_pairs}"
        f" points (interpolation error {dec.interpolation_error:.3f} sigma), predicted standstill"
        f" error at 200 samples {rep.standstill_error_rate:.2e}"
    )
    rng = np.random.default_rng(100 + seed)
    angles = rng.uniform(0.0, TWO_PI, 500)
    # at rest, 200 samples
    right = locked = wrong_lock = mismatch = 0
    lock_at = []
    for i, a in enumerate(angles):
        res, j = pu.run(a, 200, 0.0, seed=10_000 * seed + i)
        ident = dec.identify(res.d)
        right += ident.offset == j
        mismatch += ident.status is ab.PowerUpStatus.MISMATCH
        if ident.status is ab.PowerUpStatus.IDENTIFIED:
            locked += 1
            wrong_lock += ident.offset != j
            lock_at.append(ident.lock_sample + 1)
    print(
        f"   standstill, 200 samples: right {right}/500 ({100 * right / 500:.1f}%), locked "
        f"{locked}/500 (wrong locks {wrong_lock}, false mismatch {mismatch}), samples to lock "
        f"median {np.median(lock_at):.0f}, 99th percentile {np.percentile(lock_at, 99):.0f}, "
        f"max {max(lock_at)}"
    )
    # moving, one electrical revolution
    for speed in (0.5, 5.0):
        rev = int(round(TWO_PI / cfg.pole_pairs / (speed * cfg.sample_time)))
        ok = ml_ok = mismatch = 0
        lock_at = []
        err2, count, per_run = 0.0, 0, []
        for i, a in enumerate(angles):
            res, j = pu.run(a, rev, speed, seed=10_000 * seed + 1000 + i)
            out = ab.absolute_reconstruction(dec, cal.lut, res.d)
            ident = out.identification
            ok += ident.status is ab.PowerUpStatus.IDENTIFIED and ident.offset == j
            mismatch += ident.status is ab.PowerUpStatus.MISMATCH
            ml_ok += int(dec.identify(res.d, lock=False).offset == j)
            if ident.lock_sample is not None:
                lock_at.append(ident.lock_sample + 1)
                if speed == 0.5 and ident.offset == j:
                    e = wrap(out.y_star - res.y0)[ident.lock_sample + 1 :]
                    err2 += float(np.sum(e * e))
                    count += e.size
                    per_run.append(float(np.std(e)))
        print(
            f"   moving {speed:3.1f} rad/s ({rev} samples per electrical revolution): locked on "
            f"the right pole pair within one electrical revolution {ok}/500 "
            f"({100 * ok / 500:.1f}%), ML at its end right {ml_ok}/500, false mismatch "
            f"{mismatch}; samples to lock median {np.median(lock_at):.0f}, max {max(lock_at)}"
        )
        if speed == 0.5:
            rms = math.sqrt(err2 / count)
            print(
                f"   f_star after the lock (0.5 rad/s runs, {count} samples): RMS "
                f"{rms * 1e3:.4f} mrad = {rms / floor:.3f} x floor ({floor * 1e3:.4f} mrad); "
                f"per run about its mean: median {np.median(per_run) / floor:.3f} x floor"
            )


def weak_bench() -> None:
    s = default_setup()
    setup = dataclasses.replace(
        s,
        pole_pairs=7,
        model=dataclasses.replace(s.model, harmonics=tuple(range(1, 8))),
        bench=dataclasses.replace(s.bench, seed=0, magnet_variation=0.01),
    )
    cal, took = calibrate_bench(setup)
    rep = cal.identifiability
    dec = rep.decoder(cal.flux, cal.lut)
    cfg = BenchConfig(pole_pairs=7, magnet_variation=0.01, seed=0)
    pu = PowerUps(cfg)
    print(f"\n-- weak bench: 7 pole pairs, magnet variation 0.01 (calibration {took:.1f} s) --")
    print(f"   {rep.message}")
    Ks = np.array([1, 3, 10, 30, 100, 200])
    pred = ab.standstill_error_rate(dec, Ks)
    rng = np.random.default_rng(7)
    T = 2000
    wrong = np.zeros(Ks.size)
    stated, miss = [], []
    for i in range(T):
        res, j = pu.run(rng.uniform(0.0, TWO_PI), int(Ks[-1]), 0.0, seed=50_000 + i)
        lam = dec.cumulative_costs(res.d)
        for k, K in enumerate(Ks):
            lk = lam[K - 1] - lam[K - 1].min()
            best = int(np.argmin(lk))
            wrong[k] += best != j
            stated.append(1.0 - 1.0 / float(np.sum(np.exp(-0.5 * lk))))
            miss.append(best != j)
    print("   standstill error rate, predicted (analysis) vs observed (2000 power-ups at rest):")
    print("      K   predicted   observed   (+-2 binomial sd)")
    for K, p, w in zip(Ks, pred, wrong / T, strict=True):
        sd = math.sqrt(max(p * (1 - p), 1e-12) / T)
        print(f"   {K:4d}   {p:9.4f}   {w:8.4f}   ({2 * sd:.4f})")
    stated, miss = np.array(stated), np.array(miss, dtype=float)
    print("   stated error probability (1 - posterior) vs observed, all K pooled:")
    edges = [0.0, 1e-4, 1e-3, 1e-2, 0.05, 0.2, 0.5, 1.0]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (stated >= lo) & (stated < hi)
        if m.sum():
            print(
                f"   [{lo:g}, {hi:g}): {m.sum():5d} decisions, stated {stated[m].mean():.4f}, "
                f"observed {miss[m].mean():.4f}"
            )
    # sequential test at rest, long budget (a lock that waits for motion: also the same decoder
    # locking at once, the sequential test's own error rate)
    runs = [pu.run(rng.uniform(0.0, TWO_PI), 4000, 0.0, seed=90_000 + i) for i in range(1000)]
    decoders = [("", dec)]
    if dec.lock_travel > 0.0:
        decoders.append((" (the same, locking at once)", dataclasses.replace(dec, lock_travel=0.0)))
    for name, dd in decoders:
        wrong_lock = undecided = mismatch = 0
        lock_at = []
        for res, j in runs:
            ident = dd.identify(res.d)
            if ident.status is ab.PowerUpStatus.IDENTIFIED:
                wrong_lock += ident.offset != j
                lock_at.append(ident.lock_sample + 1)
            elif ident.status is ab.PowerUpStatus.MISMATCH:
                mismatch += 1
            else:
                undecided += 1
        when = (f"samples to lock median {np.median(lock_at):.0f}, 99th percentile "
                f"{np.percentile(lock_at, 99):.0f}" if lock_at else "no lock")  # fmt: skip
        print(
            f"   sequential test at rest{name} (alpha = {dd.error_target:g}), 1000 power-ups, up "
            f"to 4000 samples: wrong locks {wrong_lock}, undecided {undecided}, false mismatch "
            f"{mismatch}, {when}; analysis: {100 * rep.standstill_fraction_ok:.1f}% of positions "
            f"within 200, worst {rep.standstill_samples_worst:.0f}"
        )


def ring_jig() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_real_ringjig import CAL_REVOLUTIONS, FILES, POLE_PAIRS, load_dataset

    from hallcal.fit.constant_speed import (
        calibrate_constant_speed,
        default_harmonics,
        find_constant_speed,
    )
    from hallcal.sensor.flux import FourierBasis

    if not all(f.exists() for f in FILES):
        print("\n-- ring-jig: recordings not available --")
        return
    n = POLE_PAIRS
    print("\n-- ring-jig recordings (25 pole pairs; calibration on 2 revolutions) --")
    print(
        "   file  verdict       sigma(total/white)  grid  50 starts: agree  locked  lock median/max"
        "  every start: wrong locks  false mismatch"
    )
    captures = {}
    for i, path in enumerate(FILES, start=1):
        d = load_dataset(path).d
        seg = find_constant_speed(d, n)
        start, mid, stop = seg.split(CAL_REVOLUTIONS)
        basis = FourierBasis(default_harmonics(n))
        res = calibrate_constant_speed(d, n, basis, start=start, stop=mid)
        dec, rep = ab.analyze_calibration(
            res.model, res.lut, d, start=start, stop=mid, basis_size=basis.size
        )
        y_cont = res.lut.f_init(d)
        rng = np.random.default_rng(1000 + i)
        W = 200  # > K0 = 96: the gate decides within the window
        agree = locked = 0
        lock_at = []
        for s in rng.integers(mid, stop - W, 50):
            ident = dec.identify(d[s : s + W])
            y0 = res.lut.f_init(d[s : s + 1])[0]
            agree += ident.offset == int(np.round((y_cont[s] - y0) * n / TWO_PI)) % n
            if ident.lock_sample is not None:
                locked += 1
                lock_at.append(ident.lock_sample + 1)
        wrong = mismatch = total = 0
        for s in range(mid, stop - W):  # every start, a fresh power-up each
            ident = dec.identify(d[s : s + W])
            expected = int(np.round((y_cont[s] - res.lut.f_init(d[s : s + 1])[0]) * n / TWO_PI))
            total += 1
            wrong += ident.status is ab.PowerUpStatus.IDENTIFIED and ident.offset != expected % n
            mismatch += ident.status is ab.PowerUpStatus.MISMATCH
        when = f"{np.median(lock_at):6.0f}/{max(lock_at):<4d}" if lock_at else "     -/-   "
        print(
            f"   {i:4d}  {rep.status.value:12s} {rep.noise.total_std:7.1f} / "
            f"{rep.noise.white_std:4.1f}      {dec.grid:4d}  {agree:9d}/50 {locked:5d}/50"
            f"  {when}  {wrong:10d}/{total}"
            f"  {mismatch:8d}/{total} ({100 * mismatch / total:.2f}%)"
        )
        print(f"         {rep.message}")
        captures[i] = (d, seg, dec)
    remounted(captures)


def remounted(captures) -> None:
    """Item 4 of the module doc: the calibration of one capture, power-ups on another."""
    W = 1000
    print(
        "\n-- ring-jig remounted: calibration of capture c, 60 power-ups of 1000 samples at "
        "random starts in capture d's constant-speed part --"
    )
    print(
        "   c  d   lock rule alone: locked (posterior >= 0.999)   now: identified  mismatch"
        "  samples to refuse median/max  whole recording"
    )
    total_old = total_locked = 0
    for ci, (_, _, dec) in captures.items():
        for di, (d, seg, _) in captures.items():
            if ci == di:
                continue
            old, locked, refused, at = remount_trials(
                dec, d, seg.start, seg.stop, window=W, seed=100 * ci + di
            )
            whole = model_misfit(dec, d[seg.start : seg.stop])
            total_old += old
            total_locked += locked
            print(
                f"   {ci}  {di}  {old:27d}/60  {locked:20d}/60 {refused:6d}/60"
                f"  {np.median(at):17.0f}/{max(at):<4d}       {whole.status.value} after "
                f"{whole.samples} (cost {whole.cost_per_dof:.2f} x noise)"
            )
    print(
        f"   all pairs: the lock rule alone locked {total_old}/360 (posterior >= 0.999 on signals "
        f"that do not match the calibration); now {total_locked}/360"
    )


def changed_sensors() -> None:
    """Item 5 of the module doc."""
    from hallcal.sensor.lut import build_lut

    cfg = BenchConfig()
    truth, loop = cfg.truth(), cfg.loop()
    lut = build_lut(truth, 11, projection=loop.projection, offset=loop.offset)
    dec = ab.build_decoder(truth, lut, noise_std=math.sqrt(cfg.noise_variance))
    pu = PowerUps(cfg)
    print(
        "\n-- changed sensors, paper bench (exact model; 100 power-ups of 1000 samples, half at "
        "rest, half at 2 rad/s) --"
    )
    print("   change          lock rule alone: locked  wrong    now: refused  locked right  wrong")
    cases = [("d3 gain x 1.05", [1, 1, 1.05]), ("d3 gain x 1.02", [1, 1, 1.02]),
             ("all x 0.998", [0.998] * 3), ("all x 0.995", [0.995] * 3),
             ("all x 0.98", [0.98] * 3)]  # fmt: skip
    for name, gains in cases:
        rng = np.random.default_rng(31)
        old = old_wrong = refused = right = wrong = 0
        for i in range(100):
            res, j = pu.run(rng.uniform(0.0, TWO_PI), 1000, 0.0 if i % 2 else 2.0, seed=700 + i)
            d = res.d * np.asarray(gains)
            lam = np.cumsum(dec.sample_costs(d), axis=0)
            lam -= lam.min(axis=1, keepdims=True)
            hit = np.flatnonzero(np.sum(np.exp(-0.5 * lam), axis=1) - 1.0 <= dec.lock_threshold)
            if hit.size:
                old += 1
                old_wrong += int(np.argmin(lam[hit[0]])) != j
            ident = dec.identify(d)
            refused += ident.status is ab.PowerUpStatus.MISMATCH
            if ident.status is ab.PowerUpStatus.IDENTIFIED:
                right += ident.offset == j
                wrong += ident.offset != j
        print(
            f"   {name:16s} {old:20d}/100 {old_wrong:6d}   {refused:12d}/100 {right:13d} {wrong:6d}"
        )


def ideal_sensors() -> None:
    s = default_setup()
    setup = dataclasses.replace(s, bench=dataclasses.replace(s.bench, magnet_variation=0.0))
    cal, took = calibrate_bench(setup)
    rep = cal.identifiability
    print(f"\n-- ideal sensors, no magnet variation (calibration {took:.1f} s, {cal.status}) --")
    print(f"   {rep.message}")
    print(
        f"   revolution separation {rep.revolution_separation_worst:.4f} sigma, model floor "
        f"{rep.model_floor:.4f} sigma (fit noise alone)"
    )
    run = simulate(setup, seed=5)
    try:
        cal.reconstruct(Dataset.from_columns(run.columns()), absolute=True)
        print("   reconstruct(absolute=True): ran (unexpected)")
    except CalibrationRefused as exc:
        print(f"   reconstruct(absolute=True) refuses: {exc}")


def main() -> None:
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())} (2 cores, shared)")
    t0 = time.perf_counter()
    for seed in (0, 1, 2):
        paper_bench(seed)
    weak_bench()
    ring_jig()
    changed_sensors()
    ideal_sensors()
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
