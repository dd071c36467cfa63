"""Fleet benchmark: 40 paper-size motors on 2 Dask workers against a sequential loop.

Each motor is the paper's simulation study with its own magnets (bench seed): 11 pole pairs, the
ramp 0 -> 13 rad in 26 s at 4 kHz (104 000 samples), the paper's G(s) and C(q), a Fourier model
with harmonics 1..11, and a validation run (another noise realization) on which f_init and
f_star are measured. Inputs are .npz files; every run writes the artifacts, the records and the
summary, as ``hallcal fleet`` does.

Three configurations, interleaved and repeated (``--repeats``, the best of each reported):

1. Sequential: ``run_fleet(..., scheduler="sequential")``, the motors one after the other in
   this process (numba compiled and BLAS pinned to one thread beforehand, so the loop is at its
   best).
2. Dask, as a user runs it: ``run_fleet(..., workers=2)``, a local cluster of 2 single-threaded
   worker processes started and closed inside the timed call.
3. Dask, steady state: the same on a cluster started beforehand (``scheduler=client``): what a
   long-running cluster on the line costs per batch.

Figures: wall time, motors per minute, and the speed-up of 2 and 3 over 1; for 1 and 3 also the
CPU time per motor (of this process, of the workers): equal CPU times and a smaller speed-up than
2x mean the time went to other users of the machine, not to Dask. The machine has
2 cores shared with others: the load average is printed before and after; figures taken under
load understate the speed-up.

Run: ``python benchmarks/bench_fleet.py [--motors 40] [--workers 2]``; the output is committed
in ``benchmarks/bench_fleet.txt``.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from hallcal import pipeline
from hallcal.fleet import run_fleet, summary_counts
from hallcal.io import default_setup, setup_from_dict, setup_to_toml, write_dataset


def uptime() -> str:
    """The load average line of ``uptime`` (the machine is shared)."""
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return "load average: " + ", ".join(f"{x:.2f}" for x in os.getloadavg())


def make_motors(root: Path, n: int) -> Path:
    """n paper-size motors (seed 1000 + i) and their manifest; returns the manifest."""
    base = default_setup().to_dict()
    lines = ["motor_id,data,setup,validation"]
    for i in range(n):
        d = {**base, "bench": {**base["bench"], "seed": 1000 + i}}
        setup = setup_from_dict(d)
        mid = f"motor{i:03d}"
        (root / f"{mid}.toml").write_text(setup_to_toml(setup))
        write_dataset(root / f"{mid}.npz", pipeline.simulate(setup).columns())
        write_dataset(root / f"{mid}-val.npz", pipeline.simulate(setup, seed=5000 + i).columns())
        lines.append(f"{mid},{mid}.npz,{mid}.toml,{mid}-val.npz")
    manifest = root / "manifest.csv"
    manifest.write_text("\n".join(lines) + "\n")
    return manifest


def timed(fn, n: int) -> tuple[float, str]:
    """Wall time of one batch and a line about it."""
    t0 = time.perf_counter()
    table = fn()
    dt = time.perf_counter() - t0
    c = summary_counts(table)
    assert c["ok"] + c["warning"] == n, c
    secs = np.array(table.column("seconds").to_pylist(), dtype=float)
    return dt, f"{dt:6.1f} s (per motor in its worker: median {np.median(secs):.2f} s)"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--motors", type=int, default=40)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    n = args.motors

    import dask
    import numba
    from distributed import Client

    from hallcal.fleet.run import _local_cluster

    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
        f"{platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, "
        f"dask {dask.__version__}"
    )
    print(f"load before: {uptime()}")
    root = Path(tempfile.mkdtemp(prefix="bench-fleet-"))
    try:
        t0 = time.perf_counter()
        manifest = make_motors(root, n)
        print(
            f"{n} motors of 104 000 samples (+ validation runs) simulated in "
            f"{time.perf_counter() - t0:.1f} s; {args.repeats} repeats of each configuration, "
            "interleaved; the best is the least disturbed by other users of the machine"
        )
        # compile and warm up once in this process, so the sequential loop is at its best
        run_fleet(_first(manifest, root), root / "warm", scheduler="sequential")
        w = args.workers
        names = (
            "sequential loop (1 process)",
            f"Dask, {w} workers, cluster started in the call",
            f"Dask, {w} workers, cluster already running",
        )
        times: dict[str, list[float]] = {k: [] for k in names}
        cpu: dict[str, list[float]] = {k: [] for k in names}
        with _local_cluster(w) as cluster, Client(cluster) as client:
            client.run(lambda: __import__("hallcal.fleet"))  # workers ready, as on a line
            run_fleet(_first(manifest, root), root / "warm2", scheduler=client, report=False)
            for rep in range(args.repeats):
                runs = (
                    lambda k: run_fleet(manifest, root / k, scheduler="sequential", report=False),
                    lambda k: run_fleet(manifest, root / k, workers=w, report=False),
                    lambda k: run_fleet(manifest, root / k, scheduler=client, report=False),
                )
                for i, (name, fn) in enumerate(zip(names, runs, strict=True)):
                    key = f"r{rep}-{i}"
                    cpu0 = _cpu(client) if i != 1 else None
                    dt, line = timed(lambda fn=fn, key=key: fn(key), n)
                    times[name].append(dt)
                    if cpu0 is not None:  # CPU time of the processes that calibrated
                        used = _cpu(client)[i == 2] - cpu0[i == 2]
                        cpu[name].append(used / n)
                        line += f", CPU {used / n:.2f} s per motor"
                    print(f"  repeat {rep + 1}: {name:<44s} {line}")
        print(f"\n{n} motors, best of {args.repeats}:")
        best = {k: min(v) for k, v in times.items()}
        for name in names:
            print(
                f"{name:<46s} {best[name]:6.1f} s  {60 * n / best[name]:6.1f} motors/min  "
                f"(median {np.median(times[name]):.1f} s)"
            )
        for name in (names[0], names[2]):
            print(f"CPU time per motor, {name}: median {np.median(cpu[name]):.2f} s")
        t_seq = best[names[0]]
        print(
            f"speed-up over the sequential loop, cluster started in the call: "
            f"{t_seq / best[names[1]]:.2f}x"
        )
        print(
            f"speed-up over the sequential loop, cluster already running:     "
            f"{t_seq / best[names[2]]:.2f}x"
        )
        t0 = time.perf_counter()
        again = run_fleet(manifest, root / "r0-1", workers=w, report=False)
        assert all(again.column("reused").to_pylist())
        print(f"rerun with every motor up to date: {time.perf_counter() - t0:.1f} s (hashing only)")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(f"load after: {uptime()}")


def _cpu(client) -> tuple[float, float]:
    """CPU seconds (user + system) used so far by this process and by the cluster's workers."""

    def used() -> float:
        t = os.times()
        return t.user + t.system

    return used(), sum(client.run(used).values())


def _first(manifest: Path, root: Path) -> list[dict[str, str]]:
    """The manifest's first motor as a row (to warm up)."""
    header, row = manifest.read_text().splitlines()[:2]
    return [
        {
            k: (str(root / v) if k != "motor_id" else v)
            for k, v in zip(header.split(","), row.split(","), strict=True)
        }
    ]


if __name__ == "__main__":
    main()
