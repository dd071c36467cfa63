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


@pytest.fixture(scope="module")
def readme_run(tmp_path_factory) -> tuple[Path, dict[str, list[subprocess.CompletedProcess]]]:
    """The README's "Your own motor" block run once, in order, in a fresh folder: its folder
    and each command's results (by subcommand). The other examples run in the same folder
    (``motor_dir``) after this module's first test has checked it."""
    d = tmp_path_factory.mktemp("readme-motor")
    (d / "setup.toml").write_text(small_setup(readme_setup()), encoding="utf-8")
    results: dict[str, list[subprocess.CompletedProcess]] = {}
    for args in readme_commands():
        res = _run(args, d)
        results.setdefault(args[1], []).append(res)
    return d, results


def test_readme_steps_run_as_written(readme_run):
    tmp_path, results = readme_run
    # the BLA is the plant actually used, and the choice is said once and recorded
    cal = results["calibrate"][0]
    assert cal.stderr.count("wins over the setup's [plant]") == 1, cal.stderr
    art = json.loads((tmp_path / "cal.json").read_text())
    assert art["plant"]["source"] == "bla"
    assert any("wins over the setup's [plant]" in m for m in art["diagnostics"]["messages"])
    bla = json.loads((tmp_path / "bla.json").read_text())
    assert bla["status"] == "ok"
    # the plant used is the BLA (refined by the run within the BLA's uncertainty, a few per cent),
    # not [plant]
    assert art["plant"]["den"] == pytest.approx(bla["plant"]["den"], rel=0.05)
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


# ------------------------------------------------------------------------------------------------
# every other example of the README, and every example of `--help`, as written

#: The README's commands that are not hallcal's: installing and testing (CI runs those itself).
SETUP_LINES = (
    "git clone <the repository's URL> hallcal",
    "cd hallcal",
    "python -m venv .venv && . .venv/bin/activate",
    'pip install -c constraints.txt -e ".[test]"',
    "python -m pytest -q -n auto",
)


def readme_blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README.read_text(encoding="utf-8"), re.S)


def _lines(block: str) -> list[str]:
    return [ln.split("  #", 1)[0].strip() for ln in block.splitlines() if ln.strip()]


def other_readme_commands() -> list[list[str]]:
    """The README's bash lines outside "Your own motor", setup lines excepted (asserted)."""
    own = re.search(r"```bash\n(.*?)```", _section(), re.S).group(1)
    out = []
    for block in readme_blocks("bash"):
        if block == own:
            continue
        for line in _lines(block):
            if line in SETUP_LINES:
                continue
            assert line.startswith("hallcal "), line  # nothing else may hide here
            out.append(shlex.split(line))
    return out


