"""Power-up without homing as a user runs it: ``hallcal calibrate`` reports identifiability and
stores it; ``hallcal reconstruct --absolute`` identifies the pole pair (subprocess), or refuses
with one line (exit 3) when the sensors are too uniform; the front door does the same.

The power-up recordings are made with the virtual bench of the setup (``power_up_run``: the
rotor starts at a random angle, f_init from its own atan2), written as CSV with the true angle
as ``y_ref`` (validation only).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hallcal
from hallcal.io import read_dataset, read_setup, write_dataset
from hallcal.pipeline import bench_config
from hallcal.sim.bench import power_up_run

TWO_PI = 2.0 * math.pi

SETUP = """\
pole_pairs = 11
sample_time = 2.5e-4
[controller]
num = [2.94, -3.29, -2.10, 2.45]
den = [1, -3.45, 4.52, -2.68, 0.61]
[plant]
num = [1.663e5]
den = [1, 632.6, 2702, 0]
delay = 1.2e-4
[model]
basis = "fourier"
harmonics = [1,2,3,4,5,6,7,8,9,10,11]
[bench]
ramp_end = 7.0
duration = 14.0
seed = 0
magnet_variation = {mv}
"""


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "hallcal.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


def power_up_csv(path: Path, setup_path: Path, angle: float, *, speed: float, seed: int) -> None:
    cfg = bench_config(read_setup(setup_path))
    r = power_up_run(cfg, angle, samples=4000, speed=speed, seed=seed)
    cols = {"d1": r.d[:, 0], "d2": r.d[:, 1], "d3": r.d[:, 2], "y_ref": r.y0}
    write_dataset(path, cols)


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    d = tmp_path_factory.mktemp("powerup")
    (d / "s.toml").write_text(SETUP.format(mv=0.04))
    res = run("simulate", "--setup", "s.toml", "--out", "cal.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    res = run("calibrate", "cal.csv", "--setup", "s.toml", "--out", "cal.json", cwd=d)
    assert res.returncode == 0, res.stderr
    return d, res


@pytest.fixture(scope="module")
def ideal(tmp_path_factory):
    d = tmp_path_factory.mktemp("ideal")
    (d / "s.toml").write_text(SETUP.format(mv=0.0))
    res = run("simulate", "--setup", "s.toml", "--out", "cal.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    res = run("calibrate", "cal.csv", "--setup", "s.toml", "--out", "cal.json", cwd=d)
    assert res.returncode == 0, res.stderr
    return d, res


def test_calibrate_reports_and_stores_identifiability(paper):
    d, res = paper
    lines = [ln for ln in res.stdout.splitlines() if "pole pair" in ln]
    assert len(lines) == 1 and "identifiable at power-up" in lines[0], res.stdout
    art = json.loads((d / "cal.json").read_text())
    ident = art["identifiability"]
    assert ident["status"] in ("identifiable", "needs-motion")
    assert ident["pole_pairs"] == 11 and ident["grid"] >= 32
    # sigma is the calibration's own estimate across the curve: the bench's 2.74e-3 within 5 %
    # (56 000 samples give 0.3 %; the rest is room for the model's error)
    assert ident["noise_std"] == pytest.approx(math.sqrt(7.5e-6), rel=0.05)
    assert ident["separation_median"] > 5.0
    assert ident["standstill_error_rate"] < 1e-3


@pytest.mark.parametrize(("angle", "speed"), [(2.7, 0.0), (5.9, 0.5), (0.4, -0.5)])
def test_reconstruct_absolute_finds_the_pole_pair(paper, angle, speed):
    """At rest and moving either way: the angles land in the calibration's frame (modulo one
    revolution) at the noise level after the lock, while the plain table, applied from an
    arbitrary power-up, is off by whole pole pairs."""
    d, _ = paper
    name = f"pu_{angle}_{speed}.csv"
    power_up_csv(d / name, d / "s.toml", angle, speed=speed, seed=int(angle * 10))
    res = run("reconstruct", "cal.json", name, "--absolute", "--out", "abs.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    assert "identified after" in res.stdout, res.stdout
    out = read_dataset(d / "abs.csv", required=("y_init", "y_star"))
    assert set(out.names) == {"y_init", "y_star"}
    y_ref = read_dataset(d / name)["y_ref"]
    err = np.mod(out["y_star"] - y_ref + math.pi, TWO_PI) - math.pi
    floor = math.sqrt(7.5e-6) * math.sqrt(2 / 3) / 11
    # after the first 50 samples (locks take a few): within 6 x the noise floor everywhere
    # (a Gaussian's 6-sigma peak over 4000 samples) and never a pole pair (0.57 rad) off
    assert np.max(np.abs(err[50:])) < 6 * floor
    res = run("reconstruct", "cal.json", name, "--out", "rel.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    rel = read_dataset(d / "rel.csv", required=("y_star",))
    err_rel = np.mod(rel["y_star"] - y_ref + math.pi, TWO_PI) - math.pi
    if int(np.round(np.median(err_rel) * 11 / TWO_PI)) % 11 != 0:  # power-up in another pair
        assert np.median(np.abs(err_rel)) > 0.4


def test_ideal_sensors_are_not_identifiable_and_absolute_refuses(ideal):
    d, res = ideal
    lines = [ln for ln in res.stdout.splitlines() if "pole pair" in ln]
    assert len(lines) == 1 and "NOT identifiable" in lines[0], res.stdout
    art = json.loads((d / "cal.json").read_text())
    assert art["identifiability"]["status"] == "not-identifiable"
    power_up_csv(d / "pu.csv", d / "s.toml", 1.0, speed=0.0, seed=1)
    res = run("reconstruct", "cal.json", "pu.csv", "--absolute", "--out", "abs.csv", cwd=d)
    assert res.returncode == 3, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hallcal: refused:"), res.stderr
    assert "NOT identifiable" in lines[0] and "home the axis" in lines[0]
    assert not (d / "abs.csv").exists()
    # the relative reconstruction still works with this artifact
    res = run("reconstruct", "cal.json", "pu.csv", "--out", "rel.csv", cwd=d)
    assert res.returncode == 0, res.stderr


def test_artifact_without_identifiability_is_a_named_input_error(paper):
    d, _ = paper
    art = json.loads((d / "cal.json").read_text())
    del art["identifiability"]
    (d / "old.json").write_text(json.dumps(art))
    power_up_csv(d / "pu_old.csv", d / "s.toml", 3.0, speed=0.0, seed=3)
    res = run("reconstruct", "old.json", "pu_old.csv", "--absolute", "--out", "x.csv", cwd=d)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "identifiability" in lines[0] and "Traceback" not in res.stderr
    assert not (d / "x.csv").exists()


def test_front_door_absolute(paper):
    """hallcal.load(...).reconstruct(data, absolute=True) gives what the CLI writes, and the
    identification is reported on the result."""
    d, _ = paper
    power_up_csv(d / "pu_fd.csv", d / "s.toml", 4.4, speed=0.5, seed=44)
    cal = hallcal.load(d / "cal.json")
    assert cal.identifiability is not None and cal.identifiability.status.success
    rec = cal.reconstruct(d / "pu_fd.csv", absolute=True)
    assert rec.identification is not None and rec.identification.status.success
    assert rec.validation is not None
    assert rec.validation.star.rms < 1.3 * math.sqrt(7.5e-6) * math.sqrt(2 / 3) / 11
    res = run("reconstruct", "cal.json", "pu_fd.csv", "--absolute", "--out", "fd.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    out = read_dataset(d / "fd.csv", required=("y_star",))
    np.testing.assert_allclose(out["y_star"], rec.y_star, atol=1e-12)
