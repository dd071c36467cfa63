"""Benchmark: every magnet different: automatic model choice and the kernel model.

Bench (the paper's loop and plant, experiment-shaped run): 11 pole pairs, trapezoidal flux
(3rd electrical harmonic 10 %, 5th 4 %), 2 electrical degrees misalignment of sensor 2, per-magnet
shape variation ``shape_variation`` s (:func:`hallcal.sim.bench.shape_deformation`: every pole
pair's waveform deformed on its own, truth on mechanical harmonics 1..55) at two strengths, s =
0.02 and 0.075 (f_init about 3 and 6 mrad RMS), Hall noise variance 7.5e-6, ramp 0 -> 20 rad in
40 s at 4 kHz (160 000 samples). Validation on a fresh run of the same motor (another noise seed,
0 -> 18 rad in 36 s) against the true angle.

Each calibration is :func:`hallcal.calibrate` (the whole pipeline: model, adequacy, table) in a
fresh Python process, so that the wall time, the CPU time (both cores: up to twice the wall
time when the machine is free for it) and the peak resident memory (the child's own high-water
mark ``VmHWM``, imports included; not ``ru_maxrss``, which on Linux also counts the parent's
memory at the fork) belong to that calibration alone; the model step (choosing the harmonics, or
the kernel SEM) is timed on its own from the pipeline's progress messages, with the peak memory
at its end (``benchmarks/bench_memory.py`` shows the peak of every step).
Models: ``harmonics = "auto"``, ``basis = "kernel"`` (m = 400, the defaults), and, as a
reference, the Fourier model with the truth's harmonics 1..55 given by hand.

Run: ``python benchmarks/bench_rich.py > benchmarks/bench_rich.txt`` (about 10 minutes on two
cores). Times are wall-clock on a shared 2-core machine; the load average is printed.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hallcal.sim.bench import BenchConfig, ramp_run

STRENGTHS = (0.02, 0.075)
SEEDS = (1, 2, 3, 4, 5)
MODELS = {
    "auto": {"basis": "fourier", "harmonics": "auto"},
    "kernel": {"basis": "kernel"},
    "F1..55": {"basis": "fourier", "harmonics": list(range(1, 56))},
}


def config(seed: int, strength: float) -> BenchConfig:
    """The rich-shape motor with per-magnet shape variation ``strength``."""
    return BenchConfig(
        pole_pairs=11,
        electrical_harmonics=((3, 0.10), (5, 0.04)),
        magnet_variation=0.0,
        misalignment_deg=(0.0, 2.0, 0.0),
        shape_variation=strength,
        seed=seed,
    )


def setup(cfg: BenchConfig, model: dict) -> dict:
    """The setup mapping (TOML layout) of the bench's loop and a model."""
    return {
        "pole_pairs": cfg.pole_pairs,
        "sample_time": cfg.sample_time,
        "controller": {"num": list(cfg.controller.num), "den": list(cfg.controller.den)},
        "plant": {
            "num": list(cfg.plant.num),
            "den": list(cfg.plant.den),
            "delay": cfg.plant.delay,
        },
        "model": model,
    }


