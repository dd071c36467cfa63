"""What a user waits for: the ``hallcal`` command end to end, against a same-process yardstick.

Measured in one run, on the paper-size closed-loop run (the virtual bench's defaults: 11 pole
pairs, ramp 0 -> 13 rad in 26 s at 4 kHz, 104 000 samples, written as CSV; ``[plant]`` given,
Fourier basis with harmonics 1..11):

- the normalizer: a plain-Python closed-loop simulation of the same 104 000 samples (the same
  per-sample recursion as :mod:`hallcal.sim.loop`, one sample at a time, no NumPy in the loop),
  timed in this process; it makes the figures comparable across machines and loads;
- ``hallcal calibrate`` end to end in a fresh process (start-up, imports, numba cache loading,
  reading the CSV, SEM, adequacy, table, validation, writing the artifact), as seconds and as a
  ratio to the normalizer (runs interleaved with the normalizer's, ratio per pair), with its
  peak resident memory and where the time goes;
- ``hallcal --help`` and ``hallcal calibrate --help`` against Python's own start-up;
- reading the 104 000-row CSV (``hallcal.io.read_dataset``, in this process, pyarrow loaded);
- ``hallcal reconstruct`` on 10 million samples end to end in a fresh process, input and output
  as ``.npz`` (uncompressed: the columns are mapped from the file), with its peak memory;
- the machine's load average (``os.getloadavg``, as ``uptime`` prints it) before and after.

The machine is shared: wall times on a busy machine are longer than on a quiet one, the ratio
to the normalizer less so. Run: ``python benchmarks/bench_cli.py [--repeats N] [--keep DIR]``;
the output is committed in ``benchmarks/bench_cli.txt``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hallcal._constants import TWO_PI
from hallcal.io import default_setup, read_dataset, write_dataset, write_json, write_setup
from hallcal.pipeline import simulate
from hallcal.pipeline.plant import closed_loop
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sim.loop import simulate_loop

RECONSTRUCT_SAMPLES = 10_000_000


# ---- the normalizer ----------------------------------------------------------------------------


def python_closed_loop(r, loop, theta, harmonics, pole_pairs):
    """The closed loop of :mod:`hallcal.sim.loop` in plain Python, one sample at a time.

    Line by line the recursion of the compiled kernel ``hallcal.sim.loop_kernel.simulate``
    (without noise):
    plant angle y0 = C_G x_G; Hall signals d_h = theta_h . [1, sin(h y0), cos(h y0), ...];
    f_init (projection, atan2, unwrapping around n_m y[k-1]); e = r - y; controller output
    u = C_C x_C + D_C e; both state updates. Returns the f_init output y of every sample.
    """
    Ag, Bg, Cg = loop.plant.A.tolist(), loop.plant.B.tolist(), loop.plant.C.tolist()
    Ac, Bc, Cc = loop.controller.A.tolist(), loop.controller.B.tolist(), loop.controller.C.tolist()
    Dc = float(loop.controller.D)
    P, off = loop.projection.tolist(), loop.offset.tolist()
    theta = theta.tolist()
    harmonics = [float(h) for h in harmonics]
    n = float(pole_pairs)
    ng, nc, m = len(Bg), len(Bc), 1 + 2 * len(harmonics)
    xg, xc = [0.0] * ng, [0.0] * nc
    basis = [0.0] * m
    d = [0.0] * 3
    y_prev = 0.0
    ys = []
    for rk in r.tolist():
        y0 = 0.0
        for i in range(ng):
            y0 += Cg[i] * xg[i]
        basis[0] = 1.0
        for j in range(len(harmonics)):
            basis[1 + 2 * j] = math.sin(harmonics[j] * y0)
            basis[2 + 2 * j] = math.cos(harmonics[j] * y0)
        for h in range(3):
            acc = 0.0
            for j in range(m):
                acc += theta[h][j] * basis[j]
            d[h] = acc
        alpha = 0.0
        beta = 0.0
        for h in range(3):
            alpha += P[0][h] * (d[h] - off[h])
            beta += P[1][h] * (d[h] - off[h])
        ref = n * y_prev
        x = math.atan2(beta, alpha) - ref + math.pi
        y = (ref + x - TWO_PI * math.floor(x / TWO_PI) - math.pi) / n
        e = rk - y
        u = Dc * e
        for i in range(nc):
            u += Cc[i] * xc[i]
        xc_next = [0.0] * nc
        for i in range(nc):
            acc = Bc[i] * e
            for j in range(nc):
                acc += Ac[i][j] * xc[j]
            xc_next[i] = acc
        xg_next = [0.0] * ng
        for i in range(ng):
            acc = Bg[i] * u
            for j in range(ng):
                acc += Ag[i][j] * xg[j]
            xg_next[i] = acc
        xc, xg = xc_next, xg_next
        y_prev = y
        ys.append(y)
    return ys


# ---- helpers -----------------------------------------------------------------------------------


#: The commands run as a user's would: with Python's bytecode cache (this machine's sessions set
#: PYTHONDONTWRITEBYTECODE, which makes every start compile hallcal's modules anew).
CHILD_ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}

#: Runs the command line like the ``hallcal`` script and, at exit, writes the process's peak
#: resident memory (VmHWM of /proc/self/status) to the file named by HALLCAL_BENCH_PEAK. The
#: rusage of a child is no good here: Linux counts in it the parent's memory at fork time.
_RUN_AND_REPORT_PEAK = """
import atexit, os, sys
def _peak():
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                with open(os.environ["HALLCAL_BENCH_PEAK"], "w") as f:
                    f.write(line.split()[1])
