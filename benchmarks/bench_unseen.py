"""Motors the zoo does not contain: is the verdict honest where nobody tuned it?

``bench_zoo.py`` draws its motors from one family (pole pairs 2..28 from a fixed list, 2-16 kHz,
sensors within 3 degrees and 5 %, noise 0.1-1 %, ramps of 1.5-3 revolutions in closed loop).
This script draws cases from other families, with seeds of its own (``[seed, 4242]``), and
scores them the same way: errors RMS about zero (the table's offset included) over the ORACLE
floor of a fresh validation run (:mod:`hallcal.sim.oracle`). Families (``seed`` cycles):

- ``lowpp``: 1-2 pole pairs, 2-40 kHz;
- ``highpp``: 12, 13, 16-20 pole pairs (numbers the zoo never draws);
- ``spacing``: sensor spacing errors of 5-15 degrees each;
- ``gains``: per-sensor gains +-10-20 % and offsets +-5-15 %;
- ``harm357``: a strongly distorted magnet: 3rd/5th/7th electrical harmonics of 8-20/4-10/2-5 %;
- ``noisy``: Hall noise 1-3 % of the amplitude;
- ``adc10``: a 10- or 11-bit ADC over +-1.3 with analog noise of 0.2-0.6 codes;
- ``short``: 1.02-1.3 revolutions (calibration needs one whole revolution: below, exit 2);
- ``slow``: a ramp of 0.08-0.2 rad/s at 2 kHz, 1.05-1.3 revolutions (the zoo's slowest is
  0.3 rad/s; the loop's integral action hides more of the error the slower the ramp);
- ``open``: an open-loop spin at constant speed (``trajectory.kind = "constant-speed"``;
  the spin fixes no frame, so errors are RMS about the mean, for the floor too), 2.5-4
  revolutions, 20-200 samples per electrical period, 10-12 bit ADC, 3rd/5th/7th electrical
  harmonics up to 15/8/4 % and magnet shapes of their own (content up to 3-7 n_m);
- ``blaload``: the plant from a BLA experiment (no ``[plant]``) with a constant load torque and a
  random low-frequency torque in the loop.

Common to all: a plant ``K e^{-s tau} / (s (s + a) (s / p + 1))``, the zoo's lead-lag PI
(:func:`hallcal.sim.bench.position_controller`), per-magnet variation, noise 0.2-1 % unless the
family says otherwise, and a calibration run of at most ``N_MAX`` samples. Calibration uses
what a user writes: the true loop and the defaults (``harmonics = "auto"``, ``cogging =
"auto"``). ``--repeat`` calibrates the first cases twice and checks the results are identical
(everything must count work, not seconds).

Columns as bench_zoo's: ``star/fl``, ``init/fl``, ``pred/fl``, ``act/pred``, ``off/fl`` (the
table's mean error / floor), ``sec`` (wall clock under the load printed), the model chosen.

``--powerup 202 213 ...``: after calibrating those cases, 40 closed-loop power-ups (half at rest,
half at two electrical revolutions per second, 600 samples) with the sensors as calibrated and
after one sensor's gain or offset, or all gains, changed: identified right, identified WRONG (a
lock claiming certainty on data that no longer match), mismatch (refused), undecided.

Found (``bench_unseen.txt``): the constant-speed route predicted the noise floor whatever its basis
missed, so spins of magnets with strong 5th/7th harmonics were "ok" at 11x (case 210) and 45x (221)
the floor; now :mod:`hallcal.fit.held_out` predicts from a held-out revolution and chooses the band
(210: ok at 1.03x, predicted 0.99x; 221: warning at 22x, predicted 22x). A random low-frequency
load torque with the plant from a BLA (``blaload`` 222) left a table at 670x the floor (f_init 17x)
as a "warning" predicted 124x. Cause, measured: the torque is motion the model lacks (SEM cost
2.15x the noise level, flux shape 1.1x); the SEM turns the rotor's departure from the plant model's
motion into a slow warp of the flux (sidebands 11 and 13 of the 12 pole pairs at 0.5-0.6 of the
fundamental: about 1.4 rad electrical of phase modulation once per revolution), in the directions
the run determines worst (the covariance's table error: 77 % its offset, 51 % harmonics 9, 11, 13),
and the covariance, which assumes the model explains the data up to noise, cannot see a bias. Not
the BLA: with the true plant the table is 460x (refused for a missing harmonic, predicted 444x
now); without the random torque (constant load only) 222 is a warning at 3.7x predicted 4.9x (cost
1.01x the noise level: no motion bias). Not the SEM's iteration limit (its remaining Gauss-Newton
step moves the table by 16x only) nor a longer correlation (batch means with 2-8 times longer
batches: 99-121x); a refit on the first 75 % of the run gives the same table (619x), so a held-out
check passes it. The batch-means variance over the white one ("colour": 254 on 222, 403 on 211, 280
on 233, 0.05-5.1 on the zoo and 13 other closed-loop cases) also separated them, but refused good
tables with a BLA and a random torque. What does: of the model's 624x correction, 618x lies in
directions of the table whose own standard deviation exceeds a quarter of the floor; with the cost
above its warning level :func:`hallcal.fit.adequacy.motion_bias` counts that part in the predicted
error: 222 is refused at 631x predicted (actual/predicted 1.06), 211 stays refused (532x predicted
for 576x), 233 too (22.9x for 16.6x); the paper's bench with a BLA and random torques of 0.01 and
0.03 is predicted 6.8x and 15.5x for tables at 6.4x and 14.2x (2.4x and 6.5x before; the first
stays a warning, its table 2x better than f_init). Case 226 (``gains``, 6 pole pairs) stays a
warning at 3.55x with 2.19x predicted (actual/predicted 1.62, the only one outside the band): its
fit explains the data (cost 1.003x the noise level: no motion bias) and its error is mostly the
table's constant offset (-1.95x the floor), one direction along which one run scatters far; the 95
% quantile of one run that the verdict also uses is 3.56x. Not fixed: the power-up lock after a
sensor change on motors whose magnets differ by a few per cent (202, 213: 20 and 16 pole pairs,
noise 0.9 %): a common gain of 0.97 (25 K of NdFeB remanence) locked on the WRONG pole pair in
24/40 and 20/40 power-ups, one sensor's gain 0.95-1.10 or offset +0.05 in 9-20/40: at one position
a gain change and another magnet look alike, the changed signals fit the wrong hypothesis (cost
0.6-2.2 per degree of freedom), so the misfit test (kappa = 8) passes them (218, 6 pole pairs,
10-bit ADC: 0-2/40; 227, 19 pole pairs: 1-4/40).

Run: ``nice python benchmarks/bench_unseen.py [--seeds 201 202 ...] [--jobs 2] [--out
benchmarks/bench_unseen.txt]``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_bla import _multisine  # noqa: E402
from bench_support import run_rows  # noqa: E402

from hallcal import pipeline  # noqa: E402
from hallcal._constants import TWO_PI  # noqa: E402
from hallcal.errors import HallcalError  # noqa: E402
from hallcal.io import Dataset, ModelSpec, Setup  # noqa: E402
from hallcal.io.setup import BLASpec, TrajectorySpec  # noqa: E402
from hallcal.sensor.metrics import angle_error  # noqa: E402
from hallcal.sim.bench import BenchConfig, position_controller, simulate_run  # noqa: E402
from hallcal.sim.lti import ContinuousTF  # noqa: E402
from hallcal.sim.oracle import oracle_table  # noqa: E402

FAMILIES = ("lowpp", "highpp", "spacing", "gains", "harm357", "noisy", "adc10", "short", "slow",
            "open", "blaload")  # fmt: skip
#: Calibration runs hold at most this many samples (a shared 2-core machine).
N_MAX = 60_000
CALIBRATED = (0.67, 1.5)
FIRST_SEED = 201


def draw_case(seed: int) -> dict:
    """One unseen case: the bench, the run's length and speed, the family."""
    fam = FAMILIES[(seed - FIRST_SEED) % len(FAMILIES)]
    rng = np.random.default_rng([seed, 4242])
    if fam == "lowpp":
        n = int(rng.choice([1, 2]))
    elif fam == "highpp":
        n = int(rng.choice([12, 13, 16, 17, 18, 19, 20]))
    else:
        n = int(rng.choice([1, 2, 6, 9, 12, 13, 16, 17, 19, 21]))
    fs = float(np.exp(rng.uniform(np.log(2000.0), np.log(40000.0))))
    if fam == "blaload":
        fs = float(rng.uniform(2000.0, 5000.0))  # one-second multisine periods stay small
    fs = round(fs / 100.0) * 100.0
    ts = 1.0 / fs
    a = float(np.exp(rng.uniform(np.log(2.0), np.log(120.0))))
    p = float(np.exp(rng.uniform(np.log(300.0), np.log(5000.0))))
    delay = float(rng.uniform(0.0, 2.0)) * ts
    K = float(np.exp(rng.uniform(np.log(50.0), np.log(2e4))))
    plant = ContinuousTF((K * p,), tuple(np.polymul([1.0, a, 0.0], [1.0, p])), delay)
    fc = min(fs / float(rng.uniform(120.0, 700.0)), 60.0)
    controller = position_controller(plant, ts, fc)
    sigma = float(np.exp(rng.uniform(np.log(2e-3), np.log(1e-2))))
    cfg = BenchConfig(
        pole_pairs=n, sample_time=ts, plant=plant, controller=controller,
        noise_variance=sigma**2, magnet_variation=float(rng.uniform(0.005, 0.05)),
        misalignment_deg=tuple(rng.uniform(-2.0, 2.0, 3)),
        gain_mismatch=tuple(rng.uniform(-0.03, 0.03, 3)),
        offset=tuple(rng.uniform(-0.03, 0.03, 3)),
        electrical_harmonics=((3, float(rng.uniform(0.0, 0.05))),),
        seed=seed,
    )  # fmt: skip
    revolutions = float(rng.uniform(1.5, 3.0))
    if fam == "spacing":
        cfg = replace(cfg, misalignment_deg=tuple(rng.choice([-1, 1], 3) * rng.uniform(5, 15, 3)))
    elif fam == "gains":
        cfg = replace(
            cfg,
            gain_mismatch=tuple(rng.choice([-1, 1], 3) * rng.uniform(0.1, 0.2, 3)),
            offset=tuple(rng.choice([-1, 1], 3) * rng.uniform(0.05, 0.15, 3)),
        )
    elif fam == "harm357":
        cfg = replace(cfg, electrical_harmonics=(
            (3, float(rng.uniform(0.08, 0.2))), (5, float(rng.uniform(0.04, 0.1))),
            (7, float(rng.uniform(0.02, 0.05)))))  # fmt: skip
    elif fam == "noisy":
        cfg = replace(cfg, noise_variance=float(rng.uniform(0.01, 0.03)) ** 2)
    elif fam in ("adc10", "open"):
        bits = int(rng.choice([10, 11] if fam == "adc10" else [10, 11, 12]))
        code = 2.6 / (2**bits - 1)
        cfg = replace(cfg, adc_low=(-1.3,) * 3, adc_high=(1.3,) * 3, adc_bits=bits,
                      noise_variance=float(rng.uniform(0.2, 0.6) * code) ** 2)  # fmt: skip
        if fam == "open":  # a ring's magnets: strong odd harmonics, shapes of their own
            cfg = replace(cfg, electrical_harmonics=(
                (3, float(rng.uniform(0.0, 0.15))), (5, float(rng.uniform(0.0, 0.08))),
                (7, float(rng.uniform(0.0, 0.04)))), shape_variation=float(rng.uniform(0, 0.02)),
                shape_harmonics=int(rng.integers(3, 8)))  # fmt: skip
    elif fam == "short":
        revolutions = float(rng.uniform(1.02, 1.3))
    elif fam == "blaload":
        u_ramp = 1.0 * a / K  # torque a 1 rad/s ramp needs against the mechanical pole
        cfg = replace(cfg, cogging_terms=((0, float(rng.uniform(0.3, 2.0)) * u_ramp, 0.0),),
                      torque_disturbance=float(rng.uniform(0.0, 0.3)) * u_ramp)  # fmt: skip
    speed = max(0.3, revolutions * TWO_PI * fs / N_MAX)  # rad/s: at most N_MAX samples
    speed = min(speed, fc)
    if fam == "slow":  # 0.08-0.2 rad/s (the zoo: >= 0.3), at most 2.5 N_MAX samples
        revolutions = float(rng.uniform(1.05, 1.3))
        cfg = replace(
            cfg,
            sample_time=1.0 / 2000.0,
            controller=position_controller(plant, 1.0 / 2000.0, min(fc, 2000.0 / 150)),
        )
        speed = max(float(rng.uniform(0.08, 0.2)), revolutions * TWO_PI * 2000.0 / (2.5 * N_MAX))
    end = revolutions * TWO_PI
    duration = end / speed
    spc = float(rng.uniform(20.0, 200.0))  # open: samples per electrical period
    return {"cfg": cfg, "end": end, "duration": duration, "fam": fam, "rev": revolutions,
            "spc": spc, "phase": float(rng.uniform(0, TWO_PI))}  # fmt: skip


