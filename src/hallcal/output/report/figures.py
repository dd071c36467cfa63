"""The report's figures (:func:`make_figures`), one builder per figure, drawn by
:mod:`hallcal.output.plots`."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hallcal.output.report.content import ReportContent

# ------------------------------------------------------------------------------------------------
# Figures
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReportFigure:
    """One figure of the report.

    Attributes
    ----------
    key : str
        File stem and HTML id (``fig-<key>``).
    title : str
    caption : str
        What the figure shows and what to look for.
    figure : matplotlib.figure.Figure
    """

    key: str
    title: str
    caption: str
    figure: Any = field(repr=False)


def make_figures(content: ReportContent) -> list[ReportFigure]:
    """The report's figures, in order (paper figures first, then the steps' diagnostics).

    Parameters
    ----------
    content : ReportContent
        What the report shows (recordings, model, validation, diagnostics).

    Returns
    -------
    list of ReportFigure
        Key, title, caption and matplotlib figure of each; only the figures the content has
        data for.
    """
    figs = (build(content) for build in _FIGURES)
    return [f for f in figs if f is not None]


def _figure_ripple(c: ReportContent) -> ReportFigure | None:
    from hallcal.output import plots

    vt = c.validation_traces
    if vt is None or vt.y_ref is None:
        return None
    where = c.validation_source or "the validation recording"
    return ReportFigure(
        "ripple",
        "f_init against the true angle (the paper's Fig. 2)",
        f"Two of the {c.pole_pairs} pole pairs of {where}: the Clarke + atan2 angle f_init (blue) "
        "against the reference (black dashed); below, the error itself, with f_star (red) "
        "after calibration. The ripple repeats per pole pair and differs slightly from "
        "magnet to magnet.",
        plots.plot_ripple(vt.y_ref, vt.y_init, pole_pairs=c.pole_pairs, y_star=vt.y_star),
    )


def _figure_hall_model(c: ReportContent) -> ReportFigure | None:
    from hallcal.output import plots

    if c.d_model is None:
        return None
    nv = c.true_noise_variance
    if nv is None and c.sem is not None:
        nv = float(c.sem.noise_variance)
    if nv is None or not math.isfinite(nv):
        nv = c.hall_noise_variance
    simulated = "y₀_sim" in c.d_model_label
    where = (
        "evaluated at the angle the closed-loop simulation predicts, which needs no encoder"
        if simulated
        else "evaluated at the calibrated angle f_star"
    )
    lines = (
        " it should look like white noise inside the ±2σ lines of the Hall noise."
        if nv is not None and math.isfinite(nv)
        else " it should look like white noise (the Hall noise level is unknown here)."
    )
    return ReportFigure(
        "hall_model",
        "Hall signal and identified model (the paper's Figs. 4 and 6)",
        "The measured Hall signal d1 of the calibration recording (blue) and the model "
        f"(red dashed), {where}. Below, the residual over the whole recording:" + lines,
        plots.plot_hall_model(
            c.d,
            c.d_model,
            t=c.t,
            noise_variance=nv,
            model_label=c.d_model_label,
        ),
    )


def _figure_angle_error(c: ReportContent) -> ReportFigure | None:
    from hallcal.output import plots

    vt = c.validation_traces
    if vt is None or vt.y_ref is None:
        return None
    return ReportFigure(
        "angle_error",
        "Angle error before and after calibration (the paper's Figs. 5 and 7)",
        f"Error of f_init (blue) and f_star (red) against the reference of "
        f"{c.validation_source}, about its mean. The dashed lines are ±3 times the noise "
        f"floor ({c.noise_floor_source}): white noise alone, and so a calibration at "
        "the noise floor, stays between them.",
        plots.plot_angle_error(vt.y_ref, vt.y_init, vt.y_star, noise_floor=c.noise_floor),
    )


def _figure_spectrum(c: ReportContent) -> ReportFigure | None:
    from hallcal.output import plots

    if c.validation is None:
        return None
    return ReportFigure(
        "spectrum",
        "Cumulative PSD of the angle error (the paper's Fig. 8)",
        f"Cumulative power of the error over spatial frequency. The step of f_init (blue) "
        f"at n_m = {c.pole_pairs} cycles/rev is the magnet pitch; after calibration (red) the "
        "power grows evenly, as white noise does, towards the noise floor squared.",
        plots.plot_error_spectrum(c.validation, pole_pairs=c.pole_pairs, noise_floor=c.noise_floor),
    )


def _figure_correction(c: ReportContent) -> ReportFigure | None:
    """Without an encoder: the correction along the calibration recording."""
    from hallcal.output import plots

    vt, cv = c.validation_traces, c.calibration
    if (vt is not None and vt.y_ref is not None) or cv.y_star is None:
        return None
    return ReportFigure(
        "correction",
        "Correction f_star - f_init along the recording (no encoder needed)",
        "The correction the lookup table adds to f_init along the calibration "
        "recording: the error the calibration attributes to f_init.",
        plots.plot_correction(cv.y_init, cv.y_star, pole_pairs=c.pole_pairs),
    )


def _figure_bla(c: ReportContent) -> ReportFigure | None:
    from hallcal.output import plots

    if c.bla is None:
        return None
    return ReportFigure(
        "bla",
        "Closed-loop BLA of the plant (paper sec. Obtaining a BLA)",
        "Nonparametric BLA (blue dots) with the standard deviations of the estimate from "
        "realization to realization (orange squares: the total, used as the fit's "
        "weights) and from period to period (grey: the noise), each with its running "
        "median; the parametric fit (red)"
        + (
            ", the model after the gain correction (orange dash-dot)"
            if c.gain_correction is not None
            else ""
        )
        + (" and the true plant (black dashed)" if c.true_plant is not None else "")
        + ". A total std well below |G| means a trustworthy BLA. The grey curve can lie "
        "above the orange one: with few realizations single lines scatter (about 38 % "
        "for 8), and in closed loop the period-to-period spread also holds the loop's "
        "leakage and the sensor error swept by the drift, which cancel in each "
        "realization's mean; the orange curve is the reliable one.",
        plots.plot_bla(
            c.bla,
            true_plant=c.true_plant,
            corrected_plant=c.plant if c.gain_correction is not None else None,
            gain_correction=c.gain_correction,
        ),
    )


def _figure_sem_cost(c: ReportContent) -> ReportFigure | None:
    from hallcal.output import plots

    if c.sem is None:
        return None
    which = "true" if c.true_noise_variance is not None else "estimated"
    return ReportFigure(
        "sem_cost",
        "SEM cost per iteration (the paper's SEM problem)",
        "Simulation-error cost per accepted Levenberg-Marquardt step. A converged model "
        f"ends at the noise level 3Nσ² ({which} σ², dashed).",
        plots.plot_sem_cost(c.sem, noise_variance=c.true_noise_variance),
    )


def _figure_cogging(c: ReportContent) -> ReportFigure | None:
    from hallcal.output import plots

    if c.cogging is None or not c.cogging.size:
        return None
    return ReportFigure(
        "cogging",
        "Cogging torque identified with the flux (paper sec. Discussion)",
        "The position-periodic torque at the plant input that the closed-loop "
        "simulation needed to reproduce the data, in the unit of the torque command"
        + (", with its ±2σ band from the covariance" if c.cogging.covariance is not None else "")
        + (" and the virtual bench's torque (black dashed)" if c.true_cogging is not None else "")
        + ". Identified jointly with the flux, it no longer leaks into the lookup "
        "table; subtracted from the torque command it is an anticogging feed-forward.",
        plots.plot_cogging(c.cogging, true_cogging=c.true_cogging),
    )


def _figure_lut(c: ReportContent) -> ReportFigure:
    from hallcal.output import plots

    band = c.eta_std is not None
    truth = c.true_lut is not None
    return ReportFigure(
        "lut",
        "Lookup table η and its uncertainty (the paper's table correction f_star)",
        "The correction η over one revolution"
        + (" with its ±2σ band from cov(θ)" if band else "")
        + (" and the true η of the virtual bench (black dashed)" if truth else "")
        + (
            "; below, the band on its own scale"
            + (" and the error of the identified table" if truth else "")
            if (band or truth)
            else ""
        )
        + ".",
        plots.plot_lut(c.lut, eta_std=c.eta_std, true_lut=c.true_lut),
    )


#: The report's figures in order: the paper's first, then the steps' diagnostics. Each builder
#: returns None when the content has nothing for its figure.
_FIGURES: tuple[Callable[[ReportContent], ReportFigure | None], ...] = (
    _figure_ripple,
    _figure_hall_model,
    _figure_angle_error,
    _figure_spectrum,
    _figure_correction,
    _figure_bla,
    _figure_sem_cost,
    _figure_cogging,
    _figure_lut,
)
