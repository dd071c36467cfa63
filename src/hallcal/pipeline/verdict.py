"""The one status policy of a calibration: ok, warning or refused, from what the steps found.

Every route (closed loop, constant speed) ends here (:func:`decide`), so that a status means the
same thing whatever produced it. Without an encoder the status and the predicted error are the
user's only reference, so the policy is stated on them:

1. **Refused, no table can be right**: the map y0 -> f_init(g(y0)) is not bijective (the paper's
   bijectivity condition, eq. recon_biject) -> ``NOT_BIJECTIVE``.
2. **Refused, the model does not explain the data**: the adequacy check's verdict is inadequate
   (:func:`hallcal.fit.adequacy.assess`) -> ``INADEQUATE``.
3. **Refused, the table may not help**: the table's own predicted error ``sqrt(predicted^2 -
   floor^2)`` is at least the correction it applies (RMS eta about zero, the model's view of
   f_init's error), or at least :data:`WORSE_FRACTION` of it and more than half the noise
   floor: f_star may be worse than f_init ->
   ``INADEQUATE``, never a table written with exit status 0. Half, not all: the prediction is
   an expectation, and when a few weakly determined directions carry it (slow warps, the
   table's offset, which only the start of the run informs) one run's table error scatters
   about it by up to 2x (``benchmarks/bench_zoo.txt``: 1.4x and 1.7x on two slow ramps whose
   tables came out worse than f_init with a prediction just below it).
4. **Warning**: any warning another step raised (``checks_passed`` False), an adequacy
   warning, no finite predicted error, or a predicted error above :data:`OK_RATIO` times the
   noise floor.
5. **Ok**: none of the above; then ``predicted <= OK_RATIO * floor`` and every check passed.

What a refusal means for the user is stated once too (:func:`refusal`, "refuse unless
forced"): a table that is not bijective is never written, an inadequate one only when forced
(``--force``, ``force=True``, ``[model] force = true``); the command line exits with status 3.

The predicted error is the expected RMS error of f_star about zero on a fresh run,
``sqrt(floor^2 + mean_y0 var eta(y0) + bias^2)`` (cov(theta) propagated to the table with its
constant offset, :func:`hallcal.fit.sem.predicted_angle_error`); a validation against an encoder
(:func:`hallcal.pipeline.calibration.validate`) measures the same quantity, ``rms_raw``.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from hallcal.messages import Message, MessageCode

__all__ = ["OK_RATIO", "WORSE_FRACTION", "CalibrationStatus", "Verdict", "decide", "refusal"]

#: Fraction of the correction the table's own predicted error may reach before the table is
#: refused as possibly worse than f_init (see the module docstring).
WORSE_FRACTION = 0.5

#: Predicted error / noise floor up to which a calibration may be "ok" (a user reads
#: "ok" as "at the noise floor"; 1.15 leaves room for the spread of one run's error, about
#: sqrt(2 / revolutions-worth of independent samples), and for a few weak directions).
OK_RATIO = 1.15


class CalibrationStatus(enum.StrEnum):
    """Outcome of a calibration; the string values are the artifact's ``diagnostics.status``.

    ``OK`` and ``WARNING`` give a usable table (a warning says what to look at);
    ``INADEQUATE`` (the model does not explain the data) and ``NOT_BIJECTIVE`` (no table can
    invert the sensor map, the paper's bijectivity condition) are refusals.
    """

    OK = "ok"
    WARNING = "warning"
    INADEQUATE = "inadequate"
    NOT_BIJECTIVE = "not_bijective"

    @property
    def success(self) -> bool:
        """True when the table may be used."""
        return self in (CalibrationStatus.OK, CalibrationStatus.WARNING)

    @property
    def refused(self) -> bool:
        """True when the table must not be used."""
        return not self.success


@dataclass(frozen=True)
class Verdict:
    """Outcome of :func:`decide`.

    Attributes
    ----------
    status : CalibrationStatus
    refusal : str or None
        Why the table must not be used (one line), None unless refused.
    leading : tuple of Message
        Warnings to put first in the calibration's messages (the reason for a "warning").
    """

    status: CalibrationStatus
    refusal: str | None
    leading: tuple[Message, ...]


def decide(
    *,
    bijective: bool,
    predicted: float,
    floor: float,
    correction_rms: float,
    adequacy: str = "adequate",
    adequacy_message: str = "",
    checks_passed: bool = True,
    min_slope: float = math.nan,
) -> Verdict:
    """The status of a calibration (see the module docstring for the policy).

    Parameters
    ----------
    bijective : bool, keyword-only
        Whether the table is invertible.
    predicted : float, keyword-only
        Predicted RMS error of f_star about zero [rad] (NaN when unknown).
    floor : float, keyword-only
        Noise floor of the angle [rad RMS].
    correction_rms : float, keyword-only
        RMS of the table's correction eta about zero [rad]: the model's view of f_init's error.
    adequacy : str, keyword-only
        Verdict of the adequacy check: "adequate", "warning" or "inadequate".
    adequacy_message : str, keyword-only
        Its one-line message.
    checks_passed : bool, keyword-only
        False when another step raised a warning (a preflight check, the plant, the fit's
        status): the calibration is then a warning at best.
    min_slope : float, keyword-only
        Smallest slope of the table's map (for the not_bijective message).

    Returns
    -------
    Verdict
    """
    mrad = 1e3
    if not bijective:
        return Verdict(
            CalibrationStatus.NOT_BIJECTIVE,
            "the identified model's map y0 -> f_init(g(y0)) is not bijective (the paper's "
            "bijectivity condition"
            + (f", min slope {min_slope:.3g}" if math.isfinite(min_slope) else "")
            + "): a lookup table would give wrong angles",
            (),
        )
    if adequacy == "inadequate":
        return Verdict(CalibrationStatus.INADEQUATE, adequacy_message, ())
    own = math.sqrt(max(predicted**2 - floor**2, 0.0)) if math.isfinite(predicted) else math.nan
    # worse than f_init outright, or (beyond half the floor) within the scatter of one run
    if (
        math.isfinite(own)
        and math.isfinite(correction_rms)
        and (
            own >= correction_rms or (own >= WORSE_FRACTION * correction_rms and own > 0.5 * floor)
        )
    ):
        init = math.hypot(floor, correction_rms)
        return Verdict(
            CalibrationStatus.INADEQUATE,
            f"f_star may be worse than f_init: predicted {mrad * predicted:.3g} mrad RMS against "
            f"{mrad * init:.3g} mrad for f_init (noise floor {mrad * floor:.3g} mrad); the "
            f"table's own error {mrad * own:.3g} mrad is at least {WORSE_FRACTION:g} of the "
            f"correction it applies ({mrad * correction_rms:.3g} mrad): the run determines the "
            "table too poorly (a longer or faster ramp helps, see the ramp advice)",
            (),
        )
    leading: list[Message] = []
    if adequacy == "warning":  # the adequacy message starts with its verdict, "warning: "
        text = adequacy_message.removeprefix(f"{adequacy}: ")
        leading.append(Message.warning(MessageCode.ADEQUACY, text))
    ratio = predicted / floor if floor > 0 else math.nan
    if not math.isfinite(ratio):
        leading.append(
            Message.warning(
                MessageCode.NO_PREDICTION,
                "no predicted error (the covariance of theta is not available)",
            )
        )
    elif ratio > OK_RATIO and not leading:
        leading.append(
            Message.warning(
                MessageCode.ABOVE_NOISE_FLOOR,
                f"predicted error {mrad * predicted:.3g} mrad RMS is {ratio:.2f}x the noise "
                f"floor ({mrad * floor:.3g} mrad), above the {OK_RATIO}x of an ok calibration",
            )
        )
    if leading or not checks_passed:
        return Verdict(CalibrationStatus.WARNING, None, tuple(leading))
    return Verdict(CalibrationStatus.OK, None, ())


def refusal(status: CalibrationStatus, reason: str | None, *, force: bool) -> Message | None:
    """The one refusal rule, "refuse unless forced": why a result must not be written, or None.

    Used by :meth:`hallcal.pipeline.Calibration.save` (which raises
    :class:`~hallcal.errors.CalibrationRefused`, exit status 3), the command line and the fleet
    worker (a "refused" row).

    Parameters
    ----------
    status : CalibrationStatus
        The calibration's status (:func:`decide`).
    reason : str or None
        Its refusal reason (:attr:`Verdict.refusal`).
    force : bool, keyword-only
        Write an inadequate model anyway (``--force``, ``force=True``, ``[model] force``); a
        table that is not bijective is refused all the same.

    Returns
    -------
    Message or None
        A refusal (code ``NOT_BIJECTIVE`` or ``INADEQUATE``) naming the reason; None when the
        result may be written.
    """
    if status is CalibrationStatus.NOT_BIJECTIVE:
        return Message.refusal(MessageCode.NOT_BIJECTIVE, reason or "the table is not bijective")
    if status.refused and not force:
        return Message.refusal(MessageCode.INADEQUATE, reason or str(status))
    return None