atexit.register(_peak)
from hallcal.cli import main
sys.argv = ["hallcal", *sys.argv[1:]]
main()
"""


def run_measured(args: list[str], cwd: Path) -> tuple[float, float, float]:
    """Run ``hallcal ARGS`` in a fresh process: wall time [s], CPU time (user + sys) [s] and peak
    resident memory [MB] of that process."""
    peak_file = cwd / ".peak"
    env = {**CHILD_ENV, "HALLCAL_BENCH_PEAK": str(peak_file)}
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-c", _RUN_AND_REPORT_PEAK, *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        err = proc.stderr.read().decode() if proc.stderr else ""
        raise RuntimeError(f"hallcal {' '.join(args)} failed ({code}): {err}")
    peak = int(peak_file.read_text()) / 1024.0 if peak_file.exists() else float("nan")
    return wall, usage.ru_utime + usage.ru_stime, peak


def run_wall(cmd: list[str], cwd: Path) -> float:
    """Wall time [s] of a command."""
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, env=CHILD_ENV, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def load_note() -> str:
    one, five, _ = os.getloadavg()
    cores = os.cpu_count() or 1
    busy = one > 0.75 * cores
    note = f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {cores} cores"
    if busy:
        note += " -- BUSY: the machine is shared with other work; wall times are inflated"
    return note


def stat(values: list[float]) -> str:
    v = np.asarray(values)
    return f"median {np.median(v):.3f} s, min {v.min():.3f} s, max {v.max():.3f} s (n={v.size})"


STAGES = r"""
import json, sys, time
t0 = time.perf_counter()
marks = {}
memory = {}
def status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) / 1024.0
def mark(name, t):
    marks[name] = marks.get(name, 0.0) + time.perf_counter() - t
    memory[name] = (status("VmRSS:"), status("VmHWM:"))
t = time.perf_counter()
from hallcal.cli import main
import hallcal.api, hallcal.pipeline.closed_loop as cl, hallcal.fit.sem as sem
mark("imports (numpy, scipy.linalg, numba, pyarrow, hallcal)", t)
import numba
from numba.core import dispatcher
def wrap(owner, name, label):
    f = getattr(owner, name)
    def g(*a, **k):
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            mark(label, t)
    setattr(owner, name, g)
wrap(dispatcher.Dispatcher, "_compile_for_args",
     "numba: first call of each kernel (cache load, runtime start)")
import hallcal.io.dataset as ds
wrap(hallcal.api, "read_dataset", "read the CSV")
wrap(cl, "solve_sem", "SEM (all iterations, numba loads inside)")
wrap(cl, "select_cogging", "cogging torque search in the residual")
wrap(cl, "assess", "model adequacy")
wrap(cl, "build_lut", "lookup table")
wrap(cl.sensors, "examine", "sensor examination (rails, noise, drift in f_init's view, spacing)")
wrap(cl, "observer_check", "observer check (injectivity of the three-signal curve)")
wrap(cl, "power_up_analysis", "power-up identifiability of the pole pair")
wrap(cl, "validate", "validation against y_ref")
import hallcal.pipeline.calibration as pc  # api.Calibration saves through it
wrap(pc.Calibration, "save", "write the artifact")
sys.argv = ["hallcal", *sys.argv[1:]]
try:
    main()
