"""Benchmark: the paper's kernel model (m = 400) at the experiment size, against Fourier 1..11.

Benches shaped like the experiment section of van Meer et al.: 11 pole pairs, trapezoidal flux
(electrical harmonics 3 and 5), per-magnet variation 0.04, Hall noise 7.5e-6, ramp 0 -> 20 rad
in 40 s at 4 kHz (160 000 samples); with per-pole amplitude modulation 0.02 ("pole_modulation"
bench: sidebands 11k +- 1..3 in the truth) or without it (truth harmonics 1..11, 33, 55).
Validation on a fresh run (another noise seed, 0 -> 18 rad in 36 s) against the true angle.

Rows: the kernel model by :func:`hallcal.fit.kernel.solve_kernel_sem` with its spectrum learned per
harmonic (ARD, the default) and with the squared-exponential kernel's own Bessel spectrum
(evidence and GCV), the Fourier model with harmonics 1..11 by :func:`hallcal.fit.sem.solve_sem` on
the same data, and, as a reference, a Fourier model with exactly the truth's harmonics (oracle
structure, dense :func:`solve_sem`). Tables over seeds 1..4 follow for both benches (another truth
and noise each); a last run with 100x less noise shows whether the remaining excess over the
noise floor is variance (it scales with the noise) or bias.

Run: ``python benchmarks/bench_kernel.py > benchmarks/bench_kernel.txt`` (about 10 minutes on
2 cores). Times are wall-clock on a shared 2-core machine and vary with its load.
"""

from __future__ import annotations

import math
import os
import platform
import resource
import time
from dataclasses import replace

import numpy as np

from hallcal.fit.kernel import solve_kernel_sem
from hallcal.fit.sem import solve_sem
from hallcal.sensor.flux import FourierBasis
from hallcal.sensor.lut import build_lut
from hallcal.sensor.metrics import angle_error
from hallcal.sim.bench import BenchConfig, ramp_run


def config(seed: int, pole_modulation: float = 0.02) -> BenchConfig:
    return BenchConfig(
        pole_pairs=11,
        electrical_harmonics=((3, 0.10), (5, 0.04)),
        pole_modulation=pole_modulation,
        magnet_variation=0.04,
        seed=seed,
    )


def errors(flux, val) -> tuple[float, float]:
    lut = build_lut(flux, 11)
    return (
        angle_error(lut.f_init(val.d), val.y0).rms,
        angle_error(lut.f_star(val.d), val.y0).rms,
    )


