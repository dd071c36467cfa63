"""The command line as a user runs it: one subprocess runner shared by the CLI tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

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
