"""Messages for the user: one type, :class:`Message`, for every note, warning and refusal.

A step that has something to tell the user (a warning that makes a calibration "warning" at
best, a note of advice, a line saying which plant model was used) returns a :class:`Message`
with its :class:`Severity` and a typed :class:`MessageCode`; the severity is a field, never read
back from the text. Two renderings, both stable contracts:

* :meth:`Message.line`: the line as the command line prints it (``warning: ...``,
  ``note: ...``, an info line as is);
* :meth:`Message.record`: the string stored in the artifact's ``diagnostics.messages`` and in a
  fleet summary's ``message`` (a warning keeps its ``warning:`` label, a note or info line is
  stored bare, as every artifact since 0.1.0 has stored them).

:meth:`Message.from_record` reads a stored string back (artifacts written by any version, see
CHANGELOG.md): the one place a label in a text is interpreted.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = ["Graded", "Message", "MessageCode", "Outcome", "Severity", "has_warning"]


class Outcome(enum.StrEnum):
    """A result's typed status (how a solve, search or step ended).

    The first member is the success: :attr:`success` is True for it alone. A status with more
    than one acceptable outcome overrides :attr:`success`.
    """

    @property
    def success(self) -> bool:
        """True for the first member (the success)."""
        return self is next(iter(type(self)))


class Graded(Outcome):
    """An outcome graded ``ok``, ``warning`` (usable, look at the messages) or worse.

    :attr:`success` is True for the members ``ok`` and ``warning``; every other member is a
    refusal or a failure (a calibration's, a plant model's, a fleet motor's status).
    """

    @property
    def success(self) -> bool:
        """True for ``ok`` and ``warning``: the result may be used."""
        return self in ("ok", "warning")


class Severity(enum.StrEnum):
    """How much a :class:`Message` matters.

    ``INFO`` states what was used (printed as is); ``NOTE`` is advice that changes no status
    (printed ``note: ...``); ``WARNING`` makes a calibration "warning" at best (printed
    ``warning: ...``); ``REFUSAL`` says why a result must not be used (exit status 3, printed
    ``refused: ...``).
    """

    INFO = "info"
    NOTE = "note"
    WARNING = "warning"
    REFUSAL = "refusal"


#: The label a line carries for each severity (``INFO`` has none).
_LABELS = {
    Severity.INFO: "",
    Severity.NOTE: "note: ",
    Severity.WARNING: "warning: ",
    Severity.REFUSAL: "refused: ",
}


class MessageCode(enum.StrEnum):
    """What a :class:`Message` is about (stable identifiers, snake_case)."""

    # the data and the setup
    Y_COLUMN_MISMATCH = "y_column_mismatch"
    CLIPPING = "clipping"
    SENSOR_GEOMETRY = "sensor_geometry"
    SKEWED_SENSORS = "skewed_sensors"
    CENSORED_SAMPLES = "censored_samples"
    SENSOR_DRIFT = "sensor_drift"
    PREFLIGHT_CHECK = "preflight_check"
    TRAJECTORY_WINDOW = "trajectory_window"
    SPEED_VARIES = "speed_varies"
    UNUSED_INPUT = "unused_input"
    DEFAULT_USED = "default_used"
    # the plant
    PLANT = "plant"
    BLA_EXPERIMENT = "bla_experiment"
    PLANT_FIT = "plant_fit"
    PLANT_MISFIT = "plant_misfit"
    GAIN_AT_BOUND = "gain_at_bound"
    # the fit
    SEARCH_BUDGET = "search_budget"
    KERNEL_UNSETTLED = "kernel_unsettled"
    COGGING = "cogging"
    UNMODELLED_COGGING = "unmodelled_cogging"
    SPEED_FIT = "speed_fit"
    # the verdict
    ADEQUACY = "adequacy"
    NO_PREDICTION = "no_prediction"
    ABOVE_NOISE_FLOOR = "above_noise_floor"
    ONE_RUN_SPREAD = "one_run_spread"
    PLANT_REFINED = "plant_refined"
    PLANT_DISAGREES = "plant_disagrees"
    FOLDING = "folding"
    RAMP_ADVICE = "ramp_advice"
    NOT_BIJECTIVE = "not_bijective"
    INADEQUATE = "inadequate"
    FORCED = "forced"
    # validation, power-up and export
    VALIDATION_SKIPPED = "validation_skipped"
    VALIDATION_WORSE = "validation_worse"
    POWERUP = "powerup"
    POWERUP_DRIFT = "powerup_drift"
    C_EXPORT = "c_export"
    SEE_DIAGNOSTICS = "see_diagnostics"
    #: a stored string read back (:meth:`Message.from_record`): its producer is not recorded
    STORED = "stored"


def _constructor(severity: Severity) -> classmethod[Message, [MessageCode, str], Message]:
    """``Message.<severity>(code, text)``: the constructor of one severity (the four share it)."""

    def make(cls: type[Message], code: MessageCode, text: str) -> Message:
        return cls(severity, code, text)

    make.__name__ = severity.value
    make.__qualname__ = f"Message.{severity.value}"
    make.__doc__ = f"""A :attr:`Severity.{severity.name}` message.

    Parameters
    ----------
    code : MessageCode
        What it is about.
    text : str
        One line without a severity label.

    Returns
    -------
    Message
    """
    return classmethod(make)


@dataclass(frozen=True)
class Message:
    """One note, warning or refusal for the user.

    Attributes
    ----------
    severity : Severity
        How much it matters; decides the status, never the text.
    code : MessageCode
        What it is about.
    text : str
        One line without a severity label (``"the parametric fit of G(s) did not converge"``).
    """

    severity: Severity
    code: MessageCode
    text: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "severity", Severity(self.severity))
        object.__setattr__(self, "code", MessageCode(self.code))

    info = _constructor(Severity.INFO)
    note = _constructor(Severity.NOTE)
    warning = _constructor(Severity.WARNING)
    refusal = _constructor(Severity.REFUSAL)

    @property
    def is_warning(self) -> bool:
        """True for a warning or a refusal (the status cannot be "ok")."""
        return self.severity in (Severity.WARNING, Severity.REFUSAL)

    def line(self) -> str:
        """The line as the command line prints it: the severity's label, then the text."""
        return _LABELS[self.severity] + self.text

    def record(self) -> str:
        """The string stored in an artifact or a fleet summary (notes and info lines bare)."""
        if self.severity in (Severity.WARNING, Severity.REFUSAL):
            return self.line()
        return self.text

    def __str__(self) -> str:
        return self.line()

    @classmethod
    def from_record(cls, record: str) -> Message:
        """Read back a string :meth:`record` (or any hallcal version) stored.

        A ``warning:``, ``refused:`` or ``note:`` label gives the severity (artifacts up to
        0.1.0 stored two notes with their label); anything else is a note.

        Parameters
        ----------
        record : str
            The stored string.

        Returns
        -------
        Message
            With code :attr:`MessageCode.STORED` (the producer is not stored).
        """
        for severity in (Severity.WARNING, Severity.REFUSAL, Severity.NOTE):
            label = _LABELS[severity]
            if record.startswith(label):
                return cls(severity, MessageCode.STORED, record[len(label) :])
        return cls(Severity.NOTE, MessageCode.STORED, record)


def has_warning(messages: tuple[Message, ...] | list[Message]) -> bool:
    """Whether any of `messages` is a warning or a refusal (a status "warning" at best).

    Parameters
    ----------
    messages : sequence of Message
        What the steps reported.

    Returns
    -------
    bool
    """
    return any(m.is_warning for m in messages)
