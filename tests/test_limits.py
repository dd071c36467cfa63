"""Resource limits, plausibility checks and the one artifact validator, case by case.

The hostile suite (tests/test_hostile.py) checks the command line end to end; here the pieces:
that each limit refuses what is above it with a message naming the key and the limit, that no
limit refuses what a real motor needs (100 pole pairs, a few hundred harmonics, 10 M samples),
and that :func:`hallcal.io.validate_artifact` returns the typed view the other consumers use.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hallcal import limits
from hallcal.errors import HallcalInputError
from hallcal.io import (
    ARTIFACT_FORMAT,
    ArtifactData,
    default_setup,
    read_artifact,
    read_dataset,
    read_json,
    setup_from_dict,
    validate_artifact,
    write_artifact,
)
from hallcal.io.artifact import ARTIFACT_STATUSES
from hallcal.io.dataset import Dataset
from hallcal.pipeline import CalibrationStatus
from hallcal.sensor.lut import build_lut
from hallcal.sensor.reconstruction import clarke_matrix

# ------------------------------------------------------------------------------------------------
# Setup limits


def _setup(**changes: Any) -> dict[str, Any]:
    """The paper's setup with ``table__key=value`` changes (a kernel basis drops harmonics)."""
    d = default_setup().to_dict()
    for name, value in changes.items():
        table, _, key = name.rpartition("__")
        (d.setdefault(table, {}) if table else d)[key] = value
    if d["model"].get("basis") == "kernel":
        d["model"].pop("harmonics", None)
    return d


@pytest.mark.parametrize(
    ("changes", "key", "limit"),
    [
        ({"pole_pairs": limits.MAX_POLE_PAIRS + 1}, "pole_pairs", limits.MAX_POLE_PAIRS),
        (
            {"model__harmonics": list(range(1, limits.MAX_HARMONICS + 2))},
            "model.harmonics",
            limits.MAX_HARMONICS,
        ),
        (
            {"model__harmonics": [1, limits.MAX_HARMONIC + 1]},
            "model.harmonics",
            limits.MAX_HARMONIC,
        ),
        (
            {
                "model__basis": "kernel",
                "model__points": limits.MAX_KERNEL_POINTS + 1,
                "model__lengthscale": "auto",
            },
            "model.points",
            limits.MAX_KERNEL_POINTS,
        ),
        (
            {"model__lut_points": limits.MAX_LUT_POINTS + 1},
            "model.lut_points",
            limits.MAX_LUT_POINTS,
        ),
        (
            {"model__max_iterations": limits.MAX_ITERATIONS + 1},
            "model.max_iterations",
            limits.MAX_ITERATIONS,
        ),
        ({"plant__den": [1.0] * (limits.MAX_TF_ORDER + 2)}, "plant.den", limits.MAX_TF_ORDER + 1),
        (
            {"controller__den": [1.0] * (limits.MAX_TF_ORDER + 2)},
            "controller.den",
            limits.MAX_TF_ORDER + 1,
        ),
        (
            {"plant__delay": (limits.MAX_DELAY_SAMPLES + 1) * 2.5e-4},
            "plant.delay",
            limits.MAX_DELAY_SAMPLES,
        ),
        ({"bla__realizations": limits.MAX_REALIZATIONS + 1}, "bla.realizations", 1000),
        ({"bench__amplitude": 1e13}, "bench.amplitude", 1e12),
    ],
)
def test_each_setup_limit_names_the_key_and_the_limit(
    changes: dict[str, Any], key: str, limit: float
) -> None:
    with pytest.raises(HallcalInputError) as excinfo:
        setup_from_dict(_setup(**changes), source="s.toml")
    message = str(excinfo.value)
    assert message.startswith(f"s.toml: key '{key}'"), message
    shown = str(int(limit)) if float(limit).is_integer() and limit < 1e15 else f"{limit:g}"
    assert f"limit of {shown}" in message, message
    assert "\n" not in message


