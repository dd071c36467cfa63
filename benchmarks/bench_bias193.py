"""The table's constant offset with the Hall noise fed back by the loop (zoo motor 193 and others).

Zoo motor 193 (``bench_zoo.py``, class "shape", 5 pole pairs, 16 kHz, 25 000 samples) was "ok"
at 1.239x the oracle floor with 1.018x predicted: its table's offset was -0.70x the floor, 3.9
of the offset's predicted standard deviations. The SEM simulates the loop without noise, while
the drive's loop acted on f_init of the noisy signals; the rotor's noise-driven motion is not in
the white covariance, and the offset, which only the start of the run informs, is where it
shows (:func:`hallcal.fit.offset_variance.offset_loop_noise`). This prints, per case, the
offset's standard deviations (over the floor): ``white`` ``sigma^2 c^T A^-1 c``, ``cov`` the
larger of white and batch-means (the prediction before), ``loop`` with the loop's noise, and the
offset's z-score against ``cov`` and against ``max(cov, loop)``; then the predicted error and
one run's upper quantile (over the floor) and the status, with the loop term
(``--before``: without it, as before).

Cases: ``--zoo 193:0-9`` zoo motors with calibration noise draws (``bench_zoo.run_motor``, the
oracle floor); ``--open 193:0-9`` the control: the same motor's loop run without noise and the
same kind of noise added to its signals afterwards (what the white covariance assumes);
``--scale 193:0.1`` its run with the Hall noise scaled (a bias would stay, noise scales);
``--ideal 0-9`` the paper's bench with ideal sensors over noise seeds (f_init at the floor;
its f_init error printed last); ``--paper 1-6`` the paper's bench over bench seeds
(``bench_offset_hac.py``'s rows; the bench's floor).

Run ``nice python benchmarks/bench_bias193.py [--before] [--zoo 193:0-9 179:0-2 ...]
[--open 193:0-9] [--scale 193:0.01 193:0.1] [--ideal 0-9] [--paper 1-6]``; the output is
committed beside it.
"""

from __future__ import annotations

import argparse
import functools
import math
import os

import numpy as np

import hallcal.pipeline as hp
import hallcal.pipeline.closed_loop as cl
from hallcal.fit._table_error import _theta_covariances
from hallcal.fit.offset_variance import (
    LoopNoiseExcess,
    _offset_functional,
    offset_loop_excess,
    offset_loop_noise,
)

_CAP: dict = {}


def _capture(loop, r, sem):
    _CAP.update(loop=loop, r=r, sem=sem)
    return LoopNoiseExcess(0.0, None) if _CAP.get("before") else offset_loop_excess(loop, r, sem)


cl.offset_loop_excess = _capture


def _sds() -> dict:
    """The offset's sd's [rad] at the captured final fit."""
    loop, r, sem = _CAP["loop"], _CAP["r"], _CAP["sem"]
    c = _offset_functional(loop, sem)
    white = math.sqrt(max(float(c @ sem.covariance @ c), 0.0))
    cov = math.sqrt(max(float(c @ C @ c) for C in _theta_covariances(sem)))
    var = offset_loop_noise(loop, r, sem)
    return {"white": white, "cov": cov, "loop": math.sqrt(var) if var else math.nan}


def _line(name, status, star, off, sd, floor, pred, upper) -> str:
    w, c, lo = (sd[k] / floor for k in ("white", "cov", "loop"))
    new = max(c, lo) if math.isfinite(lo) else c
    return (f"{name:>14} {status:>8} {star:6.3f} {off:+6.3f} | {w:5.3f} {c:5.3f} {lo:5.3f} "
            f"{lo / w:5.2f} | {off / c:+6.2f} {off / new:+6.2f} | {pred:6.3f} {upper:6.3f} "
            f"{star / pred:5.2f}")  # fmt: skip


