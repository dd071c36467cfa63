"""Absolute angle at power-up in the pipeline: the identifiability analysis that ``calibrate``
stores in the artifact, the absolute reconstruction behind ``reconstruct --absolute``, and the
check that a recording's signals still fit the calibration's model (:func:`check_signals`, run
by every ``reconstruct``: a ring remounted, sensors swapped or rewired, gains drifted).

The numeric work is :mod:`hallcal.sensor.absolute` (maximum-likelihood choice of the pole pair
from the magnets' signatures, sequential test, identifiability); this module ties it to a
:class:`~hallcal.pipeline.calibration.Calibration` and to datasets, and turns its verdicts into
the package's errors.
"""

from __future__ import annotations

import enum
import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from hallcal._constants import TWO_PI
from hallcal.errors import CalibrationRefused, HallcalInputError
from hallcal.io.dataset import Dataset
from hallcal.messages import Message, MessageCode
from hallcal.pipeline.checks import CheckStatus, check_direction
from hallcal.sensor.absolute import (
    AbsoluteAngles,
    IdentifiabilityReport,
    PowerUpDecoder,
    PowerUpStatus,
    analyze_calibration,
)
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT
from hallcal.sensor.misfit import MisfitResult, MisfitStatus, common_scale, model_misfit

__all__ = [
    "MISMATCH_TEXT",
    "SignalCheck",
    "SignalStatus",
    "check_signals",
    "decoder_for",
    "drift_message",
    "identifiability_from_artifact",
    "identification_check",
    "power_up_analysis",
    "same_revolution",
]

#: The one line of a recording whose signals no pole pair of the calibration's model fits.
MISMATCH_TEXT = (
    "these signals do not match this calibration (ring remounted, wiring changed or sensors "
    "drifted): recalibrate"
)
#: Samples the signal check of plain ``reconstruct`` looks at (from the first): the sequential
#: test decides within a few dozen (a mismatch after about 11 samples far off the model, a fit
#: after about 6), so this bounds the work (n_m costs per sample) on long recordings.
CHECK_SAMPLES = 20_000


def power_up_analysis(
    flux: FluxModel, lut: LUT, d: ArrayLike, *, start: int = 0, stop: int | None = None
) -> IdentifiabilityReport | None:
    """How well the pole pair can be identified at power-up with this calibration.

    Parameters
    ----------
    flux : FluxModel
        The calibration's g_theta.
    lut : LUT
        The calibration's table.
    d : array_like (N, 3)
        The calibration recording.
    start, stop : int, keyword-only
        The samples the model was fitted on.

    Returns
    -------
    IdentifiabilityReport or None
        None when the table is not bijective (no table, nothing to place).
    """
    if not lut.bijective:
        return None
    _, report = analyze_calibration(
        flux, lut, d, start=start, stop=stop, basis_size=flux.basis.size
    )
    return report


def identifiability_from_artifact(
    artifact: Mapping[str, Any], source: str = "artifact"
) -> IdentifiabilityReport | None:
    """The artifact's ``"identifiability"`` entry, or None for an artifact made without it.

    Parameters
    ----------
    artifact : mapping
        The parsed artifact.
    source : str
        Its name in messages (the file).

    Returns
    -------
    IdentifiabilityReport or None

    Raises
    ------
    HallcalInputError
        When the entry is malformed (the message names the key).
    """
    entry = artifact.get("identifiability")
    if entry is None:
        return None
    if not isinstance(entry, Mapping):
        raise HallcalInputError(
            f"{source}: key 'identifiability' must be an object",
            source=source,
            key="identifiability",
        )
    try:
        return IdentifiabilityReport.from_dict(entry)
    except ValueError as exc:
        raise HallcalInputError(f"{source}: {exc}", source=source, key="identifiability") from None


