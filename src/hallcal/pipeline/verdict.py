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
   ``INADEQUATE``, never a table written with exit status 0. Half, not all, and of the
   table's upper quantile (item 5) rather than its expectation: when a few weakly determined
   directions carry the error (slow warps, the table's offset, which only the start of the run
   informs) one run's table error scatters about it by up to 2x (``benchmarks/bench_zoo.txt``:
   1.4x and 1.7x on two slow ramps whose tables came out worse than f_init with a prediction
   just below it). With unmodelled motion (the fit's cost above its noise level: a varying
   load torque, cogging or a plant error the model lacks) the model's correction in the
   directions the run determines poorly is no evidence of f_init's error: the adequacy check
   counts it in the predicted error (:func:`hallcal.fit.adequacy.motion_bias`), so a table the
   motion has bent is refused here (``benchmarks/bench_unseen.py`` case 222, a random load
   torque with the plant from a BLA: the table 670x the noise floor, f_init 17x, was a
   "warning" predicted 124x from the covariance alone; 618x of the model's 624x correction lay
   in such directions: predicted 631x, refused; on small benches of that kind, 2-6 pole pairs
   as in ``tests/test_verdict_motion.py``, two tables 1.07x f_init's error that were warnings
   predicted 1.1-1.2x are refused at 2.9x and 3.9x, and by the half-the-correction rule so are
   two 1.4-1.5x better than f_init, 3.1x and 2.1x the floor, predicted 3.4x and 2.2x; five
   good ones stay warnings, actual/predicted 0.83-0.97). Not caught, by construction: a table
   wrong beyond its covariance while the fit explains the data (no motion bias to count). No
   such table is known on the zoo now (``benchmarks/bench_zoo.txt``, ``bench_zoo_choice2.txt``,
   ``bench_unseen.txt``: no table worse than f_init with exit status 0). Zoo motor 113 was one
   (harmonics chosen with holes in a dense band: the table 64x the floor, f_init 27x, predicted
   13x, a "warning"); since the harmonic choice changed (the short holes of a dense band
   filled, :func:`hallcal.fit.order.fill_gaps`, and the evidence without its cancellation:
   ``bench_zoo_choice2.txt``) it is a warning at 1.08x the floor, predicted 1.59x
   (reproduced by ``bench_zoo.py --seeds 113 --table-only``). The largest under-predictions
   left are warnings whose error lies along the table's constant offset, at about the upper
   quantile of item 5: ``benchmarks/bench_unseen.py`` case 226 at 3.55x the floor predicted
   2.19x (actual/predicted 1.62; upper quantile 3.56x) and the unseen zoo motor 179 at 3.05x
   predicted 1.86x (1.64; upper 3.13x; ``benchmarks/bench_zoo_bias.txt``; its offset +2.49x the
   floor is 1.8 of its standard deviation with the loop's noise; ``bench_zoo_noise.txt``:
   0.92-1.27 on eight of ten noise draws, and the cogging search's false orders can bend the
   table beyond its covariance).
4. **Warning**: any warning another step raised (``checks_passed`` False), an adequacy
   warning, no finite predicted error, or a predicted error above :data:`OK_RATIO` times the
   noise floor.
5. **Warning, one run may be far off**: the upper quantile of one run's error
   (:func:`hallcal.fit.adequacy.error_spread`, 95 %) above :data:`OK_UPPER_RATIO` times the
   floor. The predicted error is an expectation; when a few directions carry it (the table's
   constant offset, which only the start of the run informs, a single chi-square(1) term) one
   run's table scatters far about it: zoo motor 30 was "ok" at 1.34x the floor with 1.12x
   predicted (its offset 0.86x the floor; 1.11-1.34x over four noise seeds).
6. **Ok**: none of the above; then ``predicted <= OK_RATIO * floor``, the upper quantile within
   ``OK_UPPER_RATIO * floor`` and every check passed.