def zoo_row(seed: int, k: int) -> tuple[str, float, dict]:
    from bench_zoo import run_motor

    _CAP.pop("loop", None)
    row = run_motor(seed, noise=k)
    sd = _sds() if "loop" in _CAP else {"white": math.nan, "cov": math.nan, "loop": math.nan}
    # run_motor reports ratios to the oracle floor, the sd's are in rad: the oracle floor is
    # the predicted error over its ratio
    floor = _CAP["pred_rad"] / row["pred"]
    line = _line(f"zoo {seed} k={k}", row["status"], row["star"], row["off"], sd, floor,
                 row["pred"], row["upper"])  # fmt: skip
    return line, row["off"] * floor, sd


def control_row(seed: int, k: int, *, scale: float = 1.0, clean_loop: bool = True) -> tuple:
    """The controls on a zoo motor. ``clean_loop``: its calibration run simulated WITHOUT noise
    (the loop ran on clean signals) and the same kind of Hall noise added afterwards (seed
    ``[seed, k, 99]``): what the white covariance assumes. Otherwise the run with the motor's
    Hall noise sigma times ``scale`` (calibration noise draw k): does the offset scale with
    the noise (no model bias) or stay (a bias)?"""
    from dataclasses import replace

    import bench_zoo as bz

    from hallcal.io import Dataset
    from hallcal.sensor.metrics import angle_error
    from hallcal.sim.oracle import oracle_error, oracle_table

    cfg0, end, duration, _, _ = bz.draw_motor(seed)
    if clean_loop:
        cols = bz.ramp(replace(cfg0, noise_variance=0.0), end, duration, seed).columns()
        rng = np.random.default_rng([seed, k, 99])
        sigma = math.sqrt(cfg0.noise_variance)
        for h in range(3):
            cols[f"d{h + 1}"] = cols[f"d{h + 1}"] + sigma * rng.standard_normal(cols["r"].size)
        name = f"open {seed} k={k}"
    else:
        cfg = replace(cfg0, noise_variance=cfg0.noise_variance * scale**2)
        cols = bz.ramp(cfg, end, duration, seed + 20_000 * k).columns()
        name = f"{seed} x{scale:g} k={k}"
    cal = hp.calibrate(Dataset.from_columns(cols), bz.setup_for(cfg0))
    # the scale is the motor's own oracle floor (at its own noise), as in the zoo
    val = bz.ramp(cfg0, 0.8 * end, 0.8 * duration, seed + 10_000)
    floor = oracle_error(val, table=oracle_table(cfg0)).rms_raw
    e = angle_error(cal.lut.f_star(val.d), val.y0)
    sd = _sds()
    upper = cal.adequacy.predicted_upper / floor
    line = _line(name, str(cal.status), e.rms_raw / floor, e.mean / floor, sd, floor,
                 cal.predicted_error / floor, upper)  # fmt: skip
    return line, e.mean, sd


def ideal_row(k: int) -> tuple[str, float, dict]:
    """The paper's bench with ideal sensors (no magnet variation: f_init at the floor), the run of
    ``tests/test_cli_powerup.py`` (ramp to 7 rad in 14 s) with noise seed k, harmonics 1..11,
    no cogging; the table against f_init on a fresh run."""
    from hallcal.io import Dataset, ModelSpec, Setup
    from hallcal.sensor.metrics import angle_error
    from hallcal.sim.bench import BenchConfig, ramp_run

    cfg = BenchConfig(magnet_variation=0.0, seed=0)
    run = ramp_run(cfg, ramp_end=7.0, duration=14.0, seed=k)
    val = ramp_run(cfg, ramp_end=5.6, duration=11.2, seed=999)
    setup = Setup(pole_pairs=cfg.pole_pairs, sample_time=cfg.sample_time,
                  controller=cfg.controller, plant=cfg.plant,
                  model=ModelSpec(harmonics=tuple(range(1, 12)), cogging="none"))  # fmt: skip
    cal = hp.calibrate(Dataset.from_columns(run.columns()), setup)
    floor = cfg.noise_floor
    e = angle_error(cal.lut.f_star(val.d), val.y0)
    init = angle_error(cal.lut.f_init(val.d), val.y0).rms_raw / floor
    sd = _sds()
    upper = cal.adequacy.predicted_upper / floor
    line = _line(f"ideal k={k}", str(cal.status), e.rms_raw / floor, e.mean / floor, sd, floor,
                 cal.predicted_error / floor, upper)  # fmt: skip
    return f"{line}  f_init {init:.4f}", e.mean, sd


