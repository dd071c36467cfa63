"""The new user's path on the command line (subprocess, as a user runs it).

No silent choices (which plant and why; conflicting inputs warned), a plant to look at (`hallcal
bla` with its Bode plot, unstable fits refused with the fix), checks before the expensive steps,
`hallcal inspect` and a complete report for the open-loop route, human wording, help texts with
an example and the exit statuses.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from hallcal.io import read_artifact, setup_from_dict, setup_to_toml

RING = Path(__file__).resolve().parent / "data" / "ring-jig"

MOTOR = {
    "pole_pairs": 4,
    "sample_time": 1e-4,
    "controller": {"num": [9.8472, -19.6285, 9.7814], "den": [1.0, -1.962998, 0.962998]},
    "plant": {"num": [5000.0], "den": [1.0, 50.0, 0.0], "delay": 1.5e-4},
    "model": {"harmonics": [1, 2, 3, 4]},
    "bla": {"period_samples": 4000, "periods": 3, "realizations": 4},
    "bench": {"ramp_end": 7.0, "duration": 8.0, "seed": 3},
}

#: LaTeX labels of the paper and grammar slips that must not reach a user.
LEAKS = re.compile(
    r"\beq\. ?\(?[a-z_]{3,}\)?|Figs?\. [a-z_]{3,}|problem \(problem\)|\b1 iterations\b|"
    r"sec\. BLA|c_hat"
)


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "hallcal.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


def write_setup(path: Path, data: dict) -> None:
    path.write_text(setup_to_toml(setup_from_dict(data)), encoding="utf-8")


@pytest.fixture(scope="module")
def motor(tmp_path_factory):
    d = tmp_path_factory.mktemp("motor")
    write_setup(d / "setup.toml", MOTOR)
    for args in (
        ("--out", "cal.csv"),
        ("--experiment", "multisine", "--out", "bla.csv"),
    ):
        res = run("simulate", "--setup", "setup.toml", *args, cwd=d)
        assert res.returncode == 0, res.stderr
    return d


@pytest.fixture(scope="module")
def ring(tmp_path_factory):
    """Ring-jig file 1 as the capture wrote it (headerless whitespace text: d1 d2 d3)."""
    d = tmp_path_factory.mktemp("ring")
    shutil.copy(RING / "hall_calibration_one_rotation_1.txt", d / "ring.txt")
    return d


# ------------------------------------------------------------------------------------------------
# help, version


def test_every_command_has_an_example_and_the_exit_statuses(tmp_path):
    from hallcal.cli import cli

    names = ["", *sorted(cli.commands)]
    for name in names:
        res = run(*([name] if name else []), "--help", cwd=tmp_path)
        assert res.returncode == 0, name
        assert "Example" in res.stdout, name
        assert "Exit status: 0 success, 2 bad input" in res.stdout, name
        assert "hallcal " in res.stdout.split("Example", 1)[1], name
    assert "inspect" in cli.commands


def test_version_is_a_string_not_importlibs_function(tmp_path):
    import importlib.metadata

    import hallcal

    assert isinstance(hallcal.__version__, str)
    assert getattr(hallcal, "version", None) is not importlib.metadata.version
    with pytest.raises(AttributeError):
        hallcal.version  # noqa: B018 - the lazy module must not invent it
    res = run("--version", cwd=tmp_path)
    assert res.returncode == 0 and hallcal.__version__ in res.stdout


# ------------------------------------------------------------------------------------------------
# hallcal bla


def test_bla_chooses_the_order_and_writes_a_bode_plot(motor):
    res = run("bla", "bla.csv", "--setup", "setup.toml", "--out", "bla.json", cwd=motor)
    assert res.returncode == 0, res.stderr
    assert "<- chosen" in res.stdout and "G(s) = " in res.stdout
    assert "denominator order 1 chosen from the data" in res.stderr
    data = json.loads((motor / "bla.json").read_text())
    assert data["status"] == "ok" and data["order_selection"]["chosen_denominator_order"] == 1
    png = (motor / "bla.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert not LEAKS.search(res.stdout + res.stderr)


def test_unstable_bla_is_refused_with_the_fix(motor):
    """The issue: denominator_order = 2 on this motor put a pole at about +1e9 rad/s and said
    "ok"; now exit 3 names the pole and the order to use, and the plot is there to look at."""
    write_setup(motor / "two.toml", {**MOTOR, "bla": {**MOTOR["bla"], "denominator_order": 2}})
    res = run("bla", "bla.csv", "--setup", "two.toml", "--out", "bla2.json", cwd=motor)
    assert res.returncode == 3, (res.stdout, res.stderr)
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith(
        "hallcal: refused: bla.csv: the plant model fitted to the BLA is unstable"
    )
    assert "lower [bla] denominator_order (now 2) to 1" in line
    assert json.loads((motor / "bla2.json").read_text())["status"] == "refused"
    assert (motor / "bla2.png").is_file()
    # and calibrate with that BLA refuses before the gain correction and SEM
    res = run(
        "calibrate", "cal.csv", "--setup", "two.toml", "--bla-data", "bla.csv", "--out", "x.json",
        cwd=motor,
    )  # fmt: skip
    assert res.returncode == 3
    assert "lower [bla] denominator_order" in res.stderr and "SEM" not in res.stderr
    assert not (motor / "x.json").exists()


# ------------------------------------------------------------------------------------------------
# calibrate: choices said once, checks before the expensive steps


def test_calibrate_says_which_plant_once_and_records_it(motor):
    res = run(
        "calibrate", "cal.csv", "--setup", "setup.toml", "--bla-data", "bla.csv",
        "--out", "cal.json", "--units", "electrical-deg", cwd=motor,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert res.stderr.count("plant: the BLA identified from bla.csv") == 1
    assert "wins over the setup's [plant]" in res.stderr
    assert "electrical deg" in res.stdout and "mrad" not in res.stdout
    art = read_artifact(motor / "cal.json")
    assert art["plant"]["source"] == "bla"
    assert any("wins over" in m for m in art["diagnostics"]["messages"])
    assert not LEAKS.search(res.stdout + res.stderr), res.stdout
    res = run("calibrate", "cal.csv", "--setup", "setup.toml", "--out", "plant.json", cwd=motor)
    assert res.returncode == 0, res.stderr
    assert "plant: G(s) from the setup's [plant] table" in res.stderr
    assert read_artifact(motor / "plant.json")["plant"]["source"] == "setup"


def test_wrong_pole_pairs_are_named_before_anything_expensive(motor):
    write_setup(motor / "pp5.toml", {**MOTOR, "pole_pairs": 5})
    res = run("calibrate", "cal.csv", "--setup", "pp5.toml", "--out", "x.json", cwd=motor)
    assert res.returncode == 2, res.stderr
    msg = res.stderr.strip().splitlines()[-1]
    assert msg.startswith("hallcal: error: cal.csv: pole_pairs = 5 does not match the data")
    assert "set pole_pairs = 4" in msg
    assert "SEM" not in res.stderr and "harmonics" not in res.stderr


def test_unstable_loop_is_named_before_sem(motor):
    flipped = {"num": [-9.8472, 19.6285, -9.7814], "den": [1.0, -1.962998, 0.962998]}
    write_setup(motor / "flip.toml", {**MOTOR, "controller": flipped})
    res = run("calibrate", "cal.csv", "--setup", "flip.toml", "--out", "x.json", cwd=motor)
    assert res.returncode == 2, res.stderr
    msg = res.stderr.strip().splitlines()[-1]
    assert msg.startswith("hallcal: error: flip.toml: the closed loop of [controller] and [plant]")
    assert "unstable: pole at z = " in msg and "SEM" not in res.stderr
    res = run("simulate", "--setup", "flip.toml", "--out", "y.csv", cwd=motor)
    assert res.returncode == 2 and "unstable: pole at z = " in res.stderr


# ------------------------------------------------------------------------------------------------
# the open-loop route: inspect, calibrate, report


def test_inspect_finds_the_window_and_the_pole_pairs(ring):
    res = run("inspect", "ring.txt", cwd=ring)
    assert res.returncode == 0, res.stderr
    out = res.stdout
    assert "6000 samples" in out and "the data suggest 25 (magnet signature)" in out
    assert "against the sensor order" in out
    m = re.search(r"constant-speed window: samples (\d+)\.\.(\d+)", out)
    start, stop = int(m.group(1)), int(m.group(2))
    # the README of the data: accelerate (about 100 samples), cruise, decelerate (from ~5760)
    assert 60 < start < 200 and 5650 < stop < 5780
    toml = out[out.index("[trajectory]") :]
    assert 'kind = "constant-speed"' in toml
    (ring / "ring.toml").write_text("pole_pairs = 25\nsample_time = 1.0\n\n" + toml)
    wrong = run("inspect", "ring.txt", "--pole-pairs", "24", cwd=ring)
    # a wrong count exits 2 with one line, and the report counts with the data's 25
    assert wrong.returncode == 2
    assert "pole pairs: 24 (given, WRONG)" in wrong.stdout and "set pole_pairs = 25" in wrong.stdout
    last = wrong.stderr.strip().splitlines()[-1]
    assert last.startswith("hallcal: error: ring.txt: pole_pairs = 24 does not match the data")
    assert "the lines below count with the data's 25" in wrong.stdout


def test_open_loop_report_is_complete_in_electrical_degrees(ring):
    """No "noise floor: -", no "not assessed", the ±2σ lines drawn, the held-out check shown."""
    if not (ring / "ring.toml").exists():
        test_inspect_finds_the_window_and_the_pole_pairs(ring)
    res = run("calibrate", "ring.txt", "--setup", "ring.toml", "--out", "ring.json", cwd=ring)
    assert res.returncode == 0, res.stderr
    res = run(
        "report", "ring.json", "ring.txt", "--out", "rep", "--units", "electrical-deg", cwd=ring
    )
    assert res.returncode == 0, res.stderr
    html = (ring / "rep" / "report.html").read_text(encoding="utf-8")
    text = re.sub(r"<[^>]+>", " ", re.sub(r"<img[^>]*>", "", html))
    assert "not assessed" not in text
    assert re.search(r"noise floor \(RMS\)\s+0\.\d+ electrical deg", text), text[:3000]
    assert "model adequacy (constant speed)" in text
    assert "inside the ±2σ lines of the Hall noise" in text
    m = re.search(r"f_init\s+([0-9.]+) electrical deg\s+f_star\s+([0-9.]+) electrical deg", text)
    init, star = float(m.group(1)), float(m.group(2))
    # tests/test_real_ringjig.py, file 1: 4.87 -> 0.82 electrical degrees on the held-out part
    assert 4.0 < init < 6.0 and star < 1.2
    assert "time in samples" in text and "sample time 1 s" not in text
    assert not LEAKS.search(text), LEAKS.search(text)


def test_bla_data_with_a_constant_speed_run_is_a_warning(ring, motor):
    if not (ring / "ring.toml").exists():
        test_inspect_finds_the_window_and_the_pole_pairs(ring)
    res = run(
        "calibrate", "ring.txt", "--setup", "ring.toml", "--bla-data", str(motor / "bla.csv"),
        "--out", "ring2.json", cwd=ring,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "warning: the BLA experiment is not used" in res.stderr
    assert read_artifact(ring / "ring2.json")["diagnostics"]["status"] == "warning"


# ------------------------------------------------------------------------------------------------
# outputs


def test_generated_c_files_are_world_readable_and_worded(motor, tmp_path):
    if not (motor / "plant.json").exists():
        test_calibrate_says_which_plant_once_and_records_it(motor)
    old = os.umask(0o022)
    try:
        res = run(
            "export-c", str(motor / "plant.json"), "--out", "fw", "--adc-scale", "2048",
            cwd=tmp_path,
        )  # fmt: skip
    finally:
        os.umask(old)
    assert res.returncode == 0, res.stderr
    for p in (tmp_path / "fw").iterdir():
        assert stat.S_IMODE(p.stat().st_mode) == 0o644, p
        assert not LEAKS.search(p.read_text(encoding="ascii")), p  # the C comments are read too
