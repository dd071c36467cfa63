"""The audit's fixes as a user meets them (subprocess): a recording whose first samples hold a
transient (one channel at its rail) is reconstructed (it fit everywhere else, yet plain
``reconstruct`` refused it with exit 3 "recalibrate"); ``reconstruct --absolute`` on it still
refuses (no lock was made) but names the transient, not a changed calibration."""

from __future__ import annotations

import numpy as np
import pytest
from cli_support import calibrated_folder, paper_setup
from cli_support import run_cli as run

from hallcal.io import read_setup, write_dataset
from hallcal.pipeline import bench_config
from hallcal.sim.bench import power_up_run

SETUP = paper_setup(duration=14.0, seed=0)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d, _ = calibrated_folder(tmp_path_factory.mktemp("unseen"), SETUP)
    cfg = bench_config(read_setup(d / "s.toml"))
    r = power_up_run(cfg, 1.3, samples=3000, speed=0.5, seed=3)
    dd = r.d.copy()
    dd[:20, 1] = 1.5 * np.max(np.abs(r.d[:, 1]))  # d2 at a rail for the first 20 samples
    write_dataset(d / "railed.csv", {"d1": dd[:, 0], "d2": dd[:, 1], "d3": dd[:, 2]})
    return d


def test_plain_reconstruct_accepts_a_transient_at_the_start(folder):
    res = run("reconstruct", "cal.json", "railed.csv", "--out", "out.csv", cwd=folder)
    assert res.returncode == 0, res.stderr
    assert "recalibrate" not in res.stdout + res.stderr


def test_absolute_names_the_transient(folder):
    res = run("reconstruct", "cal.json", "railed.csv", "--absolute", "--out", "a.csv", cwd=folder)
    assert res.returncode == 3, res.stdout
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "transient at power-up" in lines[0], res.stderr