def _setup(cfg: BenchConfig, **kw) -> Setup:
    return Setup(pole_pairs=cfg.pole_pairs, sample_time=cfg.sample_time,
                 controller=cfg.controller, plant=cfg.plant,
                 model=ModelSpec(harmonics="auto"), **kw)  # fmt: skip


def _ramp(cfg: BenchConfig, end: float, duration: float, seed: int):
    n = int(round(duration / cfg.sample_time))
    return simulate_run(cfg, end * np.arange(n) / n, seed=seed)


def _spin(cfg: BenchConfig, revolutions: float, spc: float, phase: float, seed: int):
    """An open-loop spin at constant speed: y0 = phase + b k, the sensors' static map, the ADC
    and noise; returns (d, y0)."""
    n = cfg.pole_pairs
    b = TWO_PI / (n * spc)
    N = int(round(revolutions * TWO_PI / b))
    y0 = phase + b * np.arange(N)
    rng = np.random.default_rng([seed, 7])
    d = cfg.truth()(y0) + math.sqrt(cfg.noise_variance) * rng.standard_normal((N, 3))
    lo, hi = np.asarray(cfg.adc_low), np.asarray(cfg.adc_high)
    step = (hi - lo) / (2.0 ** int(cfg.adc_bits) - 1.0)
    d = lo + step * np.round((np.clip(d, lo, hi) - lo) / step)
    return d, y0


