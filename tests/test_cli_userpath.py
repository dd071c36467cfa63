"""The new user's path on the command line (subprocess, as a user runs it).

No silent choices (which plant and why; conflicting inputs warned), a plant to look at (`hallcal
bla` with its Bode plot, unstable fits refused with the fix), checks before the expensive steps,
`hallcal inspect` and a complete report for the open-loop route, human wording, help texts with
an example and the exit statuses.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_support import run_cli as run
from motor_support import SMALL_LOOP

from hallcal.io import read_artifact, setup_from_dict, setup_to_toml

RING = Path(__file__).resolve().parent / "data" / "ring-jig"

MOTOR = {
    **SMALL_LOOP,
    "model": {"harmonics": [1, 2, 3, 4]},
    "bla": {"period_samples": 4000, "periods": 3, "realizations": 4},
    "bench": {"ramp_end": 7.0, "duration": 8.0, "seed": 3},
}

#: LaTeX labels of the paper and grammar slips that must not reach a user.
LEAKS = re.compile(
    r"\beq\. ?\(?[a-z_]{3,}\)?|Figs?\. [a-z_]{3,}|problem \(problem\)|\b1 iterations\b|"
    r"sec\. BLA|c_hat"
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
    """denominator_order = 2 on this motor put a pole at about +1e9 rad/s and said
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


@pytest.fixture(scope="module")
def with_bla(motor) -> subprocess.CompletedProcess:
    """The motor calibrated with its BLA, angles shown in electrical degrees (``cal.json``):
    once for the module (test_report_wording reports from it)."""
    return run(
        "calibrate", "cal.csv", "--setup", "setup.toml", "--bla-data", "bla.csv",
        "--out", "cal.json", "--units", "electrical-deg", cwd=motor,
    )  # fmt: skip


@pytest.fixture(scope="module")
def plant_run(motor) -> subprocess.CompletedProcess:
    """The motor calibrated with the setup's [plant] (``plant.json``), once for the module."""
    return run("calibrate", "cal.csv", "--setup", "setup.toml", "--out", "plant.json", cwd=motor)


def test_calibrate_says_which_plant_once_and_records_it(motor, with_bla, plant_run):
    res = with_bla
    assert res.returncode == 0, res.stderr
    assert res.stderr.count("plant: the BLA identified from bla.csv") == 1
    assert "wins over the setup's [plant]" in res.stderr
    assert "electrical deg" in res.stdout and "mrad" not in res.stdout
    art = read_artifact(motor / "cal.json")
    assert art["plant"]["source"] == "bla"
    assert any("wins over" in m for m in art["diagnostics"]["messages"])
    assert not LEAKS.search(res.stdout + res.stderr), res.stdout
    res = plant_run
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


def test_generated_c_files_are_world_readable_and_worded(motor, plant_run, tmp_path):
    assert plant_run.returncode == 0, plant_run.stderr
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


# ------------------------------------------------------------------------------------------------
# each mistake as a user makes it -> exit status and the one line, before the work


def _variant(motor: Path, source: str, name: str, change) -> str:
    """A copy of ``source`` with its columns changed by ``change(columns)`` (a user's mistake)."""
    from hallcal.io import read_dataset, write_dataset

    ds = read_dataset(motor / source, required=())
    cols = {k: np.array(v) for k, v in ds.columns.items()}
    change(cols)
    write_dataset(motor / name, cols)
    return name


