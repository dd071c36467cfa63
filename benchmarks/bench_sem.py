"""SEM speed: the paper-size run against the paper's solver configuration, and a large model.

Paper-size run: the virtual bench's defaults (11 pole pairs, ramp 0 -> 13 rad in 26 s at 4 kHz,
104 000 samples), Fourier basis with harmonics 1..11 (3 x 23 = 69 parameters).

1. hallcal: Levenberg-Marquardt on exact forward sensitivities (after numba compilation), wall
   time of several repetitions.
2. The paper's configuration: an interior-point/trust-region method on finite-difference
   gradients over the same (compiled) simulator: scipy's ``trust-constr`` with ``jac="2-point"``
   and a BFGS Hessian, from the same start, stopped when it reaches hallcal's final cost (+0.1%)
   or after 10 minutes, whichever comes first.

3. A large model: the experiment-shaped bench (trapezoidal flux: 3rd electrical harmonic 10 %,
   5th 4 %; 2 degrees misalignment; the magnets differ in harmonics 1..10), 160 000 samples (ramp
   0 -> 20 rad in 40 s), the Fourier SEM with harmonics 1..55 given (333 parameters), which
   contain the truth. Each line runs in a fresh process, so that its peak resident memory (the
   bench simulation included) is its own; one and two threads. (How one Gauss-Newton pass grows
   with the model size: ``bench_loop.py``.)

Run: ``python benchmarks/bench_sem.py [--fd-budget SECONDS]``; the output is committed in
``benchmarks/bench_sem.txt``. The machine has two cores shared with other work: the load average
is printed before and after.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import subprocess
import sys
import time

import numpy as np
import scipy
import scipy.optimize

from hallcal.fit.sem import solve_sem
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run
from hallcal.sim.loop import simulate_loop


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed_sem(repeats: int, loop, run, basis, **options):
    """The SEM of `run` solved `repeats` times: the last result and each solve's wall time [s]."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = solve_sem(loop, run.r, run.d, basis, y=run.y, **options)
        times.append(time.perf_counter() - t0)
    return res, times


def _validation_errors(res, cfg, val) -> tuple[float, float]:
    """RMS errors of f_init and f_star (the table of `res`'s flux) on the validation run."""
    lut = build_lut(res.flux, cfg.pole_pairs)
    return angle_error(lut.f_init(val.d), val.y0).rms, angle_error(lut.f_star(val.d), val.y0).rms


