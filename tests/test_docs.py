"""The setup reference (docs/setup-reference.md) and the setup parser say the same thing.

Every key the parser accepts is documented, every documented key is accepted, and every default
written in the reference is the parser's default. Each check is also run on a planted defect.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

from hallcal.io import setup as setup_parser
from hallcal.io import setup_from_dict

REFERENCE = Path(__file__).resolve().parents[1] / "docs" / "setup-reference.md"


def documented(text: str) -> dict[str, str]:
    """``{"table.key": default cell}`` from the reference's tables (top level: ``"key"``)."""
    out: dict[str, str] = {}
    table = None
    for line in text.splitlines():
        head = re.match(r"^## (?:Top level|`\[(\w+)\]`)\s*$", line)
        if head:
            table = head.group(1) or ""
            continue
        row = re.match(r"^\| `(\w+)` \| [^|]* \| ([^|]*) \|", line)
        if row and table is not None:
            name = f"{table}.{row.group(1)}" if table else row.group(1)
            out[name] = row.group(2).strip()
    return out


def accepted() -> set[str]:
    return set(setup_parser._ALL_SETUP_KEYS)


def test_every_accepted_key_is_documented_and_vice_versa():
    docs = documented(REFERENCE.read_text(encoding="utf-8"))
    assert sorted(accepted() - set(docs)) == [], "keys the parser accepts but the docs omit"
    assert sorted(set(docs) - accepted()) == [], "documented keys the parser refuses"


def test_the_key_check_catches_a_planted_omission():
    text = REFERENCE.read_text(encoding="utf-8")
    planted = "\n".join(ln for ln in text.splitlines() if not ln.startswith("| `drift` |"))
    assert "bla.drift" not in documented(planted)
    extra = text + "\n| `planted_key` | number | `1` | any | nothing |\n"
    assert "bench.planted_key" in documented(extra)  # the last table is [bench]


def _parsed_defaults() -> dict[str, Any]:
    """The parser's default of every optional key, from minimal setups."""
    base = {
        "pole_pairs": 3,
        "sample_time": 1e-3,
        "controller": {"num": [1.0], "den": [1.0]},
        "plant": {"num": [1.0], "den": [1.0, 0.0]},
        "bla": {"period_samples": 100, "periods": 2},
    }
    fourier = setup_from_dict(base)
    kernel = setup_from_dict({**base, "model": {"basis": "kernel"}})
    spin = setup_from_dict({**base, "trajectory": {"kind": "constant-speed"}})
    out: dict[str, Any] = {"plant.delay": fourier.plant.delay}
    for table, spec in (("model", fourier.model), ("bla", fourier.bla), ("bench", fourier.bench)):
        for key in setup_parser._SETUP_KEYS[table]:
            out[f"{table}.{key}"] = getattr(spec, key)
    out["model.points"] = kernel.model.points
    out["model.lengthscale"] = kernel.model.lengthscale
    out["trajectory.kind"] = fourier.trajectory.kind
    out["trajectory.start"] = spin.trajectory.start
    return out


def _normal(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_normal(v) for v in value]
    return value


def _literal(cell: str) -> Any:
    """The TOML value of a default cell like ``\\`0.05\\``` (None when it is prose)."""
    m = re.fullmatch(r"`([^`]+)`", cell)
    if m is None:
        return None
    return tomllib.loads(f"v = {m.group(1)}")["v"]


def test_documented_defaults_are_the_parsers():
    docs = documented(REFERENCE.read_text(encoding="utf-8"))
    defaults = _parsed_defaults()
    checked = 0
    for key, value in defaults.items():
        if docs[key] == "required":
            continue  # the minimal setups above give these; the reference says "required"
        literal = _literal(docs[key])
        if key == "trajectory.kind":
            literal = docs[key].strip("`").strip('"')
        assert literal is not None, (key, docs[key])
        assert _normal(literal) == _normal(value), (key, docs[key], value)
        checked += 1
    assert checked >= 35  # every optional key with a value default
    # the ones without a literal default say why
    for key in ("pole_pairs", "sample_time", "bla.period_samples", "bla.periods", "plant.num"):
        assert docs[key] == "required", key
    assert docs["trajectory.stop"] == "end of the data"


def test_the_default_check_catches_a_planted_wrong_default():
    text = REFERENCE.read_text(encoding="utf-8").replace("| `0.05` |", "| `0.5` |")
    assert _literal(documented(text)["bla.rms"]) == 0.5
    with pytest.raises(AssertionError):
        assert _normal(_literal(documented(text)["bla.rms"])) == _parsed_defaults()["bla.rms"]


def test_the_readme_and_the_cli_point_to_the_reference():
    readme = (REFERENCE.parents[1] / "README.md").read_text(encoding="utf-8")
    assert "docs/setup-reference.md" in readme
    from hallcal.cli import cli

    assert "docs/setup-reference.md" in (cli.help or "")


def test_keys_documented_as_required_are_required():
    from hallcal.errors import HallcalInputError

    docs = documented(REFERENCE.read_text(encoding="utf-8"))
    full = {
        "pole_pairs": 3,
        "sample_time": 1e-3,
        "controller": {"num": [1.0], "den": [1.0]},
        "plant": {"num": [1.0], "den": [1.0, 0.0]},
        "bla": {"period_samples": 100, "periods": 2},
    }
    setup_from_dict(full)
    required = [k for k, v in docs.items() if v == "required"]
    assert len(required) == 8  # pole_pairs, sample_time, controller/plant num+den, bla x2
    for key in required:
        data = {k: dict(v) if isinstance(v, dict) else v for k, v in full.items()}
        if "." in key:
            table, name = key.split(".")
            del data[table][name]
        else:
            del data[key]
        with pytest.raises(HallcalInputError, match=re.escape(key)):
            setup_from_dict(data)