def test_the_limits_accept_what_real_motors_need() -> None:
    """100 pole pairs, 300 harmonics up to 8 n_m, 3 samples of delay, the paper's kernel
    (400 points) and ten times it, the firmware's largest table, a 20-state loop is refused but
    order 16 is not."""
    setup_from_dict(_setup(pole_pairs=100, model__harmonics=list(range(1, 301))))
    setup_from_dict(_setup(pole_pairs=100, model__harmonics=[1, 100, 200, 800]))
    setup_from_dict(_setup(plant__delay=3 * 2.5e-4))
    for points in (400, 4000):
        setup_from_dict(
            _setup(model__basis="kernel", model__points=points, model__lengthscale="auto")
        )
    setup_from_dict(_setup(model__lut_points=65000, model__max_iterations=1000))
    setup_from_dict(_setup(controller__den=[1.0] + [0.0] * 15 + [0.1], controller__num=[1.0]))
    setup_from_dict(
        _setup(bla__period_samples=40_000, bla__periods=10, bla__realizations=50)
    )  # 20 M samples: an hour-long BLA experiment at 4 kHz


def test_ten_million_samples_are_read(tmp_path: Path) -> None:
    """A 10 M-sample recording (40 min at 4 kHz) is not refused by any limit."""
    n = 10_000_000
    phase = np.linspace(0.0, 2000.0, n, dtype=np.float32)
    path = tmp_path / "long.npz"
    np.savez(path, d1=np.cos(phase), d2=np.cos(phase - 2.1), d3=np.cos(phase + 2.1))
    ds = read_dataset(path)
    assert ds.n_samples == n and ds.d.shape == (n, 3)


def test_a_large_integer_in_a_setup_is_an_error_not_an_overflow() -> None:
    for key in ("sample_time", "bench__noise_variance"):
        with pytest.raises(HallcalInputError, match="finite"):
            setup_from_dict(_setup(**{key: 10**400}))


# ------------------------------------------------------------------------------------------------
# JSON and TOML


def test_json_depth_size_and_number_range(tmp_path: Path) -> None:
    p = tmp_path / "x.json"
    p.write_text("[" * 10_000 + "]" * 10_000)
    with pytest.raises(HallcalInputError, match="nested far more than 32 levels"):
        read_json(p)
    p.write_text('{"a": ' + "[" * 33 + "]" * 33 + "}")
    with pytest.raises(HallcalInputError, match="nested more than 32 levels"):
        read_json(p)
    p.write_text('{"a": ' + "[" * 31 + "]" * 31 + "}")
    assert read_json(p)["a"] == [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]
    p.write_text('{"a": {"b": [1, 2, 1e999]}}')
    with pytest.raises(HallcalInputError, match=r"key 'a\.b\[2\]' holds a number out of"):
        read_json(p)
    p.write_text('{"a": 1' + "0" * 30 + "}")
    with pytest.raises(HallcalInputError, match="key 'a' holds an integer out of the 64-bit"):
        read_json(p)
    with open(p, "w") as f:
        f.write('{"a": 1}')
        f.write(" " * (limits.MAX_JSON_BYTES + 1))
    with pytest.raises(HallcalInputError, match="above the limit of 67.1 MB"):
        read_json(p)


# ------------------------------------------------------------------------------------------------
# Dataset plausibility


def _hall(n: int = 2000, amplitude: float = 1.0, offset: float = 0.0) -> dict[str, np.ndarray]:
    y = np.linspace(0.0, 40.0, n)
    return {f"d{h + 1}": offset + amplitude * np.cos(y - 2.0 * math.pi * h / 3.0) for h in range(3)}


@pytest.mark.parametrize(
    ("amplitude", "offset"),
    [(1.0, 0.0), (0.05, 1.65), (1800.0, 2048.0), (3e6, 8e6), (1e-6, 0.0)],
    ids=["normalized", "volts", "12-bit counts", "24-bit counts", "microvolts"],
)
def test_real_units_are_plausible(amplitude: float, offset: float) -> None:
    cols = _hall(amplitude=amplitude, offset=offset)
    cols["d1"][::97] = offset  # exact values at the offset (an ADC's mid code) are fine
    Dataset.from_columns(cols)


@pytest.mark.parametrize(
    ("value", "why"),
    [
        (1e13, "above 1e\\+12"),
        (1e-200, "nonzero but below 1e-30"),
        (5e6, "times the column's typical magnitude"),
    ],
)
def test_implausible_hall_values_are_refused_with_their_row(value: float, why: str) -> None:
    cols = _hall()
    cols["d2"][17] = value
    with pytest.raises(HallcalInputError, match="column 'd2' row 18: the value .* is "):
        Dataset.from_columns(cols, path="run.h5")
    with pytest.raises(HallcalInputError, match=why):
        Dataset.from_columns(cols, path="run.h5")