def _row(case: dict, seed: int) -> dict:
    cfg = case["cfg"]
    return {"seed": seed, "fam": case["fam"], "n_m": cfg.pole_pairs,
            "fs": int(round(1 / cfg.sample_time)), "N": 0, "status": "diverged",
            "init": math.nan, "star": math.nan, "pred": math.nan, "off": math.nan,
            "sec": math.nan, "model": "", "fp": ""}  # fmt: skip


def _fingerprint(cal) -> str:
    """Hash of what a user gets (status, prediction, table): the same input must give it again."""
    import hashlib

    h = hashlib.sha256(str(cal.status).encode())
    h.update(np.float64(cal.predicted_error).tobytes())
    h.update(np.ascontiguousarray(cal.lut.eta).tobytes())
    return h.hexdigest()[:10]


def _model(cal) -> str:
    h = cal.model_info.get("harmonics", [])
    s = f"{len(h)}h<={max(h) if h else 0}"
    if cal.cogging is not None:
        s += " cog " + "+".join(str(k) for k in cal.cogging.orders)
    return s


def run_open(seed: int, case: dict) -> dict:
    cfg, row = case["cfg"], _row(case, seed)
    n = cfg.pole_pairs
    d, _ = _spin(cfg, 1.0 + case["rev"], case["spc"], case["phase"], seed)
    row["N"] = d.shape[0]
    setup = Setup(pole_pairs=n, sample_time=1.0, controller=None,
                  model=ModelSpec(harmonics="auto"),
                  trajectory=TrajectorySpec(kind="constant-speed"))  # fmt: skip
    t0 = time.perf_counter()
    cal = pipeline.calibrate(Dataset.from_columns({f"d{h + 1}": d[:, h] for h in range(3)}), setup)
    row["sec"] = time.perf_counter() - t0
    row["status"], row["model"], row["fp"] = str(cal.status), _model(cal), _fingerprint(cal)
    # the spin fixes no frame but f_init's pole pair at the first sample: validate from the same
    # power-up position (module doc of hallcal.fit.constant_speed, "Gauge")
    dv, y0v = _spin(cfg, 1.0, case["spc"], case["phase"], seed + 10_000)
    # the oracle in the truth's frame (its f_init starts at the true angle), about the mean
    floor = angle_error(oracle_table(cfg).f_star(dv, y_initial=case["phase"]), y0v).rms
    row["init"] = angle_error(cal.lut.f_init(dv), y0v).rms / floor
    if cal.lut.bijective:
        row["star"] = angle_error(cal.lut.f_star(dv), y0v).rms / floor
        row["off"] = 0.0
    row["pred"] = cal.predicted_error / floor
    return row