def drift_message(report: IdentifiabilityReport | None, *, warning: bool = False) -> Message | None:
    """The line saying the power-up lock does not survive a plausible sensor change, or None.

    Said when the drift margin (:mod:`hallcal.sensor.drift_margin`) of a common gain change is
    below the one a plausible temperature swing produces (``DriftMargin.fragile``: 5 %, 40 K of
    NdFeB remanence at -0.12 %/K): the decoder of an artifact made before the lock that waits
    for motion on such motors (:func:`hallcal.sensor.absolute.analyze_calibration`; its verdict
    says it instead). ``calibrate`` says it as a note (the table is not in question, so the
    calibration's status stays what it is; the note qualifies the power-up verdict),
    ``reconstruct --absolute`` as a warning (``warning=True``).

    Parameters
    ----------
    report : IdentifiabilityReport or None
        The calibration's identifiability analysis (None, or one without a drift margin from an
        older version: nothing to say).
    warning : bool, keyword-only
        Severity WARNING instead of NOTE.

    Returns
    -------
    Message or None
    """
    m = None if report is None else report.drift
    if m is None or not m.fragile:
        return None

    def pct(x: float) -> str:
        return "beyond 10 %" if not math.isfinite(x) else f"+-{100 * x:.2g} %"

    text = (
        f"the power-up lock holds only for sensor gains within {pct(m.common_gain)} of "
        f"calibration (about {m.kelvin:.0f} K of magnet temperature; one sensor's gain "
        f"{pct(m.sensor_gain)}, its offset {pct(m.sensor_offset)} of its amplitude): beyond, a "
        f"wrong pole pair fits the changed signals and locks with claimed certainty at up to "
        f"{100 * m.share_at_plausible:.0f} % of positions within +-{100 * m.plausible_gain:.0f} "
        "% (a 40 K swing); after a temperature change re-home the axis, or calibrate at the "
        "temperature of use"
    )
    make = Message.warning if warning else Message.note
    return make(MessageCode.POWERUP_DRIFT, text)


def decoder_for(flux: FluxModel, lut: LUT, report: IdentifiabilityReport | None) -> PowerUpDecoder:
    """The power-up decoder of a calibration, refusing when identification cannot work.

    Parameters
    ----------
    flux : FluxModel
        The calibration's g_theta.
    lut : LUT
        The calibration's table.
    report : IdentifiabilityReport or None
        The calibration's identifiability analysis (None: made by an older version).

    Returns
    -------
    PowerUpDecoder

    Raises
    ------
    HallcalInputError
        The calibration has no identifiability analysis (made by an older version).
    CalibrationRefused
        The analysis says the pole pair is not identifiable (homing stays necessary).
    """
    if report is None:
        raise HallcalInputError(
            "artifact: no 'identifiability' entry (made before power-up identification "
            "existed); calibrate again to use --absolute",
            key="identifiability",
        )
    if not report.status.success:
        raise CalibrationRefused(report.message)
    if not lut.bijective:
        raise CalibrationRefused("the lookup table is not bijective; refusing to use it")
    return report.decoder(flux, lut)


def same_revolution(y: ArrayLike, y_ref: ArrayLike) -> np.ndarray:
    """``y_ref`` shifted by the whole revolutions that bring it nearest to ``y`` (median): the
    turn count at power-up is arbitrary, so absolute angles are compared modulo revolutions.

    Parameters
    ----------
    y : array_like (N,)
        Reconstructed angle [rad].
    y_ref : array_like (N,)
        Encoder (or true) angle [rad].

    Returns
    -------
    ndarray (N,)
        ``y_ref + 2 pi k`` with the integer k nearest to median(y - y_ref) / (2 pi).
    """
    y = np.asarray(y, dtype=np.float64)
    ref = np.asarray(y_ref, dtype=np.float64)
    return ref + TWO_PI * float(np.round(np.median(y - ref) / TWO_PI))


class SignalStatus(enum.StrEnum):
    """Do a recording's signals fit the calibration's model (:func:`check_signals`)?"""

    FITS = "fits"  # the misfit test accepted the model (or never rejected it)
    MISMATCH = "mismatch"  # no pole pair fits, in no order of d1..d3: recalibrate
    WIRING = "wiring"  # they fit with d1..d3 in another order: sensors swapped or rewired
    UNCHECKED = "unchecked"  # the artifact has no identifiability analysis (older version)

    @property
    def success(self) -> bool:
        """False for a mismatch or a wiring change (``reconstruct`` exits 3)."""
        return self not in (SignalStatus.MISMATCH, SignalStatus.WIRING)


@dataclass(frozen=True)
class SignalCheck:
    """The recording's signals against the calibration's model, with a message.

    Attributes
    ----------
    status : SignalStatus
    message : str
        One line: the verdict, and the order of the Hall columns that fits when one does.
    misfit : MisfitResult or None
        The sequential misfit test (:func:`hallcal.sensor.misfit.model_misfit`) on the
        recording as given (None when unchecked).
    order : tuple of int or None
        With WIRING: the order of the columns (0-based indices of d1..d3) that fits.
    scale : float
        The signals' common amplitude relative to the calibration's when it had to be divided
        out for them to fit (:func:`hallcal.sensor.misfit.common_scale`), else 1: harmless to
        f_init and f_star, and to the power-up decoder with the gain profile (the one without
        it needs 1).
    """

    status: SignalStatus
    message: str
    misfit: MisfitResult | None = None
    order: tuple[int, int, int] | None = None
    scale: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "status": self.status.value,
            "message": self.message,
            "misfit": None if self.misfit is None else self.misfit.to_dict(),
            "order": None if self.order is None else [f"d{i + 1}" for i in self.order],
            "scale": float(self.scale),
        }

    @property
    def warning(self) -> Message | None:
        """A line worth printing although the signals fit: their amplitude far from the
        calibration's (another unit or ADC scale?), else None."""
        if self.status.success and _far(self.scale):
            return Message.warning(MessageCode.POWERUP, self.message)
        return None

    def raise_if_failed(self) -> None:
        """Raise :class:`CalibrationRefused` (exit status 3) with the message on a failure."""
        if not self.status.success:
            raise CalibrationRefused(self.message)