except SystemExit:
    pass
marks["total in the process"] = time.perf_counter() - t0
memory["total in the process"] = (status("VmRSS:"), status("VmHWM:"))
print(json.dumps([marks, memory]), file=sys.stderr)
"""


# ---- the benchmark -----------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5, help="calibrate/normalizer pairs")
    ap.add_argument("--keep", type=Path, default=None, help="work in this folder and keep it")
    args = ap.parse_args()

    work = args.keep or Path(tempfile.mkdtemp(prefix="bench_cli_"))
    work.mkdir(parents=True, exist_ok=True)
    # hallcal's byte-code, as an installation has it (pip compiles on install): without it, a
    # shell with PYTHONDONTWRITEBYTECODE=1 compiles hallcal's sources at every start (measured
    # 0.10 s of CPU per calibrate, 1.73 against 1.63 s)
    import compileall

    import hallcal

    compileall.compile_dir(Path(hallcal.__file__).parent, quiet=1)
    import pyarrow
    import scipy

    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
        f"{platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}, "
        f"pyarrow {pyarrow.__version__}"
    )
    print(f"at start: {load_note()}")

    # the paper-size run, as a user would have it: CSV data, setup with [plant]
    setup = default_setup()
    run = simulate(setup)
    write_dataset(work / "cal.csv", run.columns())
    write_json(work / "cal.truth.json", run.truth_dict())
    write_setup(work / "setup.toml", setup)
    calibrate = ["calibrate", "cal.csv", "--setup", "setup.toml", "--out", "cal.json"]
    run_measured(calibrate, work)  # fills the numba cache if this is a fresh checkout
    csv_mb = os.path.getsize(work / "cal.csv") / 1e6
    print(f"\npaper run: {run.n_samples} samples, CSV {csv_mb:.1f} MB")

    # the normalizer: check it is the same loop, then time it interleaved with calibrate
    truth = run.truth_dict()
    loop = closed_loop(setup, setup.plant)
    basis = FourierBasis(tuple(truth["harmonics"]))
    theta = np.asarray(truth["theta"], dtype=np.float64)
    ref = simulate_loop(loop, FluxModel(basis, theta), run.r[:2000]).y
    check = python_closed_loop(run.r[:2000], loop, theta, basis.harmonics, setup.pole_pairs)
    mismatch = float(np.max(np.abs(np.asarray(check) - ref)))
    assert mismatch < 1e-9, mismatch

    norm_times, norm_cpu, cal_times, cal_cpu, cal_rss, ratios, cpu_ratios = ([] for _ in range(7))
    for _ in range(args.repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        python_closed_loop(run.r, loop, theta, basis.harmonics, setup.pole_pairs)
        norm_times.append(time.perf_counter() - t0)
        norm_cpu.append(time.process_time() - c0)
        wall, cpu, rss = run_measured(calibrate, work)
        cal_times.append(wall)
        cal_cpu.append(cpu)
        cal_rss.append(rss)
        ratios.append(wall / norm_times[-1])
        cpu_ratios.append(cpu / norm_cpu[-1])
    print(
        f"\n[normalizer] plain-Python closed loop, {run.n_samples} samples "
        f"(matches hallcal.sim.loop to {mismatch:.1e} rad): {stat(norm_times)}; "
        f"CPU median {np.median(norm_cpu):.3f} s"
    )
    print(
        "\n[hallcal calibrate cal.csv --setup setup.toml --out cal.json] fresh process, end to end"
    )
    print(f"  wall time: {stat(cal_times)}")
    print(f"  CPU time (user + sys): median {np.median(cal_cpu):.3f} s")
    print(
        f"  ratio to the normalizer (per interleaved pair): wall median {np.median(ratios):.3f}, "
        f"min {np.min(ratios):.3f}; CPU median {np.median(cpu_ratios):.3f} (target <= 0.25)"
    )
    print(
        f"  peak RSS: median {np.median(cal_rss):.0f} MB, max {np.max(cal_rss):.0f} MB "
        "(target <= 300 MB)"
    )

    stages = subprocess.run(
        [
            sys.executable,
            "-c",
            STAGES,
            "calibrate",
            "cal.csv",
            "--setup",
            "setup.toml",
            "--out",
            "cal.json",
        ],
        cwd=work,
        env=CHILD_ENV,
        capture_output=True,
        text=True,
        check=True,
    )
    marks, memory = json.loads(stages.stderr.strip().splitlines()[-1])
    print(
        "  where the time and memory go (one more run; wall time of each stage, nested stages "
        "overlap; resident memory after the stage and the peak so far):"
    )
    for name, seconds in marks.items():
        now, peak = memory[name]
        print(f"    {seconds:7.3f} s  {now:5.0f} MB  peak {peak:5.0f} MB  {name}")
    print(
        "  (every pipeline step's peak memory and time: benchmarks/bench_memory.py; the "
        "interpreter's exit is in the end-to-end figures above, not in these stages)"
    )

    # start-up
    print()
    script = Path(sys.executable).with_name("hallcal")  # the console script a user runs
    for label, cmd in [
        ("python -c pass (Python's own start-up)", [sys.executable, "-c", "pass"]),
        ("hallcal --help", [str(script), "--help"]),
        ("hallcal calibrate --help", [str(script), "calibrate", "--help"]),
    ]:
        times = [run_wall(cmd, work) for _ in range(9)]
        print(f"[{label}] {stat(times)}" + (" (target <= 0.3 s)" if "hallcal" in label else ""))

    # reading the CSV
    read_dataset(work / "cal.csv")
    times = []
    for _ in range(15):
        t0 = time.perf_counter()
        read_dataset(work / "cal.csv")
        times.append(time.perf_counter() - t0)
    print(
        f"\n[read_dataset cal.csv] {run.n_samples} rows x 8 columns, pyarrow loaded: "
        f"{stat(times)} (target <= 0.060 s)"
    )
    columns = read_dataset(work / "cal.csv").columns
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        write_dataset(work / "copy.csv", columns)
        times.append(time.perf_counter() - t0)
    print(f"[write_dataset copy.csv] the same table, atomically (synced): {stat(times)}")

    # reconstruct on 10 million samples
    big = work / "run10M.npz"
    _ten_million(big, truth)
    cmd = ["reconstruct", "cal.json", big.name, "--out", "angles10M.npz"]
    run_measured(cmd, work)
    walls, cpus, rsss = [], [], []
    for _ in range(3):
        wall, cpu, rss = run_measured(cmd, work)
        walls.append(wall)
        cpus.append(cpu)
        rsss.append(rss)
    size = os.path.getsize(big) / 1e6
    print(
        f"\n[hallcal reconstruct cal.json run10M.npz --out angles10M.npz] {RECONSTRUCT_SAMPLES} "
        f"samples (d1, d2, d3 in an uncompressed .npz of {size:.0f} MB, in the page cache; "
        f"y_init, y_star written to .npz, synced to disk), fresh process, end to end"
    )
    print(f"  wall time: {stat(walls)} (target <= 1.5 s)")
    print(f"  CPU time (user + sys): median {np.median(cpus):.3f} s")
    print(f"  peak RSS: median {np.median(rsss):.0f} MB (target <= 1500 MB)")
    print(f"  throughput: {RECONSTRUCT_SAMPLES / np.median(walls) / 1e6:.1f} million samples/s")

    print(f"\nat end: {load_note()}")
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)


def _ten_million(path: Path, truth: dict) -> None:
    """Hall signals of the bench's motor turning back and forth over 60 rad, with its noise."""
    flux = FluxModel(FourierBasis(tuple(truth["harmonics"])), np.asarray(truth["theta"]))
    rng = np.random.default_rng(1)
    n = RECONSTRUCT_SAMPLES
    cols = {name: np.empty(n) for name in ("d1", "d2", "d3")}
    sigma = math.sqrt(truth["noise_variance"])
    for start in range(0, n, 1 << 20):
        k = np.arange(start, min(start + (1 << 20), n))
        y0 = 2.0 * np.sin(TWO_PI * 2.5e-6 * k) + 60.0 * k / n
        d = flux(y0) + sigma * rng.standard_normal((k.size, 3))
        for h, name in enumerate(cols):
            cols[name][k] = d[:, h]
    write_dataset(path, cols)


if __name__ == "__main__":
    main()