def help_examples() -> list[list[str]]:
    """Every example line of every command's ``--help`` (the epilogs), without duplicates."""
    from hallcal.cli import cli

    seen: list[list[str]] = []
    for command in [cli, *cli.commands.values()]:
        text = command.epilog or ""
        block = text.split("Examples:", 1)[1].split("\n\n", 1)[0]
        for line in block.splitlines():
            line = line.split("  #", 1)[0].strip()
            if line and shlex.split(line) not in seen:
                seen.append(shlex.split(line))
    return seen


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    assert args[0] == "hallcal", args
    res = subprocess.run(
        [sys.executable, "-m", "hallcal.cli", *args[1:]],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert res.returncode == 0, (args, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    return res


@pytest.fixture(scope="module")
def motor_dir(readme_run) -> Path:
    """The README's motor (small sizes), after the README's own steps (``readme_run``: the
    same commands are not run twice)."""
    d, _ = readme_run
    (d / "manifest.csv").write_text("motor_id,data,setup\nm1,cal.csv,setup.toml\n")
    return d


@pytest.fixture(scope="module")
def other_run(motor_dir) -> dict[str, list[subprocess.CompletedProcess]]:
    """Every bash line of the README outside "Your own motor" (the demo aside: it is a --help
    example, run by test_every_help_example_runs_as_written), run once in order in the README
    motor's folder: each command's results by subcommand. The --help examples that are the same
    command in the same folder are not run again."""
    results: dict[str, list[subprocess.CompletedProcess]] = {}
    for args in other_readme_commands():
        if args[1] != "demo":
            results.setdefault(args[1], []).append(_run(args, motor_dir))
    return results


def test_the_other_readme_examples_run_as_written(motor_dir, other_run):
    """Quick start aside (the demo: run by the --help test), every bash line of the README."""
    cmds = other_readme_commands()
    assert [c[1] for c in cmds] == ["demo", "plan", "fleet", "fleet", "reconstruct", "reconstruct"]
    assert len(other_run["fleet"]) == 2
    for res in other_run["fleet"]:
        assert "1 ok" in res.stdout or "1 motors: 1 ok" in res.stdout, res.stdout
    assert (motor_dir / "batch" / "m1" / "c" / "hallcal.c").is_file()  # fleet --export-c
    # the prose's inline examples
    _run(["hallcal", "export-c", "cal.json", "--out", "fw/"], motor_dir)
    assert (motor_dir / "fw" / "hallcal.c").is_file()


def test_the_readme_python_runs_as_written(motor_dir, tmp_path):
    """The notebook block, then the prose's report and export_c calls; status prints as shown.
    They run in a folder of their own holding the README motor's recordings and setup: the
    block saves its own cal.json, which must not replace the CLI's that the --help examples
    read in the motor's folder."""
    (block,) = readme_blocks("python")
    for name in ("cal.csv", "run.csv", "setup.toml"):
        (tmp_path / name).write_bytes((motor_dir / name).read_bytes())
    code = block + '\ncal.report("report/", data="cal.csv")\ncal.export_c("fw_py/")\n'
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900
    )
    assert res.returncode == 0, res.stderr
    shown = re.search(r"print\(cal\.status, cal\.predicted_error\)\s+# (\S+) ", block).group(1)
    assert res.stdout.splitlines()[0].split()[0] == shown  # what the README says is printed
    assert (tmp_path / "fw_py" / "hallcal.c").is_file()
    assert (tmp_path / "report" / "report.html").is_file()


#: Order in which the --help examples run (inputs before the commands that read them).
ORDER = ("simulate", "inspect", "bla", "calibrate", "reconstruct", "plan", "export-c", "report",
         "fleet", "demo")  # fmt: skip


def test_every_help_example_runs_as_written(motor_dir, other_run, tmp_path):
    """Each example of each ``--help``, in the README motor's folder, or, when it names a
    ring-jig file, in a folder holding the ring jig's capture (ring.txt, its CSV ring.csv and
    the setup inspect suggests, ring.toml). An example that is also a bash line of the README
    has run there already (``readme_run``, ``other_run``: each exited 0), in the same folder:
    it is not run twice."""
    from hallcal.io import read_dataset, write_dataset

    examples = help_examples()
    assert {e[1] for e in examples} == set(ORDER)
    ring = tmp_path / "ring"
    ring.mkdir()
    src = (
        Path(__file__).resolve().parent
        / "data"
        / "ring-jig"
        / "hall_calibration_one_rotation_1.txt"
    )
    (ring / "ring.txt").write_bytes(src.read_bytes())
    write_dataset(ring / "ring.csv", read_dataset(ring / "ring.txt").columns)
    out = _run(["hallcal", "inspect", "ring.txt"], ring).stdout
    (ring / "ring.toml").write_text(
        "pole_pairs = 25\nsample_time = 1.0\n\n" + out[out.index("[trajectory]") :]
    )
    (motor_dir / "powerup.csv").write_bytes((motor_dir / "run.csv").read_bytes())
    # run as written in motor_dir by readme_run and other_run (each exit 0)
    ran = readme_commands() + [c for c in other_readme_commands() if c[1] != "demo"]
    for args in sorted(examples, key=lambda a: ORDER.index(a[1])):
        where = ring if any(a.startswith("ring.") for a in args) else motor_dir
        if where == motor_dir and args in ran:
            continue  # the same command in the same folder: readme_run ran it
        _run(args, where)
    assert (ring / "report" / "report.html").is_file()
    assert (motor_dir / "hallcal-demo").is_dir()
