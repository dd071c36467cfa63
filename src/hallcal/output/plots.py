"""Figures of a calibration, of the kinds in van Meer et al., and of its intermediate results.

Paper figures: the example ripple (Fig. 2), the measured Hall signal with the
identified model (Figs. 4 and 6), the angle error of f_init and f_star (Figs. 5 and
7) and its cumulative power spectral density over spatial frequency (Fig. 8).
Diagnostics beyond the paper: the closed-loop BLA (section "Obtaining a Best Linear
Approximation"), the SEM cost per iteration (the SEM problem), the lookup table eta with its
uncertainty band (the table correction f_star = f_init + eta), the correction f_star - f_init
applied along a recording and the cogging torque identified with the flux (the cause of residual
errors named in the paper's discussion).

Compute first, plot separately: every function takes arrays or result objects that are already
computed (:mod:`hallcal.pipeline`, :mod:`hallcal.sensor.metrics`, :mod:`hallcal.fit.sem`, ...)
and returns a new :class:`matplotlib.figure.Figure`; nothing here runs a simulation, a fit or an
optimization.
The figures are built without pyplot (no global state, no GUI; ``savefig`` renders with Agg), so
they are safe in scripts, servers and tests; in Jupyter a returned figure displays itself.

Colours follow the paper: f_init blue, f_star red, the true angle (or encoder) black dashed, the
measured Hall signal blue and the identified model red dashed. Angles are shown in mechanical
degrees, angle errors in mrad, spatial frequencies in cycles per revolution.
"""

from __future__ import annotations

import io
import math
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.formatting import AngleUnit

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from hallcal.fit.sem import SEMResult
    from hallcal.identify.bla import NonparametricBLA
    from hallcal.pipeline import BLAIdentification, Validation
    from hallcal.sensor.lut import LUT
    from hallcal.sim.cogging import CoggingTorque
    from hallcal.sim.lti import ContinuousTF

__all__ = [
    "INIT_COLOR",
    "MODEL_COLOR",
    "NOISE_COLOR",
    "STAR_COLOR",
    "TRUTH_COLOR",
    "figure_png",
    "log_axis",
    "plot_angle_error",
    "plot_bla",
    "plot_cogging",
    "plot_correction",
    "plot_error_spectrum",
    "plot_hall_model",
    "plot_lut",
    "plot_ripple",
    "plot_sem_cost",
]

#: f_init and measured signals (blue in the paper).
INIT_COLOR = "#1f77b4"
#: f_star and the identified model (red in the paper).
STAR_COLOR = "#d62728"
MODEL_COLOR = STAR_COLOR
#: The true angle, an encoder or the true plant (black dashed in the paper).
TRUTH_COLOR = "#000000"
#: Noise levels and bands.
NOISE_COLOR = "#7f7f7f"
_ACCENT = "#ff7f0e"

_WIDTH = 8.0  # inches; 960 px at the report's 120 dpi


def _figure(
    rows: int, height: float, *, sharex: bool = True, ratios: Sequence[float] | None = None
):
    fig = Figure(figsize=(_WIDTH, height), layout="constrained")
    axes = fig.subplots(
        rows, 1, sharex=sharex, squeeze=False, gridspec_kw={"height_ratios": ratios}
    )[:, 0]
    for ax in axes:
        ax.grid(True, color="#dddddd", linewidth=0.6)
        ax.set_axisbelow(True)
    return fig, list(axes)


def _vec(x: ArrayLike, name: str) -> NDArray[np.float64]:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {a.shape}")
    return a


def _deg(x: ArrayLike) -> NDArray[np.float64]:
    return AngleUnit.DEG.convert(np.asarray(x, dtype=np.float64))


def _mrad(x: ArrayLike) -> NDArray[np.float64]:
    return AngleUnit.MRAD.convert(np.asarray(x, dtype=np.float64))


def figure_png(fig: Figure, *, dpi: int) -> bytes:
    """The figure as PNG bytes, without the matplotlib version in its metadata.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    dpi : int, keyword-only
        Resolution [dots per inch].

    Returns
    -------
    bytes
        The PNG file.
    """
    buf = io.BytesIO()
    with warnings.catch_warnings():
        # a figure of degenerate data (a flat trace, a tiny run) may not fit constrained layout;
        # matplotlib then draws it without and says so on stderr, which is no news to the user
        warnings.filterwarnings("ignore", message="constrained_layout not applied")
        fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    return buf.getvalue()


def _centred(e: NDArray[np.float64]) -> NDArray[np.float64]:
    return e - float(np.mean(e))


_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _log_label(value: float, _pos: object = None) -> str:
    """Plain-text tick label of a logarithmic axis: 0.01 ... 1000, else 10⁴ style."""
    if not value > 0:
        return ""
    e = math.log10(value)
    if abs(e - round(e)) < 1e-6:
        k = int(round(e))
        return f"{value:g}" if -2 <= k <= 3 else "10" + str(k).translate(_SUPERSCRIPT)
    return f"{value:.3g}"