def large(harmonics: int, threads: int, repeats: int) -> None:
    """One line: the Fourier SEM with harmonics 1..K on the 160 000-sample run (own process)."""
    cfg = BenchConfig(
        electrical_harmonics=((3, 0.10), (5, 0.04)), misalignment_deg=(0.0, 2.0, 0.0), seed=1
    )
    run = ramp_run(cfg, ramp_end=20.0, duration=40.0)
    val = ramp_run(cfg, ramp_end=12.0, duration=24.0, seed=101)
    basis = FourierBasis(tuple(range(1, harmonics + 1)))
    loop = cfg.loop()
    solve_sem(loop, run.r[:3000], run.d[:3000], basis, y=run.y[:3000], max_iterations=1)
    before = _rss_mb()
    res, times = _timed_sem(repeats, loop, run, basis, threads=threads)
    e_init, e_star = _validation_errors(res, cfg, val)
    print(
        f"  1..{harmonics:<3d} p = {3 * basis.size:>3d}  {threads} thread(s): "
        f"median {np.median(times):.2f} s (min {np.min(times):.2f}), {res.iterations} "
        f"iterations, {res.status}; f_star {e_star / cfg.noise_floor:.3f} x floor "
        f"(f_init {e_init / cfg.noise_floor:.1f} x); peak RSS {_rss_mb():.0f} MB "
        f"({before:.0f} MB before the SEM)",
        flush=True,
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fd-budget", type=float, default=600.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--large", nargs=2, type=int, metavar=("HARMONICS", "THREADS"))
    args = ap.parse_args()
    if args.large:
        large(args.large[0], args.large[1], repeats=3)
        return
    print(f"uptime: {_uptime()}")

    cfg = BenchConfig(seed=2024)
    run = ramp_run(cfg)
    val = ramp_run(cfg, ramp_end=12.0, duration=24.0, seed=99)
    basis = FourierBasis(tuple(range(1, 12)))
    loop = cfg.loop()
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
        f"{platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}"
    )
    print(
        f"problem: N = {run.n_samples} samples, p = {3 * basis.size} parameters, "
        f"3N = {3 * run.n_samples} residuals"
    )

    solve_sem(loop, run.r[:2000], run.d[:2000], basis, y=run.y[:2000])  # compile
    starts = {
        "paper's start theta_0 = pure sinusoids": _sinusoid_start(basis, run.d),
        "hallcal's default start (least squares at the measured f_init angle)": None,
    }
    for label, theta0 in starts.items():
        print(f"\n=== start: {label}")
        res, times = _timed_sem(args.repeats, loop, run, basis, theta0=theta0)
        e_init, e_star = _validation_errors(res, cfg, val)
        print("[hallcal] Levenberg-Marquardt, exact forward sensitivities")
        print(
            f"  wall time: median {np.median(times):.3f} s, min {np.min(times):.3f} s, "
            f"max {np.max(times):.3f} s over {len(times)} runs (target <= 2 s), "
            f"start included"
        )
        print(
            f"  iterations {res.iterations}, status {res.status}, cost {res.initial_cost:.6g} "
            f"-> {res.cost:.6g} (3 N sigma^2 = {3 * run.n_samples * cfg.noise_variance:.6g})"
        )
        print(
            f"  validation: f_init {1e3 * e_init:.4f} mrad, f_star {1e3 * e_star:.4f} mrad, "
            f"noise floor {1e3 * cfg.noise_floor:.4f} mrad"
        )
        th0 = res.theta0.ravel()
        fd_time, best, nfev, reached, status = _finite_difference_run(
            loop, basis, run.r, run.d, th0, res.cost * 1.001, args.fd_budget
        )
        print(
            "[paper configuration] scipy trust-constr, 2-point finite-difference gradients, "
            "BFGS Hessian, same simulator and start"
        )
        print(
            f"  wall time {fd_time:.1f} s, {nfev} simulations, final cost {best:.6g} "
            f"({'reached' if reached else 'did NOT reach'} hallcal's cost {res.cost:.6g} "
            f"+ 0.1%); {status}"
        )
        ratio = fd_time / np.median(times)
        print(
            f"  ratio (paper configuration / hallcal): {ratio:.0f}x"
            + (
                ""
                if reached
                else f"  (a lower bound: stopped at the {args.fd_budget:.0f} s budget)"
            )
        )
    print(
        "\n=== large model: experiment-shaped bench, 160000 samples, Fourier SEM with the "
        "harmonics given (each line a fresh process; 3 solves)"
    )
    for harmonics, threads in ((55, 2), (55, 1)):
        subprocess.run(
            [sys.executable, __file__, "--large", str(harmonics), str(threads)], check=True
        )
    print(f"uptime: {_uptime()}")


def _sinusoid_start(basis: FourierBasis, d: np.ndarray) -> np.ndarray:
    """The paper's theta_0: pure sinusoids (the inverse of f_init), amplitude and offset from
    the data's RMS and mean."""
    from hallcal.sensor.flux import sinusoidal_theta

    amp = np.sqrt(2.0) * np.std(d, axis=0)
    return sinusoidal_theta(basis, 11, amplitude=amp, offset=np.mean(d, axis=0))


def _finite_difference_run(loop, basis, r, d, theta0, target, budget):
    nfev = [0]

    def cost(th: np.ndarray) -> float:
        nfev[0] += 1
        s = simulate_loop(loop, FluxModel(basis, th.reshape(3, -1)), r)
        if s.status != "ok":
            return 1e12
        e = d - s.d
        return float(np.vdot(e, e))

    best = [cost(theta0)]
    t0 = time.perf_counter()

    def callback(xk, state=None):
        best[0] = min(best[0], float(state.fun) if state is not None else cost(xk))
        return bool(best[0] <= target or time.perf_counter() - t0 > budget)

    out = scipy.optimize.minimize(
        cost,
        theta0,
        method="trust-constr",
        jac="2-point",
        hess=scipy.optimize.BFGS(),
        callback=callback,
        options={"maxiter": 100000, "gtol": 1e-12, "xtol": 1e-14},
    )
    best[0] = min(best[0], float(out.fun))
    return time.perf_counter() - t0, best[0], nfev[0], best[0] <= target, out.message


if __name__ == "__main__":
    main()