def paper_row(seed: int) -> tuple[str, float, dict]:
    import bench_cogging as bc

    import hallcal
    from hallcal.io import Dataset, setup_from_dict
    from hallcal.pipeline import simulate, validate
    from hallcal.pipeline.simulate import bench_config

    bc.SEED = seed
    sim = setup_from_dict(bc._setup(0.0, 132, 0.0, plant=True))
    floor = bench_config(sim).noise_floor
    run = simulate(sim, experiment="ramp")
    val = simulate(sim, experiment="ramp", seed=seed + 100, ramp_end=12.0, duration=24.0)
    cal = hallcal.calibrate(run.columns(with_encoder=False), bc._setup(0.0, 132, 0.0, plant=True))
    v = validate(cal.lut, Dataset.from_columns(val.columns(), path="validation"))
    sd = _sds()
    upper = cal.computed.adequacy.predicted_upper / floor
    line = _line(f"paper s={seed}", cal.status.value, v.star.rms / floor, v.star.mean / floor,
                 sd, floor, cal.predicted_error / floor, upper)  # fmt: skip
    return line, v.star.mean, sd


def _keep_pred():
    calibrate = hp.calibrate

    def keep(*a, **kw):
        cal = calibrate(*a, **kw)
        _CAP["pred_rad"] = cal.predicted_error
        return cal

    hp.calibrate = keep


def _span(text: str) -> range:
    """``"0-9"`` -> 0..9, ``"3"`` -> 3 (inclusive)."""
    lo, _, hi = text.partition("-")
    return range(int(lo), int(hi or lo) + 1)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--zoo", nargs="*", default=[])  # "193:0-9" or "176"
    ap.add_argument("--paper", default="")  # "1-6"
    ap.add_argument("--ideal", default="")  # "0-9": ideal sensors, noise seeds
    ap.add_argument("--open", nargs="*", default=[])  # "193:0-9": the control (control_row)
    ap.add_argument("--scale", nargs="*", default=[])  # "193:0.01": noise times 0.01, draw 0
    ap.add_argument("--before", action="store_true", help="without the loop-noise term")
    a = ap.parse_args()
    _CAP["before"] = a.before
    _keep_pred()
    print(f"bench_bias193 ({'before: without' if a.before else 'with'} the loop-noise term); "
          f"load average at start {os.getloadavg()[0]:.1f} (2 cores)")  # fmt: skip
    print(f"{'case':>14} {'status':>8} {'star':>6} {'off':>6} | {'white':>5} {'cov':>5} "
          f"{'loop':>5} {'l/w':>5} | {'z_cov':>6} {'z_new':>6} | {'pred':>6} {'upper':>6} "
          f"{'a/p':>5}")  # fmt: skip
    z: dict[str, list] = {}

    def rows(name: str, row, ks: range) -> None:  # print the rows, keep their offsets
        for k in ks:
            line, off, sd = row(k)
            print(line, flush=True)
            z.setdefault(name, []).append((off, sd))

    for specs, row, name in ((a.zoo, zoo_row, "zoo"), (a.open, control_row, "open")):
        for spec in specs:  # "193:0-9": the motor, its noise draws
            seed, _, ks = spec.partition(":")
            rows(f"{name} {seed}", functools.partial(row, int(seed)), _span(ks or "0"))
    for spec in a.scale:
        seed, _, factor = spec.partition(":")
        print(control_row(int(seed), 0, scale=float(factor), clean_loop=False)[0], flush=True)
    if a.paper:
        rows("paper", paper_row, _span(a.paper))
    if a.ideal:
        rows("ideal", ideal_row, _span(a.ideal))
    print("\nRMS of the offset's z-score, against cov -> against max(cov, loop):")
    for name, rows in z.items():
        zc = [o / s["cov"] for o, s in rows]
        zn = [o / max(s["cov"], s["loop"]) for o, s in rows]
        print(f"  {name}: {len(rows)} runs, {math.sqrt(np.mean(np.square(zc))):.2f} -> "
              f"{math.sqrt(np.mean(np.square(zn))):.2f}")  # fmt: skip
    print(f"load average at end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