def log_axis(axis: Any, lo: float, hi: float) -> None:
    """Plain-text labels on a log axis (no mathtext: faster and the same font as the rest).

    Spans of less than about two decades also get labels at 2x and 5x each decade.

    Parameters
    ----------
    axis : matplotlib.axis.Axis
        An axis already on a log scale.
    lo, hi : float
        The span of the data on it (> 0).
    """
    axis.set_major_locator(LogLocator(base=10.0))
    axis.set_major_formatter(FuncFormatter(_log_label))
    if lo > 0 and hi > 0 and math.log10(hi / lo) < 2.2:
        axis.set_minor_locator(LogLocator(base=10.0, subs=(2.0, 5.0)))
        axis.set_minor_formatter(FuncFormatter(_log_label))
    else:
        axis.set_minor_locator(LogLocator(base=10.0, subs=tuple(range(2, 10))))
        axis.set_minor_formatter(NullFormatter())


def _legend(ax, **kwargs) -> None:
    kwargs.setdefault("fontsize", "small")
    kwargs.setdefault("framealpha", 0.9)
    ax.legend(**kwargs)


def _legend_above(ax, *, ncols: int = 3) -> None:
    """Legend in a row just above the axes, where it cannot hide data."""
    ax.legend(
        loc="lower left",
        bbox_to_anchor=(0.0, 1.0),
        ncols=ncols,
        fontsize="small",
        frameon=False,
        borderaxespad=0.2,
        handlelength=2.2,
    )


def _title(fig: Figure, title: str) -> None:
    fig.suptitle(title, fontsize="large")


def _finish(ax, xlabel: str | None, ylabel: str, *, ncols: int) -> None:
    """Axis labels, no margin along x, and the legend in a row above the axes."""
    if xlabel is not None:
        ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.margins(x=0)
    _legend_above(ax, ncols=ncols)


def _band(ax, x: ArrayLike, lo: ArrayLike, hi: ArrayLike, label: str) -> None:
    """The shaded +-2 sigma band of an estimate, in the estimate's colour."""
    ax.fill_between(x, lo, hi, color=STAR_COLOR, alpha=0.25, lw=0, label=label)


def _level_lines(ax, level: float, k: int, *, lw: float, label: str) -> None:
    """Dashed lines at +-k level (a noise band), with one legend entry."""
    for sign in (-k, k):
        ax.axhline(sign * level, color=TRUTH_COLOR, lw=lw, ls="--", zorder=5)
    ax.plot([], [], color=TRUTH_COLOR, lw=lw, ls="--", label=label)


# ------------------------------------------------------------------------------------------------
# Paper figures
# ------------------------------------------------------------------------------------------------


def plot_ripple(
    y_ref: ArrayLike,
    y_init: ArrayLike,
    *,
    pole_pairs: int,
    y_star: ArrayLike | None = None,
    start: float | None = None,
    pole_pairs_shown: int = 2,
    reference_label: str = "true angle y₀",
) -> Figure:
    """f_init against the true angle over a few pole pairs (Fig. 2).

    The top panel shows the reconstructed angle over the true one (the paper's figure); as the
    ripple is a few mrad on an angle of tens of degrees, the bottom panel shows the error
    ``f_init - y0`` itself (not mean-removed), with the pole-pair boundaries marked so that the
    repetition per magnet, and its variation from magnet to magnet, is visible.

    Parameters
    ----------
    y_ref : array_like (N,)
        True angle y0 or encoder angle [rad].
    y_init : array_like (N,)
        f_init output on the same samples [rad].
    pole_pairs : int, keyword-only
        n_m.
    y_star : array_like (N,), optional
        f_star output, drawn in the error panel when given.
    start : float, optional
        Start of the window [rad]; default: a pole-pair boundary near the middle of the record.
    pole_pairs_shown : int
        Width of the window in pole pairs (the paper shows two).
    reference_label : str
        Legend label of ``y_ref``.

    Returns
    -------
    matplotlib.figure.Figure
    """
    yr, yi = _vec(y_ref, "y_ref"), _vec(y_init, "y_init")
    ys = None if y_star is None else _vec(y_star, "y_star")
    pitch = TWO_PI / int(pole_pairs)
    span = pole_pairs_shown * pitch
    lo, hi = float(np.min(yr)), float(np.max(yr))
    if start is None:
        mid = 0.5 * (lo + hi) - 0.5 * span
        start = math.floor(mid / pitch) * pitch
        if start < lo:
            start = math.ceil(lo / pitch) * pitch
    sel = (yr >= start) & (yr < start + span)
    if not np.any(sel):
        sel = np.ones(yr.size, dtype=bool)
    fig, (ax1, ax2) = _figure(2, 5.2, ratios=(1, 1.6))
    x = _deg(yr[sel])
    ax1.plot(x, _deg(yi[sel]), color=INIT_COLOR, lw=1.4, label="f_init (Clarke + atan2)")
    ax1.plot(x, x, color=TRUTH_COLOR, lw=1.0, ls="--", label=reference_label)
    ax1.set_ylabel("angle [deg]")
    _legend(ax1, loc="upper left")
    _title(
        fig,
        f"f_init over {pole_pairs_shown} of {pole_pairs} pole pairs (cf. the paper's Fig. 2)",
    )
    ax2.plot(x, _mrad(yi[sel] - yr[sel]), color=INIT_COLOR, lw=1.0, label="f_init − y₀")
    if ys is not None:
        ax2.plot(x, _mrad(ys[sel] - yr[sel]), color=STAR_COLOR, lw=0.8, label="f_star − y₀")
    ax2.axhline(0.0, color=TRUTH_COLOR, lw=0.8, ls="--")
    k0 = math.ceil(float(np.min(yr[sel])) / pitch - 0.01)
    k1 = math.floor(float(np.max(yr[sel])) / pitch + 0.01)
    for k in range(k0, k1 + 1):
        for ax in (ax1, ax2):
            ax.axvline(math.degrees(k * pitch), color=NOISE_COLOR, lw=0.8, ls=":")
    ax2.plot([], [], color=NOISE_COLOR, lw=0.8, ls=":", label="pole-pair boundary")
    ax2.set_ylabel("angle error [mrad]")
    ax2.set_xlabel("true mechanical angle y₀ [deg]")
    _legend_above(ax2, ncols=3)
    return fig


