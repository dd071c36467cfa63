"""The README's "Your own motor" steps, run literally as a user runs them (subprocess, temp dir).

The test takes the README's ``setup.toml`` block and its ``bash`` block as they are written, shrinks
only the sizes (a shorter ramp, fewer BLA realizations) in the setup it writes, and runs every
command of the block in order. Each must exit 0, and the calibration must use the BLA of
``bla.csv`` as its plant (the README's setup also has ``[plant]``, for the virtual bench), say so
once, and write that choice into the artifact.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from hallcal.io import setup_from_dict, setup_to_toml

README = Path(__file__).resolve().parents[1] / "README.md"


def _section() -> str:
    text = README.read_text(encoding="utf-8")
    start = text.index("## Your own motor")
    end = text.index("\n## ", start + 1)
    return text[start:end]


def readme_setup() -> str:
    return re.search(r"```toml\n(.*?)```", _section(), re.S).group(1)


def readme_commands() -> list[list[str]]:
    block = re.search(r"```bash\n(.*?)```", _section(), re.S).group(1)
    commands = []
    for line in block.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            commands.append(shlex.split(line))
    return commands


def small_setup(text: str) -> str:
    """The README's setup with smaller sizes: a 1.1-revolution ramp in 8 s, 4 BLA realizations."""
    data = tomllib.loads(text)
    data["bench"].update(ramp_end=7.0, duration=8.0)
    data["bla"].update(realizations=4)
    return setup_to_toml(setup_from_dict(data))


def test_the_readme_block_is_what_this_test_runs():
    """The parsing is sharp: the commands and the tables the README promises are all there."""
    names = [c[1] for c in readme_commands()]
    assert all(c[0] == "hallcal" for c in readme_commands())
    assert names == [
        "simulate",
        "simulate",
        "simulate",
        "inspect",
        "bla",
        "calibrate",
        "reconstruct",
        "report",
        "export-c",
    ]
    data = tomllib.loads(readme_setup())
    assert {"controller", "plant", "bla", "bench"} <= set(data)
    # run.csv, used by reconstruct and report, is made by one of the commands before them
    made = [c[c.index("--out") + 1] for c in readme_commands() if "--out" in c]
    assert "run.csv" in made[: made.index("angles.csv")]


def test_readme_steps_run_as_written(tmp_path):
    (tmp_path / "setup.toml").write_text(small_setup(readme_setup()), encoding="utf-8")
    results = {}
    for args in readme_commands():
        res = subprocess.run(
            [sys.executable, "-m", "hallcal.cli", *args[1:]],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert res.returncode == 0, (args, res.stdout, res.stderr)
        assert "Traceback" not in res.stderr
        results.setdefault(args[1], []).append(res)
    # the BLA is the plant actually used, and the choice is said once and recorded
    cal = results["calibrate"][0]
    assert cal.stderr.count("wins over the setup's [plant]") == 1, cal.stderr
    art = json.loads((tmp_path / "cal.json").read_text())
    assert art["plant"]["source"] == "bla"
    assert any("wins over the setup's [plant]" in m for m in art["diagnostics"]["messages"])
    bla = json.loads((tmp_path / "bla.json").read_text())
    assert bla["status"] == "ok"
    # the plant used is the BLA (gain-corrected), not [plant]: its denominator is the BLA's
    assert art["plant"]["den"] == pytest.approx(bla["plant"]["den"])
    assert art["plant"]["den"] != [1.0, 50.0, 0.0]
    # the model order was chosen from the data: one pole besides the integrator (s^2 + a s)
    assert len(bla["plant"]["den"]) == 3
    assert (tmp_path / "bla.png").stat().st_size > 10_000
    for name in ("angles.csv", "report/report.html", "firmware/hallcal.c"):
        assert (tmp_path / name).is_file(), name
    # the report shows the BLA next to the artifact (bla.json) with its two standard deviations
    html = (tmp_path / "report" / "report.html").read_text(encoding="utf-8")
    assert "Closed-loop BLA of the plant" in html and "realization to realization" in html
    # the validation run was calibrated to near its noise floor (f_star << f_init on run.csv)
    line = next(ln for ln in results["reconstruct"][0].stdout.splitlines() if "y_ref" in ln)
    init, star = (float(x) for x in re.findall(r"RMS ([0-9.]+) mrad", line))
    assert star < 0.3 * init, line  # measured 0.56 vs 5.85 mrad with the README's full sizes
