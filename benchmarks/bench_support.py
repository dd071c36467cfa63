"""What the benchmark scripts share: their two calibrations (the demo, ring-jig 1) and the end
of their report (the load average, printed and optionally written)."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: The shipped ring-jig captures (25 pole pairs, raw 16-bit counts).
RINGJIG = Path(__file__).resolve().parents[1] / "tests" / "data" / "ring-jig"
#: ADC counts per unit of the demo's normalized Hall signals, for its fixed-point export.
DEMO_ADC_SCALE = 2.0**14


def demo_case(folder: Path) -> tuple[dict, np.ndarray]:
    """The demo's artifact (written to `folder`) and its validation run's Hall signals."""
    from hallcal.demo import run_demo
    from hallcal.io import read_artifact, read_dataset

    run_demo(folder, report=False)
    return read_artifact(folder / "calibration.json"), read_dataset(folder / "validation.npz").d


def ringjig_case(folder: Path) -> tuple[dict, np.ndarray] | None:
    """Ring-jig capture 1 calibrated on its first two constant-speed revolutions (the artifact
    in `folder`), and the whole capture; None when the capture is not shipped."""
    import hallcal
    from hallcal.fit.constant_speed import find_constant_speed
    from hallcal.io import read_artifact

    path = RINGJIG / "hall_calibration_one_rotation_1.txt"
    if not path.exists():
        return None
    d = np.loadtxt(path, dtype=np.int64).astype(np.float64)
    start, mid, _ = find_constant_speed(d, 25).split(2.0)
    setup = {"pole_pairs": 25, "sample_time": 1.0,
             "trajectory": {"kind": "constant-speed", "start": start, "stop": mid}}  # fmt: skip
    cal = hallcal.calibrate({f"d{h + 1}": d[:, h] for h in range(3)}, setup)
    cal.save(folder / "ringjig1.json")
    return read_artifact(folder / "ringjig1.json"), d


def run_rows(run: Callable[[int], dict], seeds: list[int], jobs: int,
             line: Callable[[dict], str], lines: list[str]) -> list[dict]:  # fmt: skip
    """Each seed's row by ``run`` (in a pool of ``jobs`` processes when jobs > 1, in seed order),
    its formatted ``line`` appended to ``lines`` and printed as it comes."""
    rows: list[dict] = []

    def take(r: dict) -> None:
        rows.append(r)
        lines.append(line(r))
        print(lines[-1], flush=True)

    if jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(jobs) as pool:
            for r in pool.map(run, seeds):
                take(r)
    else:
        for s in seeds:
            take(run(s))
    return rows


def finish_report(lines: list[str], out: Path | None) -> int:
    """Append the load average, print the report and write it to `out` when given; exit 0."""
    load = os.getloadavg()
    lines.append(f"load average at the end: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    report = "\n".join(lines) + "\n"
    print(report, end="")
    if out is not None:
        out.write_text(report)
    return 0


def arm_args(argv: list[str] | None, doc: str) -> argparse.Namespace | None:
    """The ``--out`` option of an ARM benchmark; None (after one line on stderr) when the ARM
    toolchain or QEMU is missing (``tests/arm_harness.py`` must be importable)."""
    import arm_harness as ah

    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="also write the report here")
    args = ap.parse_args(argv)
    missing = ah.toolchain()
    if missing is not None:
        print(f"{missing} not found: install gcc-arm-none-eabi, libnewlib-arm-none-eabi and "
              "qemu-system-arm", file=sys.stderr)  # fmt: skip
        return None
    return args
