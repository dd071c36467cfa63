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

#: Wall-clock limit of one command [s]: a watchdog for a hung process, not an assertion about
#: speed (a calibration takes seconds; a cold numba cache adds about a minute).
WATCHDOG_SECONDS = 600


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``hallcal ARGS`` in `cwd` with this interpreter; stdout and stderr as text."""
    return subprocess.run(
        [sys.executable, "-m", "hallcal.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=WATCHDOG_SECONDS,
    )
