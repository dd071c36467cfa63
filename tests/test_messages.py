"""One message type and one refusal rule.

- :class:`hallcal.messages.Message`: the severity is a field; the printed line and the stored
  record are renderings of it, and a stored record reads back to the same severity and text.
- :func:`hallcal.pipeline.verdict.refusal`: "refuse unless forced" (exit status 3), the one
  rule behind ``Calibration.save``, ``hallcal calibrate`` and the fleet worker.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hallcal.messages import Message, MessageCode, Severity, has_warning
from hallcal.pipeline.calibration import CalibrationStatus
from hallcal.pipeline.verdict import refusal

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