def run_closed(seed: int, case: dict) -> dict:
    cfg, row = case["cfg"], _row(case, seed)
    cal_run = _ramp(cfg, case["end"], case["duration"], seed)
    row["N"] = cal_run.n_samples
    if cal_run.status != "ok":
        return row
    kw = {}
    setup = _setup(cfg)
    if case["fam"] == "blaload":
        fs = 1.0 / cfg.sample_time
        spec = BLASpec(period_samples=int(round(fs)), periods=3, transient_periods=1,
                       band=(1.0, min(400.0, fs / 8)))  # fmt: skip
        setup = replace(_setup(cfg, bla=spec), plant=None)
        kw["bla_dataset"] = Dataset.from_columns(_multisine(cfg, spec, seed + 500).columns())
    t0 = time.perf_counter()
    cal = pipeline.calibrate(Dataset.from_columns(cal_run.columns()), setup, **kw)
    row["sec"] = time.perf_counter() - t0
    row["status"], row["model"], row["fp"] = str(cal.status), _model(cal), _fingerprint(cal)
    val = _ramp(cfg, 0.8 * case["end"], 0.8 * case["duration"], seed + 10_000)
    table = oracle_table(cfg)
    floor = (angle_error(table.f_star(val.d), val.y0).rms_raw if table.bijective
             else cfg.noise_floor)  # fmt: skip
    row["init"] = angle_error(cal.lut.f_init(val.d), val.y0).rms_raw / floor
    if cal.lut.bijective:
        e = angle_error(cal.lut.f_star(val.d), val.y0)
        row["star"], row["off"] = e.rms_raw / floor, e.mean / floor
    row["pred"] = cal.predicted_error / floor
    return row