def _order_text(order: tuple[int, ...]) -> str:
    """``"d2, d1, d3 (d1 and d2 swapped)"`` or ``"d3, d1, d2 (d1, d2, d3 rotated)"``."""
    names = ", ".join(f"d{i + 1}" for i in order)
    moved = [f"d{i + 1}" for i in range(3) if order[i] != i]
    what = f"{moved[0]} and {moved[1]} swapped" if len(moved) == 2 else "d1, d2, d3 rotated"
    return f"{names} ({what})"


def _mismatch_text(misfit: MisfitResult) -> str:
    return (
        f"{MISMATCH_TEXT} (misfit {misfit.cost_per_dof:.1f} times the calibrated noise "
        f"variance over the first {misfit.samples} samples)"
    )


def check_signals(
    decoder: PowerUpDecoder | None,
    dataset: Dataset,
    *,
    misfit: MisfitResult | None = None,
    samples: int = CHECK_SAMPLES,
) -> SignalCheck:
    """Do the recording's Hall signals fit the calibration's flux model at all?

    The sequential misfit test of :mod:`hallcal.sensor.misfit` (the one the power-up lock
    uses: the best pole-pair hypothesis's distance to the model, against the calibrated
    noise) on the first ``samples`` samples. On a mismatch, their common gain about f_init's
    offsets is divided out (:func:`hallcal.sensor.misfit.common_scale`; harmless to f_init and
    f_star, temperature moves it): if they fit then over at least one electrical turn, plain
    ``reconstruct`` goes on (the gain named), the power-up refuses (its decoder needs the
    calibrated amplitude). Else the other
    five orders of d1..d3 are
    tried: one that fits names the wiring ("d1 and d2 swapped"); else, with a reference (``r``
    or ``y_ref``), the calibration's direction check
    (:func:`hallcal.pipeline.checks.check_direction`) names a reversed order; else the
    signals do not match this calibration.

    Parameters
    ----------
    decoder : PowerUpDecoder or None
        The calibration's decoder (None: artifact without an identifiability analysis).
    dataset : Dataset
        The recording (d1, d2, d3; r or y_ref optional).
    misfit : MisfitResult, keyword-only, optional
        The power-up test's verdict (``reconstruct --absolute``, which needs the calibrated
        amplitude): a mismatch stays one, with the reason named.
    samples : int, keyword-only
        How many samples from the first to test.

    Returns
    -------
    SignalCheck
    """
    if decoder is None:
        return SignalCheck(
            SignalStatus.UNCHECKED,
            "signals not checked against the model: the artifact has no 'identifiability' "
            "entry (made by an older version; calibrate again to check)",
        )
    d = np.asarray(dataset.d, dtype=np.float64)[:samples]
    result = misfit if misfit is not None else model_misfit(decoder, d)
    if result.status.success:
        return SignalCheck(
            SignalStatus.FITS,
            f"signals fit the calibration's model (misfit {result.cost_per_dof:.2f} times the "
            f"calibrated noise variance over {result.samples} samples)",
            result,
        )
    # a common gain (temperature, supply, another unit) is harmless to f_init and f_star; it
    # can be told from one sensor's gain only over a whole electrical turn (at one position a
    # gain and another pole pair's magnet look alike)
    scale = common_scale(decoder, d)
    scaled = model_misfit(decoder, decoder.offset + (d - decoder.offset) / scale)
    # with its gain profile the power-up decoder divides the common gain out itself: the scaled
    # signals are its view at any length (its own mismatch stays one)
    profiled = decoder.gain_sd > 0.0
    if scaled.status.success and (
        (profiled and misfit is None) or (not profiled and _electrical_turns(decoder, d) >= 1.0)
    ):
        if misfit is not None:  # the power-up decoder needs the calibrated amplitude
            return SignalCheck(
                SignalStatus.MISMATCH,
                f"{MISMATCH_TEXT} (the signals' amplitude is {scale:.4g} times the "
                "calibration's: the power-up identification needs the calibrated amplitude; "
                "temperature, supply or ADC reference changed?)",
                misfit,
                scale=scale,
            )
        return SignalCheck(
            SignalStatus.FITS,
            f"signals fit the calibration's model with their amplitude {scale:.4g} times the "
            f"calibration's (misfit {scaled.cost_per_dof:.2f} times the calibrated noise "
            f"variance over {scaled.samples} samples)",
            scaled,
            scale=scale,
        )
    fits = []
    for order in itertools.permutations(range(3)):
        if order == (0, 1, 2):
            continue
        other = model_misfit(decoder, d[:, list(order)])
        if other.status is MisfitStatus.FITS:
            fits.append((other.cost_per_dof, order))
    if fits:
        order = min(fits)[1]
        return SignalCheck(
            SignalStatus.WIRING,
            "sensors swapped or wiring changed: these signals do not match this calibration, "
            f"but they do with the Hall columns in the order {_order_text(order)}; fix the "
            "wiring or the column order",
            result,
            (order[0], order[1], order[2]),
            scale,
        )
    direction = check_direction(dataset)
    if direction.status is CheckStatus.FAILED:
        return SignalCheck(SignalStatus.WIRING, f"{direction.text}", result, scale=scale)
    return SignalCheck(SignalStatus.MISMATCH, _mismatch_text(result), result, scale=scale)


