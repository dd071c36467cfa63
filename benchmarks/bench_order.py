"""Speed of the automatic model order, ``harmonics = "auto"`` (:func:`select_harmonics`).

The benches of ``tests/test_order.py`` (the paper's loop and plant, 11 pole pairs, default ramp
run: 104 000 samples at 4 kHz): the paper's flux, a trapezoidal flux (3rd electrical harmonic
10 %, 5th 4 %), and the paper's flux with cogging or a load torque. The test asserts what the
selection finds and how much work it takes (models fitted, SEM iterations); the wall time it
takes on this machine is measured here, against the default time budget (30 s), after a warm-up
call that compiles the numba kernels. Validation on a fresh run (another noise seed, ramp
0 -> 12 rad in 24 s) against the true angle.

Run: ``python benchmarks/bench_order.py > benchmarks/bench_order.txt`` (about a minute on two
cores). Times are wall-clock on a shared 2-core machine; the load average is printed.
"""

from __future__ import annotations

import platform
import subprocess
import time

import numpy as np

from hallcal.fit.order import select_harmonics
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run

BENCHES = {
    "paper": BenchConfig(),
    "trapezoid": BenchConfig(electrical_harmonics=((3, 0.10), (5, 0.04)), seed=7),
    "cogging 2e-2": BenchConfig(cogging=2e-2),
    "disturbance 2e-2": BenchConfig(torque_disturbance=2e-2),
}
REPEATS = 3
BUDGET = 30.0  # the target for a whole calibrate [s] (the search has a work budget only)


def _load() -> str:
    out = subprocess.run(["uptime"], capture_output=True, text=True).stdout
    return out.strip().rpartition("load average:")[2].strip()


def main() -> None:
    print('Benchmark: harmonics = "auto" (select_harmonics) on the benches of tests/test_order.py')
    print(f"python {platform.python_version()}, numpy {np.__version__}, load average {_load()}")
    warm = ramp_run(BenchConfig(), duration=2.0, ramp_end=1.0)
    select_harmonics(BenchConfig().loop(), warm.r, warm.d, y=warm.y, pole_pairs=11)
    print(
        f"{'bench':<17} {'samples':>7}  {'wall s (min..max)':<18} {'budget':>6}  {'status':<10} "
        f"{'harmonics':>9}  models  SEM it.  f_star/floor  load"
    )
    for name, cfg in BENCHES.items():
        run = ramp_run(cfg)
        val = ramp_run(cfg, ramp_end=12.0, duration=24.0, seed=99)
        times, sel = [], None
        for _ in range(REPEATS):
            t0 = time.perf_counter()
            sel = select_harmonics(cfg.loop(), run.r, run.d, y=run.y, pole_pairs=cfg.pole_pairs)
            times.append(time.perf_counter() - t0)
        assert sel is not None
        lut = build_lut(sel.sem.flux, cfg.pole_pairs)
        e_star = angle_error(lut.f_star(val.d), val.y0).rms if lut.bijective else np.inf
        wall = f"{np.median(times):5.2f} ({min(times):.2f}..{max(times):.2f})"
        print(
            f"{name:<17} {run.r.size:>7}  {wall:<18} {np.median(times) / BUDGET:6.0%}  "
            f"{sel.status:<10} {len(sel.harmonics):>9}  "
            f"{len(sel.candidates):>6}  {sel.sem.iterations:>7}  {e_star / cfg.noise_floor:12.3f}"
            f"  {_load()}",
            flush=True,
        )
    print(f"wall: median of {REPEATS} calls; budget: median wall time / the default budget")


if __name__ == "__main__":
    main()