def test_other_columns_keep_their_own_units() -> None:
    cols = {**_hall(), "t_ns": np.full(2000, 1.7e18), "u": np.zeros(2000)}
    cols["u"][5] = 1e9  # a torque spike far above a zero median: not checked for spikes
    Dataset.from_columns(cols)


# ------------------------------------------------------------------------------------------------
# The artifact validator


def _artifact() -> dict[str, Any]:
    setup = default_setup()
    theta = np.zeros((3, 23))
    theta[:, 22] = np.cos(2 * np.pi * np.arange(3) / 3)  # cos(11 y0) per sensor
    theta[:, 21] = np.sin(2 * np.pi * np.arange(3) / 3)
    from hallcal.sensor.flux import FluxModel, FourierBasis

    flux = FluxModel(FourierBasis(tuple(range(1, 12))), theta)
    lut = build_lut(flux, 11, points=256)
    assert lut.bijective
    return {
        "format": ARTIFACT_FORMAT,
        "hallcal_version": "0.1.0",
        "pole_pairs": 11,
        "reconstruction": {"projection": clarke_matrix()[:2].tolist(), "offset": [0.0] * 3},
        "lut": lut.to_dict(),
        "model": {"basis": "fourier", "harmonics": list(range(1, 12)), "theta": theta.tolist()},
        "setup": setup.to_dict(),
        "diagnostics": {"status": "ok", "messages": []},
    }


def test_validate_artifact_returns_the_typed_view(tmp_path: Path) -> None:
    art = _artifact()
    data = validate_artifact(art, "cal.json")
    assert isinstance(data, ArtifactData)
    assert data.format == ARTIFACT_FORMAT and data.version == "0.1.0"
    assert data.pole_pairs == 11 and data.points == 256 and data.source == "cal.json"
    assert data.projection.shape == (2, 3) and not data.projection.flags.writeable
    np.testing.assert_array_equal(data.y_hat, art["lut"]["y_hat"])
    np.testing.assert_allclose(data.y0, art["lut"]["y0"], atol=1e-15)
    assert data.setup == default_setup()
    lut = data.lut()
    assert lut.bijective and lut.points == 256
    # the same view from the file, and the same hash
    write_artifact(tmp_path / "cal.json", art)
    again = read_artifact(tmp_path / "cal.json")
    assert again.pole_pairs == 11 and len(again.sha256) == 64
    # the one reader's view is also the artifact's JSON, key by key (read-only)
    assert dict(again) == json.loads((tmp_path / "cal.json").read_text())
    assert again["lut"]["points"] == 256 and again.get("no such key") is None
    # read from a file, the digest is the file's (what sha256sum prints, what export-c embeds)
    raw = (tmp_path / "cal.json").read_bytes()
    assert again.sha256 == hashlib.sha256(raw).hexdigest()
    assert validate_artifact(json.loads(raw)).sha256 != again.sha256  # the canonical form's


def test_validate_artifact_accepts_the_in_memory_form() -> None:
    art = _artifact()
    art["setup"] = default_setup()
    art["reconstruction"]["projection"] = clarke_matrix()[:2]
    art["lut"]["eta"] = np.asarray(art["lut"]["eta"])
    assert validate_artifact(art).pole_pairs == 11


def _mutated(path: str, value: Any) -> dict[str, Any]:
    art = copy.deepcopy(_artifact())
    *parents, last = path.split(".")
    target = art
    for p in parents:
        target = target[p]
    target[last] = value
    return art


