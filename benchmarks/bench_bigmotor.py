"""Calibrate time and work on many-pole-pair motors (issue 25: under 30 s at up to 200 000 samples).

Motors of ``bench_zoo`` with 24-28 pole pairs (seeds 15, 16 and 20: 400-900 flux parameters;
the unseen zoo motor 178, 1155: a clipped sensor on 1.5 revolutions, whose first fit uses up the
harmonic search's work budget, so that the cogging search is skipped,
:func:`hallcal.pipeline.closed_loop._cogging_unaffordable`) and seed 16's motor on a ramp of
200 000 samples, calibrated with the defaults
(``harmonics = "auto"``, ``cogging = "auto"``). Besides the wall and CPU time of ``calibrate``
(both depend on the machine's load, printed with them) the script counts the work, which does
not: SEM solves (parameters p, samples N, Levenberg-Marquardt iterations), Gauss-Newton systems
(strided ones of the iterations and exact ones for a covariance), the rank-one work
``sum N p^2 / stride`` over the systems, and the band search's un-warp iterations. Accuracy as in
``bench_zoo``: f_star and the predicted error over the oracle floor on a fresh validation run.

Run ``PYTHONPATH=src python benchmarks/bench_bigmotor.py [--seeds 15 16 20 178] [--long 16]``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_zoo  # noqa: E402

import hallcal.fit.gauss_newton as gn  # noqa: E402
import hallcal.fit.sem as sem_module  # noqa: E402
import hallcal.fit.warp as warp  # noqa: E402
from hallcal import pipeline  # noqa: E402
from hallcal.io import Dataset  # noqa: E402
from hallcal.sensor.metrics import angle_error  # noqa: E402
from hallcal.sim.oracle import oracle_error, oracle_table  # noqa: E402


class Counters:
    """Work counted by wrapping the solver's entry points (no change to what they compute)."""

    def __init__(self) -> None:
        self.solves: list[tuple[int, int, int, str]] = []  # (p, N, iterations, status)
        self.systems = {"strided": 0, "exact": 0}
        self.work = 0.0  # sum N p^2 / stride
        self.unwarp_iterations = 0
        self.unwarp_trials = 0

    def install(self) -> None:
        system, solve, unwarp = gn.gauss_newton_system, sem_module.solve_sem, warp.unwarp

        def counted_system(loop, layout, x, r, d, **kw):
            stride = max(1, int(kw.get("stride", 1)))
            if kw.get("gram", True):
                self.systems["exact" if stride == 1 else "strided"] += 1
                self.work += len(r) * float(layout.size) ** 2 / stride
            return system(loop, layout, x, r, d, **kw)

        def counted_solve(loop, r, d, basis, **kw):
            out = solve(loop, r, d, basis, **kw)
            p = out.layout.size if out.layout is not None else -1
            self.solves.append((p, len(r), out.iterations, str(out.status)))
            return out

        def counted_unwarp(view, edge, **kw):
            out = unwarp(view, edge, **kw)
            self.unwarp_trials += 1
            self.unwarp_iterations += out.iterations
            return out

        sem_module.gauss_newton_system = counted_system
        warp.unwarp = counted_unwarp
        import hallcal.fit.cogging_search as cogging
        import hallcal.fit.order as order
        import hallcal.pipeline.closed_loop as closed_loop
        import hallcal.pipeline.sensors as sensors

        for module in (order, cogging, sensors, closed_loop):
            module.solve_sem = counted_solve


def run(seed: int, samples: int | None, counters: Counters) -> dict:
    """Calibrate one motor (``samples``: the same ramp stretched to this many samples)."""
    cfg, end, duration, kind, _ = bench_zoo.draw_motor(seed)
    if samples is not None:
        duration = samples * cfg.sample_time
    run_ = bench_zoo.ramp(cfg, end, duration, seed)
    data = Dataset.from_columns(run_.columns())
    load0 = os.getloadavg()[0]
    c0, t0 = time.process_time(), time.perf_counter()
    cal = pipeline.calibrate(data, bench_zoo.setup_for(cfg))
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    load1 = os.getloadavg()[0]
    val = bench_zoo.ramp(cfg, 0.8 * end, 0.8 * duration, seed + 10_000)
    table = oracle_table(cfg)
    floor = oracle_error(val, table=table).rms_raw if table.bijective else cfg.noise_floor
    star = (
        angle_error(cal.lut.f_star(val.d), val.y0).rms_raw / floor
        if cal.lut.bijective
        else math.nan
    )
    h = cal.model_info.get("harmonics", [])
    return {
        "seed": seed, "kind": kind, "n_m": cfg.pole_pairs, "N": run_.n_samples,
        "status": str(cal.status), "star": star, "pred": cal.predicted_error / floor,
        "model": f"{len(h)}h<={max(h) if h else 0}", "cpu": cpu, "wall": wall,
        "load": (load0, load1),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="*", default=[15, 16, 20, 178])
    ap.add_argument("--long", type=int, nargs="*", default=[16],
                    help="seeds also run on a ramp of --samples samples")  # fmt: skip
    ap.add_argument("--samples", type=int, default=200_000)
    args = ap.parse_args()
    print(f"bench_bigmotor: calibrate with the defaults on bench_zoo motors of 24-28 pole pairs; "
          f"{os.cpu_count()} cores, load average at start {os.getloadavg()[0]:.1f}")  # fmt: skip
    print("work: SEM solves (p/N/iterations), Gauss-Newton systems (strided + exact), "
          "sum N p^2 / stride, un-warp trials/iterations; time: calibrate's CPU and wall [s] "
          "with the 1-minute load average before/after\n")  # fmt: skip
    jobs = [(s, None) for s in args.seeds] + [(s, args.samples) for s in args.long]
    for seed, samples in jobs:
        c = Counters()
        c.install()
        r = run(seed, samples, c)
        solves = ", ".join(f"{p}/{n}/{it}" for p, n, it, _ in c.solves)
        print(f"seed {r['seed']:2d} {r['kind']:>6} n_m {r['n_m']} N {r['N']:6d}: {r['status']:<8} "
              f"star/fl {r['star']:.3f} pred/fl {r['pred']:.3f} model {r['model']}")  # fmt: skip
        print(f"   SEM solves {len(c.solves)} [{solves}]; systems {c.systems['strided']} strided + "
              f"{c.systems['exact']} exact; N p^2/stride {c.work:.3g}; un-warp "
              f"{c.unwarp_trials} trials / {c.unwarp_iterations} iterations")  # fmt: skip
        print(f"   calibrate CPU {r['cpu']:.1f} s, wall {r['wall']:.1f} s at load "
              f"{r['load'][0]:.1f}->{r['load'][1]:.1f}", flush=True)  # fmt: skip
    print(f"\nload average at end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
