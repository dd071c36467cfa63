"""The command line as a user runs it: one subprocess runner shared by the CLI tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

#: The paper's loop as setup tables: C(q) and G(s) with its input delay (docs/design.md).
PAPER_LOOP_TOML = """\
[controller]
num = [2.94, -3.29, -2.10, 2.45]
den = [1, -3.45, 4.52, -2.68, 0.61]
[plant]
num = [1.663e5]
den = [1, 632.6, 2702, 0]
delay = 1.2e-4
"""


def paper_setup(*, duration: float, seed: int, bench_extra: str = "") -> str:
    """A setup TOML of the paper's motor and loop with its Fourier model (harmonics 1..11) and
    a bench ramp to 7 rad over `duration` seconds; `bench_extra`: more [bench] lines."""
    return (
        "pole_pairs = 11\nsample_time = 2.5e-4\n"
        + PAPER_LOOP_TOML
        + '[model]\nbasis = "fourier"\nharmonics = [1,2,3,4,5,6,7,8,9,10,11]\n'
        + f"[bench]\nramp_end = 7.0\nduration = {duration}\nseed = {seed}\n{bench_extra}"
    )


#: Wall-clock limit of one command [s]: a watchdog for a hung process, not an assertion about
#: speed (a calibration takes seconds; a cold numba cache adds about a minute).
WATCHDOG_SECONDS = 600


def calibrated_folder(folder: Path, setup: str) -> tuple[Path, subprocess.CompletedProcess]:
    """`folder` with ``s.toml`` (`setup`), a simulated ``cal.csv`` and ``cal.json`` calibrated
    from it, as a user makes them; returns the folder and the calibrate run."""
    (folder / "s.toml").write_text(setup)
    res = run_cli("simulate", "--setup", "s.toml", "--out", "cal.csv", cwd=folder)
    assert res.returncode == 0, res.stderr
    res = run_cli("calibrate", "cal.csv", "--setup", "s.toml", "--out", "cal.json", cwd=folder)
    assert res.returncode == 0, res.stderr
    return folder, res


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``hallcal ARGS`` in `cwd` with this interpreter; stdout and stderr as text."""
    return subprocess.run(
        [sys.executable, "-m", "hallcal.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=WATCHDOG_SECONDS,
    )
