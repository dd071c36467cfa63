"""The power-up lock's drift margin (hallcal.sensor.drift_margin) against measured wrong locks.

For each case: calibrate (the unseen motors 202, 213, 218, 227 of ``bench_unseen.py``, its
generator and ramp; the paper bench, magnet sets 0, 1, 2, as ``bench_powerup.py``), print the
drift margin the artifact stores (common gain, one sensor's gain, one sensor's offset; the worst
wrong-lock share within +-5 %) and whether ``calibrate`` notes it, then for sensor changes
after calibration the predicted wrong-lock share (share of positions where the noise-free
changed signals let a wrong pole pair win the lock and pass the misfit test) against the
measured outcome of 40 closed-loop power-ups per change (``bench_unseen.py --powerup``'s
procedure: half at rest, half at two electrical revolutions per second, 600 samples): right /
WRONG (a lock claiming certainty on the wrong pole pair) / mismatch (refused) / undecided.

Where calibrate kept the decoder with the common-gain profile and the lock after one electrical
revolution of motion (its lock without them breaks at a plausible drift), the decoder before
("no profile") is measured on the same power-ups, and 20 more power-ups turning 1.5 electrical
revolutions show the lock that waits for motion against the profile locking at once; the
samples to each right lock are given (median/max).

Where calibrate kept the plain decoder (the lock at standstill), the same decoder without the
goodness-of-fit gate at the lock ("no gate": alpha_g = 0, K0 = 0, the decoder before it,
:data:`hallcal.sensor.absolute.DEFAULT_GATE_SAMPLES`) is measured on the same power-ups: its
WRONG locks are the ones the gate is for (a sensor change beyond the calibration that looks
like another magnet). Where calibrate also kept the gate's bias half (the winner's residual
mean, ``gate_bias_dispersion``; :mod:`hallcal.sensor._absolute_gate`), the gate without it
("gate alone": its chi-square half at alpha_g, the decoder before the bias half) is measured
on the same power-ups too.

Last, the false alarm on healthy motors: more unseen motors whose calibration keeps the
standstill lock, 80 healthy power-ups each (half at rest), the gate alone against the kept
decoder; among them five with a 10-11-bit ADC and 0.23-0.32 codes of analog noise (174, 185,
240, 207, 210), whose quantizer rounds a standstill's samples to the same codes: calibrate
gives them the lock after one electrical revolution of motion (reason ``quantizer``). For
those, the standstill decoder it replaces ("before": gate, phi from the calibration
recording) against the kept one at rest, moving (bench_unseen's 600 samples at two electrical
revolutions per second), turning 1.5 electrical revolutions, and resting 5000 samples before
turning (the rounding error of the rest in the evidence), and the standstill decoder on
400 healthy power-ups at rest of K0 samples (its false "mismatch" against the nominal 1e-4).

The prediction is a standstill figure (the moving half sees many positions, where a wrong
hypothesis must win on average); it is meant to rank motors, not to be the rate.

Run: ``nice python benchmarks/bench_powerup_margin.py``; output committed beside it
(bench_powerup_margin.txt).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_unseen as bu  # noqa: E402

from hallcal import pipeline  # noqa: E402
from hallcal._constants import TWO_PI  # noqa: E402
from hallcal.io import Dataset, default_setup  # noqa: E402
from hallcal.messages import MessageCode  # noqa: E402
from hallcal.sensor import absolute as ab  # noqa: E402
from hallcal.sensor.drift_margin import _amplitudes, _table_signals, wrong_lock_share  # noqa: E402
from hallcal.sim.bench import BenchConfig  # noqa: E402

#: Changes after calibration: bench_unseen's audit set and a few more common gains (gains
#: multiply d as in the audit; offsets added in the signal's unit).
CHANGES = (*bu.CHANGES,
           ("all gains x0.995", (0.995,) * 3, (0.0,) * 3),
           ("all gains x0.99", (0.99,) * 3, (0.0,) * 3),
           ("all gains x1.03", (1.03,) * 3, (0.0,) * 3),
           ("all gains x0.95", (0.95,) * 3, (0.0,) * 3),
           ("all gains x1.05", (1.05,) * 3, (0.0,) * 3),
           ("d1 gain x0.99", (0.99, 1.0, 1.0), (0.0,) * 3),
           ("d3 offset +0.01", (1.0,) * 3, (0.0, 0.0, 0.01)))  # fmt: skip


def unseen(seed: int):
    case = bu.draw_case(seed)
    cfg = case["cfg"]
    run = bu._ramp(cfg, case["end"], case["duration"], seed)
    cal = pipeline.calibrate(Dataset.from_columns(run.columns()), bu._setup(cfg))
    return f"{seed} {case['fam']} n_m {cfg.pole_pairs}", cfg, cal


def paper(seed: int):
    s = default_setup()
    setup = dataclasses.replace(s, bench=dataclasses.replace(s.bench, seed=seed))
    run = pipeline.simulate(setup)
    cal = pipeline.calibrate(Dataset.from_columns(run.columns(with_encoder=False)), setup)
    return f"paper bench seed {seed} n_m 11", BenchConfig(seed=seed), cal


def predicted(dec, gains, offs) -> float:
    """wrong_lock_share for ``d g + delta`` (the audit's change), rewritten about f_init's
    offsets o: ``o + g (d - o) + ((g - 1) o + delta)``, offsets in channel amplitudes."""
    g = np.asarray(gains, dtype=np.float64)
    amp = _amplitudes(_table_signals(dec), dec.offset)
    extra = ((g - 1.0) * dec.offset + np.asarray(offs, dtype=np.float64)) / amp
    return wrong_lock_share(dec, g, extra)


def power_ups(cfg, seed: int, trials: int = 40, *, turning: bool = False):
    """bench_unseen's power-ups (``powerup_counts``: same seeds, half at rest, half at two
    electrical revolutions per second, 600 samples), simulated once per case: (d, true j).
    ``turning``: instead, all at ten electrical revolutions per second for 1.5 electrical
    revolutions (a lock that waits for one electrical revolution of motion can come)."""
    from hallcal.sim.bench import power_up_run

    n = cfg.pole_pairs
    rng = np.random.default_rng([seed, 99])
    samples = int(1.5 / (10.0 * cfg.sample_time)) if turning else 600
    out = []
    for i in range(trials):
        speed = 10.0 * TWO_PI / n if turning else (0.0 if i % 2 else 2.0 * TWO_PI / n)
        pu = power_up_run(cfg, float(rng.uniform(0, TWO_PI)), samples=samples, speed=speed,
                          seed=seed * 1000 + i)  # fmt: skip
        out.append((pu.d, int(np.round((pu.y0[0] - pu.y[0]) * n / TWO_PI)) % n))
    return out


def measured(runs, dec, gains, offs) -> tuple[dict[str, int], list[int]]:
    """bench_unseen's count for one change (``d * gains + offs``): right / WRONG / mismatch /
    undecided, and the samples to each right lock."""
    counts = {"right": 0, "WRONG": 0, "mismatch": 0, "undecided": 0}
    samples = []
    for d, j in runs:
        ident = dec.identify(d * np.asarray(gains) + np.asarray(offs))
        if ident.status is ab.PowerUpStatus.IDENTIFIED:
            counts["right" if ident.offset == j else "WRONG"] += 1
            if ident.offset == j:
                samples.append(ident.samples)
        elif ident.status is ab.PowerUpStatus.MISMATCH:
            counts["mismatch"] += 1
        else:
            counts["undecided"] += 1
    return counts, samples


def pct(x: float) -> str:
    return "none within 10%" if not math.isfinite(x) else f"{100 * x:.2f}%"


def report(name: str, cfg, cal, seed: int) -> tuple[float, int, float]:
    """Print one case; returns the predicted shares summed and the WRONG locks counted over the
    changes (healthy excluded)."""
    rep = cal.identifiability
    print(f"\n-- {name}: calibration {cal.status}, power-up {rep.status} --")
    print(f"   {rep.message}")
    m = rep.drift
    print(
        f"   drift margin (wrong-lock share > {100 * m.share:.0f}%): common gain "
        f"{pct(m.common_gain)}, one sensor's gain {pct(m.sensor_gain)}, one sensor's offset "
        f"{pct(m.sensor_offset)} of its amplitude; worst share within +-"
        f"{100 * m.plausible_gain:.0f}%: {100 * m.share_at_plausible:.1f}%"
    )
    notes = [x for x in cal.messages if x.code is MessageCode.POWERUP_DRIFT]
    print(f"   calibrate says: {notes[0].line() if notes else '(nothing: margin beyond 5 %)'}")
    runs = power_ups(cfg, seed)
    chosen = rep.decoder(cal.flux, cal.lut)
    decoders = [("chosen", chosen)]
    if chosen.gate_rate > 0.0 and not chosen.gain_sd > 0.0:
        decoders = [("no gate", dataclasses.replace(chosen, gate_rate=0.0, gate_samples=0,
                                                    gate_bias_dispersion=0.0)),
                    ("kept", chosen)]  # fmt: skip
        if chosen.gate_bias_dispersion > 0.0:
            alone = dataclasses.replace(chosen, gate_bias_dispersion=0.0)
            decoders.insert(1, ("gate alone", alone))
    if chosen.gain_sd > 0.0:  # the profile was chosen: the decoder without it for comparison
        plain = dataclasses.replace(rep, gain_sd=0.0, lock_travel=0.0).decoder(cal.flux, cal.lut)
        decoders = [("no profile", plain), ("kept", chosen)]
    kept = f"plain (lock at standstill, gate {chosen.gate_rate:g} after {chosen.gate_samples})"
    if chosen.gate_bias_dispersion > 0.0:
        kept = kept[:-1] + f", bias half phi_b {chosen.gate_bias_dispersion:.3g})"
    if chosen.gain_sd > 0.0:
        kept = f"common-gain profile, lock after {chosen.lock_travel:g} electrical revolution"
    print(f"   decoder kept by calibrate: {kept}")
    print("   change             decoder     predicted share   measured (40 power-ups)"
          "                           lock samples median/max")  # fmt: skip
    pred_sum, wrong, before, alone = 0.0, 0, 0, 0
    for label, gains, offs in CHANGES:
        for name, dec in decoders:
            c, k = measured(runs, dec, gains, offs)
            p = predicted(dec, gains, offs)
            if label != "healthy" and dec is chosen:
                pred_sum, wrong = pred_sum + p, wrong + c["WRONG"]
            if label != "healthy" and name == "no gate":
                before += c["WRONG"]
            if label != "healthy" and name == "gate alone":
                alone += c["WRONG"]
            lock = f"{np.median(k):5.0f}/{max(k):3d}" if k else "    -"
            print(f"   {label:18s} {name:10s} {100 * p:8.1f}%   "
                  + "  ".join(f"{key} {v:2d}" for key, v in c.items()) + f"   {lock}")  # fmt: skip
    if chosen.lock_travel > 0.0:
        _turning(cfg, seed, decoders)
    gated = decoders[0][0] == "no gate"
    return (pred_sum, wrong, chosen.lock_travel, before if gated else None,
            alone if chosen.gate_bias_dispersion > 0.0 else None)  # fmt: skip


def _turning(cfg, seed: int, decoders) -> None:
    """The same changes on 20 power-ups turning 1.5 electrical revolutions (10 per second)."""
    runs = power_ups(cfg, seed, 20, turning=True)
    # the same decoder without the travel: what the profile alone does with that motion
    prof = decoders[-1][1]
    more = [*decoders[:-1], ("profile, lock at once", dataclasses.replace(prof, lock_travel=0.0)),
            ("kept (profile + travel)", prof)]  # fmt: skip
    print(f"   20 power-ups turning 1.5 electrical revolutions ({runs[0][0].shape[0]} samples):")
    for label, gains, offs in CHANGES:
        for name, dec in more:
            c, k = measured(runs, dec, gains, offs)
            lock = f"{np.median(k):6.0f}/{max(k):5d}" if k else "     -"
            print(f"   {label:18s} {name:22s} "
                  + "  ".join(f"{key} {v:2d}" for key, v in c.items()) + f"   {lock}")  # fmt: skip


#: Unseen motors for the healthy false-alarm count (174, 185, 207, 210, 240: ADC codes).
HEALTHY = (174, 185, 240, 205, 207, 208, 210)


def healthy(seeds=HEALTHY) -> None:
    """Healthy power-ups (80: bench_unseen's procedure) on more unseen motors: gate alone vs
    the kept decoder, at rest and in all. Where calibrate kept the lock after motion because
    the ADC's rounding decides the evidence at rest (reason ``quantizer``), the standstill
    decoder it replaces (gate at phi from the calibration recording) is "before", and 20
    power-ups turning 1.5 electrical revolutions show the kept lock."""
    print("\nhealthy power-ups on more unseen motors (80 each, half at rest): right / mismatch")
    print("   motor                  bias half   gate alone: all   at rest    kept: all   at rest")
    rows = []
    for seed in seeds:
        name, cfg, cal = unseen(seed)
        dec = cal.identifiability.decoder(cal.flux, cal.lut)
        runs = power_ups(cfg, seed, 80)
        out = []
        for d in (dataclasses.replace(dec, gate_bias_dispersion=0.0), dec):
            c, _ = measured(runs, d, (1.0,) * 3, (0.0,) * 3)
            r, _ = measured(runs[1::2], d, (1.0,) * 3, (0.0,) * 3)
            out.append(f"{c['right']:3d}/{c['mismatch']:2d}    {r['right']:3d}/{r['mismatch']:2d}")
        half = "yes" if dec.gate_bias_dispersion > 0.0 else "no"
        print(f"   {name:22s} {half:9s}   {out[0]}    {out[1]}")
        if cal.identifiability.reason == "quantizer":
            rows.append((name, cfg, seed, dec, runs))
    if not rows:
        return
    _rest_false_alarm(rows)
    print("\nlock after motion for the ADC's rounding (reason quantizer): right / WRONG / "
          "mismatch / undecided")  # fmt: skip
    for name, cfg, seed, dec, runs in rows:
        before = _standstill(cfg, seed, dec)
        turning = power_ups(cfg, seed, 20, turning=True)
        for label, sub in (("at rest (40)", runs[1::2]), ("moving (40)", runs[0::2]),
                           ("turning 1.5 rev (20)", turning),
                           ("rest 5000, turning (20)", _rest_then_turning(cfg, seed))):  # fmt: skip
            for tag, x in (("before", before), ("kept", dec)):
                c, k = measured(sub, x, (1.0,) * 3, (0.0,) * 3)
                lock = f"{np.median(k):6.0f}/{max(k):5d}" if k else "     -"
                cs = "  ".join(f"{key} {v:2d}" for key, v in c.items())
                print(f"   {name:22s} {label:23s} {tag:6s} {cs}   {lock}")


def _rest_then_turning(cfg, seed: int, rest: int = 5000, trials: int = 20):
    """Power-ups that rest ``rest`` samples, then turn 1.5 electrical revolutions (10 per
    second) from the same angle: the rounding error of the rest is in the evidence before the
    motion's. (d, true j)."""
    from hallcal.sim.bench import power_up_run

    n = cfg.pole_pairs
    rng = np.random.default_rng([seed, 77])
    samples = int(1.5 / (10.0 * cfg.sample_time))
    out = []
    for i in range(trials):
        a = float(rng.uniform(0, TWO_PI))
        still = power_up_run(cfg, a, samples=rest, speed=0.0, seed=seed * 1000 + 500 + i)
        move = power_up_run(cfg, a, samples=samples, speed=10.0 * TWO_PI / n,
                            seed=seed * 1000 + 700 + i)  # fmt: skip
        j = int(np.round((move.y0[0] - move.y[0]) * n / TWO_PI)) % n
        out.append((np.vstack([still.d, move.d]), j))
    return out


def _standstill(cfg, seed: int, dec):
    """The standstill decoder (gate at phi from the calibration recording) that the lock after
    motion for the ADC's rounding replaces."""
    case = bu.draw_case(seed)
    d = bu._ramp(cfg, case["end"], case["duration"], seed).d
    phi = ab.gate_dispersion(dec, d, ab.DEFAULT_GATE_SAMPLES)
    gate = {"gate_rate": ab.DEFAULT_GATE_RATE, "gate_samples": ab.DEFAULT_GATE_SAMPLES}
    return dataclasses.replace(dec, lock_travel=0.0, gate_dispersion=phi, **gate)


def _rest_false_alarm(rows, trials: int = 400) -> None:
    """The standstill decoder on ``trials`` healthy power-ups at rest of K0 samples: its false
    "mismatch" (nominal alpha_g = 1e-4), and the right hypothesis's cost over K0 as a z-score
    of the gate's chi-square (sd 1 if the K0 samples were independent draws)."""
    from hallcal.sim.bench import power_up_run

    print(f"\nthe standstill decoder on {trials} healthy power-ups at rest of K0 samples: "
          "right / WRONG / mismatch, sd of the right pole pair's cost as a z-score")  # fmt: skip
    K = ab.DEFAULT_GATE_SAMPLES
    for name, cfg, seed, dec, _ in rows:
        before, n = _standstill(cfg, seed, dec), cfg.pole_pairs
        rng = np.random.default_rng([seed, 55])
        z, c = [], {"right": 0, "WRONG": 0, "mismatch": 0, "undecided": 0}
        for i in range(trials):
            pu = power_up_run(cfg, float(rng.uniform(0, TWO_PI)), samples=K, speed=0.0,
                              seed=seed * 100000 + i)  # fmt: skip
            j = int(np.round((pu.y0[0] - pu.y[0]) * n / TWO_PI)) % n
            q = before.cumulative_costs(pu.d)[-1, j]
            z.append((q - 2 * K) / math.sqrt(4 * K * before.gate_dispersion))
            c2, _ = measured([(pu.d, j)], before, (1.0,) * 3, (0.0,) * 3)
            c = {key: c[key] + c2[key] for key in c}
        cs = "  ".join(f"{key} {v:3d}" for key, v in c.items() if key != "undecided")
        print(f"   {name:22s} {cs}   z sd {np.std(z):.2f}")


def main() -> None:
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())} (2 cores, shared)")
    t0 = time.perf_counter()
    rows = [(s, report(*unseen(s), s)) for s in (202, 213, 218, 227)]
    rows += [(f"paper {s}", report(*paper(s), s)) for s in (0, 1, 2)]
    k = len(CHANGES) - 1
    print(f"\npooled over the {k} changes (40 power-ups each): mean predicted share, WRONG locks")
    for name, (p, w, travel, before, alone) in rows:
        note = " (kept decoder; the prediction is a standstill lock's, this one waits for motion)"
        gate = "" if before is None else f"; without the gate {before:3d}"
        gate += "" if alone is None else f", gate alone {alone:3d}"
        print(f"   {name!s:9s} predicted {100 * p / k:5.1f}%   measured {w:3d}/{40 * k} "
              f"({100 * w / (40 * k):4.1f}%){gate}{note if travel else ''}")  # fmt: skip
    healthy()
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
