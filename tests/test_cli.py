"""The command line as a user runs it (subprocess): the happy path and the error messages."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from cli_support import paper_setup
from cli_support import run_cli as run

from hallcal.io import read_dataset, write_dataset

SETUP = paper_setup(duration=10.0, seed=5)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    (d / "s.toml").write_text(SETUP)
    res = run("simulate", "--setup", "s.toml", "--out", "cal.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    res = run("simulate", "--setup", "s.toml", "--out", "val.npz", "--seed", "77", cwd=d)
    assert res.returncode == 0, res.stderr
    return d


def test_simulate_writes_dataset_and_truth_sidecar(workdir):
    ds = read_dataset(workdir / "cal.csv")
    assert {"r", "y", "u", "d1", "d2", "d3", "t", "y_ref"} <= set(ds.names)
    assert ds.n_samples == 40000
    truth = json.loads((workdir / "cal.truth.json").read_text())
    assert truth["pole_pairs"] == 11 and len(truth["theta"]) == 3


def test_calibrate_then_reconstruct(workdir):
    res = run("calibrate", "cal.csv", "--setup", "s.toml", "--out", "cal.json", cwd=workdir)
    assert res.returncode == 0, res.stderr
    assert "cost" in res.stdout and "iterations" in res.stdout and "predicted" in res.stdout
    art = json.loads((workdir / "cal.json").read_text())
    assert art["format"] == "hallcal-calibration/1"
    assert art["diagnostics"]["bijective"] is True
    res = run("reconstruct", "cal.json", "val.npz", "--out", "out.csv", cwd=workdir)
    assert res.returncode == 0, res.stderr
    out = read_dataset(workdir / "out.csv", required=("y_init", "y_star"))
    val = read_dataset(workdir / "val.npz")
    assert out.n_samples == val.n_samples
    e_init = np.std(out["y_init"] - val["y_ref"])
    e_star = np.std(out["y_star"] - val["y_ref"])
    assert e_star < 0.25 * e_init  # 8 s of data: the table is good, if not at the floor yet


def error_of(res: subprocess.CompletedProcess) -> str:
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.startswith("hallcal: error:")]
    assert len(lines) == 1, res.stderr
    return lines[0]


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda s: s.replace("harmonics", "harmonix"), "model.harmonix"),
        (lambda s: s.replace("pole_pairs = 11", "pole_pairs = 0"), "pole_pairs"),
        (lambda s: s.replace('basis = "fourier"', 'basis = "wavelet"'), "model.basis"),
        (lambda s: s.replace("[plant]", "[plant\n"), "line 6"),
    ],
)
def test_bad_setup(workdir, mutate, expected):
    (workdir / "bad.toml").write_text(mutate(SETUP))
    msg = error_of(
        run("calibrate", "cal.csv", "--setup", "bad.toml", "--out", "x.json", cwd=workdir)
    )
    assert expected in msg and "bad.toml" in msg
    assert not (workdir / "x.json").exists()


def test_bad_data(workdir):
    ds = read_dataset(workdir / "cal.csv")
    cols = dict(ds.columns)
    assert ds.n_samples > 20000  # so that partial.csv (20 000 rows) really is a part of the run
    cases = {
        "missing.csv": None,
        "nocol.csv": {k: v for k, v in cols.items() if k != "d2"},
        "short.csv": {k: v[:20] for k, v in cols.items()},
        "partial.csv": {k: v[:20000] for k, v in cols.items()},
    }
    for name, c in cases.items():
        if c is not None:
            write_dataset(workdir / name, c)
    (workdir / "nan.csv").write_text("r,d1,d2,d3\n0,1,2,3\n0,nan,2,3\n")
    (workdir / "text.csv").write_text("r,d1,d2,d3\n0,1,2,3\n0,abc,2,3\n")
    (workdir / "empty.csv").write_text("")
    expect = {
        "missing.csv": "missing.csv",
        "nocol.csv": "d2",
        "short.csv": "electrical period",
        "partial.csv": "full revolution",
        "nan.csv": "d1",
        "text.csv": "d1",
        "empty.csv": "empty.csv",
    }
    for name, needle in expect.items():
        msg = error_of(run("calibrate", name, "--setup", "s.toml", "--out", "x.json", cwd=workdir))
        assert needle in msg, (name, msg)
        assert not (workdir / "x.json").exists()


def test_missing_plant_names_the_setup_file(workdir):
    text = SETUP.split("[plant]")[0] + SETUP.split("delay = 1.2e-4\n")[1]
    (workdir / "noplant.toml").write_text(text)
    msg = error_of(
        run("calibrate", "cal.csv", "--setup", "noplant.toml", "--out", "x.json", cwd=workdir)
    )
    assert "noplant.toml" in msg and "[plant]" in msg and "--bla-data" in msg


def test_not_an_artifact(workdir):
    (workdir / "notcal.json").write_text('{"hello": 1}')
    msg = error_of(run("reconstruct", "notcal.json", "val.npz", "--out", "o.csv", cwd=workdir))
    assert "notcal.json" in msg
    msg = error_of(run("reconstruct", "nothere.json", "val.npz", "--out", "o.csv", cwd=workdir))
    assert "nothere.json" in msg
    assert not (workdir / "o.csv").exists()


def test_help_lists_the_contract_commands(workdir):
    res = run("--help", cwd=workdir)
    assert res.returncode == 0
    for cmd in ("demo", "simulate", "bla", "calibrate", "reconstruct", "export-c", "report"):
        assert cmd in res.stdout


def test_export_c_writes_sources(workdir):
    if not (workdir / "cal.json").exists():
        res = run("calibrate", "cal.csv", "--setup", "s.toml", "--out", "cal.json", cwd=workdir)
        assert res.returncode == 0, res.stderr
    res = run("export-c", "cal.json", "--out", "fw", "--adc-scale", "1000", cwd=workdir)
    assert res.returncode == 0, res.stderr
    names = {p.name for p in (workdir / "fw").iterdir()}
    assert {"hallcal.h", "hallcal.c", "hallcal_q.h", "hallcal_q.c"} <= names
    assert "hallcal_update" in (workdir / "fw" / "hallcal.h").read_text()
    assert "power-up" in res.stderr  # whether the C identifies the pole pair, and why (not)


def test_calibrate_with_the_kernel_basis(workdir):
    """[model] basis = "kernel" with points works end to end."""
    text = SETUP.replace('basis = "fourier"\n', "").replace(
        "harmonics = [1,2,3,4,5,6,7,8,9,10,11]", 'basis = "kernel"\npoints = 64'
    )
    (workdir / "k.toml").write_text(text)
    res = run("calibrate", "cal.csv", "--setup", "k.toml", "--out", "k.json", cwd=workdir)
    assert res.returncode == 0, res.stderr
    assert "periodic kernel basis, 64 points" in res.stdout
    art = json.loads((workdir / "k.json").read_text())
    assert art["model"]["basis"] == "kernel" and art["model"]["points"] == 64
    assert np.asarray(art["model"]["weights"]).shape == (3, 64)
    res = run("reconstruct", "k.json", "val.npz", "--out", "kout.csv", cwd=workdir)
    assert res.returncode == 0, res.stderr
