"""The setup schema (hallcal.settings, hallcal.io.setup.SETUP_SCHEMA) drives the parser, the bench
and the reference.

Property: a value inside a key's declared range round-trips through the parser; a value outside
it is refused with one line naming the file and the dotted key (and the command exits 2).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import pytest
from cli_support import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hallcal.errors import HallcalInputError
from hallcal.io.setup import (
    SETUP_SCHEMA,
    BenchSpec,
    read_setup,
    render_setup_reference,
    setup_from_dict,
    setup_to_toml,
)
from hallcal.settings import REQUIRED, Setting, render_table, settings_of
from hallcal.sim.bench import BenchConfig

REFERENCE = Path(__file__).resolve().parents[1] / "docs" / "setup-reference.md"

#: A small valid setup; the key under test is set on top of it (with the table it needs).
BASE: dict[str, Any] = {
    "pole_pairs": 3,
    "sample_time": 1e-3,
    "controller": {"num": [1.0], "den": [1.0]},
    "plant": {"num": [1.0], "den": [1.0, 0.0]},
}
#: bla keys need the table's required keys; the smallest experiment leaves room for each one.
BLA_BASE = {"period_samples": 8, "periods": 2, "realizations": 1}

#: Keys whose accepted values depend on another key beyond their own declared range (the
#: reference says so in their "accepted values"), or limited jointly with other keys: checked by
#: their own tests in test_io.py, not by the one-key property below.
JOINT = {
    "plant.delay",  # delay / sample_time <= limits.MAX_DELAY_SAMPLES
    "bla.period_samples",  # period_samples x periods x realizations <= limits.MAX_SAMPLES
    "bla.periods",
    "bla.realizations",
}


def _dotted(table: str, name: str) -> str:
    return f"{table}.{name}" if table else name


def _generic() -> list[tuple[str, Setting]]:
    """Keys the parser reads from their declaration alone (kind, range, limit, choices)."""
    out = []
    for table, keys in SETUP_SCHEMA.items():
        for s in keys:
            if s.kind in ("custom", "table") or s.accepts or _dotted(table, s.name) in JOINT:
                continue
            out.append((table, s))
    return out


GENERIC = _generic()


def _setup_with(table: str, s: Setting, value: Any) -> dict[str, Any]:
    data = {k: dict(v) if isinstance(v, dict) else v for k, v in BASE.items()}
    if table == "bla":
        data["bla"] = dict(BLA_BASE)
    if table:
        data.setdefault(table, {})
        if s.only is not None:
            data[table][s.only[0]] = s.only[1]
        data[table][s.name] = value
    else:
        data[s.name] = value
    return data


def _parsed(setup: Any, table: str, name: str) -> Any:
    return getattr(getattr(setup, table) if table else setup, name)


def _inside(s: Setting) -> st.SearchStrategy[Any]:
    """Values inside the declared range (the resource limit included)."""
    if s.kind == "integer":
        return st.integers(int(s.minimum or 0), int(s.limit) if s.limit else 2**62)
    top = s.limit if s.limit is not None else 1e300
    if s.kind == "number":
        low = 0.0 if s.positive else (s.minimum if s.minimum is not None else -top)
        floats = st.floats(low, top, exclude_min=s.positive, allow_nan=False)
        return floats | st.integers(math.ceil(low), 10**6).filter(lambda v: v > 0 or not s.positive)
    if s.kind == "numbers":
        return st.lists(st.floats(-top, top, allow_nan=False), min_size=s.length, max_size=s.length)
    if s.kind == "choice":
        return st.sampled_from(s.choices)
    assert s.kind == "boolean", s
    return st.booleans()


def _outside(s: Setting) -> st.SearchStrategy[Any]:
    """Values outside the declared range, of a wrong type, or not finite."""
    wrong_type = st.sampled_from(["x", [], {}]) | st.just(True)
    if s.kind == "integer":
        bad = st.integers(max_value=int(s.minimum or 0) - 1) | st.floats(0.5, 1e6)
        if s.limit is not None:
            bad |= st.integers(min_value=int(s.limit) + 1)
        return bad | wrong_type
    if s.kind == "number":
        bad = st.sampled_from([math.nan, math.inf, -math.inf])
        if s.positive:
            bad |= st.floats(max_value=0.0, allow_nan=False, allow_infinity=False)
        elif s.minimum is not None:
            bad |= st.floats(max_value=s.minimum, exclude_max=True, allow_infinity=False)
        if s.limit is not None:
            bad |= st.floats(min_value=s.limit, exclude_min=True, allow_infinity=False)
        return bad | wrong_type
    if s.kind == "numbers":
        n = s.length or 1
        bad = st.lists(st.floats(-1, 1), min_size=n + 1, max_size=n + 2)
        bad |= st.lists(st.just(math.inf), min_size=n, max_size=n)
        if s.limit is not None:
            bad |= st.lists(st.just(10 * s.limit), min_size=n, max_size=n)
        return bad | st.sampled_from(["x", [], ["a"] * n, True])
    if s.kind == "choice":
        return st.text(max_size=12).filter(lambda v: v not in s.choices) | st.integers()
    return st.integers() | st.sampled_from(["true", "yes", 1.0, []])


def test_the_generic_keys_cover_most_of_the_schema():
    total = sum(len(keys) for keys in SETUP_SCHEMA.values())
    assert total == 53  # 6 tables + 47 keys: a new key shows up here and in the reference
    assert len(GENERIC) == 28, [_dotted(t, s.name) for t, s in GENERIC]


@pytest.mark.parametrize("table, s", GENERIC, ids=[_dotted(t, s.name) for t, s in GENERIC])
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_a_value_inside_the_declared_range_round_trips(table, s, data):
    value = data.draw(_inside(s))
    setup = setup_from_dict(_setup_with(table, s, value))
    got = _parsed(setup, table, s.name)
    expected = tuple(float(v) for v in value) if s.kind == "numbers" else value
    assert got == expected and type(got) is type(s.default if not s.required else got)
    assert setup_from_dict(setup.to_dict()) == setup


@pytest.mark.parametrize("table, s", GENERIC, ids=[_dotted(t, s.name) for t, s in GENERIC])
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_a_value_outside_the_declared_range_is_refused_naming_the_key(table, s, data):
    value = data.draw(_outside(s))
    with pytest.raises(HallcalInputError) as info:
        setup_from_dict(_setup_with(table, s, value), source="motor.toml")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("motor.toml: ") and f"'{_dotted(table, s.name)}'" in message


def test_every_optional_key_defaults_to_its_declaration():
    full = {**BASE, "bla": {"period_samples": 8, "periods": 2}}
    parsed = {
        None: setup_from_dict(full),
        ("basis", "kernel"): setup_from_dict({**full, "model": {"basis": "kernel"}}),
        ("kind", "constant-speed"): setup_from_dict(
            {**full, "trajectory": {"kind": "constant-speed"}}
        ),
    }
    checked = 0
    for table, keys in SETUP_SCHEMA.items():
        for s in keys:
            if s.required or s.kind == "table":
                continue
            value = _parsed(
                parsed[s.only if s.only != ("basis", "fourier") else None], table, s.name
            )
            assert value == s.default, (table, s.name)
            checked += 1
    assert checked == 39  # the 47 keys but the 8 required ones


def test_every_declaration_is_complete():
    kinds = {"integer", "number", "boolean", "choice", "numbers", "table", "custom"}
    for table, keys in SETUP_SCHEMA.items():
        for s in keys:
            where = _dotted(table, s.name)
            assert s.kind in kinds and s.doc and "\n" not in s.doc, where
            assert s.doc.rstrip().endswith((".", ")")), where  # one sentence (or more) per key
            if s.kind == "choice":
                assert s.default is REQUIRED or s.default in s.choices, where
            if s.kind == "custom":
                assert s.type_text and s.accepts, where  # the reference cannot derive them


def test_the_reference_is_the_rendering_of_the_schema():
    text = REFERENCE.read_text(encoding="utf-8")
    assert text.count("<!-- generated from the schema: ") == len(SETUP_SCHEMA)
    assert render_setup_reference(text) == text, (
        "docs/setup-reference.md differs from the schema; regenerate its tables with "
        "hallcal.io.setup.render_setup_reference"
    )


def test_the_rendering_check_catches_a_planted_edit_and_a_planted_default():
    text = REFERENCE.read_text(encoding="utf-8")
    edited = text.replace("| `0.05` |", "| `0.5` |")
    assert edited != text and render_setup_reference(edited) != edited
    bench = settings_of(BenchSpec)
    planted = [dataclasses.replace(s, default=2.0) if s.name == "amplitude" else s for s in bench]
    assert render_table(planted) != render_table(bench)
    assert "| `amplitude` | number, Hall unit | `2.0` | > 0 |" in render_table(planted)


def test_the_bench_is_declared_once():
    """BenchConfig is a BenchSpec: every [bench] key reaches the simulated bench unchanged."""
    from hallcal.pipeline.simulate import bench_config

    assert issubclass(BenchConfig, BenchSpec)
    assert BenchSpec().amplitude == BenchConfig().amplitude  # one default, inherited
    changed = {
        "seed": 7,
        "noise_variance": 1e-5,
        "ramp_end": 2.0,
        "duration": 1.5,
        "amplitude": 0.8,
        "magnet_variation": 0.01,
        "pole_modulation": 0.02,
        "shape_variation": 0.03,
        "shape_harmonics": 2,
        "misalignment_deg": [1.0, -2.0, 0.5],
        "gain_mismatch": [0.01, 0.0, -0.02],
        "offset": [0.001, 0.0, 0.0],
        "electrical_harmonics": [[3, 0.05]],
        "torque_disturbance": 0.1,
        "cogging": 0.2,
        "cogging_periods": 4,
    }
    assert set(changed) | {"experiment"} == {s.name for s in SETUP_SCHEMA["bench"]}
    setup = setup_from_dict({**BASE, "bench": changed})
    cfg = bench_config(setup)
    for f in dataclasses.fields(BenchSpec):
        assert getattr(cfg, f.name) == getattr(setup.bench, f.name), f.name
    assert cfg.pole_pairs == 3 and cfg.sample_time == 1e-3 and cfg.plant == setup.plant
    assert cfg.adc() is None and cfg.spike_rate == 0.0  # the knobs only code sets: defaults


def test_a_key_out_of_range_in_a_file_exits_2_with_one_line(tmp_path):
    bad = setup_to_toml(setup_from_dict(BASE)).replace("lut_points = 4096", "lut_points = 15")
    (tmp_path / "motor.toml").write_text(bad, encoding="utf-8")
    with pytest.raises(HallcalInputError, match=r"'model\.lut_points' must be an integer >= 16"):
        read_setup(tmp_path / "motor.toml")
    res = run_cli("simulate", "--setup", "motor.toml", "--out", "run.csv", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "motor.toml" in lines[0] and "'model.lut_points'" in lines[0]