#: Sensor changes after calibration for the power-up audit: (name, gains, offsets added).
CHANGES = (("healthy", (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)),
           ("d2 gain x1.10", (1.0, 1.1, 1.0), (0.0, 0.0, 0.0)),
           ("d1 gain x0.95", (0.95, 1.0, 1.0), (0.0, 0.0, 0.0)),
           ("d3 offset +0.05", (1.0, 1.0, 1.0), (0.0, 0.0, 0.05)),
           ("all gains x0.97", (0.97, 0.97, 0.97), (0.0, 0.0, 0.0)))  # fmt: skip


def run_powerup(seed: int, trials: int = 40) -> list[str]:
    """Power-ups on a calibrated unseen motor: healthy, and after a sensor's gain or offset
    changed (the table no longer matches). Counts: identified right / identified WRONG (a lock
    claiming certainty on the wrong pole pair) / mismatch (refused) / undecided, at rest (half)
    and at 2 electrical revolutions per second (half), 600 samples each."""
    case = draw_case(seed)
    cfg = case["cfg"]
    run = _ramp(cfg, case["end"], case["duration"], seed)
    cal = pipeline.calibrate(Dataset.from_columns(run.columns()), _setup(cfg))
    rep = cal.identifiability
    head = (f"{seed:4d} {case['fam']:>8} n_m {cfg.pole_pairs:2d} calibration {cal.status}, "
            f"power-up {rep.status if rep is not None else '-'}")  # fmt: skip
    if rep is None or not rep.status.success:
        return [head + ": no decoder"]
    dec = rep.decoder(cal.flux, cal.lut)
    out = [head]
    for name, gains, offs in CHANGES:
        counts = powerup_counts(cfg, dec, seed, gains, offs, trials)
        out.append(f"     {name:16s} " + "  ".join(f"{k} {v:2d}" for k, v in counts.items()))
    return out


def powerup_counts(cfg, dec, seed: int, gains, offs, trials: int = 40) -> dict[str, int]:
    """Power-ups after the sensor change (gains, offsets): half at rest, half at two electrical
    revolutions per second, 600 samples each: right / WRONG (a claimed lock on the wrong pole
    pair) / mismatch (refused) / undecided."""
    from hallcal.sensor import absolute as ab
    from hallcal.sim.bench import power_up_run

    n = cfg.pole_pairs
    rng = np.random.default_rng([seed, 99])
    counts = {"right": 0, "WRONG": 0, "mismatch": 0, "undecided": 0}
    for i in range(trials):
        speed = 0.0 if i % 2 else 2.0 * TWO_PI / n
        pu = power_up_run(cfg, float(rng.uniform(0, TWO_PI)), samples=600, speed=speed,
                          seed=seed * 1000 + i)  # fmt: skip
        j = int(np.round((pu.y0[0] - pu.y[0]) * n / TWO_PI)) % n
        ident = dec.identify(pu.d * np.asarray(gains) + np.asarray(offs))
        if ident.status is ab.PowerUpStatus.IDENTIFIED:
            counts["right" if ident.offset == j else "WRONG"] += 1
        elif ident.status is ab.PowerUpStatus.MISMATCH:
            counts["mismatch"] += 1
        else:
            counts["undecided"] += 1
    return counts


