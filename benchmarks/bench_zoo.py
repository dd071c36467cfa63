"""A zoo of motors unlike the paper's bench: is the status honest and the predicted error right?

Each motor is drawn at random (seeded): pole pairs 2..28, sampling 2-16 kHz, a plant
``K e^{-s tau} / (s (s + a) (s / p + 1))`` with its own mechanical and amplifier poles and a
delay of 0-1.5 samples, a lead-lag PI controller designed for it (crossover fs/600..fs/150, about
50 degrees of phase margin, Tustin), sensors with misalignment, gain mismatch and offsets, a
flux with 3rd/5th electrical harmonics and per-magnet variation, Hall noise 0.1-1 % of the
amplitude, and a ramp of 1.5-3 revolutions (at most 100 000 samples; "fast" motors run the same
revolutions 4-8 times faster). On top, one class per motor (``seed`` cycles through them):

- ``shape``: every magnet's flux shape its own (variation 1-3 %, content up to 3-7 n_m);
- ``clip``: one sensor's ADC rail cuts its peaks (2-5 % of its samples on the rail);
- ``adc12``: a 12-bit ADC over +-1.5 with analog noise below one code;
- ``drift``: one sensor's gain drifts 1-3 % over the run, another's offset 0.5-1 % (a sensor
  warming up; the static truth at the middle of the run);
- ``skew``: sensors at about 0/100/230 electrical degrees;
- ``cogload``: cogging at 6 n_m and a slot order, and a constant load torque (order 0);
- ``spikes``: impulsive outliers on 0.02-0.2 % of the samples, 10-50 % of the amplitude;
- ``plain``: only the common imperfections.

Calibration uses the setup a user would write: the true controller and plant and the defaults
(``harmonics = "auto"``, ``cogging = "auto"``). Validation is a fresh run (0.8 of the ramp, another
noise seed) against the true angle. Every error is an RMS about ZERO, the table's and f_init's
constant offsets included, as ``reconstruct`` outputs them and as the predicted error states
(:mod:`hallcal.pipeline.verdict`): ``AngleError.rms_raw``. The scale is the ORACLE floor
(:func:`hallcal.sim.oracle.oracle_floor`): the error of the exact inverse of the true map applied
to the validation run's f_init (noise, spikes and quantization included).

Columns: ``star/fl`` f_star / floor, ``init/fl`` f_init / floor, ``pred/fl`` the predicted error
/ floor, ``act/pred`` f_star / predicted (calibrated within [0.67, 1.5]), the status, the
calibration's seconds (wall clock under the load printed in the header), the class; diagnostics:
``off/fl`` f_star's mean error (the table's offset) / floor, ``efl`` the floor the calibration
estimated / the oracle floor, ``white`` and ``batch`` the prediction from each covariance alone
(the calibration takes the larger), ``upper`` the upper 95 % quantile of one run's error
/ floor ("ok" needs it within 1.3x, :mod:`hallcal.pipeline.verdict`), ``B`` batches, ``p``
flux parameters, the model chosen.

Run ``nice python benchmarks/bench_zoo.py [--motors 30] [--out benchmarks/bench_zoo.txt]
[--plot benchmarks/bench_zoo_calibration.png] [--jobs 2]``; ``--seeds 1 3 5`` picks motors,
``--table-only`` prints the table without the plot, ``-v`` each calibration's messages (one job).
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import time
from dataclasses import replace

import numpy as np
from bench_support import run_rows

from hallcal import pipeline
from hallcal._constants import TWO_PI
from hallcal.io import Dataset, ModelSpec, Setup
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, position_controller, simulate_run
from hallcal.sim.lti import ContinuousTF
from hallcal.sim.oracle import oracle_error, oracle_table

CLASSES = ("shape", "clip", "adc12", "drift", "skew", "cogload", "spikes", "plain")
POLE_PAIRS = (2, 3, 4, 5, 7, 8, 10, 11, 14, 15, 21, 24, 28)
#: Calibration runs hold at most this many samples (the zoo runs on a shared 2-core machine).
N_MAX = 100_000
#: Calibrated prediction: actual / predicted within these bounds.
CALIBRATED = (0.67, 1.5)


def draw_motor(seed: int) -> tuple[BenchConfig, float, float, str, float]:
    """A random motor of class ``CLASSES[(seed - 1) % 8]``: config, ramp end [rad], duration
    [s], class, ramp speed-up (1: the slowest ramp within N_MAX samples)."""
    kind = CLASSES[(seed - 1) % len(CLASSES)]
    rng = np.random.default_rng([seed, 25])
    n = int(rng.choice(POLE_PAIRS))
    fs = float(rng.choice([2000.0, 4000.0, 8000.0, 16000.0]))
    ts = 1.0 / fs
    a = float(np.exp(rng.uniform(np.log(3.0), np.log(80.0))))  # mechanical pole [rad/s]
    p = float(np.exp(rng.uniform(np.log(400.0), np.log(3000.0))))  # amplifier pole [rad/s]
    delay = float(rng.uniform(0.0, 1.5)) * ts
    K = float(np.exp(rng.uniform(np.log(1e2), np.log(1e4))))
    plant = ContinuousTF((K * p,), tuple(np.polymul([1.0, a, 0.0], [1.0, p])), delay)
    fc = fs / float(rng.uniform(150.0, 600.0))
    controller = position_controller(plant, ts, fc)
    sigma = float(np.exp(rng.uniform(np.log(1e-3), np.log(1e-2))))
    cfg = BenchConfig(
        pole_pairs=n,
        sample_time=ts,
        plant=plant,
        controller=controller,
        noise_variance=sigma**2,
        magnet_variation=float(rng.uniform(0.005, 0.06)),
        misalignment_deg=tuple(rng.uniform(-3.0, 3.0, 3)),
        gain_mismatch=tuple(rng.uniform(-0.05, 0.05, 3)),
        offset=tuple(rng.uniform(-0.05, 0.05, 3)),
        electrical_harmonics=((3, float(rng.uniform(0.0, 0.1))), (5, float(rng.uniform(0, 0.04)))),
        seed=seed,
    )
    revolutions = float(rng.uniform(1.5, 3.0))
    speed = max(0.3, revolutions * TWO_PI * fs / N_MAX)  # rad/s, at most N_MAX samples
    fast = float(rng.choice([1.0, 1.0, 4.0, 8.0]))
    speed = min(speed * fast, fc)  # slow next to the loop bandwidth (rad/s vs Hz: a loose bound)
    end = revolutions * TWO_PI
    duration = end / speed
    u_ramp = speed * a / K  # torque the ramp needs against the mechanical pole [plant input]
    if kind == "shape":
        k_max = max(3, min(7, 120 // n))  # content up to k_max n_m (at most ~120 harmonics)
        cfg = replace(
            cfg,
            shape_variation=float(rng.uniform(0.01, 0.03)),
            shape_harmonics=int(rng.integers(3, k_max + 1)),
        )
    elif kind == "clip":
        h = int(rng.integers(0, 3))
        frac = float(rng.uniform(0.02, 0.05))
        y0 = TWO_PI * np.arange(1 << 14) / (1 << 14)
        rail = float(np.quantile(cfg.truth()(y0)[:, h], 1.0 - frac))
        high = [math.inf] * 3
        high[h] = rail
        cfg = replace(cfg, adc_high=tuple(high))
    elif kind == "adc12":
        cfg = replace(
            cfg,
            adc_low=(-1.5,) * 3,
            adc_high=(1.5,) * 3,
            adc_bits=12,
            noise_variance=float(rng.uniform(0.1, 0.5) * 3.0 / 4095) ** 2,
        )
    elif kind == "drift":
        g, o = rng.permutation(3)[:2]
        gain = [0.0] * 3
        off = [0.0] * 3
        gain[g] = float(rng.choice([-1, 1]) * rng.uniform(0.01, 0.03)) / duration
        off[o] = float(rng.choice([-1, 1]) * rng.uniform(0.005, 0.01)) / duration
        cfg = replace(
            cfg, gain_drift=tuple(gain), offset_drift=tuple(off),
            drift_reference_time=0.5 * duration,
        )  # fmt: skip
    elif kind == "skew":
        cfg = replace(cfg, misalignment_deg=tuple(np.array([0.0, -20.0, -10.0])
                                                  + rng.uniform(-2.0, 2.0, 3)))  # fmt: skip
    elif kind == "cogload":
        slots = int(rng.choice([12 * n, int(np.lcm(int(rng.choice([9, 12, 24, 36])), 2 * n))]))
        cfg = replace(
            cfg,
            cogging_terms=(
                (0, float(rng.uniform(0.05, 0.5)) * u_ramp, 0.0),
                (6 * n, float(rng.uniform(0.05, 0.5)) * u_ramp, float(rng.uniform(0, 360))),
                (slots, float(rng.uniform(0.0, 0.2)) * u_ramp, float(rng.uniform(0, 360))),
            ),
        )
    elif kind == "spikes":
        cfg = replace(
            cfg, spike_rate=float(rng.uniform(2e-4, 2e-3)),
            spike_size=float(rng.uniform(0.1, 0.5)),
        )  # fmt: skip
    return cfg, end, duration, kind, fast


def setup_for(cfg: BenchConfig, *, cogging: str = "auto") -> Setup:
    """What a user would write: the true loop, the default model (auto harmonics and cogging;
    ``cogging`` overrides the latter for ``bench_zoo_noise.py``)."""
    return Setup(
        pole_pairs=cfg.pole_pairs,
        sample_time=cfg.sample_time,
        controller=cfg.controller,
        plant=cfg.plant,
        model=ModelSpec(harmonics="auto", cogging=cogging),
    )


def ramp(cfg: BenchConfig, end: float, duration: float, seed: int):
    n = int(round(duration / cfg.sample_time))
    return simulate_run(cfg, end * np.arange(n) / n, seed=seed)


def run_motor(seed: int, verbose: bool = False, *, noise: int = 0, cogging: str = "auto") -> dict:
    """Calibrate one motor of the zoo and score it against the oracle floor (``noise`` k > 0:
    the calibration run's noise seed ``seed + 20000 k`` instead of ``seed``, the same motor and
    validation run; ``cogging``: the model's cogging setting)."""
    cfg, end, duration, kind, fast = draw_motor(seed)
    cal_run = ramp(cfg, end, duration, seed + 20_000 * noise)
    row = {
        "seed": seed, "kind": kind, "n_m": cfg.pole_pairs,
        "fs": int(round(1 / cfg.sample_time)), "N": cal_run.n_samples, "fast": fast,
        "status": "diverged", "init": math.nan, "star": math.nan, "pred": math.nan,
        "sec": math.nan, "model": "", "off": math.nan, "efl": math.nan, "white": math.nan,
        "batch": math.nan, "B": 0, "p": 0, "upper": math.nan,
    }  # fmt: skip
    if cal_run.status != "ok":
        return row
    t0 = time.perf_counter()
    cal = pipeline.calibrate(
        Dataset.from_columns(cal_run.columns()), setup_for(cfg, cogging=cogging)
    )
    row["sec"] = time.perf_counter() - t0
    row["status"] = str(cal.status)
    if verbose:
        for m in ((cal.refusal,) if cal.refusal else ()) + cal.messages:
            print(f"     {m}", flush=True)
    val = ramp(cfg, 0.8 * end, 0.8 * duration, seed + 10_000)
    table = oracle_table(cfg)
    floor = oracle_error(val, table=table).rms_raw if table.bijective else cfg.noise_floor
    row["init"] = angle_error(cal.lut.f_init(val.d), val.y0).rms_raw / floor
    if cal.lut.bijective:
        e = angle_error(cal.lut.f_star(val.d), val.y0)
        row["star"], row["off"] = e.rms_raw / floor, e.mean / floor
    row["pred"] = cal.predicted_error / floor
    if cal.adequacy is not None:
        row["upper"] = cal.adequacy.predicted_upper / floor
    row["efl"] = cal.noise_floor / floor
    row.update(_predictions(cal, floor))
    h = cal.model_info.get("harmonics", [])
    row["model"] = f"{len(h)}h<={max(h) if h else 0}"
    if cal.cogging is not None:
        row["model"] += " cog " + "+".join(str(k) for k in cal.cogging.orders)
    return row


def _predictions(cal, floor: float) -> dict:
    """The two covariances behind the prediction, each propagated to the table (about zero,
    with the estimated floor) / oracle floor: white ``sigma^2 (J^T J)^-1`` and batch-means."""
    from hallcal.fit.sem import predicted_angle_error

    sem = cal.sem
    if sem is None or sem.covariance is None:
        return {}
    n = sem.covariance.shape[0]
    kw = dict(projection=cal.lut.projection, offset=cal.lut.offset)
    out = {"B": int(sem.batches), "p": int(n)}
    covs = {"white": sem.covariance}
    if sem.batch_covariance is not None:
        covs["batch"] = np.asarray(sem.batch_covariance)[:n, :n]
    for name, C in covs.items():
        try:
            v = float(np.mean(predicted_angle_error(cal.flux, C, cal.lut.pole_pairs, **kw) ** 2))
        except (ValueError, np.linalg.LinAlgError):
            continue
        out[name] = math.sqrt(cal.noise_floor**2 + v) / floor
    return out


def _line(r: dict) -> str:
    ratio = r["star"] / r["pred"]
    return (
        f"{r['seed']:4d} {r['kind']:>7} {r['n_m']:3d} {r['fs']:6d} {r['N']:7d} x{r['fast']:<2g}"
        f"{r['status']:>13} {r['star']:8.3f} {r['init']:8.2f} {r['pred']:8.3f} {ratio:8.2f} "
        f"{r['sec']:6.1f} {r['off']:6.2f} {r['efl']:5.2f} {r['white']:7.2f} {r['batch']:7.2f} "
        f"{r['upper']:6.2f} {r['B']:3d} {r['p']:4d}  {r['model']}"
    )


def summary(rows: list[dict]) -> list[str]:
    """Counts: calibrated, ok within 1.15x, dishonest (ok above 1.3x, exit 0 worse than f_init)."""
    used = [r for r in rows if r["status"] in ("ok", "warning")]
    ratio = np.array([r["star"] / r["pred"] for r in used])
    inside = np.sum((ratio >= CALIBRATED[0]) & (ratio <= CALIBRATED[1]))
    ok = [r for r in used if r["status"] == "ok"]
    star = np.array([r["star"] for r in used])
    return [
        "",
        f"{len(rows)} motors: {len(ok)} ok, {len(used) - len(ok)} warning, "
        f"{len(rows) - len(used)} refused or failed",
        f"actual/predicted within [{CALIBRATED[0]}, {CALIBRATED[1]}] on {int(inside)} of "
        f"{len(used)} calibrated motors (min {np.nanmin(ratio):.2f}, max {np.nanmax(ratio):.2f})"
        if used
        else "no calibrated motor",
        f"f_star within 1.15x the oracle floor on {int(np.sum(star <= 1.15))} of {len(used)} "
        f"calibrated motors; ok above 1.3x the floor: "
        f"{sum(r['star'] > 1.3 for r in ok)}; exit 0 worse than f_init: "
        f"{sum(r['star'] > r['init'] for r in used)}",
    ]


def plot(rows: list[dict], path: str) -> None:
    """Predicted against actual error (both / oracle floor), one colour per class."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    colours = dict(zip(CLASSES, plt.get_cmap("tab10").colors, strict=False))
    for kind in CLASSES:
        for refused in (False, True):
            sel = [r for r in rows if r["kind"] == kind
                   and (r["status"] not in ("ok", "warning")) == refused
                   and np.isfinite(r["pred"]) and np.isfinite(r["star"])]  # fmt: skip
            if sel:
                ax.scatter([r["pred"] for r in sel], [r["star"] for r in sel],
                           c=[colours[kind]], marker="x" if refused else "o",
                           label=kind + (" (refused)" if refused else ""))  # fmt: skip
    seen = [v for r in rows for v in (r["pred"], r["star"]) if np.isfinite(v)]
    lo, hi = 0.8, max([30.0] + [1.3 * v for v in seen])
    xs = np.array([lo, hi])
    ax.plot(xs, xs, "k-", lw=0.8, label="actual = predicted")
    ax.plot(xs, CALIBRATED[1] * xs, "k--", lw=0.6, label="x0.67, x1.5")
    ax.plot(xs, CALIBRATED[0] * xs, "k--", lw=0.6)
    ax.axvline(1.15, color="g", lw=0.6, ls=":", label="ok: predicted <= 1.15x")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_xlabel("predicted error / oracle floor (RMS about zero)")
    ax.set_ylabel("actual f_star error / oracle floor (fresh run)")
    ax.set_title("bench_zoo: predicted against actual error")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def rows_from_table(path: str) -> list[dict]:
    """The rows of a table this script wrote (or printed), for ``--replot``."""
    rows = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            parts = line.split()
            if len(parts) < 17 or not parts[0].isdigit() or parts[1] not in CLASSES:
                continue
            rows.append({
                "seed": int(parts[0]), "kind": parts[1], "status": parts[6],
                "star": float(parts[7]), "init": float(parts[8]), "pred": float(parts[9]),
            })  # fmt: skip
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--motors", type=int, default=30)
    ap.add_argument("--first", type=int, default=1)
    ap.add_argument("--seeds", type=int, nargs="*", default=None)
    ap.add_argument("-v", "--verbose", action="store_true")
    ap.add_argument("--out", default=None, help="write the table here")
    ap.add_argument("--plot", default=None, help="write the calibration plot (PNG) here")
    ap.add_argument("--table-only", action="store_true", help="no plot")
    ap.add_argument("--jobs", type=int, default=1, help="motors calibrated in parallel")
    ap.add_argument("--replot", default=None, help="only draw --plot from this table's rows")
    args = ap.parse_args()
    if args.replot:
        rows = rows_from_table(args.replot)
        print("\n".join(summary(rows)))
        if args.plot:
            plot(rows, args.plot)
        return
    seeds = args.seeds or list(range(args.first, args.first + args.motors))
    lines = [
        "bench_zoo: random motors, calibrate with the defaults, fresh validation run; errors are "
        "RMS about zero (offset included) over the ORACLE floor",
        f"load average at start {os.getloadavg()[0]:.1f} (2 cores); xF: ramp F times faster than "
        f"the slowest within {N_MAX} samples",
        "",
        f"{'seed':>4} {'class':>7} {'n_m':>3} {'fs':>6} {'N':>7} {'':3}{'status':>13} "
        f"{'star/fl':>8} {'init/fl':>8} {'pred/fl':>8} {'act/pred':>8} {'sec':>6} "
        f"{'off/fl':>6} {'efl':>5} {'white':>7} {'batch':>7} {'upper':>6} {'B':>3} {'p':>4}  model",
    ]
    print("\n".join(lines), flush=True)
    # verbose only in this process (the pool's workers print nothing of their own)
    run = functools.partial(run_motor, verbose=args.verbose and args.jobs <= 1)
    rows = run_rows(run, seeds, args.jobs, _line, lines)
    tail = summary(rows) + [f"load average at end {os.getloadavg()[0]:.1f}"]
    print("\n".join(tail))
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write("\n".join(lines + tail) + "\n")
    if args.plot and not args.table_only:
        plot(rows, args.plot)


if __name__ == "__main__":
    main()
