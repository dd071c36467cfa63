"""One message type and one refusal rule.

- :class:`hallcal.messages.Message`: the severity is a field; the printed line and the stored
  record are renderings of it, and a stored record reads back to the same severity and text.
- :func:`hallcal.pipeline.verdict.refusal`: "refuse unless forced" (exit status 3), the one
  rule behind ``Calibration.save``, ``hallcal calibrate`` and the fleet worker.
- Status values: every status enum a StrEnum with snake_case values; files written before the
  renaming are read with the new values (``RENAMED_VALUES``).
- The command line prints a warning and a refusal as before (subprocess).
"""

from __future__ import annotations

import enum
import importlib
import json
import pkgutil
import re
from pathlib import Path

import numpy as np
import pytest
from cli_support import PAPER_LOOP_TOML
from cli_support import run_cli as run
from hypothesis import given
from hypothesis import strategies as st

import hallcal
from hallcal.formatting import AngleUnit
from hallcal.io import read_artifact, read_dataset, write_dataset
from hallcal.io.artifact import RENAMED_VALUES, migrate_values
from hallcal.messages import Message, MessageCode, Severity, has_warning
from hallcal.pipeline.calibration import CalibrationStatus
from hallcal.pipeline.verdict import refusal
from hallcal.sensor.absolute import Identifiability

OLD_ARTIFACT = Path(__file__).parent / "data" / "artifacts" / "inadequate-main.json"

#: one-line texts, as messages hold (any printable characters, no line break)
TEXTS = st.text(st.characters(blacklist_categories=("Cc", "Cs", "Zl", "Zp")), max_size=80)


@given(st.sampled_from(Severity), st.sampled_from(MessageCode), TEXTS)
def test_record_reads_back_to_the_same_severity_and_text(severity, code, text):
    m = Message(severity, code, text)
    back = Message.from_record(m.record())
    if severity is Severity.INFO:  # stored bare like a note: an info line reads back as a note
        assert (back.severity, back.text) == (Severity.NOTE, text)
    elif severity is Severity.NOTE and text.startswith(("warning: ", "refused: ", "note: ")):
        assert back.record() == m.record()  # a bare note that looks labelled stays the same string
    else:
        assert (back.severity, back.text) == (severity, text)
    assert Message.from_record(back.record()).record() == back.record()  # stable


@given(st.sampled_from(Severity), st.sampled_from(MessageCode), TEXTS)
def test_the_line_is_the_label_then_the_text(severity, code, text):
    line = Message(severity, code, text).line()
    label = {"info": "", "note": "note: ", "warning": "warning: ", "refusal": "refused: "}
    assert line == label[severity] + text
    assert str(Message(severity, code, text)) == line


def test_severity_and_code_are_typed_and_validated():
    m = Message("warning", "plant_fit", "the parametric fit of G(s) did not converge")
    assert m.severity is Severity.WARNING and m.code is MessageCode.PLANT_FIT
    assert has_warning([Message.note(MessageCode.RAMP_ADVICE, "x"), m])
    assert not has_warning([Message.note(MessageCode.RAMP_ADVICE, "warning: in the text")])
    with pytest.raises(ValueError):
        Message("severe", MessageCode.PLANT, "x")
    with pytest.raises(ValueError):
        Message(Severity.NOTE, "no-such-code", "x")


def test_old_records_read_back():
    # strings as artifacts of hallcal 0.1.0 store them
    assert Message.from_record("warning: gain correction c = 0.5 hit its search bound") == (
        Message.warning(MessageCode.STORED, "gain correction c = 0.5 hit its search bound")
    )
    note = Message.from_record("ramp speed: at 0.7 rad/s the loop hides part of the error")
    assert note.severity is Severity.NOTE and note.text.startswith("ramp speed")
    labelled = Message.from_record("note: the kernel's learned spectrum was still moving")
    assert labelled.line() == "note: the kernel's learned spectrum was still moving"


@given(st.sampled_from(CalibrationStatus), st.booleans())
def test_refuse_unless_forced(status, force):
    why = refusal(status, "the reason", force=force)
    if status is CalibrationStatus.NOT_BIJECTIVE:  # never written, forced or not
        assert why == Message.refusal(MessageCode.NOT_BIJECTIVE, "the reason")
    elif status is CalibrationStatus.INADEQUATE:
        assert (
            why is None if force else why == Message.refusal(MessageCode.INADEQUATE, "the reason")
        )
    else:  # a usable table is written whatever force says
        assert why is None
    assert (why is None) == (
        status.success or (force and status is not CalibrationStatus.NOT_BIJECTIVE)
    )


# ---- status values: one spelling, and old files read with the new values


def _status_enums() -> list[type[enum.StrEnum]]:
    """Every StrEnum of hallcal whose values are statuses, codes or verdicts (not units)."""
    found = []
    for info in pkgutil.walk_packages(hallcal.__path__, "hallcal."):
        if info.name in ("hallcal.cli", "hallcal.__main__"):
            continue
        module = importlib.import_module(info.name)
        for obj in vars(module).values():
            if (
                isinstance(obj, type)
                and issubclass(obj, enum.Enum)
                and obj.__module__ == info.name
                and obj is not AngleUnit  # "electrical-deg" is a --units option value
            ):
                found.append(obj)
    return found


