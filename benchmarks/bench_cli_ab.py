"""``hallcal calibrate`` on the paper run, two source trees interleaved: is one slower?

The shared machine's speed drifts by 10-20 % within minutes (other tenants), so one tree's
wall time measured now is not comparable with another's measured an hour ago
(``bench_cli.txt``). Here the two trees run in alternation, fresh processes on the same files,
so the drift hits both alike; the medians are what to compare.

Run ``python benchmarks/bench_cli_ab.py OLD_SRC NEW_SRC [--pairs 10] [--keep DIR]`` with each
tree's ``src`` folder (e.g. a ``git worktree`` of the older commit); the paper run and its
setup are written by ``bench_cli.py --keep DIR`` (made here when DIR has none).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", type=Path, help="the first tree's src folder")
    ap.add_argument("new", type=Path, help="the second tree's src folder")
    ap.add_argument("--pairs", type=int, default=10)
    ap.add_argument("--keep", type=Path, default=Path("/tmp/hallcal_bench_cli_ab"))
    args = ap.parse_args()
    work = args.keep
    if not (work / "cal.csv").is_file():
        here = Path(__file__).resolve().parent
        subprocess.run(
            [sys.executable, str(here / "bench_cli.py"), "--repeats", "1", "--keep", str(work)],
            check=True,
            capture_output=True,
        )
    trees = {"old": args.old.resolve(), "new": args.new.resolve()}
    times: dict[str, list[float]] = {k: [] for k in trees}
    for _ in range(args.pairs):
        for name, src in trees.items():
            env = dict(os.environ, PYTHONPATH=str(src))
            cmd = [sys.executable, "-m", "hallcal.cli", "calibrate", "cal.csv", "--setup"]
            cmd += ["setup.toml", "--out", f"ab_{name}.json"]
            t0 = time.perf_counter()
            subprocess.run(cmd, cwd=work, env=env, capture_output=True, check=True)
            times[name].append(time.perf_counter() - t0)
    load = os.getloadavg()
    print(
        f"load average at end {load[0]:.2f} (1 min), {load[1]:.2f} (5 min), {os.cpu_count()} cores"
    )
    for name, src in trees.items():
        v = times[name]
        print(
            f"{name} ({src}): wall median {statistics.median(v):.3f} s, "
            f"min {min(v):.3f} s, max {max(v):.3f} s (n={len(v)})"
        )


if __name__ == "__main__":
    main()
