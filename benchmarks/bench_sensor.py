"""Imperfect sensors in the loop: clipping, a fine ADC, a drifting gain, skewed sensors.

Each case is the paper's bench (11 pole pairs, 4 kHz, its G(s) and C(q), per-magnet variation)
with one sensor imperfection of :class:`hallcal.sim.bench.BenchConfig`, calibrated with the setup
a user would write (the true plant and controller, ``harmonics = "auto"``) on a ramp
0 -> 13 rad in 26 s, and validated on a fresh run against the true angle:

- ``star/fl``: f_star's RMS error over the noise floor ``sqrt(sigma^2 + q^2/12) sqrt(2/3)/n_m``
  (q: the ADC step, 0 without), on a validation run of the same motor without the
  imperfection that the table cannot undo (no rails: clipping is lost information; drift:
  the sensors frozen at the calibration run's middle, the "mean temperature");
- ``raw/fl``: the same RMS about zero instead of about the mean (the table's constant offset
  included, as ``reconstruct`` outputs it);
- ``oracle``: on the validation run with the imperfection, f_star against the exact inverse of
  the true map applied to the same run (DESIGN.md's oracle floor), for the rails and the ADC.

Cases: ``clean`` the bench itself, ``clip1`` one sensor's upper rail at 0.988 (4.4 % of its
samples at the rail), ``clip3`` all three sensors clipped at both rails, ``adc12`` a 12-bit ADC
over [-1.2, 1.2] with analog noise below one code, ``quiet`` that analog noise without the ADC,
``drift`` sensor 1's gain drifting 2 % over the run, ``skew`` sensors at 0/100/230 electrical
degrees.

Run ``python benchmarks/bench_sensor.py [--cases clip1 adc12] [-v] [--out FILE]``.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from dataclasses import replace

import numpy as np

from hallcal import pipeline
from hallcal.io import Dataset, ModelSpec, Setup
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run

DURATION = 26.0
RAMP_END = 13.0
INF = math.inf


def case(name: str) -> tuple[BenchConfig, BenchConfig]:
    """The calibration bench and the validation bench of a case."""
    base = BenchConfig(seed=1)
    if name == "clean":
        return base, base
    if name == "clip1":  # 4.4 % of sensor 1's samples sit on its upper rail
        cfg = replace(base, adc_high=(0.988, INF, INF))
        return cfg, base
    if name == "clip3":  # 1-3 % of each sensor's samples on each rail
        cfg = replace(base, adc_low=(-1.01,) * 3, adc_high=(1.0,) * 3)
        return cfg, base
    if name == "adc12":
        cfg = replace(base, noise_variance=1e-4**2, adc_low=(-1.2,) * 3, adc_high=(1.2,) * 3,
                      adc_bits=12)  # fmt: skip
        return cfg, cfg
    if name == "quiet":  # the analog noise of adc12 without its ADC
        cfg = replace(base, noise_variance=1e-4**2)
        return cfg, cfg
    if name == "drift":
        cfg = replace(base, gain_drift=(0.02 / DURATION, 0.0, 0.0),
                      drift_reference_time=DURATION / 2)  # fmt: skip
        return cfg, replace(cfg, gain_drift=(0.0, 0.0, 0.0))
    if name == "skew":
        cfg = replace(base, misalignment_deg=(0.0, -20.0, -10.0))
        return cfg, cfg
    raise SystemExit(f"unknown case {name}")


def floor_of(cfg: BenchConfig) -> float:
    q2 = float(np.mean(cfg.quantization_step**2)) / 12.0
    return math.sqrt(cfg.noise_variance + q2) * math.sqrt(2.0 / 3.0) / cfg.pole_pairs


def run_case(name: str, verbose: bool, harmonics="auto") -> dict:
    cfg, val_cfg = case(name)
    cal_run = ramp_run(cfg, ramp_end=RAMP_END, duration=DURATION)
    at_rail = np.mean(np.isin(cal_run.d, np.r_[cfg.adc_low, cfg.adc_high]), axis=0)
    setup = Setup(
        pole_pairs=cfg.pole_pairs,
        sample_time=cfg.sample_time,
        controller=cfg.controller,
        plant=cfg.plant,
        model=ModelSpec(harmonics=harmonics),
    )
    t0 = time.perf_counter()
    cal = pipeline.calibrate(Dataset.from_columns(cal_run.columns(with_encoder=False)), setup)
    sec = time.perf_counter() - t0
    if verbose:
        for m in cal.messages:
            print(f"     {m}", flush=True)
        if cal.refusal:
            print(f"     refusal: {cal.refusal}", flush=True)
    floor = floor_of(cfg)
    row = {"case": name, "status": str(cal.status), "sec": sec, "rail": float(at_rail.max()),
           "star": math.nan, "raw": math.nan, "oracle": math.nan,
           "pred": cal.predicted_error / floor, "init": math.nan,
           "harm": len(cal.model_info.get("harmonics", []))}  # fmt: skip
    val = ramp_run(val_cfg, ramp_end=0.8 * RAMP_END, duration=0.8 * DURATION, seed=10_001)
    row["init"] = angle_error(cal.lut.f_init(val.d), val.y0).rms / floor
    if cal.lut.bijective:
        err = angle_error(cal.lut.f_star(val.d), val.y0)
        row["star"], row["raw"] = err.rms / floor, err.rms_raw / floor
        same = ramp_run(cfg, ramp_end=0.8 * RAMP_END, duration=0.8 * DURATION, seed=10_001)
        true_lut = build_lut(cfg.truth(), cfg.pole_pairs, points=16384)
        oracle = angle_error(true_lut.f_star(same.d), same.y0).rms
        row["oracle"] = angle_error(cal.lut.f_star(same.d), same.y0).rms / oracle
    return row


def main() -> None:
    ap = argparse.ArgumentParser()
    cases = ["clean", "clip1", "clip3", "adc12", "quiet", "drift", "skew"]
    ap.add_argument("--cases", nargs="*", default=cases)
    ap.add_argument("-v", "--verbose", action="store_true")
    ap.add_argument("--harmonics", type=int, default=0, help="1..H given instead of auto")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    lines = [
        "bench_sensor: paper bench + one sensor imperfection, harmonics = auto, fresh validation",
        f"load average {os.getloadavg()[0]:.1f} (2 cores); star/fl on the validation bench, "
        "oracle = f_star / exact inverse on the same imperfect run",
        "",
        f"{'case':>6} {'rail%':>6} {'status':>13} {'init/fl':>8} {'star/fl':>8} {'raw/fl':>7} "
        f"{'oracle':>7} "
        f"{'pred/fl':>8} {'harm':>5} {'sec':>6}",
    ]
    print("\n".join(lines), flush=True)
    for name in args.cases:
        h = tuple(range(1, args.harmonics + 1)) if args.harmonics else "auto"
        r = run_case(name, args.verbose, h)
        line = (
            f"{r['case']:>6} {100 * r['rail']:6.2f} {r['status']:>13} {r['init']:8.2f} "
            f"{r['star']:8.3f} {r['raw']:7.3f} {r['oracle']:7.3f} {r['pred']:8.3f} "
            f"{r['harm']:5d} {r['sec']:6.1f}"
        )
        print(line, flush=True)
        lines.append(line)
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