What a refusal means for the user is stated once too (:func:`refusal`, "refuse unless
forced"): a table that is not bijective is never written, an inadequate one only when forced
(``--force``, ``force=True``, ``[model] force = true``); the command line exits with status 3.

The predicted error is the expected RMS error of f_star about zero on a fresh run,
``sqrt(floor^2 + mean_y0 var eta(y0) + bias^2)`` (cov(theta) propagated to the table with its
constant offset, :func:`hallcal.fit.sem.predicted_angle_error`; the offset's variance at least
the one with the Hall noise the drive's loop fed back,
:func:`hallcal.fit.offset_variance.offset_loop_noise`: zoo motor 193 "ok" at 1.239x the floor,
predicted 1.018x before, 1.082x with it, its upper quantile 1.28x); a validation against an encoder
(:func:`hallcal.pipeline.calibration.validate`) measures the same quantity, ``rms_raw``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hallcal.messages import Graded, Message, MessageCode

if TYPE_CHECKING:  # not at run time: applying a table (reconstruct) loads no hallcal.fit
    from hallcal.fit.error_source import ErrorSources

__all__ = [
    "OK_RATIO",
    "OK_UPPER_RATIO",
    "WORSE_FRACTION",
    "CalibrationStatus",
    "Verdict",
    "decide",
    "refusal",
]

#: Fraction of the correction the table's own predicted error may reach before the table is
#: refused as possibly worse than f_init (see the module docstring).
WORSE_FRACTION = 0.5

#: Predicted error / noise floor up to which a calibration may be "ok" (a user reads
#: "ok" as "at the noise floor"; 1.15 leaves room for the spread of one run's error, about
#: sqrt(2 / revolutions-worth of independent samples), and for a few weak directions).
OK_RATIO = 1.15

#: Upper quantile of one run's error / noise floor up to which a calibration may be "ok": "ok"
#: above 1.3x the floor is what the zoo counts as dishonest (``benchmarks/bench_zoo.py``).
OK_UPPER_RATIO = 1.3


class CalibrationStatus(Graded):
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
    predicted_upper: float = math.nan,
    limit: str = "",
    limited_by: ErrorSources | None = None,
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
    predicted_upper : float, keyword-only
        Upper quantile of one run's RMS error of f_star about zero [rad] (NaN: not checked).
    limit : str, keyword-only
        What carries the table's predicted variance (one phrase,
        :func:`hallcal.fit.adequacy.error_sources`), named in a refusal for a poorly determined
        table.
    limited_by : ErrorSources or None, keyword-only
        What ``limit`` names, typed (:attr:`hallcal.fit.adequacy.AdequacyReport.limited_by`):
        when harmonics carry the table's variance (its ``harmonics``), the refusal adds fewer
        harmonics to the remedies; when unmodelled motion may have put part of the correction
        in poorly determined directions (its ``motion_bias`` > 0, counted in ``predicted``:
        :func:`hallcal.fit.adequacy.motion_bias`), the refusal says f_init's error is the
        model's view and names a steady load as a remedy. None: nothing named.

    Returns
    -------
    Verdict
    """
    mrad = 1e3
    motion = limited_by is not None and limited_by.motion_bias > 0.0
    fewer_harmonics = limited_by is not None and bool(limited_by.harmonics)
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
    # one run's table may reach its upper quantile (NaN, not known: the expectation only)
    own_up = math.sqrt(max(predicted_upper**2 - floor**2, 0.0)) if predicted_upper > 0 else own
    own_up = max(own_up, own) if math.isfinite(own_up) else own
    # worse than f_init outright, or (beyond half the floor) within the scatter of one run
    if (
        math.isfinite(own)
        and math.isfinite(correction_rms)
        and (
            own >= correction_rms
            or (own_up >= WORSE_FRACTION * correction_rms and own_up > 0.5 * floor)
        )
    ):
        init = math.hypot(floor, correction_rms)
        return Verdict(
            CalibrationStatus.INADEQUATE,
            f"f_star may be worse than f_init: predicted {mrad * predicted:.3g} mrad RMS against "
            f"{mrad * init:.3g} mrad for f_init"
            # with unmodelled motion the correction, so f_init's error, is the model's view
            + (" as the model sees it" if motion else "")
            + f" (noise floor {mrad * floor:.3g} mrad); the "
            f"table's own error {mrad * own:.3g} mrad"
            + (f" (one run's up to {mrad * own_up:.3g} mrad, 95 %)" if own_up > own else "")
            + f" is at least {WORSE_FRACTION:g} of the "
            f"correction it applies ({mrad * correction_rms:.3g} mrad): the run determines the "
            "table too poorly ("
            + (f"{limit}; " if limit else "")
            + (
                "a run under a steady load, a longer or a faster ramp helps"
                if motion
                else "a longer or faster ramp helps"
            )
            + (", or fewer harmonics" if fewer_harmonics else "")
            + ")",
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
    upper = predicted_upper / floor if floor > 0 else math.nan
    if not leading and math.isfinite(upper) and upper > OK_UPPER_RATIO:
        leading.append(
            Message.warning(
                MessageCode.ONE_RUN_SPREAD,
                f"predicted error {mrad * predicted:.3g} mrad RMS ({ratio:.2f}x the noise "
                f"floor), but one run's table may reach {upper:.2f}x (95 %): a few directions "
                "carry its error (e.g. the table's offset, which only the start of the run "
                "informs)",
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
