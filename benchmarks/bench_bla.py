"""Benchmark: calibration with the plant from a BLA (no [plant]): accuracy and an honest verdict.

The paper's method identifies G(s) from a multisine experiment (the BLA) and corrects its gain.
What the BLA leaves uncertain (a few per cent) biases the table's offset through the loop's
steady lag; ``pipeline/plant_refine.py`` refines the BLA's plant with the calibration run within
the BLA's own uncertainty and adds what remains to the predicted error.

Motors: the paper's simulation study (``hallcal demo``, seeds 1-6), the README's 4-pole-pair
motor on a 10 kHz drive, and zoo motors (``bench_zoo.draw_motor``) of several classes, each with a
multisine experiment of one-second periods. Errors are RMS about zero (offset included) over the
oracle floor of a fresh validation run (``hallcal.sim.oracle``).

Run it with the code to measure first on the path, e.g. ``PYTHONPATH=src python
benchmarks/bench_bla.py --label after``; the committed ``bench_bla.txt`` holds a run of main
before the refinement and one after.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_zoo import draw_motor  # noqa: E402

from hallcal import pipeline  # noqa: E402
from hallcal.io import Dataset, default_setup  # noqa: E402
from hallcal.io.setup import BLASpec, ModelSpec, Setup  # noqa: E402
from hallcal.sensor.metrics import angle_error  # noqa: E402
from hallcal.sim.bench import BenchConfig, simulate_run  # noqa: E402
from hallcal.sim.lti import ContinuousTF, DiscreteTF  # noqa: E402
from hallcal.sim.oracle import oracle_error, oracle_table  # noqa: E402

README_PLANT = ContinuousTF((5000.0,), (1.0, 50.0, 0.0), 1.5e-4)


def _velocity_gain(tf: ContinuousTF) -> float:
    """K_v = lim s G(s) for G with one integrator: num[-1] / den[-2]."""
    return float(tf.num[-1] / tf.den[-2])


def _score(cfg: BenchConfig, cal, val_run, plant: ContinuousTF) -> dict:
    table = oracle_table(cfg)
    floor = oracle_error(val_run, table=table).rms_raw if table.bijective else cfg.noise_floor
    row = {"status": str(cal.status), "pred": cal.predicted_error / floor}
    codes = {str(m.code) for m in cal.messages}
    row["refined"] = ("disagrees" if "plant_disagrees" in codes
                      else "refined" if "plant_refined" in codes else "-")  # fmt: skip
    row["star"] = row["off"] = math.nan
    if cal.lut.bijective:
        e = angle_error(cal.lut.f_star(val_run.d), val_run.y0)
        row["star"], row["off"] = e.rms_raw / floor, e.mean / floor
    kv = _velocity_gain(plant)
    row["kv_bla"] = 100 * (_velocity_gain(cal.bla.plant) / kv - 1) if cal.bla else math.nan
    row["kv"] = 100 * (_velocity_gain(cal.plant) / kv - 1) if cal.plant is not None else math.nan
    return row


def paper_study(seed: int) -> dict:
    """The demo: the paper's bench and experiments, the plant from the BLA."""
    s = default_setup()
    s = dataclasses.replace(s, bench=dataclasses.replace(s.bench, seed=seed))
    ms = pipeline.simulate(s, experiment="multisine")
    cal_run = pipeline.simulate(s, experiment="ramp")
    val_run = pipeline.simulate(s, experiment="ramp", seed=seed + 1000, ramp_end=12.0,
                                duration=24.0)  # fmt: skip
    user = dataclasses.replace(s, plant=None)
    t0 = time.perf_counter()
    cal = pipeline.calibrate(Dataset.from_columns(cal_run.columns()), user,
                             bla_dataset=Dataset.from_columns(ms.columns()))  # fmt: skip
    row = _score(cal_run.config, cal, val_run, s.plant)
    return {"motor": f"paper s{seed}", "n_m": 11, "sec": time.perf_counter() - t0, **row}


def _multisine(cfg: BenchConfig, spec: BLASpec, seed: int):
    from hallcal.identify.excitation import multisine_experiment

    exp = multisine_experiment(
        spec.period_samples, cfg.sample_time, periods=spec.periods,
        realizations=spec.realizations, band=spec.band, rms=spec.rms, lines=spec.lines,
        seed=seed, drift=spec.drift,
    )  # fmt: skip
    return simulate_run(cfg, exp.r, seed=seed, realization=exp.realization)


