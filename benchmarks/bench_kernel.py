"""Benchmark: the paper's kernel model (m = 400) at the experiment size, against Fourier 1..11.

Bench shaped like the experiment section of van Meer et al.: 11 pole pairs, trapezoidal flux
(electrical harmonics 3 and 5), per-pole amplitude modulation and per-magnet variation, Hall
noise 7.5e-6, ramp 0 -> 20 rad in 40 s at 4 kHz (160 000 samples). Validation on a fresh run
(another noise seed, 0 -> 18 rad in 36 s) against the true angle.

Rows: the kernel model by :func:`hallcal.kernel.solve_kernel_sem` (evidence and GCV), the Fourier
model with harmonics 1..11 by :func:`hallcal.sem.solve_sem` on the same data, and, as a reference
for what any SEM can reach on this experiment, a Fourier model with exactly the truth's harmonics
(oracle structure, dense :func:`solve_sem`). A second table repeats the three on other seeds
(another truth and noise each); a last run with 100x less noise shows whether the kernel model's
excess over the noise floor is variance (it scales with the noise) or bias.

Run: ``python benchmarks/bench_kernel.py > benchmarks/bench_kernel.txt`` (about 4 minutes on
2 cores). Times are wall-clock on a shared 2-core machine and vary with its load.
"""

from __future__ import annotations

import os
import platform
import resource
import time
from dataclasses import replace

import numpy as np

from hallcal.bench import BenchConfig, ramp_run
from hallcal.flux import FourierBasis
from hallcal.kernel import solve_kernel_sem
from hallcal.lut import build_lut
from hallcal.metrics import angle_error
from hallcal.sem import solve_sem


def config(seed: int) -> BenchConfig:
    return BenchConfig(
        pole_pairs=11,
        electrical_harmonics=((3, 0.10), (5, 0.04)),
        pole_modulation=0.02,
        magnet_variation=0.04,
        seed=seed,
    )


def errors(flux, val) -> tuple[float, float]:
    lut = build_lut(flux, 11)
    return (
        angle_error(lut.f_init(val.d), val.y0).rms,
        angle_error(lut.f_star(val.d), val.y0).rms,
    )


