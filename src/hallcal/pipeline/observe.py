"""The model-based observer on a calibration: its check at calibration time, its run on a recording.

:mod:`hallcal.sensor.observer` holds the numeric core (the tracking maximum-likelihood angle from
the flux model g_theta, the misfit monitor, the gain/offset adaptation, the one-sensor fallback);
this module connects it to a :class:`~hallcal.pipeline.calibration.Calibration`: the noise it is
calibrated against, the injectivity check that lets a calibration whose table cannot exist
(folding map) still be written for the observer, and ``reconstruct --observer``.

Loaded only when the observer is used (it compiles numba kernels on first use).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hallcal.sensor.flux import FluxModel
from hallcal.sensor.observer import (
    Injectivity,
    ObserverModel,
    ObserverRun,
    ObserverSettings,
    observer_model,
    run_observer,
)

#: A :class:`~hallcal.pipeline.calibration.Calibration` (which imports this module lazily; named
#: here without importing it, to keep the import graph one-way).
Calibration = Any

__all__ = [
    "FOLDING_NOTE",
    "calibrated_noise",
    "observer_check",
    "observer_for",
    "observer_section",
    "run_on",
]

#: The one line calibrate prints when only the table is impossible.
FOLDING_NOTE = (
    "the lookup table cannot exist (the map y0 -> f_init(g(y0)) folds), but the three signals "
    "determine the angle (curve separation {sep:.0f} noise sigmas): the artifact is written for "
    "the model-based observer only; use 'hallcal reconstruct --observer'"
)


def observer_check(flux: FluxModel, pole_pairs: int, noise_variance: float) -> Injectivity:
    """The injectivity of the three-signal curve, with its margin (calibration time).

    Parameters
    ----------
    flux : FluxModel
        The identified g_theta.
    pole_pairs : int
        n_m.
    noise_variance : float
        sigma^2 per channel from the SEM [sensor unit^2].

    Returns
    -------
    Injectivity
    """
    return observer_model(flux, pole_pairs, noise_variance).injectivity


def observer_section(
    injectivity: Injectivity, noise_variance: float | NDArray[np.float64]
) -> dict[str, Any]:
    """The artifact's ``observer`` entry: the noise the misfit is measured against and the
    injectivity check.

    Parameters
    ----------
    injectivity : Injectivity
        From :func:`observer_check`.
    noise_variance : float or ndarray, shape (3,)
        sigma^2 per channel [sensor unit^2].

    Returns
    -------
    dict
        ``noise_variance`` (3 numbers) and the fields of :class:`Injectivity`.
    """
    nv = np.broadcast_to(np.asarray(noise_variance, dtype=np.float64), (3,))
    return {"noise_variance": [float(v) for v in nv], **injectivity.to_dict()}


def calibrated_noise(
    flux: FluxModel,
    pole_pairs: int,
    d: NDArray[np.float64],
    noise_variance: float,
    *,
    start: int = 0,
    stop: int | None = None,
) -> NDArray[np.float64]:
    """The level the misfit monitor measures against: the calibration data's own residual.

    A model-free noise estimate (e.g. from second differences) misses the model's own error
    orthogonal to the curve (harmonics beyond the basis, sensor nonlinearity); on the real ring
    jig the held-out misfit against it was 5x, and that model error is not uniform over the
    revolution (scaled to a mean of 1, 12 % of a held-out capture was still 'stale'). The
    observer is run over the calibration recording and the variance scaled so that the
    largest windowed chi-square per degree of freedom over the fitted samples is 1 (never
    below the given variance): the model's worst region sets the level.

    Parameters
    ----------
    flux : FluxModel
        The identified g_theta.
    pole_pairs : int
        n_m.
    d : ndarray, shape (N, 3)
        The calibration recording's Hall signals, from its first sample (the frame's y = 0).
    noise_variance : float
        sigma^2 per channel [sensor unit^2] (model-free).
    start, stop : int, keyword-only
        The samples the model was fitted on (default: all).

    Returns
    -------
    ndarray, shape (3,)
        sigma_i^2 [sensor unit^2].
    """
    model = observer_model(flux, pole_pairs, noise_variance)
    run = run_observer(model, d[:stop])
    misfit = run.misfit[start + ObserverSettings().window :]
    level = float(np.max(misfit)) if misfit.size > 0 else 1.0
    return np.full(3, float(noise_variance) * max(1.0, level))


def _noise_variance(cal: Calibration) -> NDArray[np.float64]:
    """sigma_i^2: the calibration's observer entry, else the SEM's, else from the noise floor
    (sigma sqrt(2/3) / (A n_m) with A the fundamental's amplitude, docs/design.md)."""
    entry = cal.observer
    if isinstance(entry, Mapping) and "noise_variance" in entry:
        return np.asarray(entry["noise_variance"], dtype=np.float64)
    nv = cal.diagnostics.get("noise_variance")  # the SEM's
    if isinstance(nv, int | float) and nv > 0:
        return np.full(3, float(nv))
    n = cal.pole_pairs
    flux = cal.flux
    if n in flux.basis.harmonics and math.isfinite(cal.noise_floor) and cal.noise_floor > 0:
        js, jc = flux.basis.index(n)
        A = float(np.mean(np.hypot(flux.theta[:, js], flux.theta[:, jc])))
        sigma = cal.noise_floor * A * n / math.sqrt(2.0 / 3.0)
        return np.full(3, sigma**2)
    raise ValueError("the calibration states no noise level for the observer")


def observer_for(cal: Calibration) -> ObserverModel:
    """The tabulated model of a calibration (computed or loaded).

    Parameters
    ----------
    cal : Calibration
        Its flux model, pole pairs and noise level (the artifact's ``observer`` entry, the
        SEM's noise variance, or the noise floor).

    Returns
    -------
    ObserverModel
    """
    return observer_model(cal.flux, cal.pole_pairs, _noise_variance(cal))


def run_on(
    cal: Calibration,
    d: NDArray[np.float64],
    *,
    y_initial: float = 0.0,
    settings: ObserverSettings | None = None,
) -> ObserverRun:
    """The observer over a recording's Hall signals, from ``y_initial``.

    Parameters
    ----------
    cal : Calibration
    d : ndarray, shape (N, 3)
        Hall signals.
    y_initial : float, keyword-only
        Angle before the first sample [rad].
    settings : ObserverSettings, keyword-only, optional

    Returns
    -------
    ObserverRun
    """
    return run_observer(observer_for(cal), d, y_initial=y_initial, settings=settings)
