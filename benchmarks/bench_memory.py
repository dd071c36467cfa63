"""Benchmark: where a whole ``calibrate`` spends its memory and time, step by step.

Each case runs in a fresh Python process (imports included) with the pipeline's steps wrapped:
for every step the wall time, the CPU time of the process, the resident memory before and after
it, and its own peak: the kernel's high-water mark of the process (``VmHWM``), reset at the
start of each step (``echo 5 > /proc/self/clear_refs``), so a step's peak is the largest
resident size reached while it ran (nested steps count in their parents). ``process total`` is
the process's peak over the whole run; ``numba`` the first calls of the compiled kernels
(loading them from numba's cache, inside the steps above); the last line the child's wall and
CPU time as its parent sees them (``wait4``), interpreter start-up and exit included.

Cases:

- ``paper``: the paper-size closed-loop run (the virtual bench's defaults: 11 pole pairs, ramp
  0 -> 13 rad in 26 s at 4 kHz, 104 000 samples, ``[plant]`` given, Fourier harmonics 1..11),
  written as CSV and calibrated through the command line (``hallcal calibrate cal.csv --setup
  setup.toml --out cal.json``), as :mod:`bench_cli` does;
- ``rich-<model>``: the rich-magnet motor of :mod:`bench_rich` (every magnet its own shape,
  strength 0.075, seed 5; 160 000 samples), :func:`hallcal.calibrate` on the columns in memory,
  then ``save``, for the models ``kernel``, ``auto`` and ``F1..55`` of that benchmark.

Run: ``python benchmarks/bench_memory.py [--cases paper,rich-kernel,...] [--seed 5]
[--tracemalloc]`` (``--tracemalloc`` adds each step's peak of traced Python/NumPy allocations,
slower). Output committed in ``benchmarks/bench_memory.txt``; the load average is printed (the
machine is shared: times vary with it, memory does not).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

#: The steps wrapped in the child: (module, attribute, label). A class attribute is "Cls.meth".
STEPS = [
    ("hallcal.api", "as_dataset", "read / wrap the dataset"),
    ("hallcal.pipeline.closed_loop", "_signals", "signals (f_init of d)"),
    ("hallcal.pipeline.closed_loop", "plant_model", "plant model"),
    ("hallcal.pipeline.closed_loop", "_fit_kernel", "model: kernel SEM"),
    ("hallcal.pipeline.closed_loop", "_fit_fourier", "model: Fourier SEM / harmonic choice"),
    ("hallcal.fit.order", "select_harmonics", "harmonic choice"),
    ("hallcal.pipeline.closed_loop", "solve_sem", "SEM"),
    ("hallcal.pipeline.closed_loop", "_with_cogging", "cogging"),
    ("hallcal.pipeline.closed_loop", "assess", "model adequacy"),
    ("hallcal.pipeline.closed_loop", "build_lut", "lookup table"),
    ("hallcal.pipeline.closed_loop", "_unmodelled_cogging_bias", "cogging bias (warning only)"),
    ("hallcal.pipeline.closed_loop", "power_up_analysis", "power-up identifiability"),
    ("hallcal.sensor.absolute", "estimate_normal_noise", "noise across the curve"),
    ("hallcal.sensor.absolute", "build_decoder", "decoder tables"),
    ("hallcal.sensor.absolute", "assess_identifiability", "identifiability verdict"),
    ("hallcal.pipeline.closed_loop", "validate", "validation against y_ref"),
    ("hallcal.api", "Calibration.save", "write the artifact"),
]

CHILD = r"""
import functools, importlib, json, os, sys, time
T0 = time.perf_counter()
TRACE = os.environ.get("BENCH_TRACEMALLOC") == "1"
if TRACE:
    import tracemalloc
    tracemalloc.start()

def status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) / 1024.0

def reset_hwm():
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")

rows, stack = [], []

