"""The front door: the README's notebook example, in-memory inputs, and the CLI's equivalence."""

from __future__ import annotations

import copy
import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hallcal
from hallcal import pipeline
from hallcal.io import default_setup, read_dataset, setup_to_toml, write_dataset
from hallcal.io.files import to_jsonable
from hallcal.sensor.metrics import angle_error

README = Path(__file__).resolve().parents[1] / "README.md"


def _readme_python_block() -> str:
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Python (notebooks)") :]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match is not None, "the README's notebook section has no python block"
    return match.group(1)


@pytest.fixture(scope="module")
def paper_files(tmp_path_factory):
    """The paper bench (plant given, seed 3): setup.toml, cal.csv and a fresh run.csv."""
    folder = tmp_path_factory.mktemp("paper")
    s = default_setup()
    s = dataclasses.replace(s, bench=dataclasses.replace(s.bench, seed=3))
    cal = pipeline.simulate(s, experiment="ramp")
    run = pipeline.simulate(s, experiment="ramp", seed=77, ramp_end=12.0, duration=24.0)
    (folder / "setup.toml").write_text(setup_to_toml(s))
    write_dataset(folder / "cal.csv", cal.columns())
    write_dataset(folder / "run.csv", run.columns())
    return folder, s, cal, run


def test_readme_notebook_example_runs_and_reaches_the_noise_floor(paper_files, monkeypatch):
    folder, _, cal_run, run = paper_files
    monkeypatch.chdir(folder)
    namespace: dict = {}
    exec(compile(_readme_python_block(), "README.md", "exec"), namespace)  # noqa: S102
    cal, angles = namespace["cal"], namespace["angles"]
    assert cal.status is hallcal.CalibrationStatus.OK, cal.messages
    assert (folder / "cal.json").is_file()
    floor = cal_run.config.noise_floor
    err = angle_error(angles["y_star"], run.y0)
    # the acceptance bound on the paper bench: f_star within 15% of the noise floor
    assert err.rms <= 1.15 * floor
    assert angle_error(angles["y_init"], run.y0).rms > 5 * floor  # there was something to fix


def test_in_memory_inputs_give_the_same_calibration_as_files(paper_files):
    folder, s, cal_run, _ = paper_files
    from_files = hallcal.calibrate(folder / "cal.csv", folder / "setup.toml")
    columns = {k: np.asarray(v) for k, v in read_dataset(folder / "cal.csv").columns.items()}
    in_memory = hallcal.calibrate(columns, s.to_dict())
    # same numbers in, same deterministic solver: identical tables
    np.testing.assert_array_equal(from_files.lut.eta, in_memory.lut.eta)
    assert from_files.status == in_memory.status


def test_save_load_reconstruct_matches_the_cli_to_1e_12(paper_files, tmp_path):
    folder, *_ = paper_files
    cal = hallcal.calibrate(folder / "cal.csv", folder / "setup.toml")
    cal.save(tmp_path / "api.json")
    loaded = hallcal.load(tmp_path / "api.json")
    assert loaded.status == cal.status and loaded.pole_pairs == cal.pole_pairs
    # it wraps the pipeline's result (fields read through, frozen, copyable), and the
    # diagnostics are the artifact's whichever way the calibration was made
    assert isinstance(loaded.result, pipeline.Calibration) and loaded.lut is loaded.result.lut
    assert copy.deepcopy(loaded).status == loaded.status
    with pytest.raises(dataclasses.FrozenInstanceError):
        loaded.status = cal.status
    assert loaded.diagnostics["noise_variance"] == cal.diagnostics["noise_variance"]
    # one form: the computed and the loaded calibration are one type reading one artifact; the
    # loaded one lacks only the solver's results in memory
    assert type(loaded) is type(cal) and loaded.computed is None and cal.sem is not None
    assert loaded.to_artifact() == hallcal.io.read_json(tmp_path / "api.json")
    for name in ("status", "refusal", "predicted_error", "noise_floor", "plant_source"):
        assert getattr(loaded, name) == getattr(cal, name), name
    for name in ("model_info", "observer", "sensors", "timings"):
        assert to_jsonable(getattr(loaded, name)) == to_jsonable(getattr(cal, name)), name
    assert [m.record() for m in loaded.messages] == [m.record() for m in cal.messages]
    np.testing.assert_array_equal(loaded.lut.eta, cal.lut.eta)  # JSON floats read back exactly
    np.testing.assert_array_equal(loaded.flux.theta, cal.flux.theta)
    assert loaded.plant == cal.plant
    assert loaded.identifiability.to_dict() == cal.identifiability.to_dict()
    api = loaded.reconstruct(folder / "run.csv")
    cli = subprocess.run(
        [sys.executable, "-m", "hallcal.cli", "reconstruct", str(tmp_path / "api.json"),
         str(folder / "run.csv"), "--out", str(tmp_path / "cli.csv")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert cli.returncode == 0, cli.stderr
    out = read_dataset(tmp_path / "cli.csv", required=("y_init", "y_star"))
    # CSV stores the shortest repr that reads back exactly; the bound is the acceptance bound
    np.testing.assert_allclose(out["y_star"], api["y_star"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(out["y_init"], api["y_init"], rtol=0, atol=1e-12)
    # the in-process object and the loaded one reconstruct identically
    np.testing.assert_array_equal(cal.reconstruct(folder / "run.csv")["y_star"], api["y_star"])
    # the report is drawn from the recording: without it, the error family, not an AttributeError
    with pytest.raises(hallcal.HallcalInputError, match="report needs data="):
        loaded.report(tmp_path / "report")
    assert not (tmp_path / "report").exists()


def test_a_refused_calibration_is_not_saved(paper_files, tmp_path):
    """Too few harmonics for a trapezoidal flux: refused, with its reason, nothing written."""
    folder, s, *_ = paper_files
    bench = dataclasses.replace(s.bench, electrical_harmonics=((3, 0.1), (5, 0.04)), seed=4)
    setup = dataclasses.replace(s, bench=bench, model=dataclasses.replace(s.model, harmonics=(11,)))
    run = pipeline.simulate(setup, experiment="ramp", duration=13.0, ramp_end=6.5)
    cal = hallcal.calibrate(run.columns(), setup)
    assert cal.status.refused and cal.refusal
    with pytest.raises(hallcal.CalibrationRefused, match="no artifact written"):
        cal.save(tmp_path / "x.json")
    assert not (tmp_path / "x.json").exists()


def test_bad_inputs_raise_the_error_family(tmp_path):
    with pytest.raises(hallcal.HallcalInputError, match="file not found"):
        hallcal.calibrate(tmp_path / "missing.csv", default_setup())
    with pytest.raises(hallcal.HallcalError, match="unknown key 'pole_pair'"):
        hallcal.calibrate({"d1": [0.0]}, {"pole_pair": 11, "sample_time": 1e-3})
    with pytest.raises(hallcal.HallcalInputError, match="column 'r' is missing"):
        hallcal.calibrate({"d1": [0.0, 1.0], "d2": [1.0, 0.0], "d3": [0.0, 1.0]}, default_setup())