def own_motor(name: str, cfg: BenchConfig, end: float, duration: float, seed: int) -> dict:
    """A motor of its own: a multisine experiment of one-second periods, then the ramp."""
    fs = 1.0 / cfg.sample_time
    spec = BLASpec(period_samples=int(round(fs)), periods=4, transient_periods=1,
                   band=(1.0, min(400.0, fs / 8)))  # fmt: skip
    setup = Setup(pole_pairs=cfg.pole_pairs, sample_time=cfg.sample_time,
                  controller=cfg.controller, plant=None, bla=spec,
                  model=ModelSpec(harmonics="auto"))  # fmt: skip
    ms = _multisine(cfg, spec, seed + 500)
    n = int(round(duration / cfg.sample_time))
    cal_run = simulate_run(cfg, end * np.arange(n) / n, seed=seed)
    val_run = simulate_run(cfg, 0.8 * end * np.arange(int(0.8 * n)) / int(0.8 * n),
                           seed=seed + 10_000)  # fmt: skip
    t0 = time.perf_counter()
    cal = pipeline.calibrate(Dataset.from_columns(cal_run.columns()), setup,
                             bla_dataset=Dataset.from_columns(ms.columns()))  # fmt: skip
    assert cfg.plant is not None
    row = _score(cfg, cal, val_run, cfg.plant)
    return {"motor": name, "n_m": cfg.pole_pairs, "sec": time.perf_counter() - t0, **row}


def readme_motor(seed: int) -> dict:
    """The README's motor: 4 pole pairs, 10 kHz, its PID."""
    pid = DiscreteTF((9.8472, -19.6285, 9.7814), (1.0, -1.962998, 0.962998))
    cfg = BenchConfig(pole_pairs=4, sample_time=1e-4, plant=README_PLANT, controller=pid,
                      seed=seed)  # fmt: skip
    return own_motor(f"readme s{seed}", cfg, 13.0, 26.0, seed)


def zoo_motor(seed: int) -> dict:
    cfg, end, duration, kind, _ = draw_motor(seed)
    return own_motor(f"zoo {seed} {kind}", cfg, end, duration, seed)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--label", default="")
    ap.add_argument("--paper", type=int, nargs="*", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--readme", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--zoo", type=int, nargs="*", default=[5, 6, 7, 8, 14, 18, 24, 29])
    args = ap.parse_args()
    print(f"bench_bla {args.label}: load average at start {os.getloadavg()[0]:.1f} (2 cores)")
    print(f"{'motor':<18} {'n_m':>3} {'status':>10} {'star/fl':>8} {'off/fl':>7} {'pred/fl':>8} "
          f"{'act/pred':>8} {'Kv BLA %':>8} {'Kv %':>7} {'sec':>6}  plant")  # fmt: skip
    rows = []
    jobs = ([lambda s=s: paper_study(s) for s in args.paper]
            + [lambda s=s: readme_motor(s) for s in args.readme]
            + [lambda s=s: zoo_motor(s) for s in args.zoo])  # fmt: skip
    for job in jobs:
        r = job()
        rows.append(r)
        print(f"{r['motor']:<18} {r['n_m']:>3} {r['status']:>10} {r['star']:8.3f} {r['off']:7.2f} "
              f"{r['pred']:8.3f} {r['star'] / r['pred']:8.2f} {r['kv_bla']:8.2f} {r['kv']:7.2f} "
              f"{r['sec']:6.1f}  {r['refined']}", flush=True)  # fmt: skip
    ok = [r for r in rows if r["status"] == "ok"]
    honest = [r for r in rows if np.isfinite(r["star"]) and 0.67 <= r["star"] / r["pred"] <= 1.5]
    calibrated = [r for r in rows if np.isfinite(r["star"])]
    print(f"{len(rows)} motors: {len(ok)} ok; within 1.15x the floor: "
          f"{sum(r['star'] <= 1.15 for r in calibrated)} of {len(calibrated)}; "
          f"'ok' above 1.3x: {sum(r['star'] > 1.3 for r in ok)}; actual/predicted within "
          f"[0.67, 1.5]: {len(honest)} of {len(calibrated)}")  # fmt: skip


if __name__ == "__main__":
    main()