def _last(res: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in res.stderr, res.stderr
    return res.stderr.strip().splitlines()[-1]


def test_angles_in_degrees_are_named_before_anything_expensive(motor, plant_run):
    def degrees(c):
        for k in ("r", "y", "y_ref"):
            c[k] = np.degrees(c[k])

    deg = _variant(motor, "cal.csv", "deg.csv", degrees)
    res = run("calibrate", deg, "--setup", "setup.toml", "--out", "x.json", cwd=motor)
    assert res.returncode == 2
    assert _last(res).startswith("hallcal: error: deg.csv: r looks like degrees (so do y, y_ref)")
    assert "multiply by pi/180" in _last(res)
    assert "SEM" not in res.stderr and "harmonics" not in res.stderr  # before the work
    res = run("inspect", deg, "--setup", "setup.toml", cwd=motor)
    assert res.returncode == 2 and "r looks like degrees" in _last(res)
    bla_deg = _variant(motor, "bla.csv", "bla_deg.csv", degrees)
    res = run("bla", bla_deg, "--setup", "setup.toml", "--out", "b.json", cwd=motor)
    assert res.returncode == 2 and "bla_deg.csv: r looks like degrees" in _last(res)
    assert plant_run.returncode == 0, plant_run.stderr
    res = run("reconstruct", "plant.json", deg, "--out", "a.csv", cwd=motor)
    assert res.returncode == 2 and "deg.csv: y_ref looks like degrees" in _last(res)


@pytest.mark.parametrize(
    ("name", "change", "line"),
    [
        ("t_twice", lambda c: c.update(t=2 * c["t"]), "sample_time = 0.0001 s in the setup, but "
         "the t column steps 0.0002 s"),
        ("t_const", lambda c: c.update(t=0 * c["t"]), "the t column is constant"),
        ("t_reversed", lambda c: c.update(t=c["t"][::-1].copy()), "the t column is not "
         "increasing: it decreases at every row"),
        ("t_shuffled", lambda c: c.update(t=np.random.default_rng(1).permutation(c["t"])),
         "the t column is not increasing: it steps back"),
    ],
)  # fmt: skip
def test_sample_time_is_checked_against_the_t_column(motor, name, change, line):
    f = _variant(motor, "cal.csv", f"{name}.csv", change)
    for cmd in (("calibrate", f, "--out", "x.json"), ("inspect", f)):
        res = run(*cmd, "--setup", "setup.toml", cwd=motor)
        assert res.returncode == 2, res.stderr
        assert _last(res).startswith(f"hallcal: error: {f}: {line}"), _last(res)


def test_a_wrong_sample_time_names_both_values(motor):
    write_setup(motor / "slow.toml", {**MOTOR, "sample_time": 1e-3})
    for cmd in (("calibrate", "cal.csv", "--out", "x.json"), ("bla", "bla.csv", "--out", "b.json")):
        res = run(*cmd, "--setup", "slow.toml", cwd=motor)
        assert res.returncode == 2
        assert "sample_time = 0.001 s in the setup, but the t column steps 0.0001 s" in _last(res)
        assert "set sample_time = 0.0001" in _last(res)


@pytest.mark.parametrize("typo", ["yref", "y_enc", "Y_REF"])
def test_a_typod_encoder_column_is_named_with_the_right_one(motor, typo):
    f = _variant(motor, "cal.csv", f"typo_{typo}.csv", lambda c: c.update({typo: c.pop("y_ref")}))
    res = run("calibrate", f, "--setup", "setup.toml", "--out", "x.json", cwd=motor)
    assert res.returncode == 2
    assert _last(res).startswith(
        f"hallcal: error: {f}: column '{typo}' is not a column hallcal reads: did you mean 'y_ref'?"
    )


def test_inspect_does_not_invent_motion_at_standstill(motor):
    rng = np.random.default_rng(4)

    def still(c):
        n = c["t"].size
        for h in ("d1", "d2", "d3"):  # the Hall values of the first sample, plus the noise
            c[h] = c[h][0] + rng.normal(0.0, math.sqrt(7.5e-6), n)
        for k in ("r", "y", "y_ref", "u"):
            c[k] = np.zeros(n)

    f = _variant(motor, "cal.csv", "still.csv", still)
    res = run("inspect", f, "--setup", "setup.toml", cwd=motor)
    assert res.returncode == 0, res.stderr
    assert "rotation: none: the Hall signals do not move" in res.stdout
    assert "revolutions" not in res.stdout and "spacing" not in res.stdout
    assert "calibrate it" not in res.stdout
    res = run("calibrate", f, "--setup", "setup.toml", "--out", "x.json", cwd=motor)
    assert res.returncode == 2 and "less than one electrical period (0.00)" in _last(res)
    # Hall signals that are noise around the origin (sensors unpowered): f_init turns at random
    f = _variant(motor, f, "unpowered.csv", lambda c: [c.update({h: c[h] - c[h][0]}) for h in
                                                        ("d1", "d2", "d3")])  # fmt: skip
    res = run("calibrate", f, "--setup", "setup.toml", "--out", "x.json", cwd=motor)
    assert res.returncode == 2 and "the Hall signals do not move" in _last(res), _last(res)


def test_inspect_exits_2_on_a_wrong_count_and_counts_with_the_datas(motor):
    write_setup(motor / "pp10.toml", {**MOTOR, "pole_pairs": 10})
    res = run("inspect", "cal.csv", "--setup", "pp10.toml", cwd=motor)
    assert res.returncode == 2
    assert _last(res).startswith("hallcal: error: cal.csv: pole_pairs = 10 does not match")
    assert "set pole_pairs = 4" in _last(res)
    rotation = next(ln for ln in res.stdout.splitlines() if ln.startswith("rotation:"))
    assert "(at the data's 4 pole pairs)" in rotation  # 4.5 cycles = 1.12 revolutions, not 0.45
    assert re.search(r"= 1\.1\d revolutions", rotation), rotation


def test_inspect_says_a_multisine_run_is_a_bla_experiment(motor):
    res = run("inspect", "bla.csv", "--setup", "setup.toml", cwd=motor)
    assert res.returncode == 0, res.stderr
    assert "multisine BLA experiment (column realization: 4 realizations)" in res.stdout
    assert "calibrate it" not in res.stdout


def test_export_defaults_work_on_a_normalized_artifact(motor, plant_run, tmp_path):
    """The float pair always; the fixed-point pair needs a scale here, and a note says so."""
    assert plant_run.returncode == 0, plant_run.stderr
    res = run("export-c", str(motor / "plant.json"), "--out", "fw", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in (tmp_path / "fw").iterdir()) == ["hallcal.c", "hallcal.h"]
    assert "note: fixed-point variant (hallcal_q.c) not written" in res.stderr
    assert "--adc-scale" in res.stderr
    code = (
        "import hallcal; cal = hallcal.load('plant.json'); r = cal.export_c('fw_api/'); "
        "print(sorted(p.name for p in r.paths))"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=motor, capture_output=True, text=True, timeout=600
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "['hallcal.c', 'hallcal.h']"


def test_fleet_export_c_writes_the_float_pair_of_every_good_motor(motor, tmp_path):
    (tmp_path / "m.csv").write_text(
        f"motor_id,data,setup\nm1,{motor / 'cal.csv'},{motor / 'setup.toml'}\n", encoding="utf-8"
    )
    res = run(
        "fleet", "m.csv", "--out", "batch", "--export-c", "--scheduler", "sequential", "--quiet",
        "--no-report", cwd=tmp_path,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "batch" / "m1" / "c" / "hallcal.c").is_file()
    summary = (tmp_path / "batch" / "summary.csv").read_text(encoding="utf-8")
    assert "no C export" not in summary and ",ok," in summary, summary


def test_report_wording(motor, with_bla, tmp_path):
    """No raw backticks, no doubled c-hat, sigma^2 with its unit, ±, no '<dataset>'. The
    calibration with the BLA is ``with_bla``'s (--units changes only how angles are shown: the
    noise variance is in the Hall signals' unit, and the artifact is the same)."""
    res = with_bla
    assert res.returncode == 0, res.stderr
    assert "noise variance 7.5" in res.stdout and "(Hall signal unit)²" in res.stdout
    res = run("report", "cal.json", "cal.csv", "--out", str(tmp_path / "rep"), cwd=motor)
    assert res.returncode == 0, res.stderr
    html = (tmp_path / "rep" / "report.html").read_text(encoding="utf-8")
    text = re.sub(r"<[^>]+>", " ", re.sub(r"<img[^>]*>", "", html))
    assert "`" not in text and "<code>hallcal simulate</code>" in html
    assert "c-hat (the gain correction c-hat)" not in text and "gain correction ĉ" in text
    assert "+-" not in text and "(expected 1 ±" in text
    assert "(Hall signal unit)² per channel" in text
    from hallcal import calibrate
    from hallcal.io import read_dataset

    bla = dict(read_dataset(motor / "bla.csv", required=()).columns)  # in memory, as the demo
    cal = calibrate(motor / "cal.csv", motor / "setup.toml", bla_data=bla)
    assert not any("<dataset>" in m.text for m in cal.messages)
    assert any("the BLA identified from the multisine experiment" in m.text for m in cal.messages)


def test_plan_says_when_the_slowest_speed_meets_the_target(motor, plant_run):
    assert plant_run.returncode == 0, plant_run.stderr
    res = run("plan", "plant.json", "--revolutions", "2", "--speeds", "0.25,0.5,1,2", cwd=motor)
    assert res.returncode == 0, res.stderr
    last = res.stdout.strip().splitlines()[-1]
    assert last.startswith("ramp at >= 0.25 rad/s") and "the slowest speed tried already" in last
    res = run("plan", "plant.json", "--revolutions", "2", cwd=motor)
    assert res.returncode == 0, res.stderr
    last = res.stdout.strip().splitlines()[-1]
    # the default grid went on down until the run would exceed the stated limit
    assert "slower runs would exceed 1000000 samples" in last, last


def test_an_encoder_in_revolutions_is_named(motor):
    f = _variant(motor, "cal.csv", "revs.csv", lambda c: c.update(y_ref=c["y_ref"] / (2 * np.pi)))
    res = run("calibrate", f, "--setup", "setup.toml", "--out", "x.json", cwd=motor)
    assert res.returncode == 2
    assert _last(res).startswith("hallcal: error: revs.csv: y_ref looks like revolutions")