@pytest.mark.parametrize(
    ("path", "value", "expected"),
    [
        ("reconstruction.projection", [[0, 0, 0], [0, 0, 0]], "is all zero"),
        ("reconstruction.projection", [[1, 0, 0], [2, 0, 0]], "has rank 1, condition number inf"),
        ("reconstruction.projection", [[1, 0, 0], [1, 1e-6, 0]], "condition number 2e\\+06"),
        ("reconstruction.projection", [[1e-13, 0, 0], [0, 1e-13, 0]], "scale 1e-13"),
        ("reconstruction.offset", [1e13, 0, 0], "holds 1e\\+13, implausible"),
        ("pole_pairs", 10**6, "key 'pole_pairs' is 1000000, above the limit of 256"),
        ("diagnostics.status", "fine", "'diagnostics.status' must be one of"),
        ("diagnostics.messages", ["x" * 5000], "above the limit of 4096"),
        ("model.theta", [[0.0] * 23] * 2, "'model.theta' must be a 3x23 array"),
        ("hallcal_version", "1\n2", "version string"),
        ("format", "hallcal-calibration/2", "unsupported format"),
    ],
)
def test_validate_artifact_refuses(path: str, value: Any, expected: str) -> None:
    with pytest.raises(HallcalInputError, match=f"^cal.json: .*{expected}"):
        validate_artifact(_mutated(path, value), "cal.json")


def test_validate_artifact_refuses_broken_tables() -> None:
    art = _artifact()
    y_hat = np.array(art["lut"]["y_hat"])
    eta = np.array(art["lut"]["eta"])
    cases = {
        "not bijective": (np.r_[y_hat[:10], y_hat[11], y_hat[10], y_hat[12:]], eta),
        "pi rad or more": (y_hat, eta + math.pi),
        "at least 16": (y_hat[:8], eta[:8]),
        "outside one revolution": (y_hat + 20.0, eta),
    }
    for expected, (y, e) in cases.items():
        bad = copy.deepcopy(art)
        bad["lut"] = {"y_hat": y.tolist(), "eta": e.tolist()}
        with pytest.raises(HallcalInputError, match=expected):
            validate_artifact(bad, "cal.json")


def test_the_artifact_statuses_are_the_calibration_statuses() -> None:
    assert set(ARTIFACT_STATUSES) == {s.value for s in CalibrationStatus}


# ------------------------------------------------------------------------------------------------
# Work memory


def test_work_memory_is_checked_before_allocating() -> None:
    budget = limits.work_memory_budget()
    assert 0 < budget <= limits.MAX_WORK_BYTES
    limits.check_work_memory(budget, "a table", "use less")
    with pytest.raises(ValueError, match=r"^a table would need .* GiB, above the limit of"):
        limits.check_work_memory(budget + 1, "a table", "use less")
    with pytest.raises(ValueError, match="unbounded memory"):
        limits.check_work_memory(math.inf, "a table", "use less")


def test_the_sem_checks_its_work_memory_before_allocating(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With a budget of 64 MiB (as under a tight RLIMIT_AS), 11 harmonics over 20 000 samples
    (69 parameters: chunk buffers of 4096 x 69, 9 MB) pass and 512 harmonics (3075 parameters:
    1 GB of Gram matrix and buffers) are refused before anything is built."""
    from hallcal.fit.sem import solve_sem
    from hallcal.sensor.flux import FourierBasis
    from hallcal.sim.loop import ClosedLoop

    monkeypatch.setattr(limits, "work_memory_budget", lambda: 64 * 2**20)
    s = default_setup()
    loop = ClosedLoop.from_transfer_functions(s.plant, s.controller, s.sample_time, 11)
    n = 20_000
    r = np.linspace(0.0, 7.0, n)
    d = np.column_stack([np.cos(11 * r - 2.0 * np.pi * h / 3.0) for h in range(3)])
    small = FourierBasis(tuple(range(1, 12)))
    res = solve_sem(loop, r, d, small, max_iterations=1)
    assert res.flux.theta.shape == (3, 23)
    big = FourierBasis(tuple(range(1, limits.MAX_HARMONICS + 1)))
    with pytest.raises(ValueError, match="the Gauss-Newton system .* would need .* GiB"):
        solve_sem(loop, r, d, big, theta0=np.zeros((3, big.size)))


def test_the_sem_refuses_hall_signals_without_an_angle() -> None:
    from hallcal.fit.sem import solve_sem
    from hallcal.sensor.flux import FourierBasis
    from hallcal.sim.loop import ClosedLoop

    s = default_setup()
    loop = ClosedLoop.from_transfer_functions(s.plant, s.controller, s.sample_time, 11)
    d = 1e-300 * np.ones((100, 3))
    with pytest.raises(ValueError, match="largest magnitude is 1e-300"):
        solve_sem(loop, np.zeros(100), d, FourierBasis((11,)))