def plot_hall_model(
    d: ArrayLike,
    d_model: ArrayLike,
    *,
    t: ArrayLike | None = None,
    sensor: int = 1,
    window: tuple[float, float] | None = None,
    noise_variance: float | None = None,
    model_label: str = "model ĝ(y₀_sim)",
) -> Figure:
    """Measured Hall signal with the identified model (Figs. 4 and 6).

    Top: the measured ``d_h(t_k)`` (blue) and the model ``g_h,theta*(y0_sim(t_k))`` (red dashed)
    over a window of several magnets. Bottom: the residual ``d_h - d_model`` over the whole
    record, with +-2 sigma of the Hall noise when it is known; a model that explains the data
    leaves white noise at that level.

    Parameters
    ----------
    d : array_like (N, 3)
        Measured Hall signals.
    d_model : array_like (N, 3)
        The model's signals on the same samples, e.g. ``SEMResult.d_sim`` (the model evaluated at
        the simulated angle y0_sim).
    t : array_like (N,), optional
        Time [s]; default: the sample index.
    sensor : {1, 2, 3}
        Which Hall signal to show.
    window : (float, float), optional
        Time span of the top panel (in the units of ``t``); default: the middle quarter.
    noise_variance : float, optional
        Hall noise variance sigma^2 per channel, for the +-2 sigma lines.
    model_label : str
        Legend label of the model.

    Returns
    -------
    matplotlib.figure.Figure
    """
    D = np.asarray(d, dtype=np.float64)
    M = np.asarray(d_model, dtype=np.float64)
    if D.ndim != 2 or D.shape[1] != 3 or M.shape != D.shape:
        raise ValueError(f"d and d_model must both have shape (N, 3); got {D.shape}, {M.shape}")
    if sensor not in (1, 2, 3):
        raise ValueError("sensor must be 1, 2 or 3")
    h = sensor - 1
    n = D.shape[0]
    if t is None:
        tt = np.arange(n, dtype=np.float64)
        xlabel = "sample k"
    else:
        tt = _vec(t, "t")
        xlabel = "time t [s]"
    if window is None:
        window = (float(tt[int(0.375 * (n - 1))]), float(tt[int(0.625 * (n - 1))]))
    sel = (tt >= window[0]) & (tt <= window[1])
    res = D[:, h] - M[:, h]
    rms = float(np.sqrt(np.mean(res**2)))
    fig, (ax1, ax2) = _figure(2, 5.6, sharex=False, ratios=(1.5, 1))
    ax1.plot(tt[sel], D[sel, h], color=INIT_COLOR, lw=0.8, label=f"measured d{sensor}")
    ax1.plot(tt[sel], M[sel, h], color=MODEL_COLOR, lw=1.4, ls="--", label=model_label)
    _title(fig, f"Hall signal d{sensor} and identified flux model (cf. the paper's Figs. 4 and 6)")
    _finish(ax1, xlabel, f"Hall signal d{sensor} [as recorded]", ncols=2)
    ax2.plot(tt, res, color="#8fb8dc", lw=0.4, rasterized=True, label=f"residual (RMS {rms:.3g})")
    ax2.axvspan(window[0], window[1], color=_ACCENT, alpha=0.12, lw=0, label="window above")
    if noise_variance is not None and noise_variance > 0:
        s = math.sqrt(noise_variance)
        _level_lines(ax2, s, 2, lw=1.1, label=f"±2σ Hall noise (σ = {s:.3g})")
    _finish(ax2, xlabel, f"residual d{sensor} − model", ncols=3)
    return fig