def main() -> None:
    print(__doc__.split("\n\n")[0])
    print(
        f"python {platform.python_version()}, numpy {np.__version__}, "
        f"cpus {os.cpu_count()}, load average {os.getloadavg()[0]:.2f}"
    )
    # warm up the numba kernels (compilation is cached on disk; not part of the timings)
    cfg = config(3)
    w = ramp_run(cfg, ramp_end=1.0, duration=1.0, seed=0)
    solve_kernel_sem(cfg.loop(), w.r, w.d, points=64, rounds=1)

    run = ramp_run(cfg, ramp_end=20.0, duration=40.0, seed=3)
    val = ramp_run(cfg, ramp_end=18.0, duration=36.0, seed=103)
    loop = cfg.loop()
    floor = cfg.noise_floor
    print(f"\nseed 3: N = {run.n_samples} samples, truth harmonics {run.truth.basis.harmonics}")
    print(f"noise floor {floor * 1e3:.4f} mrad RMS (sigma sqrt(2/3) / n_m)\n")
    head = (
        f"{'model':<34}{'params':>7}{'time [s]':>10}{'f_init':>9}{'f_star':>9}{'/floor':>8}  status"
    )
    print(head + "\n" + "-" * len(head))

    rows = []
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rss1 = rss0
    for crit in ("evidence", "gcv"):
        t = time.perf_counter()
        res = solve_kernel_sem(loop, run.r, run.d, y=run.y, points=400, criterion=crit)
        wall = time.perf_counter() - t
        ei, es = errors(res.flux, val)
        rows.append((crit, res))
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(
            f"{'kernel m=400, ' + crit:<34}{res.flux.theta.size:>7}{wall:>10.1f}"
            f"{ei * 1e3:>9.3f}{es * 1e3:>9.3f}{es / floor:>8.2f}  {res.status}"
        )
    t = time.perf_counter()
    four = solve_sem(loop, run.r, run.d, FourierBasis(tuple(range(1, 12))), y=run.y)
    wall = time.perf_counter() - t
    ei, es = errors(four.flux, val)
    print(
        f"{'Fourier 1..11 (solve_sem)':<34}{four.flux.theta.size:>7}{wall:>10.1f}"
        f"{ei * 1e3:>9.3f}{es * 1e3:>9.3f}{es / floor:>8.2f}  {four.status}"
    )
    t = time.perf_counter()
    orc = solve_sem(loop, run.r, run.d, run.truth.basis, y=run.y, tol=1e-10)
    wall = time.perf_counter() - t
    ei, es = errors(orc.flux, val)
    print(
        f"{'Fourier, true harmonics (oracle)':<34}{orc.flux.theta.size:>7}{wall:>10.1f}"
        f"{ei * 1e3:>9.3f}{es * 1e3:>9.3f}{es / floor:>8.2f}  {orc.status}"
    )
    print("(errors in mrad RMS on the validation run; time = wall time of the solve)")

    for crit, res in rows:
        print(
            f"\nkernel, {crit}: l = {res.lengthscale:.4f} rad, sf = {res.sf:.4g}, "
            f"rho = sigma^2/sf^2 = {res.penalty:.3g}, sigma^2 = {res.noise_variance:.4g} "
            f"(true {cfg.noise_variance:.3g}), K = {res.harmonics} harmonics, "
            f"{res.gauss_newton_systems} Gauss-Newton systems, {res.sem.iterations} "
            f"LM iterations, settled {res.settled}, interior {res.interior}"
        )
        print(
            "  rounds (l, rho):",
            ", ".join(f"({p.lengthscale:.4f}, {p.penalty:.3g})" for p in res.rounds),
        )
        print(
            f"  criterion at the final solution over l in [{res.lengthscale_range[0]:.3f}, "
            f"{res.lengthscale_range[1]:.3f}]:"
        )
        best = min(c.value for c in res.criterion_values)
        for c in res.criterion_values:
            rel = c.value - best if crit == "evidence" else c.value / best - 1.0
            unit = "" if crit == "evidence" else " (relative)"
            print(
                f"    l = {c.lengthscale:7.4f}  rho = {c.penalty:9.3g}  "
                f"criterion - min = {rel:11.4g}{unit}  sigma^2 = {c.noise_variance:.4g}  "
                f"dof = {c.dof:6.1f}"
            )

    print("\nother seeds (truth and noise), kernel with the evidence; f_star errors in mrad:")
    head = f"{'seed':>4}{'kernel [s]':>12}{'Fourier11 [s]':>15}{'f_init':>9}{'kernel':>9}"
    head += f"{'Fourier11':>11}{'oracle':>9}{'kernel/floor':>14}{'oracle/floor':>14}"
    head += f"{'l':>8}{'K':>5}"
    print(head + "\n" + "-" * len(head))
    for seed in (1, 2, 4):
        c = config(seed)
        run = ramp_run(c, ramp_end=20.0, duration=40.0, seed=seed)
        val = ramp_run(c, ramp_end=18.0, duration=36.0, seed=seed + 100)
        t = time.perf_counter()
        res = solve_kernel_sem(c.loop(), run.r, run.d, y=run.y)
        tk = time.perf_counter() - t
        t = time.perf_counter()
        four = solve_sem(c.loop(), run.r, run.d, FourierBasis(tuple(range(1, 12))), y=run.y)
        tf = time.perf_counter() - t
        orc = solve_sem(c.loop(), run.r, run.d, run.truth.basis, y=run.y, tol=1e-10)
        ei, ek = errors(res.flux, val)
        _, ef = errors(four.flux, val)
        _, eo = errors(orc.flux, val)
        fl = c.noise_floor
        print(
            f"{seed:>4}{tk:>12.1f}{tf:>15.1f}{ei * 1e3:>9.3f}{ek * 1e3:>9.3f}{ef * 1e3:>11.3f}"
            f"{eo * 1e3:>9.3f}{ek / fl:>14.2f}{eo / fl:>14.2f}{res.lengthscale:>8.4f}"
            f"{res.harmonics:>5}"
        )

    print("\nvariance or bias? seed 3 with 100x smaller Hall noise variance (kernel, evidence):")
    c = replace(config(3), noise_variance=config(3).noise_variance / 100)
    run = ramp_run(c, ramp_end=20.0, duration=40.0, seed=3)
    val = ramp_run(c, ramp_end=18.0, duration=36.0, seed=103)
    res = solve_kernel_sem(c.loop(), run.r, run.d, y=run.y)
    ei, ek = errors(res.flux, val)
    print(
        f"  f_init {ei * 1e3:.3f} mrad, kernel f_star {ek * 1e3:.4f} mrad, floor "
        f"{c.noise_floor * 1e3:.4f} mrad, ratio {ek / c.noise_floor:.2f} (l = "
        f"{res.lengthscale:.4f}, K = {res.harmonics}, {res.status}): the excess over the floor "
        "scales with the noise"
    )
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"\npeak resident memory: {rss0:.0f} MB before the kernel solves, {rss1:.0f} MB after "
        f"them, {rss:.0f} MB at the end (the oracle's dense Jacobian in solve_sem)"
    )


if __name__ == "__main__":
    main()