class Step:
    def __init__(self, label):
        self.label = label
    def __enter__(self):
        hwm = status("VmHWM:")
        for fr in stack:  # what the parents reached so far
            fr.peak = max(fr.peak, hwm)
            if TRACE:
                fr.tpeak = max(fr.tpeak, tracemalloc.get_traced_memory()[1])
        reset_hwm()
        if TRACE:
            tracemalloc.reset_peak()
            self.tpeak = 0
        self.row = {"step": self.label, "depth": len(stack), "rss0": status("VmRSS:")}
        rows.append(self.row)
        self.peak = self.row["rss0"]
        stack.append(self)
        self.t, self.c = time.perf_counter(), time.process_time()
        return self
    def __exit__(self, *exc):
        wall, cpu = time.perf_counter() - self.t, time.process_time() - self.c
        stack.pop()
        self.peak = max(self.peak, status("VmHWM:"))
        for fr in stack:
            fr.peak = max(fr.peak, self.peak)
        r = self.row
        r.update(wall=wall, cpu=cpu, rss1=status("VmRSS:"), peak=self.peak)
        if TRACE:
            self.tpeak = max(self.tpeak, tracemalloc.get_traced_memory()[1])
            for fr in stack:
                fr.tpeak = max(fr.tpeak, self.tpeak)
            r["traced_peak"] = self.tpeak / 2**20
        return False

def wrap(fn, label):
    @functools.wraps(fn)
    def g(*a, **k):
        with Step(label):
            return fn(*a, **k)
    return g

with Step("imports (hallcal.cli, hallcal.api, pipeline)"):
    import hallcal.cli, hallcal.api, hallcal.pipeline.closed_loop, hallcal.sensor.absolute
for mod, attr, label in json.loads(os.environ["BENCH_STEPS"]):
    m = importlib.import_module(mod)
    owner = m
    if "." in attr:
        cls, attr = attr.split(".")
        owner = getattr(m, cls)
    if hasattr(owner, attr):
        setattr(owner, attr, wrap(getattr(owner, attr), label))

from numba.core import dispatcher
NUMBA = {"count": 0, "wall": 0.0, "cpu": 0.0}
_first_call = dispatcher.Dispatcher._compile_for_args
def _timed_first_call(self, *a, **k):  # a kernel's first call: loaded from the numba cache
    t, c = time.perf_counter(), time.process_time()
    try:
        return _first_call(self, *a, **k)
    finally:
        NUMBA["count"] += 1
        NUMBA["wall"] += time.perf_counter() - t
        NUMBA["cpu"] += time.process_time() - c
dispatcher.Dispatcher._compile_for_args = _timed_first_call

case = json.loads(sys.argv[1])
with Step("whole calibrate (after the imports)"):
    if case["kind"] == "cli":
        sys.argv = ["hallcal", *case["args"]]
        try:
            hallcal.cli.main()
        except SystemExit as e:
            if e.code:
                raise
    else:
        import numpy as np, hallcal
        z = np.load(case["data"])
        cols = {k: z[k] for k in ("r", "y", "u", "d1", "d2", "d3")}
        cal = hallcal.calibrate(cols, case["setup"])
        cal.save(case["out"])
        print(json.dumps({"status": str(cal.status)}), file=sys.stderr)
total = {"step": "process total", "depth": 0, "wall": time.perf_counter() - T0,
         "cpu": time.process_time(), "rss1": status("VmRSS:"), "peak": max(
         r["peak"] for r in rows)}
if TRACE:
    total["traced_peak"] = max(r.get("traced_peak", 0) for r in rows)
rows.append(total)
rows.append({"step": f"of which numba: {NUMBA['count']} kernels' first calls (cache load)",
             "depth": 1, "wall": NUMBA["wall"], "cpu": NUMBA["cpu"], "rss1": float("nan"),
             "peak": float("nan")})
with open(case["result"], "w") as f:
    json.dump(rows, f)
