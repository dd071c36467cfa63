"""Determinism: the same input and version give the same artifact bytes, timestamps aside.

Nothing in a calibration may depend on the wall clock, the machine's load or the solver's thread
count (a search stopped by elapsed time gave 113x and 91x the noise floor on two runs
of one input). Two calibrations of a small bench with ``harmonics = "auto"`` (the search that had
a time budget), one while a CPU hog spins on both cores with the Gauss-Newton passes forced to
two threads, one on an idle machine with one thread, must write the same artifact once only its
wall-clock fields (:data:`hallcal.io.artifact.TIMING_KEYS`) are removed.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

import hallcal
from hallcal.fit import gauss_newton
from hallcal.io.artifact import TIMING_KEYS, read_artifact, without_timings
from hallcal.sim.bench import BenchConfig, ramp_run

#: a motor whose model the search must work for: every magnet's shape different (flux band
#: beyond n_m), trapezoidal flux, 4 pole pairs; 2 revolutions in 6 s at 4 kHz (24 000 samples)
CONFIG = BenchConfig(
    pole_pairs=4,
    electrical_harmonics=((3, 0.08),),
    shape_variation=0.02,
    shape_harmonics=3,
    seed=11,
)
RUN = ramp_run(CONFIG, ramp_end=12.6, duration=6.0, seed=11)
SETUP = {
    "pole_pairs": CONFIG.pole_pairs,
    "sample_time": CONFIG.sample_time,
    "controller": {"num": list(CONFIG.controller.num), "den": list(CONFIG.controller.den)},
    "plant": {
        "num": list(CONFIG.plant.num),
        "den": list(CONFIG.plant.den),
        "delay": CONFIG.plant.delay,
    },
    "model": {"harmonics": "auto"},
}

#: a bounded hog: two processes spinning for at most this long [s] (killed once the run is done)
HOG_SECONDS = 120
HOG = "import time\nt = time.monotonic() + {s}\nwhile time.monotonic() < t:\n    pass\n"


def calibrate_to(path, monkeypatch: pytest.MonkeyPatch, threads: int) -> bytes:
    """Calibrate the bench with the Gauss-Newton passes at ``threads`` threads; the artifact
    with its timing fields removed, as canonical JSON bytes."""
    with monkeypatch.context() as m:
        m.setattr(gauss_newton, "_threads", lambda _t, p: threads if p >= 16 else 1)
        cal = hallcal.calibrate(RUN.columns(), SETUP)
    cal.save(path)
    return json.dumps(without_timings(read_artifact(path)), sort_keys=True).encode()


def test_same_artifact_bytes_under_load_and_idle_at_one_and_two_threads(tmp_path, monkeypatch):
    hogs = [subprocess.Popen([sys.executable, "-c", HOG.format(s=HOG_SECONDS)]) for _ in range(2)]
    try:
        loaded = calibrate_to(tmp_path / "loaded.json", monkeypatch, threads=2)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    idle = calibrate_to(tmp_path / "idle.json", monkeypatch, threads=1)
    assert loaded == idle
    # the search did real work (a band beyond n_m), and the comparison left the model in
    art = json.loads(idle)
    assert max(art["model"]["harmonics"]) > CONFIG.pole_pairs
    assert art["diagnostics"]["model_selection"]["fits"] >= 1
    assert "budget_hit" in art["diagnostics"]["model_selection"]
    # only the timing fields were removed: they are there in the file as written
    raw = read_artifact(tmp_path / "idle.json")
    assert "created" in raw and "timings" in raw["diagnostics"]
    assert {"created", "diagnostics.timings", "diagnostics.solve_time"} == set(TIMING_KEYS)
    assert "created" not in art and "timings" not in art["diagnostics"]