def test_every_status_enum_is_a_strenum_with_snake_case_values():
    enums = _status_enums()
    assert len(enums) >= 30  # the statuses of every layer were found
    for cls in enums:
        assert issubclass(cls, enum.StrEnum), cls
        for member in cls:
            assert re.fullmatch(r"[a-z0-9]+(_[a-z0-9]+)*", member.value), (cls, member.value)


def test_every_renamed_value_is_read_as_a_current_status():
    current = {m.value for cls in _status_enums() for m in cls}
    assert set(RENAMED_VALUES.values()) <= current
    assert not set(RENAMED_VALUES) & current
    old = {
        "diagnostics": {"status": "not-bijective", "constant_speed": {"status": "not-converged"}},
        "identifiability": {"status": "needs-motion", "reason": "too-uniform", "message": "x"},
        "nonparametric": {"status": "single-realization+single-period"},
        "list": [{"status": "not-found"}],
        "other": "not-found",  # only "status" and "reason" keys are statuses
    }
    assert migrate_values(old) == {
        "diagnostics": {"status": "not_bijective", "constant_speed": {"status": "not_converged"}},
        "identifiability": {"status": "needs_motion", "reason": "too_uniform", "message": "x"},
        "nonparametric": {"status": "single_realization_and_period"},
        "list": [{"status": "not_found"}],
        "other": "not-found",
    }


def test_an_artifact_written_by_the_previous_version_is_read():
    # written by `hallcal calibrate --force` of main 52b72d7 (harmonics = [11], lut_points 256)
    path = OLD_ARTIFACT
    assert '"status": "not-identifiable"' in path.read_text()  # the old spelling is in the file
    art = read_artifact(path)
    assert art.data["identifiability"]["status"] == "not_identifiable"
    assert art.data["identifiability"]["reason"] == "below_model_uncertainty"
    assert read_artifact(path)["identifiability"]["status"] == "not_identifiable"
    cal = hallcal.load(path)
    assert cal.status is CalibrationStatus.INADEQUATE
    assert cal.identifiability.status is Identifiability.NOT_IDENTIFIABLE
    stored = json.loads(path.read_text())["diagnostics"]["messages"]
    assert [m.record() for m in cal.messages] == stored  # records read back unchanged
    assert all(m.severity is Severity.NOTE for m in cal.messages)


# ---- the command line: a warning and a refusal as a user sees them

SETUP = """\
pole_pairs = 11
sample_time = 2.5e-4
[model]
basis = "fourier"
harmonics = [11]
[bench]
ramp_end = 7.0
duration = 10.0
seed = 5
"""


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    d = tmp_path_factory.mktemp("messages")
    (d / "s.toml").write_text(SETUP + PAPER_LOOP_TOML)
    res = run("simulate", "--setup", "s.toml", "--out", "cal.csv", cwd=d)
    assert res.returncode == 0, res.stderr
    return d


def test_cli_prints_a_warning_line_on_stderr(bench):
    ds = read_dataset(bench / "cal.csv")
    cols = {k: np.array(ds[k]) for k in ds.names}
    cols["d1"] = np.minimum(cols["d1"], 0.9)  # an ADC that clips d1 at 0.9
    write_dataset(bench / "clipped.csv", cols)
    res = run("inspect", "clipped.csv", "--setup", "s.toml", cwd=bench)
    assert res.returncode == 0, res.stderr
    warnings = [ln for ln in res.stderr.splitlines() if ln.startswith("warning: ")]
    assert warnings == [
        next(ln for ln in warnings if ln.startswith("warning: d1 sits at its maximum 0.9 in "))
    ]
    assert warnings[0].endswith("the ADC or the sensor clips; lower the gain or move the sensor")
    assert "warning" not in res.stdout  # findings on stdout, warnings on stderr


def test_cli_refuses_an_inadequate_model_with_exit_3_unless_forced(bench):
    res = run("calibrate", "cal.csv", "--setup", "s.toml", "--out", "x.json", cwd=bench)
    assert res.returncode == 3
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("hallcal: refused: ") and "inadequate: model cost" in last
    assert last.endswith("no artifact written (use --force, or force=True, to write it anyway)")
    assert not (bench / "x.json").exists()
    assert "note: ramp speed: " in res.stderr  # a note keeps its label
    assert "plant: G(s) from the setup's [plant] table" in res.stderr.splitlines()  # info as is
    forced = run("calibrate", "cal.csv", "--setup", "s.toml", "--out", "x.json", "--force",
                 cwd=bench)  # fmt: skip
    assert forced.returncode == 0, forced.stderr
    assert json.loads((bench / "x.json").read_text())["diagnostics"]["status"] == "inadequate"
