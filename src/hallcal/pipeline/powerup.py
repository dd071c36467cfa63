"""Absolute angle at power-up in the pipeline: the identifiability analysis that ``calibrate``
stores in the artifact, and the absolute reconstruction behind ``reconstruct --absolute``.

The numeric work is :mod:`hallcal.sensor.absolute` (maximum-likelihood choice of the pole pair
from the magnets' signatures, sequential test, identifiability); this module ties it to a
:class:`~hallcal.pipeline.calibration.Calibration` and to datasets, and turns its verdicts into
the package's errors.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from hallcal.errors import CalibrationRefused, HallcalInputError
from hallcal.sensor.absolute import (
    AbsoluteAngles,
    IdentifiabilityReport,
    PowerUpDecoder,
    absolute_reconstruction,
    analyze_calibration,
)
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT

__all__ = [
    "decoder_for",
    "identifiability_from_artifact",
    "power_up_analysis",
    "reconstruct_absolute",
    "same_revolution",
]

TWO_PI = 2.0 * math.pi


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


def identifiability_from_artifact(artifact: Mapping[str, Any]) -> IdentifiabilityReport | None:
    """The artifact's ``"identifiability"`` entry, or None for an artifact made without it.

    Parameters
    ----------
    artifact : mapping
        The parsed artifact.

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
        raise HallcalInputError("artifact: key 'identifiability' must be an object")
    try:
        return IdentifiabilityReport.from_dict(entry)
    except ValueError as exc:
        raise HallcalInputError(f"artifact: {exc}", key="identifiability") from None


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


def reconstruct_absolute(
    flux: FluxModel, lut: LUT, report: IdentifiabilityReport | None, d: ArrayLike
) -> AbsoluteAngles:
    """f_init and f_star in the calibration's frame from power-up (no homing).

    The recording starts at power-up; every sample is decoded as firmware would (the offset in
    force is the current maximum-likelihood one until the sequential test locks).

    Parameters
    ----------
    flux : FluxModel
        The calibration's g_theta.
    lut : LUT
        The calibration's table.
    report : IdentifiabilityReport or None
        The calibration's identifiability analysis.
    d : array_like (K, 3)
        Hall signals from power-up.

    Returns
    -------
    AbsoluteAngles
        y_init and y_star [rad] in the calibration's frame, and the identification.

    Raises
    ------
    HallcalInputError, CalibrationRefused
        See :func:`decoder_for`.
    """
    return absolute_reconstruction(decoder_for(flux, lut, report), lut, d)


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
