"""Validation metrics: RMS and peak angle error and the cumulative PSD over spatial frequency.

Section "Results" of van Meer et al. (Figs. 5, 7 and 8): the angle error
of f_init and f_star against an encoder (or the virtual bench's true angle), and the cumulative
power spectral density of the error versus spatial frequency in cycles per revolution, where the
pole-pair harmonic n_m stands out before calibration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI

__all__ = ["AngleError", "SpatialSpectrum", "angle_error", "spatial_spectrum"]


@dataclass(frozen=True)
class AngleError:
    """RMS, peak and mean of an angle error e = y_est - y_ref [rad].

    ``rms`` is taken after removing the mean (a constant offset of the angle origin is not an
    error of the reconstruction; ``mean`` reports it), ``rms_raw`` without removing it.
    """

    rms: float
    peak: float
    mean: float
    rms_raw: float
    n_samples: int

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("rms", "peak", "mean", "rms_raw", "n_samples")}


def angle_error(y_est: ArrayLike, y_ref: ArrayLike, *, remove_mean: bool = True) -> AngleError:
    """Summary of the error ``y_est - y_ref`` [rad].

    Parameters
    ----------
    y_est : array_like (N,)
        Estimated angle [rad].
    y_ref : array_like (N,)
        Reference angle (encoder or the bench's truth) [rad].
    remove_mean : bool, keyword-only
        Whether ``rms`` and ``peak`` are taken about the mean error (default) or about zero.

    Returns
    -------
    AngleError
        RMS, peak and mean of the error [rad], the RMS about zero, and the sample count.
    """
    e = np.asarray(y_est, dtype=np.float64) - np.asarray(y_ref, dtype=np.float64)
    mean = float(np.mean(e))
    ec = e - mean if remove_mean else e
    return AngleError(
        rms=float(np.sqrt(np.mean(ec**2))),
        peak=float(np.max(np.abs(ec))),
        mean=mean,
        rms_raw=float(np.sqrt(np.mean(e**2))),
        n_samples=int(e.size),
    )


@dataclass(frozen=True)
class SpatialSpectrum:
    """Power of an angle error per spatial frequency (cycles per revolution).

    Attributes
    ----------
    frequency : ndarray
        Spatial frequency [cycles/rev], 1 / revolutions apart.
    power : ndarray
        One-sided power per line [rad^2]; sums to the error variance (Parseval).
    cumulative : ndarray
        Cumulative sum of ``power`` [rad^2]; the last value is the variance.
    revolutions : float
        Revolutions covered by the analysed segment.
    """

    frequency: NDArray[np.float64] = field(repr=False)
    power: NDArray[np.float64] = field(repr=False)
    cumulative: NDArray[np.float64] = field(repr=False)
    revolutions: float


def spatial_spectrum(
    error: ArrayLike, position: ArrayLike, *, points_per_rev: int | None = None
) -> SpatialSpectrum:
    """Cumulative PSD of an angle error over spatial frequency (Fig. 8).

    The samples are ordered by position and the error is taken at the nearest sample on a
    uniform grid of the position over a whole number of revolutions when possible, so that
    spatial harmonics fall on DFT lines; the last cumulative value equals the variance of the
    error over that segment (Parseval).

    Parameters
    ----------
    error : array_like (N,)
        Angle error [rad].
    position : array_like (N,)
        Angle used as the spatial axis [rad] (encoder, true angle or y_star).
    points_per_rev : int, optional
        Grid density; default: as many grid points as samples in the segment.

    Returns
    -------
    SpatialSpectrum
        Power and cumulative power [rad^2] per spatial frequency [cycles/rev].
    """
    e = np.asarray(error, dtype=np.float64)
    x = np.asarray(position, dtype=np.float64)
    if x[-1] < x[0]:
        x = -x
    order = np.argsort(x, kind="stable")
    xs, es = x[order], e[order]
    span = xs[-1] - xs[0]
    if not span > 0:  # a standstill: no spatial axis, hence no lines (the RMS still holds)
        empty = np.zeros(0)
        return SpatialSpectrum(empty, empty, empty, 0.0)
    revs = span / TWO_PI
    whole = math.floor(revs)
    length = whole * TWO_PI if whole >= 1 else span
    inside = xs < xs[0] + length
    xs, es = xs[inside], es[inside]
    # One grid point per sample in the segment, each taking the nearest sample in position:
    # unlike interpolation, this keeps the variance of white noise (Parseval holds).
    n = int(points_per_rev * length / TWO_PI) if points_per_rev else xs.size
    n = max(16, n)
    grid = xs[0] + length * np.arange(n) / n
    idx = np.clip(np.searchsorted(xs, grid), 1, xs.size - 1)
    left_closer = (grid - xs[idx - 1]) < (xs[idx] - grid)
    eg = es[np.where(left_closer, idx - 1, idx)]
    eg = eg - eg.mean()
    spec = np.fft.rfft(eg) / n
    power = np.abs(spec) ** 2
    power[1:] *= 2.0
    if n % 2 == 0:
        power[-1] /= 2.0
    freq = np.arange(power.size) * TWO_PI / length
    power, freq = power[1:], freq[1:]
    return SpatialSpectrum(freq, power, np.cumsum(power), float(length / TWO_PI))