def peak_rss_mb() -> float:
    """The process's peak resident memory so far [MB] (``VmHWM``)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # not Linux


def one(data: str, model: str) -> None:
    """Child process: calibrate, validate, print one JSON line."""
    import hallcal

    z = np.load(data)
    cal_cols = {k: z[k] for k in ("r", "y", "u", "d1", "d2", "d3")}
    cfg = config(int(z["seed"]), float(z["strength"]))
    steps: list[tuple[float, float, str]] = []

    def progress(message: str) -> None:  # wall time and peak RSS at the start of every step
        rss = peak_rss_mb()
        steps.append((time.perf_counter(), rss, message))

    t, c = time.perf_counter(), time.process_time()
    cal = hallcal.calibrate(cal_cols, setup(cfg, MODELS[model]), progress=progress)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    # the model step: from "choosing the harmonics" / "SEM ..." to the next step
    first = next(i for i, s in enumerate(steps) if s[2].startswith(("choosing", "SEM")))
    model_wall = steps[first + 1][0] - steps[first][0]
    model_rss = steps[first + 1][1]
    d_val = np.column_stack([z["v_d1"], z["v_d2"], z["v_d3"]])
    y_star = cal.lut.f_star(d_val)
    e = y_star - z["v_y0"]
    e_star = float(np.std(e - np.mean(e)))
    e0 = cal.lut.f_init(d_val) - z["v_y0"]
    out = {
        "wall": wall,
        "cpu": cpu,
        "model_wall": model_wall,
        "model_rss_mb": model_rss,
        "rss_mb": peak_rss_mb(),
        "f_star": e_star,
        "f_init": float(np.std(e0 - np.mean(e0))),
        "floor": cfg.noise_floor,
        "status": str(cal.status),
        "harmonics": len(cal.flux.basis.harmonics),
        "max_harmonic": max(cal.flux.basis.harmonics),
        "predicted": float(cal.predicted_error),
    }
    print(json.dumps(out))


def run_child(data: Path, model: str) -> dict:
    res = subprocess.run(
        [sys.executable, __file__, "--one", str(data), model],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    print(__doc__.split("\n\n")[0])
    print(
        f"python {platform.python_version()}, numpy {np.__version__}, cpus {os.cpu_count()}, "
        f"load average at start {os.getloadavg()[0]:.2f}"
    )
    # warm the numba caches in a child (compilation is cached on disk, not part of the timings)
    with tempfile.TemporaryDirectory() as tmp:
        rows = []
        for strength in STRENGTHS:
            for seed in SEEDS:
                cfg = config(seed, strength)
                run = ramp_run(cfg, ramp_end=20.0, duration=40.0, seed=seed)
                val = ramp_run(cfg, ramp_end=18.0, duration=36.0, seed=seed + 100)
                path = Path(tmp) / f"s{strength}_{seed}.npz"
                np.savez(
                    path, seed=seed, strength=strength, r=run.r, y=run.y, u=run.u,
                    d1=run.d[:, 0], d2=run.d[:, 1], d3=run.d[:, 2], v_d1=val.d[:, 0],
                    v_d2=val.d[:, 1], v_d3=val.d[:, 2], v_y0=val.y0,
                )  # fmt: skip
                if not rows:
                    for model in MODELS:
                        run_child(path, model)
                for model in MODELS:
                    r = run_child(path, model)
                    r.update(strength=strength, seed=seed, model=model,
                             load=os.getloadavg()[0])  # fmt: skip
                    rows.append(r)
                    print(
                        f"  s={strength:<6} seed {seed} {model:<7} f_init {1e3 * r['f_init']:.2f} "
                        f"mrad  f_star/floor {r['f_star'] / r['floor']:.3f}  {r['wall']:5.1f} s "
                        f"(cpu {r['cpu']:5.1f} s, model {r['model_wall']:4.1f} s)  "
                        f"{r['rss_mb']:4.0f} MB (after the model {r['model_rss_mb']:3.0f} MB)  "
                        f"{r['status']:<8} {r['harmonics']} harmonics "
                        f"(max {r['max_harmonic']})  load {r['load']:.1f}",
                        flush=True,
                    )
    print("\nSummary (f_star / noise floor on the validation run; wall time and peak RSS of one")
    print("calibrate in a fresh process):")
    head = f"{'strength':>8} {'model':<8}{'f_init mrad':>12}{'f*/floor per seed':>40}"
    head += f"{'max':>7}{'time s (max)':>14}{'cpu s':>8}{'model s':>9}{'RSS MB (max)':>14}"
    head += f"{'model MB':>10}"
    print(head + "\n" + "-" * len(head))
    for strength in STRENGTHS:
        for model in MODELS:
            rs = [r for r in rows if r["strength"] == strength and r["model"] == model]
            ratios = [r["f_star"] / r["floor"] for r in rs]
            fi = np.mean([r["f_init"] for r in rs]) * 1e3
            print(
                f"{strength:>8} {model:<8}{fi:>12.2f}"
                f"{' '.join(f'{x:.3f}' for x in ratios):>40}{max(ratios):>7.3f}"
                f"{np.median([r['wall'] for r in rs]):>7.1f} ({max(r['wall'] for r in rs):.1f})"
                f"{np.median([r['cpu'] for r in rs]):>8.1f}"
                f"{np.median([r['model_wall'] for r in rs]):>9.1f}"
                f"{np.median([r['rss_mb'] for r in rs]):>8.0f} ({max(r['rss_mb'] for r in rs):.0f})"
                f"{max(r['model_rss_mb'] for r in rs):>10.0f}"
            )
    print(f"\nload average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--one":
        one(sys.argv[2], sys.argv[3])
    else:
        main()