def plot_angle_error(
    y_ref: ArrayLike,
    y_init: ArrayLike,
    y_star: ArrayLike | None = None,
    *,
    noise_floor: float | None = None,
    reference_label: str = "true angle y₀",
) -> Figure:
    """Angle error of f_init (blue) and f_star (red) over the angle (Figs. 5 and 7).

    Errors are shown about their mean, as :func:`hallcal.sensor.metrics.angle_error` measures them
    (a constant offset of the angle origin is not a reconstruction error); the legend gives the RMS
    and peak. Dashed lines at +-3 times the noise floor: white noise alone stays inside.

    Parameters
    ----------
    y_ref : array_like (N,)
        True angle or encoder angle [rad] (validation only).
    y_init : array_like (N,)
        f_init output [rad].
    y_star : array_like (N,), optional
        f_star output [rad]; absent when the table is not bijective.
    noise_floor : float, optional
        RMS angle error of white Hall noise alone [rad].
    reference_label : str
        What ``y_ref`` is, for the axis label.

    Returns
    -------
    matplotlib.figure.Figure
    """
    yr, yi = _vec(y_ref, "y_ref"), _vec(y_init, "y_init")
    x = _deg(yr)
    fig, (ax,) = _figure(1, 4.2)
    errors = [("f_init", INIT_COLOR, _centred(yi - yr))]
    if y_star is not None:
        errors.append(("f_star", STAR_COLOR, _centred(_vec(y_star, "y_star") - yr)))
    for name, color, e in errors:
        rms, peak = 1e3 * np.sqrt(np.mean(e**2)), 1e3 * np.max(np.abs(e))
        label = f"{name}: RMS {rms:.3f} mrad, peak {peak:.3f} mrad"
        ax.plot(x, _mrad(e), color=color, lw=0.6, rasterized=True, label=label)
    if noise_floor is not None and noise_floor > 0:
        nf = 1e3 * noise_floor
        _level_lines(ax, nf, 3, lw=1.0, label=f"±3 × noise floor (floor {nf:.3f} mrad RMS)")
    _title(fig, "Angle error before and after calibration (cf. the paper's Figs. 5 and 7)")
    _finish(ax, f"{reference_label} [deg] (mechanical)", "angle error − mean [mrad]", ncols=2)
    return fig


def plot_error_spectrum(
    validation: Validation,
    *,
    pole_pairs: int,
    noise_floor: float | None = None,
    log: bool = True,
) -> Figure:
    """Cumulative PSD of the angle error over spatial frequency (Fig. 8).

    Steps of the f_init curve at the pole-pair harmonic n_m (and its multiples) are the
    magnet-pitch errors the calibration removes; white noise alone makes the cumulative power
    grow in proportion to frequency up to the square of the noise floor.

    Parameters
    ----------
    validation : Validation
        ``spectrum_init`` and ``spectrum_star`` (:class:`hallcal.sensor.metrics.SpatialSpectrum`).
    pole_pairs : int, keyword-only
        n_m, marked with its first multiples.
    noise_floor : float, optional
        RMS angle error of white noise alone [rad]; its square is marked.
    log : bool
        Logarithmic power axis (default; the paper's linear axis hides the calibrated curve).

    Returns
    -------
    matplotlib.figure.Figure
    """
    si, ss = validation.spectrum_init, validation.spectrum_star
    fig, (ax,) = _figure(1, 4.2)
    unit = 1e6  # rad^2 -> mrad^2
    for name, color, sp in (("f_init", INIT_COLOR, si), ("f_star", STAR_COLOR, ss)):
        label = f"{name} (total {unit * sp.cumulative[-1]:.3g} mrad²)"
        ax.step(sp.frequency, unit * sp.cumulative, where="post", color=color, lw=1.4, label=label)
    fmax = float(max(si.frequency[-1], ss.frequency[-1]))
    fmin = float(min(si.frequency[0], ss.frequency[0]))
    for k in range(1, 6):
        f = k * pole_pairs
        if f > fmax:
            break
        ax.axvline(
            f,
            color=TRUTH_COLOR if k == 1 else NOISE_COLOR,
            lw=1.0 if k == 1 else 0.6,
            ls=":",
            label=f"n_m = {pole_pairs} and multiples" if k == 1 else None,
        )
        if k == 1:
            ax.annotate(
                f"n_m = {f}",
                xy=(f, 0.5),
                xycoords=("data", "axes fraction"),
                xytext=(-4, 0),
                textcoords="offset points",
                ha="right",
                rotation=90,
                fontsize="small",
            )
    if noise_floor is not None and noise_floor > 0:
        ax.axhline(
            unit * noise_floor**2,
            color=NOISE_COLOR,
            lw=1.0,
            ls="--",
            label=f"noise floor² ({unit * noise_floor**2:.3g} mrad²)",
        )
    ax.set_xscale("log")
    ax.set_xlim(fmin, fmax)
    log_axis(ax.xaxis, fmin, fmax)
    if log:
        ax.set_yscale("log")
        both = unit * np.concatenate([si.cumulative, ss.cumulative])
        both = both[both > 0]
        if both.size:
            log_axis(ax.yaxis, float(both.min()), float(both.max()))
    ax.set_xlabel("spatial frequency [cycles/rev]")
    ax.set_ylabel("cumulative PSD of the error [mrad²]")
    revs = f"{si.revolutions:.3g} revolution" + ("" if si.revolutions == 1 else "s")
    _title(fig, f"Cumulative PSD of the angle error over {revs} (cf. the paper's Fig. 8)")
    _legend(ax, loc="lower right")
    return fig