#: A common amplitude outside [1 / FAR_SCALE, FAR_SCALE] times the calibration's is worth a
#: warning (another unit or ADC scale?); within it, it is temperature or supply.
FAR_SCALE = 1.5


def _far(scale: float) -> bool:
    return not (1.0 / FAR_SCALE <= scale <= FAR_SCALE)


def _electrical_turns(decoder: PowerUpDecoder, d: np.ndarray) -> float:
    """Electrical turns f_init's angle spans over the samples (max - min)."""
    F = decoder.features(d)
    y = (F["psi"] + TWO_PI * F["m"])[F["valid"]]
    return float(np.ptp(y)) / TWO_PI if y.size else 0.0


def identification_check(
    decoder: PowerUpDecoder, dataset: Dataset, angles: AbsoluteAngles
) -> SignalCheck:
    """The signal check of ``reconstruct --absolute``: the power-up test's verdict, confirmed on
    the rest of the recording.

    A lock is taken within a few samples (median 6; with the goodness-of-fit gate of
    calibrations made since, after :data:`~hallcal.sensor.absolute.DEFAULT_GATE_SAMPLES`),
    where two sensors swapped, one sensor's offset or gain changed can still look like a magnet
    of the model (measured: 5-10 of 60 power-ups locked at a claimed error below 1e-7 on
    signals with d1 and d2 swapped, ``benchmarks/bench_observer_unseen.txt``); the recording
    after the lock, with motion, tells them apart. So a lock is accepted only when the whole
    recording's misfit test (:func:`check_signals`, the check of plain ``reconstruct``) does
    not reject the model either; the false-"mismatch" bound beta of that test is the price (at
    most 1e-9 per recording under the calibrated noise). A power-up that the test refused is
    checked further (:func:`check_signals`: another order of d1..d3, or the direction against a
    reference, names the wiring); when the rest of the recording fits, the refusal names a
    transient at power-up instead of a changed calibration.

    Parameters
    ----------
    decoder : PowerUpDecoder
        The decoder the power-up ran with.
    dataset : Dataset
        The recording from power-up.
    angles : AbsoluteAngles
        Its absolute reconstruction (with the identification).

    Returns
    -------
    SignalCheck
        FITS when the power-up test locked (or stayed undecided) and the whole recording does
        not contradict it; else MISMATCH or WIRING.
    """
    ident = angles.identification
    if ident.status is not PowerUpStatus.MISMATCH:
        whole = check_signals(decoder, dataset)
        if not whole.status.success:
            return whole
        return SignalCheck(
            SignalStatus.FITS,
            f"signals fit the calibration's model (misfit {ident.cost_per_dof:.2f} times the "
            f"calibrated noise variance over {ident.samples} samples)",
        )
    first = MisfitResult(
        status=MisfitStatus.MISMATCH,
        sample=ident.mismatch_sample,
        statistic=ident.misfit,
        cost_per_dof=ident.cost_per_dof,
        samples=ident.samples,
        offset=ident.offset,
    )
    rest = model_misfit(decoder, np.asarray(dataset.d, dtype=np.float64)[:CHECK_SAMPLES])
    if rest.status is MisfitStatus.FITS and rest.transients:
        return SignalCheck(
            SignalStatus.MISMATCH,
            f"the first {ident.samples} samples after power-up do not fit this calibration's "
            f"model (misfit {ident.cost_per_dof:.1f} times the calibrated noise variance) but "
            f"the rest of the recording does (misfit {rest.cost_per_dof:.2f}): a transient at "
            "power-up (noise burst, a channel at its rail?); power up again",
            first,
        )
    return check_signals(decoder, dataset, misfit=first)
