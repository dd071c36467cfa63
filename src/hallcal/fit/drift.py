"""Sensors that drift during the calibration run: a trend of the SEM residual against time.

A Hall sensor warming up changes its sensitivity and offset (per-sensor drifts of about 1 %
over 60 K, DESIGN.md "Numerical facts"). The flux model is periodic in the angle and cannot
follow it, so the drift stays in the residual ``e_h = d_h - d_sim,h`` as

    e_h[k] ~ gamma_h tau_k g_h(y0_k) + delta_h tau_k,   tau_k = t_k / T - 1/2 in [-1/2, 1/2],

with gamma_h the relative gain change of sensor h over the run and delta_h its offset change
[Hall signal unit]. Per sensor, (gamma_h, delta_h) by least squares on the simulated flux
``g_h = d_sim,h``, with standard deviations from the noise sigma_h (white noise: sigma^2 (X^T X)^-1,
Ljung 1999, sec. 9.3). A drift is named when it is significant (``threshold`` standard deviations)
and relevant: its RMS in the signal is at least ``relevance`` sigma_h (below that it changes the
angle by less than a fifth of the noise floor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.fit.sem import least_squares_start
from hallcal.sensor.flux import FluxModel, FourierBasis

__all__ = ["DriftReport", "detect_drift", "drift_in_f_init_view", "undrifted"]

#: Standard deviations for a significant trend: 10^5 samples make a normal 5-sigma excursion
#: improbable (3e-7 per test, six tests).
THRESHOLD = 5.0
#: RMS of the drift in the signal, relative to the noise sigma, below which it is not named.
RELEVANCE = 0.2
#: Samples of the trend test in f_init's view (every k-th sample beyond): the flux fit uses all
#: of them; the test's standard deviations grow as sqrt(k), far below the drifts that matter
#: (a 2 % gain drift: 300 sigma on 10^5 samples, 150 on 2.5 10^4).
SAMPLES = 25_000


@dataclass(frozen=True)
class DriftReport:
    """Per-sensor gain and offset trends of the residual over the run.

    Attributes
    ----------
    gain, gain_std : ndarray (3,)
        gamma_h: relative sensitivity change from the run's start to its end, and its std.
    offset, offset_std : ndarray (3,)
        delta_h: offset change over the run [Hall signal unit], and its std.
    rms : ndarray (3,)
        RMS of the fitted trend in each signal [Hall signal unit].
    sigma : ndarray (3,)
        Noise standard deviation used [Hall signal unit].
    drifting : ndarray (3,) of bool
        Significant and relevant (module docstring).
    """

    gain: NDArray[np.float64]
    gain_std: NDArray[np.float64]
    offset: NDArray[np.float64]
    offset_std: NDArray[np.float64]
    rms: NDArray[np.float64]
    sigma: NDArray[np.float64] = field(repr=False)
    drifting: NDArray[np.bool_]

    @property
    def any(self) -> bool:
        """Whether any sensor drifts."""
        return bool(self.drifting.any())

    def describe(self) -> str:
        """One line naming each drifting sensor with its gain and offset change."""
        parts = []
        for h in np.flatnonzero(self.drifting):
            zg = abs(self.gain[h]) / self.gain_std[h] if self.gain_std[h] > 0 else math.inf
            zo = abs(self.offset[h]) / self.offset_std[h] if self.offset_std[h] > 0 else math.inf
            parts.append(
                f"sensor {h + 1}: gain {100.0 * self.gain[h]:+.2g} % ({zg:.0f} sigma), offset "
                f"{self.offset[h]:+.2g} ({zo:.0f} sigma), {self.rms[h] / self.sigma[h]:.2g}x "
                "its noise RMS"
            )
        return "; ".join(parts)

    def to_dict(self) -> dict:
        """JSON-ready summary."""
        return {
            "gain_change": [float(v) for v in self.gain],
            "gain_change_std": [float(v) for v in self.gain_std],
            "offset_change": [float(v) for v in self.offset],
            "offset_change_std": [float(v) for v in self.offset_std],
            "drifting": [bool(v) for v in self.drifting],
        }


def detect_drift(
    d: ArrayLike,
    d_sim: ArrayLike,
    sigma: ArrayLike,
    *,
    weights: ArrayLike | None = None,
    threshold: float = THRESHOLD,
    relevance: float = RELEVANCE,
) -> DriftReport:
    """Gain and offset trends of each sensor's SEM residual against time (module docstring).

    Parameters
    ----------
    d : array_like (N, 3)
        Hall signals the fit used.
    d_sim : array_like (N, 3)
        The fit's simulated signals.
    sigma : array_like (3,)
        Noise standard deviation per channel.
    weights : array_like (N, 3), optional
        0 on censored samples (:mod:`hallcal.fit.censor`), left out.
    threshold : float, keyword-only
        Standard deviations for a significant trend.
    relevance : float, keyword-only
        Least RMS of the trend, relative to sigma_h, for a named drift.

    Returns
    -------
    DriftReport
    """
    dd = np.asarray(d, dtype=np.float64)
    ds = np.asarray(d_sim, dtype=np.float64)
    sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,)).copy()
    N = dd.shape[0]
    tau = np.arange(N) / max(N - 1, 1) - 0.5
    w = np.ones((N, 3)) if weights is None else np.asarray(weights, dtype=np.float64)
    est = np.zeros((3, 2))
    std = np.full((3, 2), math.inf)
    rms = np.zeros(3)
    for h in range(3):
        ok = (w[:, h] > 0) & np.isfinite(ds[:, h]) & np.isfinite(dd[:, h])
        X = np.column_stack([tau[ok] * ds[ok, h], tau[ok]])
        e = dd[ok, h] - ds[ok, h]
        G = X.T @ X
        try:
            Ginv = np.linalg.inv(G)
        except np.linalg.LinAlgError:
            continue
        est[h] = Ginv @ (X.T @ e)
        std[h] = sig[h] * np.sqrt(np.diag(Ginv))
        rms[h] = float(np.sqrt(np.mean((X @ est[h]) ** 2)))
    z = np.abs(est) / np.where(std > 0, std, math.inf)
    drifting = (z.max(axis=1) > threshold) & (rms > relevance * sig)
    return DriftReport(est[:, 0], std[:, 0], est[:, 1], std[:, 1], rms, sig, drifting)


def drift_in_f_init_view(
    d: ArrayLike, y: ArrayLike, sigma: ArrayLike, *, pole_pairs: int, bands: int = 3,
    weights: ArrayLike | None = None,
) -> DriftReport:  # fmt: skip
    """:func:`detect_drift` before any closed-loop fit: on the residual of each channel
    regressed on the mechanical harmonics 1..``bands`` n_m at f_init's angle y.

    A periodic function of the angle cannot follow a trend in time, so the drift stays in that
    residual as well; found here, it can be taken out of the data the model choice sees
    (:func:`undrifted`) and identified jointly in the final SEM.

    Parameters
    ----------
    d : array_like (N, 3)
        Hall signals.
    y : array_like (N,)
        f_init output [rad].
    sigma : array_like (3,)
        Noise standard deviation per channel.
    pole_pairs : int, keyword-only
        n_m.
    bands : int, keyword-only
        Electrical bandwidth of the regression.
    weights : array_like (N, 3), optional
        0 on censored samples.

    Returns
    -------
    DriftReport
    """
    basis = FourierBasis(tuple(range(1, int(bands) * int(pole_pairs) + 1)))
    yy = np.asarray(y, dtype=np.float64)
    dd = np.asarray(d, dtype=np.float64)
    theta = least_squares_start(basis, dd, yy, weights=weights)
    k = slice(None, None, max(1, -(-yy.size // SAMPLES)))  # the test on a sub-sample
    w = None if weights is None else np.asarray(weights, dtype=np.float64)[k]
    return detect_drift(dd[k], FluxModel(basis, theta)(yy[k]), sigma, weights=w)


def undrifted(d: ArrayLike, report: DriftReport) -> NDArray[np.float64]:
    """The signals with the drifts of ``report`` taken out: ``(d - delta tau) / (1 + gamma tau)``
    per sensor (tau = k / (N - 1) - 1/2), i.e. the sensors at the run's middle.

    Parameters
    ----------
    d : array_like (N, 3)
        Hall signals.
    report : DriftReport
        The drifts (only the drifting sensors are corrected).

    Returns
    -------
    ndarray (N, 3)
    """
    dd = np.array(d, dtype=np.float64)
    N = dd.shape[0]
    tau = np.arange(N) / max(N - 1, 1) - 0.5
    for h in np.flatnonzero(report.drifting):
        dd[:, h] = (dd[:, h] - report.offset[h] * tau) / (1.0 + report.gain[h] * tau)
    return dd