# ------------------------------------------------------------------------------------------------
# Diagnostics
# ------------------------------------------------------------------------------------------------


def _zoh(f: NDArray[np.float64], ts: float) -> NDArray[np.complex128]:
    x = 2j * np.pi * f * ts
    out = np.ones(x.shape, dtype=np.complex128)
    nz = x != 0
    out[nz] = -np.expm1(-x[nz]) / x[nz]
    return out


def _db(x: NDArray) -> NDArray[np.float64]:
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(np.abs(x))


def _phase_like(phase: NDArray[np.float64], ref: float) -> NDArray[np.float64]:
    """Shift an unwrapped phase [deg] by whole turns so that it starts near ``ref``."""
    return phase - 360.0 * np.round((phase[0] - ref) / 360.0)


def _running_median(
    f: NDArray[np.float64], x: NDArray[np.float64], factor: float = 1.5
) -> NDArray[np.float64]:
    """Median of ``x`` over the lines within a factor ``factor`` of each frequency ``f``.

    A variance estimate from M realizations scatters by about sqrt(1 / (M - 1)) per line; the
    median over neighbouring lines (on the log-frequency axis of a Bode plot) shows the level.
    """
    out = np.full(x.shape, np.nan)
    for i, fi in enumerate(f):
        window = x[(f >= fi / factor) & (f <= fi * factor)]
        window = window[np.isfinite(window)]
        if window.size:
            out[i] = float(np.median(window))
    return out


def plot_bla(
    bla: BLAIdentification,
    *,
    true_plant: ContinuousTF | None = None,
    corrected_plant: ContinuousTF | None = None,
    gain_correction: float | None = None,
) -> Figure:
    """Closed-loop BLA of the plant: magnitude and phase (section "Obtaining a BLA").

    The nonparametric BLA at the excited lines (dots) with two standard deviations of the
    estimate (Pintelon & Schoukens 2012, sec. 3.8), each with its running median (over the lines
    within a factor 1.5 in frequency):
    from the spread between realizations (the total, used as the fit's weights) and from the
    spread between the periods of a realization (the noise). In theory the total is the noise plus
    the stochastic nonlinear distortion, but the two estimates do not obey that ordering here:

    * with M realizations the total variance has 2 (M - 1) degrees of freedom (scatter of about
      38 % per line for M = 8), so single lines fall below the noise even for a linear plant;
    * in closed loop the noise is not periodic and each period's DFT carries the leakage of the
      loop's state at its boundaries; consecutive periods share a boundary, so these terms cancel
      in a realization's mean but inflate the period-to-period spread, up to (P + 1) times for P
      periods where the loop suppresses the steady-state noise, i.e. at low frequencies (measured
      on the paper's loop with ideal sensors: total / noise 0.2 below 5 Hz, 1.0 above 10 Hz);
    * with f_init feedback the position-dependent sensor error, swept by the slow ramp under the
      multisine, changes coherently from period to period (the rotor advances ``drift *
      period`` between periods) and largely cancels in a realization's mean (measured on the
      demo's bench: total / noise 0.3-0.9 across the band).

    The total is therefore the trustworthy uncertainty of the BLA (and is what the fit uses); the
    period-to-period curve is an upper bound on the noise. The parametric fit G_BLA; optionally
    the model after the gain correction c_hat
    (the gain correction c-hat) and the true plant. Continuous models are shown with the
    zero-order-hold factor
    of the sampled input, like the nonparametric estimate.

    Parameters
    ----------
    bla : BLAIdentification
        ``nonparametric`` (freq, G, var_noise, var_total) and ``parametric``.
    true_plant : ContinuousTF, optional
        The true G(s) (virtual bench).
    corrected_plant : ContinuousTF, optional
        The plant used in SEM (the BLA after the gain correction of the gain correction c-hat).
    gain_correction : float, optional
        c_hat, for the legend; without ``corrected_plant``, ``bla.plant.scaled(c_hat)`` is drawn.

    Returns
    -------
    matplotlib.figure.Figure
    """
    npb = bla.nonparametric
    f = np.asarray(npb.freq, dtype=np.float64)
    G = np.asarray(npb.G, dtype=np.complex128)
    fd = np.geomspace(max(float(f.min()), 1e-3), float(f.max()), 400)
    fig, (axm, axp) = _figure(2, 6.0, ratios=(1.4, 1))
    vt = _bla_magnitude_points(axm, npb, f, G)
    ref = _bla_phase_points(axp, f, G, vt)
    if corrected_plant is None and gain_correction is not None:
        corrected_plant = bla.plant.scaled(float(gain_correction))
    _bla_models(axm, axp, bla, fd, ref, corrected_plant, gain_correction, true_plant)
    axm.set_ylabel("magnitude [dB]")
    _title(
        fig,
        f"Closed-loop BLA of the plant: {npb.realizations} realizations × {npb.periods} "
        "steady-state periods (the paper's BLA section)",
    )
    _legend(axm, loc="upper right")
    axp.set_ylabel("phase [deg]")
    axp.set_xlabel("frequency [Hz]")
    axp.yaxis.set_major_locator(MaxNLocator(nbins=6, steps=[1, 2, 4.5, 9, 10]))
    for a in (axm, axp):
        log_axis(a.xaxis, float(fd[0]), float(fd[-1]))
    _legend(axp, loc="lower left")
    return fig


