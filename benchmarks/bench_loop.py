"""Issue 2 speed check: the closed-loop simulation (inner loop of the identification).

Paper-size run (104 000 samples, 11 pole pairs, Fourier flux with harmonics 1..11): wall time of
one simulation after numba compilation (target: well under 0.1 s) and of one exact Jacobian pass
(69 parameters). Run: ``python benchmarks/bench_loop.py``; output committed beside it.
"""

from __future__ import annotations

import time

import numpy as np

from hallcal.sim.bench import BenchConfig
from hallcal.sim.loop import loop_jacobian, simulate_loop


def best_of(fn, repeats: int = 7) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.min(times)), float(np.median(times))


def main() -> None:
    cfg = BenchConfig(seed=1)
    truth, loop = cfg.truth(), cfg.loop()
    r = np.linspace(0.0, 13.0, 104_000, endpoint=False)
    noise = np.sqrt(cfg.noise_variance) * np.random.default_rng(0).standard_normal((r.size, 3))
    t0 = time.perf_counter()
    simulate_loop(loop, truth, r[:100], noise=noise[:100])
    loop_jacobian(loop, truth, r[:100])
    print(f"numba compilation or cache load: {time.perf_counter() - t0:.2f} s")
    mn, md = best_of(lambda: simulate_loop(loop, truth, r, noise=noise))
    print(
        f"simulate_loop, 104000 samples: min {mn * 1e3:.1f} ms, median {md * 1e3:.1f} ms "
        f"({md / r.size * 1e9:.0f} ns/sample)"
    )
    out = np.empty((r.size, 3, truth.theta.size))
    mn, md = best_of(lambda: loop_jacobian(loop, truth, r, out=out), repeats=5)
    print(
        f"loop_jacobian, 104000 samples x {truth.theta.size} parameters: min {mn:.3f} s, "
        f"median {md:.3f} s"
    )


if __name__ == "__main__":
    main()