"""


def load_note() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {os.cpu_count()} cores"


def paper_case(work: Path) -> dict:
    from hallcal.io import default_setup, write_dataset, write_setup
    from hallcal.pipeline import simulate

    setup = default_setup()
    run = simulate(setup)
    write_dataset(work / "cal.csv", run.columns())
    write_setup(work / "setup.toml", setup)
    return {
        "kind": "cli",
        "args": ["calibrate", "cal.csv", "--setup", "setup.toml", "--out", "cal.json"],
        "label": f"paper bench, {run.n_samples} samples, CSV through `hallcal calibrate`",
    }


def rich_case(work: Path, model: str, seed: int, strength: float) -> dict:
    sys.path.insert(0, str(HERE))
    from bench_rich import MODELS, config, setup

    from hallcal.sim.bench import ramp_run

    cfg = config(seed, strength)
    path = work / f"rich_{seed}_{strength}.npz"
    if not path.exists():
        run = ramp_run(cfg, ramp_end=20.0, duration=40.0, seed=seed)
        np.savez(path, r=run.r, y=run.y, u=run.u, d1=run.d[:, 0], d2=run.d[:, 1], d3=run.d[:, 2])
    n = np.load(path)["r"].size
    return {
        "kind": "api",
        "data": str(path),
        "setup": setup(cfg, MODELS[model]),
        "out": str(work / f"rich_{model}.json"),
        "label": f"rich magnets (bench_rich, strength {strength}, seed {seed}), {n} samples, "
        f"model {model}, hallcal.calibrate + save",
    }


def run_case(case: dict, work: Path, trace: bool) -> list[dict]:
    from bench_cli import CHILD_ENV  # the user's environment (bytecode cache on)

    case = {**case, "result": str(work / "rows.json")}
    env = {**CHILD_ENV, "BENCH_STEPS": json.dumps(STEPS)}
    if trace:
        env["BENCH_TRACEMALLOC"] = "1"
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, json.dumps(case)],
        cwd=work,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{case['label']} failed:\n{proc.stderr.read()}")
    rows = json.loads((work / "rows.json").read_text())
    rows.append(
        {
            "step": "the process seen from outside (start-up to exit)",
            "depth": 0,
            "wall": wall,
            "cpu": usage.ru_utime + usage.ru_stime,
            "rss1": math.nan,
            "peak": math.nan,
        }
    )
    return rows


def show(rows: list[dict], trace: bool) -> None:
    head = f"    {'step':<52}{'wall s':>8}{'cpu s':>8}{'RSS before':>12}{'after':>8}{'peak MB':>9}"
    if trace:
        head += f"{'traced MB':>11}"
    print(head)
    for r in rows:
        name = "  " * r["depth"] + r["step"]
        line = f"    {name:<52}{r['wall']:>8.3f}{r['cpu']:>8.3f}"
        mem = (r.get("rss0", math.nan), r["rss1"], r["peak"])
        line += "".join(
            f"{v:>{w}.0f}" if math.isfinite(v) else " " * w
            for v, w in zip(mem, (12, 8, 9), strict=True)
        )
        if trace:
            line += f"{r.get('traced_peak', float('nan')):>11.0f}"
        print(line)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default="paper,rich-kernel,rich-auto,rich-F1..55")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--strength", type=float, default=0.075)
    ap.add_argument("--tracemalloc", action="store_true")
    ap.add_argument("--repeats", type=int, default=1, help="runs per case (warm-up not counted)")
    args = ap.parse_args()
    sys.path.insert(0, str(HERE))
    print(__doc__.split("\n\n")[0])
    print(f"python {platform.python_version()}, numpy {np.__version__}, cpus {os.cpu_count()}")
    print(f"at start: {load_note()}")
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        work = Path(tmp)
        for name in args.cases.split(","):
            if name == "paper":
                case = paper_case(work)
            elif name.startswith("rich-"):
                case = rich_case(work, name[5:], args.seed, args.strength)
            else:
                raise SystemExit(f"unknown case {name!r}")
            run_case(case, work, False)  # numba cache filled, page cache warm
            print(f"\n[{name}] {case['label']}")
            for k in range(args.repeats):
                rows = run_case(case, work, args.tracemalloc)
                print(f"  run {k + 1} ({load_note()}):")
                show(rows, args.tracemalloc)
    print(f"\nat end: {load_note()}")


if __name__ == "__main__":
    main()