def _bla_magnitude_points(
    axm: Axes, npb: NonparametricBLA, f: NDArray[np.float64], G: NDArray[np.complex128]
) -> NDArray[np.float64]:
    """|Ĝ| at the excited lines and its two standard deviations (each with its running
    median); returns the total variance (realization to realization)."""
    axm.semilogx(f, _db(G), "o", ms=3.5, color=INIT_COLOR, label="nonparametric BLA Ĝ")
    vt = np.asarray(npb.var_total, dtype=np.float64)
    vn = np.asarray(npb.var_noise, dtype=np.float64)
    total = "std of Ĝ from realization to realization (total; the fit's weights)"
    spreads = (
        (vt, "s", {"ms": 3, "mfc": "none", "color": _ACCENT, "label": total}),
        (
            vn,
            ".",
            {"ms": 4, "color": NOISE_COLOR, "label": "std of Ĝ from period to period (noise)"},
        ),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        for v, marker, style in spreads:
            if np.any(np.isfinite(v)):
                axm.semilogx(f, 10 * np.log10(v), marker, **style)
                axm.semilogx(f, 10 * np.log10(_running_median(f, v)), color=style["color"], lw=1.0)
    return vt


def _bla_phase_points(
    axp: Axes, f: NDArray[np.float64], G: NDArray[np.complex128], vt: NDArray[np.float64]
) -> float:
    """The phase of Ĝ with a band of two standard deviations; returns its first value [deg]."""
    ph = np.degrees(np.unwrap(np.angle(G)))
    axp.semilogx(f, ph, "o", ms=3.5, color=INIT_COLOR)
    # shade +-2 std of the phase from the total variance: std(angle) ~ std(G) / |G|
    with np.errstate(divide="ignore", invalid="ignore"):
        dph = np.degrees(2 * np.sqrt(vt) / np.abs(G))
    ok = np.isfinite(dph)
    if np.any(ok):
        axp.fill_between(
            f[ok],
            (ph - dph)[ok],
            (ph + dph)[ok],
            color=_ACCENT,
            alpha=0.2,
            lw=0,
            label="±2 std (realization to realization)",
        )
    return float(ph[0])


def _bla_models(
    axm: Axes,
    axp: Axes,
    bla: BLAIdentification,
    fd: NDArray[np.float64],
    ref: float,
    corrected_plant: ContinuousTF | None,
    gain_correction: float | None,
    true_plant: ContinuousTF | None,
) -> None:
    """The parametric fit, the plant after the gain correction and the true plant on the
    dense grid ``fd``, phases shifted by whole turns to start near ``ref``."""
    par = bla.parametric
    hold = getattr(par, "hold", "none") == "zoh" and getattr(par, "sample_time", None)
    g_fit = par.frequency_response(fd, zoh=bool(hold))
    curves: list[tuple[Any, dict[str, object]]] = [
        (g_fit, {"color": STAR_COLOR, "lw": 1.6, "label": "parametric fit"})
    ]
    if corrected_plant is not None:
        label = "after gain correction" + (
            "" if gain_correction is None else f" (ĉ = {float(gain_correction):.4g})"
        )
        curves.append((corrected_plant, {"color": _ACCENT, "ls": "-.", "label": label}))
    if true_plant is not None:
        curves.append((true_plant, {"color": TRUTH_COLOR, "ls": "--", "label": "true plant G"}))
    ts = float(bla.nonparametric.sample_time)
    for model, style in curves:
        if not isinstance(model, np.ndarray):  # a continuous model, seen through the hold
            model, style = model.frequency_response(fd) * _zoh(fd, ts), {"lw": 1.2, **style}
        axm.semilogx(fd, _db(model), **style)
        axp.semilogx(fd, _phase_like(np.degrees(np.unwrap(np.angle(model))), ref), **style)


def plot_sem_cost(sem: SEMResult, *, noise_variance: float | None = None) -> Figure:
    """SEM cost J(theta) per Levenberg-Marquardt iteration (the SEM problem), log scale.

    With white Hall noise of variance sigma^2 on 3 channels and N samples, a model that explains
    the data reaches ``J ~ (3 N - p) sigma^2 ~ 3 N sigma^2``, marked as the expected noise level.

    Parameters
    ----------
    sem : SEMResult
        ``cost_history`` (start and accepted iterations), ``n_samples``, ``noise_variance``.
    noise_variance : float, optional
        The true sigma^2 when known (virtual bench); default: the estimate from the residual.

    Returns
    -------
    matplotlib.figure.Figure
    """
    cost = np.asarray(sem.cost_history, dtype=np.float64)
    it = np.arange(cost.size)
    fig, (ax,) = _figure(1, 3.8)
    ax.semilogy(it, cost, "o-", color=STAR_COLOR, lw=1.4, ms=6, label="cost J(θ)")
    for i, c in zip(it, cost, strict=True):
        ax.annotate(f"{c:.4g}", (i, c), xytext=(6, 6), textcoords="offset points", fontsize="small")
    if noise_variance is not None:
        s2, which = float(noise_variance), "true"
    else:
        s2, which = float(sem.noise_variance), "estimated"
    if math.isfinite(s2) and s2 > 0:
        level = 3 * sem.n_samples * s2
        ax.axhline(
            level,
            color=NOISE_COLOR,
            ls="--",
            lw=1.2,
            label=f"noise level 3Nσ² = {level:.4g} ({which} σ² = {s2:.3g} (Hall signal unit)²)",
        )
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    finite = cost[np.isfinite(cost) & (cost > 0)]
    if finite.size:
        lo, hi = float(finite.min()), float(finite.max())
        if math.isfinite(s2) and s2 > 0:
            lo, hi = min(lo, 3 * sem.n_samples * s2), max(hi, 3 * sem.n_samples * s2)
        log_axis(ax.yaxis, lo, hi)
    ax.set_xlabel("iteration")
    ax.set_ylabel("cost J(θ) = Σ ‖d − d_sim‖² [(Hall signal unit)²]")
    _title(
        fig,
        f"SEM cost: {sem.iterations} iteration{'' if sem.iterations == 1 else 's'}, "
        f"'{sem.status}', {sem.solve_time:.2f} s "
        "(the paper's SEM problem)",
    )
    ax.margins(x=0.08, y=0.25)
    _legend(ax, loc="upper right")
    return fig


def plot_lut(
    lut: LUT,
    *,
    eta_std: ArrayLike | None = None,
    true_lut: LUT | None = None,
) -> Figure:
    """Lookup-table correction eta over the angle with its +-2 sigma band (f_star = f_init + eta).

    The band is the first-order uncertainty of eta implied by cov(theta)
    (:func:`hallcal.fit.sem.predicted_angle_error`). When a second panel is drawn it shows the band
    around zero on its own scale and, on the virtual bench, the error of the identified table
    against the true one, which should stay mostly inside the band.

    Parameters
    ----------
    lut : LUT
        y0 grid and eta [rad].
    eta_std : array_like, optional
        Standard deviation of eta [rad] on a uniform grid over one revolution (any length).
    true_lut : LUT, optional
        The table computed from the true flux (virtual bench).

    Returns
    -------
    matplotlib.figure.Figure
    """
    y0 = np.asarray(lut.y0, dtype=np.float64)
    eta = np.asarray(lut.eta, dtype=np.float64)
    sd = None
    if eta_std is not None:
        s = np.asarray(eta_std, dtype=np.float64)
        grid = TWO_PI * np.arange(s.size) / s.size
        sd = np.interp(np.mod(y0, TWO_PI), grid, s, period=TWO_PI)
    eta_true = None
    if true_lut is not None:
        eta_true = np.interp(
            np.mod(y0, TWO_PI), np.mod(true_lut.y0, TWO_PI), true_lut.eta, period=TWO_PI
        )
    two = sd is not None or eta_true is not None
    fig, axes = _figure(2 if two else 1, 6.0 if two else 3.8, ratios=(1.5, 1) if two else None)
    ax = axes[0]
    x = _deg(y0)
    bij = "bijective" if lut.bijective else "NOT bijective"
    ax.plot(x, _mrad(eta), color=STAR_COLOR, lw=1.2, label="identified η")
    if sd is not None:
        _band(ax, x, _mrad(eta - 2 * sd), _mrad(eta + 2 * sd), "±2σ from cov(θ)")
    if eta_true is not None:
        ax.plot(x, _mrad(eta_true), color=TRUTH_COLOR, lw=0.9, ls="--", label="true η")
    ax.set_ylabel("η [mrad]")
    _title(
        fig,
        "Lookup table η(y₀) = y₀ − f_init(g_θ(y₀)) (the paper's table correction f_star)\n"
        f"{lut.points} points, {bij} (min slope of y₀ → ŷ: {lut.min_slope:.3g})",
    )
    ax.margins(x=0)
    _legend_above(ax, ncols=3)
    if two:
        ax2 = axes[1]
        if sd is not None:
            _band(ax2, x, -2e6 * sd, 2e6 * sd, "±2σ band")
        if eta_true is not None:
            diff = eta - eta_true
            offset = float(np.mean(diff))
            dc = diff - offset
            ax2.plot(
                x,
                1e6 * dc,
                color=TRUTH_COLOR,
                lw=0.9,
                label=f"identified − true η, about its mean (RMS {1e6 * np.std(dc):.3g} µrad; "
                f"mean {1e6 * offset:.3g} µrad = angle-origin offset)",
            )
        ax2.axhline(0.0, color=NOISE_COLOR, lw=0.6)
        _finish(ax2, None, "uncertainty [µrad]", ncols=2)
    axes[-1].set_xlabel("mechanical angle y₀ [deg]")
    return fig


def plot_cogging(
    cogging: CoggingTorque,
    *,
    true_cogging: CoggingTorque | None = None,
    points: int = 2048,
) -> Figure:
    """The cogging map T_c(y0) identified jointly with the flux, with its +-2 sigma band.

    ``T_c(y0) = sum_k a_k cos(k y0) + b_k sin(k y0)`` in plant input units (the unit of the
    torque command: firmware subtracts it as a feed-forward). The band is ``2 std T_c(y0)`` from
    the covariance of the coefficients (:meth:`CoggingTorque.std`, exact for a torque linear in
    its coefficients). Panels: the map over one revolution; one period of the lowest order; the
    band on its own scale around zero with, on the virtual bench, the error of the identified
    map (which should stay mostly inside it).

    Parameters
    ----------
    cogging : CoggingTorque
        The identified torque (with its covariance for the band).
    true_cogging : CoggingTorque, optional
        The virtual bench's torque, drawn black dashed.
    points : int
        Samples per revolution.

    Returns
    -------
    matplotlib.figure.Figure
    """
    k_low = min((k for k in cogging.orders if k > 0), default=1)  # order 0: a constant load
    y = TWO_PI * np.arange(points) / points
    zoom = np.linspace(0.0, TWO_PI / k_low, 400)
    has_band = cogging.covariance is not None
    third = has_band or true_cogging is not None
    fig, axes = _figure(3 if third else 2, 8.0 if third else 6.0, sharex=False)
    for ax, yy in zip(axes[:2], (y, zoom), strict=True):
        t = cogging(yy)
        ax.plot(_deg(yy), t, color=STAR_COLOR, lw=1.0, label="identified T_c(y₀)")
        if has_band:
            sd = cogging.std(yy)
            _band(ax, _deg(yy), t - 2 * sd, t + 2 * sd, "±2σ from the covariance")
        if true_cogging is not None:
            ax.plot(_deg(yy), true_cogging(yy), color=TRUTH_COLOR, lw=0.9, ls="--",
                    label="true T_c(y₀)")  # fmt: skip
        ax.axhline(0.0, color=NOISE_COLOR, lw=0.6)
        ax.set_ylabel("torque [plant input]")
        ax.margins(x=0)
    axes[0].set_xlabel("mechanical angle y₀ [deg]")
    axes[1].set_xlabel(f"mechanical angle y₀ [deg], one period of order {k_low}")
    _legend_above(axes[0], ncols=3)
    if third:
        ax3 = axes[2]
        if has_band:
            sd = cogging.std(y)
            _band(ax3, _deg(y), -2 * sd, 2 * sd, "±2σ band")
        if true_cogging is not None:
            err = cogging(y) - true_cogging(y)
            ax3.plot(_deg(y), err, color=TRUTH_COLOR, lw=0.8,
                     label=f"identified − true (RMS {np.sqrt(np.mean(err**2)):.3g})")  # fmt: skip
        ax3.axhline(0.0, color=NOISE_COLOR, lw=0.6)
        _finish(ax3, "mechanical angle y₀ [deg]", "uncertainty [plant input]", ncols=2)
    terms = ", ".join(
        f"{k}/rev: {A:.3g} at {math.degrees(ph):.1f}°"
        for k, A, ph in zip(cogging.orders, cogging.amplitude, cogging.phase, strict=True)
    )
    _title(fig, f"Cogging torque T_c(y₀) = Σ A_k cos(k y₀ − φ_k)\n{terms}")
    return fig


def plot_correction(
    y_init: ArrayLike,
    y_star: ArrayLike,
    *,
    pole_pairs: int | None = None,
) -> Figure:
    """The correction f_star - f_init = eta(f_init) applied along a recording.

    Encoder-free: without a reference angle this is the size and shape of the error the
    calibration attributes to f_init.

    Parameters
    ----------
    y_init, y_star : array_like (N,)
        f_init and f_star outputs [rad].
    pole_pairs : int, optional
        n_m, for the title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    yi, ys = _vec(y_init, "y_init"), _vec(y_star, "y_star")
    corr = ys - yi
    fig, (ax,) = _figure(1, 3.8)
    ax.plot(
        _deg(ys),
        _mrad(corr),
        color=STAR_COLOR,
        lw=0.8,
        rasterized=True,
        label=f"f_star − f_init: RMS about mean "
        f"{1e3 * np.std(corr):.3f} mrad, peak {1e3 * np.max(np.abs(corr)):.3f} mrad",
    )
    extra = "" if pole_pairs is None else f", {pole_pairs} pole pairs"
    _title(fig, f"Correction applied along the recording (no encoder needed){extra}")
    _finish(ax, "calibrated angle f_star [deg] (mechanical)", "correction [mrad]", ncols=1)
    return fig
