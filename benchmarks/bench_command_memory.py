"""Benchmark: peak resident memory of the commands that run over a whole recording, per sample.

The numbers behind :data:`hallcal.limits.BYTES_PER_SAMPLE` (each command's memory budget,
:data:`hallcal.limits.COMMAND_MEMORY_BYTES`): for each command, the peak RSS of a real
``python -m hallcal.cli`` process (``wait4``'s ``ru_maxrss``) on two recording lengths of the
paper's bench (11 pole pairs, 4 kHz, with y_ref), and the slope between them in bytes per
sample. A command whose slope is above its constant would break its budget: the constants must
stay at or above the measured slopes.

Run: ``python benchmarks/bench_command_memory.py [--small 1e6] [--large 4e6]``. Output
committed in ``benchmarks/bench_command_memory.txt``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from cli_support import PAPER_LOOP_TOML  # noqa: E402

from hallcal.limits import BYTES_PER_SAMPLE  # noqa: E402

SETUP = (
    "pole_pairs = 11\nsample_time = 2.5e-4\n"
    + PAPER_LOOP_TOML
    + """[model]
harmonics = [1,2,3,4,5,6,7,8,9,10,11]
max_iterations = 2
[bench]
ramp_end = {end}
duration = {duration}
seed = 5
"""
)


def _run(args: list[str], cwd: Path) -> tuple[float, float]:
    """Peak RSS [MB] and wall time [s] of ``hallcal ARGS``."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "hallcal.cli", *args],
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _, status, usage = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"hallcal {' '.join(args)} failed: {proc.stderr.read().decode()[-500:]}")
    return usage.ru_maxrss / 1024.0, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--small", type=float, default=1e6)
    ap.add_argument("--large", type=float, default=4e6)
    opts = ap.parse_args()
    print(__doc__.splitlines()[0])
    print(f"python {sys.version.split()[0]}, load average {os.getloadavg()[0]:.2f} (1 min)")
    sizes = {"small": int(opts.small), "large": int(opts.large)}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "a.toml").write_text(SETUP.format(end=7.0, duration=1.5))
        for name, n in sizes.items():
            duration = n * 2.5e-4
            (d / f"{name}.toml").write_text(SETUP.format(end=0.6 * duration, duration=duration))
        # the artifact: a short calibration
        _run(["simulate", "--setup", "a.toml", "--out", "a.npz"], d)
        _run(["calibrate", "a.npz", "--setup", "a.toml", "--out", "a.json"], d)
        commands = {
            "simulate": lambda s: ["simulate", "--setup", f"{s}.toml", "--out", f"{s}-sim.npz"],
            "reconstruct": lambda s: ["reconstruct", "a.json", f"{s}.npz", "--out", "o.npz"],
            "inspect": lambda s: ["inspect", f"{s}.npz", "--setup", "a.toml"],
            "reconstruct --absolute": lambda s: [
                "reconstruct",
                "a.json",
                f"{s}.npz",
                "--absolute",
                "--out",
                "o.npz",
            ],  # fmt: skip
        }
        for name in sizes:
            _run(["simulate", "--setup", f"{name}.toml", "--out", f"{name}.npz"], d)
        print(f"\n{'command':<24}{'samples':>10}{'peak MB':>9}{'wall s':>8}"
              f"{'slope B/sample':>16}{'constant':>10}")  # fmt: skip
        for command, args in commands.items():
            small, large = sizes["small"], sizes["large"]
            if command == "reconstruct --absolute":  # its budget: about 1.15 M samples
                small, large = small // 4, large // 4
                for name, n in (("small", small), ("large", large)):
                    duration = n * 2.5e-4
                    (d / f"{name}-q.toml").write_text(
                        SETUP.format(end=0.6 * duration, duration=duration)
                    )
                    _run(["simulate", "--setup", f"{name}-q.toml", "--out", f"{name}-q.npz"], d)
                args_of = lambda s: [  # noqa: E731
                    "reconstruct", "a.json", f"{s}-q.npz", "--absolute", "--out", "o.npz",
                ]  # fmt: skip
            else:
                args_of = args
            rss_s, t_s = _run(args_of("small"), d)
            rss_l, t_l = _run(args_of("large"), d)
            slope = (rss_l - rss_s) * 2**20 / (large - small)
            print(f"{command:<24}{small:>10d}{rss_s:>9.0f}{t_s:>8.1f}")
            print(f"{'':<24}{large:>10d}{rss_l:>9.0f}{t_l:>8.1f}{slope:>16.0f}"
                  f"{BYTES_PER_SAMPLE[command]:>10d}")  # fmt: skip


if __name__ == "__main__":
    main()