def run_case(seed: int) -> dict:
    case = draw_case(seed)
    try:
        return run_open(seed, case) if case["fam"] == "open" else run_closed(seed, case)
    except HallcalError as exc:  # a bad input for the tool (exit 2): named, not scored
        row = _row(case, seed)
        row["status"], row["model"] = "input", str(exc)[:60]
        return row


def _line(r: dict) -> str:
    return (
        f"{r['seed']:4d} {r['fam']:>8} {r['n_m']:3d} {r['fs']:6d} {r['N']:7d} {r['status']:>11} "
        f"{r['star']:8.3f} {r['init']:8.2f} {r['pred']:8.3f} {r['star'] / r['pred']:8.2f} "
        f"{r['off']:6.2f} {r['sec']:6.1f}  {r['model']}"
    )


def summary(rows: list[dict]) -> list[str]:
    used = [r for r in rows if r["status"] in ("ok", "warning") and np.isfinite(r["star"])]
    ratio = np.array([r["star"] / r["pred"] for r in used])
    ok = [r for r in used if r["status"] == "ok"]
    bad_ok = [r["seed"] for r in ok if r["star"] > 1.15]
    off = [r["seed"] for r in used if not CALIBRATED[0] <= r["star"] / r["pred"] <= CALIBRATED[1]]
    return [
        "",
        f"{len(rows)} cases: {len(ok)} ok, {len(used) - len(ok)} warning, "
        f"{len(rows) - len(used)} refused or failed",
        f"actual/predicted within [{CALIBRATED[0]}, {CALIBRATED[1]}] on "
        f"{int(np.sum((ratio >= CALIBRATED[0]) & (ratio <= CALIBRATED[1])))} of {len(used)}"
        + (f" (min {ratio.min():.2f}, max {ratio.max():.2f}); outside: {off}" if used else ""),
        f"ok above 1.15x the floor: {len(bad_ok)} {bad_ok}; ok above 1.3x: "
        f"{sum(r['star'] > 1.3 for r in ok)}; f_star worse than f_init: "
        f"{sum(r['star'] > r['init'] for r in used)}",
    ]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=33)
    ap.add_argument("--seeds", type=int, nargs="*", default=None)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=0, help="calibrate the first K cases twice")
    ap.add_argument("--out", default=None)
    ap.add_argument(
        "--powerup",
        type=int,
        nargs="*",
        default=[],
        help="power-up audit on these cases (closed-loop families)",
    )
    args = ap.parse_args()
    seeds = args.seeds or list(range(FIRST_SEED, FIRST_SEED + args.cases))
    lines = [
        "bench_unseen: cases unlike the zoo's, calibrated with the defaults; errors RMS about zero "
        "(open: about the mean) over the ORACLE floor of a fresh run",
        f"load average at start {os.getloadavg()[0]:.1f} (2 cores)",
        "",
        f"{'seed':>4} {'family':>8} {'n_m':>3} {'fs':>6} {'N':>7} {'status':>11} {'star/fl':>8} "
        f"{'init/fl':>8} {'pred/fl':>8} {'act/pred':>8} {'off/fl':>6} {'sec':>6}  model",
    ]
    print("\n".join(lines), flush=True)
    rows = run_rows(run_case, seeds, args.jobs, _line, lines)
    tail = summary(rows)
    for r in rows[: args.repeat]:
        again = run_case(r["seed"])
        tail.append(f"repeat seed {r['seed']}: {r['fp']} then {again['fp']} "
                    f"({'identical' if again['fp'] == r['fp'] else 'DIFFERENT'})")  # fmt: skip
    if args.powerup:
        tail += [
            "",
            f"power-up after calibration ({len(CHANGES)} sensor states, 40 power-ups "
            "each: identified right / identified WRONG / mismatch (refused) / undecided)",
        ]
        for seed in args.powerup:
            tail += run_powerup(seed)
            print("\n".join(tail[-len(CHANGES) - 1 :]), flush=True)
    tail.append(f"load average at end {os.getloadavg()[0]:.1f}")
    print("\n".join(tail))
    if args.out:
        Path(args.out).write_text("\n".join(lines + tail) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