def seed_table(title: str, pole_modulation: float, seeds: tuple[int, ...]) -> None:
    print(f"\n== {title}: seeds {', '.join(map(str, seeds))}; f_star errors in mrad ==")
    head = f"{'seed':>4}{'ARD [s]':>9}{'Bessel [s]':>11}{'F11 [s]':>8}{'f_init':>8}{'ARD':>8}"
    head += f"{'Bessel':>8}{'F11':>7}{'oracle':>8}{'ARD/fl':>8}{'Bes/fl':>8}{'orc/fl':>8}"
    head += f"{'l':>8}{'K':>4}{'settled':>8}"
    print(head + "\n" + "-" * len(head))
    for seed in seeds:
        c = config(seed, pole_modulation)
        run = ramp_run(c, ramp_end=20.0, duration=40.0, seed=seed)
        val = ramp_run(c, ramp_end=18.0, duration=36.0, seed=seed + 100)
        t = time.perf_counter()
        res = solve_kernel_sem(c.loop(), run.r, run.d, y=run.y)
        ta = time.perf_counter() - t
        t = time.perf_counter()
        bes = solve_kernel_sem(c.loop(), run.r, run.d, y=run.y, spectrum="bessel")
        tb = time.perf_counter() - t
        t = time.perf_counter()
        four = solve_sem(c.loop(), run.r, run.d, FourierBasis(tuple(range(1, 12))), y=run.y)
        tf = time.perf_counter() - t
        orc = solve_sem(c.loop(), run.r, run.d, run.truth.basis, y=run.y, tol=1e-10)
        ei, ea = errors(res.flux, val)
        _, eb = errors(bes.flux, val)
        _, ef = errors(four.flux, val)
        _, eo = errors(orc.flux, val)
        fl = c.noise_floor
        print(
            f"{seed:>4}{ta:>9.1f}{tb:>11.1f}{tf:>8.1f}{ei * 1e3:>8.3f}{ea * 1e3:>8.3f}"
            f"{eb * 1e3:>8.3f}{ef * 1e3:>7.3f}{eo * 1e3:>8.3f}{ea / fl:>8.2f}{eb / fl:>8.2f}"
            f"{eo / fl:>8.2f}{res.lengthscale:>8.4f}{res.harmonics:>4}{str(res.settled):>8}"
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
    solve_kernel_sem(cfg.loop(), w.r, w.d, points=64)

    run = ramp_run(cfg, ramp_end=20.0, duration=40.0, seed=3)
    val = ramp_run(cfg, ramp_end=18.0, duration=36.0, seed=103)
    loop = cfg.loop()
    floor = cfg.noise_floor
    print("\n== pole_modulation bench (pole_modulation = 0.02) ==")
    print(f"\nseed 3: N = {run.n_samples} samples, truth harmonics {run.truth.basis.harmonics}")
    print(f"noise floor {floor * 1e3:.4f} mrad RMS (sigma sqrt(2/3) / n_m)\n")
    head = (
        f"{'model':<34}{'params':>7}{'time [s]':>10}{'f_init':>9}{'f_star':>9}{'/floor':>8}  status"
    )
    print(head + "\n" + "-" * len(head))

    rows = []
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rss1 = rss0
    ard = None
    nominal_excess: dict[str, float] = {}
    for spec, crit in (("ard", "evidence"), ("bessel", "evidence"), ("bessel", "gcv")):
        t = time.perf_counter()
        res = solve_kernel_sem(
            loop, run.r, run.d, y=run.y, points=400, criterion=crit, spectrum=spec
        )
        wall = time.perf_counter() - t
        ei, es = errors(res.flux, val)
        if crit == "evidence":
            nominal_excess[spec] = math.sqrt(max(es**2 - floor**2, 0.0))
        if spec == "ard":
            ard = res
        else:
            rows.append((crit, res))
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        label = "kernel m=400, ARD" if spec == "ard" else f"kernel m=400, Bessel, {crit}"
        print(
            f"{label:<34}{res.flux.theta.size:>7}{wall:>10.1f}"
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
    assert ard is not None and ard.relevance is not None
    pv = ard.prior_variance
    kept = ard.relevance.active
    print(
        f"\nkernel, ARD: band 1..{ard.harmonics} ({ard.edge.status}, {len(ard.edge.trials)} "
        f"bands tried); reference kernel l = {ard.lengthscale:.4f} rad, sf = {ard.sf:.4g}; "
        f"{ard.ard_rounds} SEM solves, settled {ard.settled}, sigma^2 = "
        f"{ard.noise_variance:.4g}; {len(kept)} of {ard.harmonics} harmonics kept"
    )
    print("  harmonics dropped:", [h for h in range(1, ard.harmonics + 1) if pv[h] == 0])
    for crit, res in rows:
        print(
            f"\nkernel, {crit}: l = {res.lengthscale:.4f} rad, sf = {res.sf:.4g}, "
            f"rho = sigma^2/sf^2 = {res.penalty:.3g}, sigma^2 = {res.noise_variance:.4g} "
            f"(true {cfg.noise_variance:.3g}), K = {res.harmonics} harmonics, "
            f"{res.sem.iterations} LM iterations, settled {res.settled}, interior {res.interior}"
        )
        print(
            f"  criterion at the un-warped angle over l in [{res.lengthscale_range[0]:.3f}, "
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

    seed_table("pole_modulation bench", 0.02, (1, 2, 4))
    seed_table("bench without pole_modulation (truth harmonics 1..11, 33, 55)", 0.0, (1, 2, 3, 4))

    print("\nvariance or bias? pole_modulation bench, seed 3, 100x smaller Hall noise variance:")
    print("  (excess = sqrt(f_star^2 - floor^2); pure variance would shrink it 10x)")
    c = replace(config(3), noise_variance=config(3).noise_variance / 100)
    run = ramp_run(c, ramp_end=20.0, duration=40.0, seed=3)
    val = ramp_run(c, ramp_end=18.0, duration=36.0, seed=103)
    for spec in ("ard", "bessel"):
        res = solve_kernel_sem(c.loop(), run.r, run.d, y=run.y, spectrum=spec)
        ei, ek = errors(res.flux, val)
        fl = c.noise_floor
        ex, ex0 = math.sqrt(max(ek**2 - fl**2, 0.0)), nominal_excess[spec]
        print(
            f"  {spec:<6}: f_init {ei * 1e3:.3f} mrad, kernel f_star {ek * 1e3:.4f} mrad, floor "
            f"{fl * 1e3:.4f} mrad, ratio {ek / fl:.2f} (l = {res.lengthscale:.4f}, K = "
            f"{res.harmonics}, {res.status}); excess {ex * 1e3:.4f} mrad, "
            f"{ex0 / max(ex, 1e-300):.1f}x smaller than at the nominal noise"
        )
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"\npeak resident memory: {rss0:.0f} MB before the kernel solves, {rss1:.0f} MB after "
        f"them, {rss:.0f} MB at the end (the oracle's dense Jacobian in solve_sem)"
    )


if __name__ == "__main__":
    main()
