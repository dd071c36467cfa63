"""Speed of the closed loop and of its sensitivities (the inner loop of the identification).

Paper-size run (104 000 samples, 11 pole pairs, Fourier flux with harmonics 1..11): one
simulation, one model simulation and one structured Gauss-Newton pass (J^T J, J^T e, e^T e
without the dense Jacobian, :mod:`hallcal.fit.gauss_newton`) with one and two threads. Then a
large model: harmonics 1..55 (333 parameters) on 160 000 samples,
exact (stride 1) and with the strided Hessian of the iterations (stride 4).

Run: ``python benchmarks/bench_loop.py``; the output is committed beside it. The machine has two
cores shared with other work: the load average is printed before and after.
"""

from __future__ import annotations

import subprocess
import time

import numpy as np

from hallcal.fit.gauss_newton import ParameterLayout, gauss_newton_system, simulate_model
from hallcal.sensor.flux import FourierBasis
from hallcal.sim.bench import BenchConfig
from hallcal.sim.loop import simulate_loop


def best_of(fn, repeats: int = 7) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.min(times)), float(np.median(times))


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _theta(truth, basis: FourierBasis) -> np.ndarray:
    y = 2 * np.pi * np.arange(4096) / 4096
    return np.linalg.lstsq(basis.evaluate(y), truth(y), rcond=None)[0].T


def main() -> None:
    print(f"uptime: {_uptime()}")
    cfg = BenchConfig(seed=1)
    truth, loop = cfg.truth(), cfg.loop()
    r = np.linspace(0.0, 13.0, 104_000, endpoint=False)
    noise = np.sqrt(cfg.noise_variance) * np.random.default_rng(0).standard_normal((r.size, 3))
    d = simulate_loop(loop, truth, r, noise=noise).d
    layout = ParameterLayout(truth.basis)
    x = truth.theta.ravel()
    t0 = time.perf_counter()
    simulate_loop(loop, truth, r[:100], noise=noise[:100])
    gauss_newton_system(loop, layout, x, r[:100], d[:100])
    simulate_model(loop, layout, x, r[:100])
    print(f"numba compilation or cache load (3 kernels): {time.perf_counter() - t0:.2f} s")
    mn, md = best_of(lambda: simulate_loop(loop, truth, r, noise=noise))
    print(
        f"simulate_loop, 104000 samples: min {mn * 1e3:.1f} ms, median {md * 1e3:.1f} ms "
        f"({md / r.size * 1e9:.0f} ns/sample)"
    )
    mn, md = best_of(lambda: simulate_model(loop, layout, x, r))
    print(f"simulate_model (trigonometric recursion), same run: min {mn * 1e3:.1f} ms, "
          f"median {md * 1e3:.1f} ms")  # fmt: skip
    for threads in (1, 2):
        mn, md = best_of(lambda t=threads: gauss_newton_system(loop, layout, x, r, d, threads=t),
                         repeats=5)  # fmt: skip
        print(f"gauss_newton_system, same run, exact J^T J, {threads} thread(s): "
              f"min {mn:.3f} s, median {md:.3f} s")  # fmt: skip

    big = BenchConfig(electrical_harmonics=((3, 0.10), (5, 0.04)), misalignment_deg=(0, 2, 0),
                      seed=1)  # fmt: skip
    basis = FourierBasis(tuple(range(1, 56)))
    lay = ParameterLayout(basis)
    rb = np.linspace(0.0, 20.0, 160_000, endpoint=False)
    xb = _theta(big.truth(), basis).ravel()
    db = simulate_model(big.loop(), lay, xb, rb).d
    print(f"large model: harmonics 1..55 ({lay.size} parameters), {rb.size} samples")
    for stride in (1, 4):
        for threads in (1, 2):
            mn, md = best_of(
                lambda t=threads, s=stride: gauss_newton_system(
                    big.loop(), lay, xb, rb, db, threads=t, stride=s
                ),
                repeats=3,
            )
            print(f"  gauss_newton_system, stride {stride}, {threads} thread(s): "
                  f"min {mn:.3f} s, median {md:.3f} s")  # fmt: skip
    mn, md = best_of(lambda: simulate_model(big.loop(), lay, xb, rb), repeats=3)
    print(f"  simulate_model: min {mn * 1e3:.0f} ms, median {md * 1e3:.0f} ms")
    print("one pass against the model size (harmonics 1..K, same run, one thread, min of 3):")
    for K in (11, 33, 55, 88):
        bk = FourierBasis(tuple(range(1, K + 1)))
        lk = ParameterLayout(bk)
        xk = _theta(big.truth(), bk).ravel()
        row = []
        for stride in (1, 4):
            mn, _ = best_of(
                lambda s=stride, lk=lk, xk=xk: gauss_newton_system(
                    big.loop(), lk, xk, rb, db, threads=1, stride=s
                ),
                repeats=3,
            )  # fmt: skip
            row.append(f"stride {stride}: {mn:.3f} s")
        print(f"  K = {K:>2d}, p = {lk.size:>3d}: " + ", ".join(row))
    print(f"uptime: {_uptime()}")


if __name__ == "__main__":
    main()
