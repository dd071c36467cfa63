"""The calibration report: figures and a self-contained HTML page (``hallcal report``, ``demo``).

Compute first, plot separately: :func:`content_from_calibration` (in memory, after
:func:`hallcal.pipeline.calibrate`) and :func:`content_from_artifact` (from a JSON artifact and
the calibration recording) gather everything the report shows into a :class:`ReportContent`;
:func:`make_figures` turns it into figures with :mod:`hallcal.output.plots`; :func:`write_report`
writes the PNG files and one HTML file with the figures embedded as base64 PNG, inline CSS, no
scripts and no external references, so it opens in a browser without network access.

The report follows the paper's results sections (van Meer et al., Figs. 2 and 4-8) and adds
the diagnostics of each step of Algorithm 1: the BLA, the SEM cost, and the lookup table with its
uncertainty band. Errors against an encoder are only
shown when a recording has the ``y_ref`` column (validation only, never used by calibration);
without one the report says so and shows what needs no encoder: the model fit, the table, the
cost and the correction f_star - f_init. For an open-loop (constant-speed) calibration the
straight-line check stands in for the encoder: f_init and f_star against their best straight line
on the constant-speed samples the calibration did not use. Angle errors are in mechanical mrad or,
with ``angle_units="electrical-deg"``, in electrical degrees.
"""

from __future__ import annotations

import base64
import dataclasses
import datetime as _dt
import html
import io as _io
import math
import os
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hallcal._version import __version__
from hallcal.errors import HallcalInputError
from hallcal.io import (
    Dataset,
    Setup,
    atomic_write,
    read_artifact,
    read_dataset,
    read_json,
    setup_from_dict,
    setup_to_toml,
)
from hallcal.pipeline.calibration import Calibration
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sim.lti import ContinuousTF

__all__ = [
    "ReportContent",
    "ReportFigure",
    "content_from_artifact",
    "content_from_calibration",
    "make_figures",
    "render_html",
    "write_calibration_report",
    "write_demo_report",
    "write_report",
    "write_report_from_files",
]

Progress = Callable[[str], None] | None
TWO_PI = 2.0 * math.pi
REPORT_NAME = "report.html"
FIGURE_DIR = "figures"
_DPI = 120


def _say(progress: Progress, message: str) -> None:
    if progress is not None:
        progress(message)


# ------------------------------------------------------------------------------------------------
# What a report shows
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Traces:
    """Per-sample angles of one recording [rad]: f_init, f_star and (when logged) the reference.

    Attributes
    ----------
    y_init : ndarray (N,)
    y_star : ndarray (N,) or None
        None when the table is not bijective.
    y_ref : ndarray (N,) or None
        Encoder or true angle.
    """

    y_init: NDArray[np.float64] = field(repr=False)
    y_star: NDArray[np.float64] | None = field(repr=False)
    y_ref: NDArray[np.float64] | None = field(repr=False, default=None)


@dataclass(frozen=True)
class ReportContent:
    """Everything a report shows, already computed.

    Attributes
    ----------
    title : str
    setup : Setup
    lut : LUT
    flux : FluxModel
        Identified g_theta*.
    sem : SEMResult or None
        The SEM solve (in memory) or its reconstruction from an artifact (cost history from the
        artifact, d_sim and y0_sim re-simulated, covariance recomputed).
    bla : BLAIdentification or None
    plant : ContinuousTF or None
        Plant used in SEM (after the gain correction).
    gain_correction : float or None
        The gain correction c-hat as applied to the BLA (refined jointly with theta when it was).
    gain_details : dict or None
        ``c`` (the gain correction c-hat), ``c_refined``, ``c_refined_std`` and the rest of the gain
        report.
    predicted_error : float or None
        Predicted RMS error of f_star [rad].
    noise_floor : float or None
        RMS angle error of Hall noise alone [rad].
    noise_floor_source : str
    status : str
    messages : list of str
    adequacy : dict or None
        ``verdict``, ``message`` and anything else the adequacy report gives.
    t : ndarray (N,) or None
        Time of the calibration recording [s].
    d : ndarray (N, 3)
        Hall signals of the calibration recording.
    d_model : ndarray (N, 3) or None
        The model's signals on the same samples.
    d_model_label : str
    calibration : Traces
        f_init / f_star on the calibration recording.
    validation : Validation or None
        Errors against the reference (see ``validation_source``).
    validation_traces : Traces or None
    validation_source : str or None
    eta_std : ndarray or None
        std of eta on a uniform grid over one revolution [rad].
    true_lut : LUT or None
        The table of the true flux (virtual bench only).
    true_plant : ContinuousTF or None
    true_noise_variance : float or None
    sources : dict of str to str
        Input files (or "in memory") by role.
    notes : list of str
        What could not be shown, and why.
    timings : dict of str to float
    model_info : dict
    hall_noise_variance : float or None
        Hall noise variance per channel from the calibration (constant speed: from the residual),
        for the ±2σ lines when there is no SEM.
    constant_speed : dict or None
        The constant-speed fit's summary (``diagnostics.constant_speed`` of the artifact).
    straight_line : StraightLineCheck or None
        f_init and f_star against a straight line on held-out constant-speed samples.
    angle_units : {"mrad", "electrical-deg"}
        Units of the angle errors in the text.
    cogging : CoggingTorque or None
        The cogging torque identified with the flux (with the covariance of its coefficients).
    true_cogging : CoggingTorque or None
        The virtual bench's cogging torque.
    """

    title: str
    setup: Setup
    lut: LUT
    flux: FluxModel
    sem: Any
    bla: Any
    plant: ContinuousTF | None
    gain_correction: float | None
    gain_details: dict[str, Any] | None
    predicted_error: float | None
    noise_floor: float | None
    noise_floor_source: str
    status: str
    messages: list[str]
    adequacy: dict[str, Any] | None
    t: NDArray[np.float64] | None = field(repr=False)
    d: NDArray[np.float64] = field(repr=False)
    d_model: NDArray[np.float64] | None = field(repr=False)
    d_model_label: str
    calibration: Traces = field(repr=False)
    validation: Any = None
    validation_traces: Traces | None = field(repr=False, default=None)
    validation_source: str | None = None
    eta_std: NDArray[np.float64] | None = field(repr=False, default=None)
    true_lut: LUT | None = field(repr=False, default=None)
    true_plant: ContinuousTF | None = None
    true_noise_variance: float | None = None
    sources: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    model_info: dict[str, Any] = field(default_factory=dict)
    hall_noise_variance: float | None = None
    constant_speed: dict[str, Any] | None = None
    straight_line: StraightLineCheck | None = None
    angle_units: str = "mrad"
    cogging: Any = None
    true_cogging: Any = None

    @property
    def pole_pairs(self) -> int:
        return int(self.setup.pole_pairs)

    def angle(self, x: float | None) -> str:
        """An angle error [rad, mechanical] in this report's units."""
        if x is None or not math.isfinite(x):
            return "–"
        if self.angle_units == "electrical-deg":
            return f"{math.degrees(x) * self.pole_pairs:.3f} electrical deg"
        return f"{1e3 * x:.3f} mrad"


@dataclass(frozen=True)
class StraightLineCheck:
    """f_init and f_star against their best straight line on constant-speed samples.

    Without an encoder this is the check of an open-loop calibration (as in
    ``tests/test_real_ringjig.py``): on samples of the constant-speed window that the
    calibration did not use, the true angle is a straight line in the sample index, so the
    residual of the best line through f_star is an upper bound of its error (rig motion included).

    Attributes
    ----------
    start, stop : int
        The held-out samples ``start <= k < stop``.
    revolutions : float
        Revolutions in them.
    init_rms, star_rms : float
        RMS residual of the best straight line through f_init and through f_star [rad].
    held_out : bool
        False when no samples were left over and the calibration samples themselves are used.
    """

    start: int
    stop: int
    revolutions: float
    init_rms: float
    star_rms: float
    held_out: bool


def _line_rms(y: NDArray[np.float64]) -> float:
    k = np.arange(y.size, dtype=np.float64)
    coef = np.polyfit(k, y, 1)
    return float(np.sqrt(np.mean((y - np.polyval(coef, k)) ** 2)))


#: Shortest held-out stretch for the straight-line check [revolutions].
_MIN_HELD_OUT_REVOLUTIONS = 0.5


def _straight_line(
    cs: Mapping[str, Any], lut: LUT, data: Dataset, traces: Traces
) -> StraightLineCheck | None:
    """The straight-line check on the constant-speed samples after the calibration segment."""
    from hallcal.fit.constant_speed import find_constant_speed

    if traces.y_star is None:
        return None
    try:
        start, stop = int(cs["start"]), int(cs["stop"])
        speed = abs(float(cs["b"]))
    except (KeyError, TypeError, ValueError):
        return None
    window = find_constant_speed(np.asarray(data.d), lut.pole_pairs)
    end = min(window.stop, data.n_samples) if window.ok else stop
    held = end > stop and speed * (end - stop) / TWO_PI >= _MIN_HELD_OUT_REVOLUTIONS
    a, b = (stop, end) if held else (start, stop)
    if b - a < 8:
        return None
    return StraightLineCheck(
        start=a,
        stop=b,
        revolutions=speed * (b - a) / TWO_PI,
        init_rms=_line_rms(traces.y_init[a:b]),
        star_rms=_line_rms(traces.y_star[a:b]),
        held_out=held,
    )


def _constant_speed_parts(
    cs: Any, lut: LUT, data: Dataset, traces: Traces
) -> tuple[dict[str, Any] | None, float | None, StraightLineCheck | None]:
    """Summary, Hall noise variance and straight-line check of a constant-speed calibration."""
    if cs is None:
        return None, None, None
    summary = dict(cs.to_dict()) if hasattr(cs, "to_dict") else dict(cs)
    noise = summary.get("noise_std")
    variance = float(noise) ** 2 if isinstance(noise, int | float) and noise > 0 else None
    return summary, variance, _straight_line(summary, lut, data, traces)


def _amplitude(flux: FluxModel, n_m: int) -> float:
    """Fundamental amplitude of the model (electrical harmonic n_m), mean over the sensors."""
    if n_m in flux.basis.harmonics:
        js, jc = flux.basis.index(n_m)
        return float(np.mean(np.hypot(flux.theta[:, js], flux.theta[:, jc])))
    y0 = TWO_PI * np.arange(1024) / 1024
    return float(np.mean(np.std(flux(y0), axis=0)) * math.sqrt(2.0))


def _estimated_floor(noise_variance: float | None, flux: FluxModel, n_m: int) -> float | None:
    """sigma sqrt(2/3) / (A n_m): the RMS angle error of white Hall noise alone (docs/design.md)."""
    if noise_variance is None or not math.isfinite(noise_variance) or noise_variance < 0:
        return None
    a = _amplitude(flux, n_m)
    if not a > 0:
        return None
    return math.sqrt(noise_variance) * math.sqrt(2.0 / 3.0) / (a * n_m)


_ESTIMATED_FLOOR = "estimated from the calibration data (model-free Hall noise level)"


def _artifact_floor(diag: Mapping[str, Any], flux: FluxModel, n_m: int) -> tuple[float | None, str]:
    """The artifact's noise floor (the calibration's own), or for artifacts written before it
    was stored, the estimate from the SEM's noise variance."""
    stored = diag.get("noise_floor")
    if isinstance(stored, int | float) and math.isfinite(stored):
        return float(stored), _ESTIMATED_FLOOR
    return (
        _estimated_floor(diag.get("noise_variance"), flux, n_m),
        "estimated from the SEM residual",
    )


def _traces(lut: LUT, dataset: Dataset) -> Traces:
    yi = lut.f_init(dataset.d)
    ys = yi + lut.correction(yi) if lut.bijective else None
    y_ref = np.asarray(dataset["y_ref"], dtype=np.float64) if "y_ref" in dataset else None
    return Traces(yi, ys, y_ref)


def _eta_std(flux: FluxModel, covariance: Any, lut: LUT) -> NDArray[np.float64] | None:
    from hallcal.fit.sem import predicted_angle_error

    if covariance is None:
        return None
    cov = np.asarray(covariance, dtype=np.float64)
    p = flux.theta.size
    if cov.shape != (p, p) or not np.all(np.isfinite(cov)):
        return None
    return predicted_angle_error(
        flux, cov, lut.pole_pairs, projection=lut.projection, offset=lut.offset, points=1024
    )


def _model_signals(sem: Any, flux: FluxModel, d: NDArray, traces: Traces) -> tuple[Any, str]:
    d_sim = getattr(sem, "d_sim", None)
    if d_sim is not None and np.shape(d_sim) == d.shape and np.all(np.isfinite(d_sim)):
        return np.asarray(d_sim, dtype=np.float64), "model ĝ(y₀_sim)"
    if traces.y_star is not None:
        return flux(traces.y_star), "model ĝ(f_star)"
    return flux(traces.y_init), "model ĝ(f_init)"


def _no_encoder_note(constant_speed: bool = False) -> str:
    shown = (
        "the straight-line check on held-out constant-speed samples, the model fit, the lookup "
        "table and the correction f_star - f_init"
        if constant_speed
        else "the model fit, the lookup table, the SEM cost and the correction f_star - f_init"
    )
    return (
        "No recording with an encoder column 'y_ref' was given: errors against an encoder are "
        f"unavailable. Shown instead: {shown}. Pass a recording with y_ref (hallcal report ... "
        "--validation RUN) to see the angle errors."
    )


def _gain_value(gain: Any) -> float | None:
    if gain is None:
        return None
    return float(getattr(gain, "value", gain.c))


def _gain_details(gain: Any) -> dict[str, Any] | None:
    if gain is None:
        return None
    if hasattr(gain, "to_dict"):
        return dict(gain.to_dict())
    return {"c": float(gain.c)}


def _adequacy_dict(adequacy: Any) -> dict[str, Any] | None:
    if adequacy is None:
        return None
    if isinstance(adequacy, Mapping):
        return dict(adequacy)
    out: dict[str, Any] = {}
    if hasattr(adequacy, "to_dict"):
        try:
            out.update(adequacy.to_dict())
        except Exception:  # noqa: BLE001 - a report must not fail on a diagnostic's serializer
            pass
    for key in ("verdict", "message"):
        if hasattr(adequacy, key):
            out[key] = getattr(adequacy, key)
    return out or None


def content_from_calibration(
    cal: Any,
    data: Dataset,
    *,
    validation_data: Dataset | None = None,
    validation: Any = None,
    noise_floor: float | None = None,
    true_flux: FluxModel | None = None,
    true_plant: ContinuousTF | None = None,
    true_noise_variance: float | None = None,
    sources: Mapping[str, str] | None = None,
    title: str = "hallcal calibration report",
    noise_floor_source: str = "given",
    true_cogging: Any = None,
) -> ReportContent:
    """Gather a report's content from an in-memory :class:`~hallcal.pipeline.Calibration`.

    Parameters
    ----------
    cal : Calibration
        Result of :func:`hallcal.pipeline.calibrate`.
    data : Dataset
        The calibration recording (for the model fit; its ``y_ref``, if any, validates when no
        ``validation_data`` is given).
    validation_data : Dataset, optional
        A fresh recording with ``y_ref`` to validate on.
    validation : Validation, optional
        Already computed errors on ``validation_data`` (recomputed when None).
    noise_floor : float, optional
        RMS angle error of Hall noise alone [rad]; default: estimated from the SEM residual.
    true_flux, true_plant, true_noise_variance, true_cogging : optional
        The virtual bench's truth, drawn for comparison.
    sources : mapping, optional
        Input names by role, listed in the report.
    title : str
    noise_floor_source : str
        Where a given ``noise_floor`` comes from, for the summary table.

    Returns
    -------
    ReportContent
    """
    from hallcal.pipeline import validate

    lut: LUT = cal.lut
    flux: FluxModel = cal.flux
    n_m = int(cal.setup.pole_pairs)
    sem = cal.sem
    d = np.asarray(data.d, dtype=np.float64)
    cal_traces = _traces(lut, data)
    notes: list[str] = []
    val_traces: Traces | None = None
    val_source: str | None = None
    if validation_data is not None:
        validation_data.require("y_ref")
        val_traces = _traces(lut, validation_data)
        val_source = (sources or {}).get("validation", validation_data.source)
        if validation is None and lut.bijective:
            validation = validate(lut, validation_data, noise_floor=noise_floor)
    elif cal_traces.y_ref is not None:
        val_traces = cal_traces
        val_source = (sources or {}).get("data", data.source) + " (the calibration recording)"
        if validation is None and lut.bijective:
            validation = validate(lut, data, noise_floor=noise_floor)
    else:
        notes.append(_no_encoder_note(cal.constant_speed is not None))
    if not lut.bijective:
        notes.append(
            "The lookup table is not bijective (the paper's bijectivity condition fails): "
            "f_star is undefined, so only f_init is shown."
        )
    floor_source = noise_floor_source
    if noise_floor is None and math.isfinite(cal.noise_floor):
        noise_floor = cal.noise_floor
        floor_source = _ESTIMATED_FLOOR
    d_model, label = _model_signals(sem, flux, d, cal_traces)
    true_lut = None
    if true_flux is not None:
        true_lut = build_lut(
            true_flux, n_m, points=lut.points, projection=lut.projection, offset=lut.offset
        )
    t = np.asarray(data["t"], dtype=np.float64) if "t" in data else None
    if t is None:
        # sample_time = 1.0 means time in samples (docs/design.md): plot over the sample index
        t = None if cal.setup.sample_time == 1.0 else cal.setup.sample_time * np.arange(d.shape[0])
    cs_summary, cs_noise, straight = _constant_speed_parts(
        cal.constant_speed, lut, data, cal_traces
    )
    return ReportContent(
        title=title,
        setup=cal.setup,
        lut=lut,
        flux=flux,
        sem=sem,
        bla=cal.bla,
        plant=cal.plant,
        gain_correction=_gain_value(cal.gain),
        gain_details=_gain_details(cal.gain),
        predicted_error=float(cal.predicted_error),
        noise_floor=noise_floor,
        noise_floor_source=floor_source,
        status=str(cal.status),
        messages=list(cal.messages),
        adequacy=_adequacy_dict(cal.adequacy),
        t=t,
        d=d,
        d_model=d_model,
        d_model_label=label,
        calibration=cal_traces,
        validation=validation,
        validation_traces=val_traces,
        validation_source=val_source,
        eta_std=None if sem is None else _eta_std(flux, sem.covariance, lut),
        true_lut=true_lut,
        true_plant=true_plant,
        true_noise_variance=true_noise_variance,
        sources=dict(sources or {}),
        notes=notes,
        timings=dict(cal.timings),
        model_info={k: v for k, v in cal.model_info.items() if k not in ("theta", "weights")},
        hall_noise_variance=cs_noise,
        constant_speed=cs_summary,
        straight_line=straight,
        cogging=getattr(cal, "cogging", None),
        true_cogging=true_cogging,
    )


# ------------------------------------------------------------------------------------------------
# From files
# ------------------------------------------------------------------------------------------------


def _artifact_flux(art: Mapping[str, Any], source: str) -> FluxModel:
    model = art["model"]
    for key in ("harmonics", "theta"):
        if key not in model:
            raise HallcalInputError(f"{source}: key 'model.{key}' is missing")
    try:
        basis = FourierBasis(tuple(int(h) for h in model["harmonics"]))
        return FluxModel(basis, np.asarray(model["theta"], dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise HallcalInputError(
            f"{source}: key 'model.theta' or 'model.harmonics': {exc}"
        ) from None


def _artifact_plant(art: Mapping[str, Any], setup: Setup, source: str) -> ContinuousTF | None:
    p = art.get("plant")
    if not isinstance(p, Mapping):
        return setup.plant
    try:
        return ContinuousTF(
            tuple(float(v) for v in p["num"]),
            tuple(float(v) for v in p["den"]),
            float(p.get("delay", 0.0)),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise HallcalInputError(f"{source}: key 'plant' is malformed ({exc})") from None


def _read_bla(path: Path) -> Any:
    from hallcal.identify.bla import NonparametricBLA, ParametricBLA
    from hallcal.pipeline import BLAIdentification

    data = read_json(path)
    if not isinstance(data, Mapping) or data.get("format") != "hallcal-bla/1":
        raise HallcalInputError(f"{path}: not a hallcal BLA file (format 'hallcal-bla/1')")
    try:
        npb = NonparametricBLA.from_dict(data["nonparametric"])
        par = ParametricBLA.from_dict(data["parametric"])
        p = data["plant"]
        plant = ContinuousTF(tuple(p["num"]), tuple(p["den"]), float(p.get("delay", 0.0)))
    except HallcalInputError as exc:
        raise HallcalInputError(f"{path}: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise HallcalInputError(f"{path}: malformed BLA file ({exc})") from None
    return BLAIdentification(npb, par, plant, str(data.get("status", "ok")))


def _resimulate(
    art: Mapping[str, Any],
    setup: Setup,
    flux: FluxModel,
    plant: ContinuousTF | None,
    data: Dataset,
    lut: LUT,
    *,
    progress: Progress,
    notes: list[str],
) -> Any:
    """The SEM result of an artifact: cost history stored, d_sim/y0_sim and covariance redone.

    The loop includes the artifact's cogging torque; for a Fourier model one structured
    Gauss-Newton pass (:mod:`hallcal.fit.gauss_newton`, with the cogging coefficients as
    parameters, as in the calibration) gives cov(theta) for the table's band.
    """
    from hallcal.fit.gauss_newton import ParameterLayout, gauss_newton_system
    from hallcal.fit.sem import SEMResult
    from hallcal.sim.cogging import CoggingTorque
    from hallcal.sim.loop import ClosedLoop

    diag = art.get("diagnostics", {})
    history = np.asarray(diag.get("cost_history", []), dtype=np.float64)
    if history.size == 0:
        return None
    n = data.n_samples
    d = data.d
    d_sim = y0_sim = None
    cov = None
    s2 = float(diag.get("noise_variance", math.nan))
    closed = setup.trajectory.kind == "closed-loop"
    cogging = CoggingTorque.from_dict(art["cogging"]) if "cogging" in art else None
    if not (closed and plant is not None and setup.controller is not None and "r" in data):
        notes.append(
            "The model fit is shown at the calibrated angle f_star: re-simulating the closed loop "
            "needs a closed-loop trajectory, the plant, the controller and the column 'r'."
        )
    else:
        _say(progress, "re-simulating the closed loop with the identified model")
        loop = ClosedLoop.from_transfer_functions(
            plant,
            setup.controller,
            setup.sample_time,
            setup.pole_pairs,
            projection=lut.projection,
            offset=lut.offset,
        )
        r = np.ascontiguousarray(data["r"], dtype=np.float64)
        layout = ParameterLayout(flux.basis, cogging_orders=() if cogging is None
                                 else cogging.orders)  # fmt: skip
        x = layout.pack(flux.theta, 0.0, cogging)
        basis_kind = art.get("model", {}).get("basis", "fourier")
        fourier = basis_kind == "fourier"
        if fourier:
            _say(progress, "parameter covariance (one sensitivity pass) for the LUT band")
        gn = gauss_newton_system(loop, layout, x, r, d, gram=fourier)
        if not gn.status.success:
            notes.append("Re-simulating the closed loop with the identified model diverged.")
        else:
            d_sim, y0_sim = gn.d, gn.y0
            cost = gn.sse
            stored = float(diag.get("cost", cost))
            if not math.isclose(cost, stored, rel_tol=1e-3):
                notes.append(
                    f"The data's simulation cost ({cost:.6g}) differs from the artifact's "
                    f"({stored:.6g}): the data may not be the calibration recording."
                )
            if fourier:
                if not math.isfinite(s2):
                    s2 = cost / max(3 * n - layout.size, 1)
                try:
                    p = flux.theta.size
                    cov = (s2 * np.linalg.inv(gn.gram))[:p, :p]
                except np.linalg.LinAlgError:
                    cov = None
            else:
                notes.append(
                    "No uncertainty band for the lookup table: the covariance of a kernel model "
                    "is only available in the calibrating process."
                )
    return SEMResult(
        flux=flux,
        theta0=np.full_like(flux.theta, np.nan),
        cost_history=history,
        iterations=int(diag.get("iterations", history.size - 1)),
        status=str(diag.get("sem_status", "unknown")),
        solve_time=float(diag.get("solve_time", math.nan)),
        noise_variance=s2,
        covariance=np.full((flux.theta.size,) * 2, np.nan) if cov is None else cov,
        n_samples=int(diag.get("n_samples", n)),
        d_sim=d_sim,
        y0_sim=y0_sim,
        cogging=cogging,
    )


def content_from_artifact(
    artifact: Mapping[str, Any],
    data: Dataset,
    *,
    validation_data: Dataset | None = None,
    bla: Any = None,
    sources: Mapping[str, str] | None = None,
    progress: Progress = None,
    title: str = "hallcal calibration report",
) -> ReportContent:
    """Gather a report's content from a calibration artifact and its calibration recording.

    The lookup table and the flux model come from the artifact; the closed loop is re-simulated
    with the stored plant and controller to show the model fit (Fig. 4), and for a Fourier
    model one sensitivity pass gives cov(theta) for the table's uncertainty band. The noise
    floor is the calibration's own (``diagnostics.noise_floor``).

    Parameters
    ----------
    artifact : dict
        As returned by :func:`hallcal.io.read_artifact`.
    data : Dataset
        The calibration recording (d1..d3; r for the re-simulation; y_ref validates when no
        ``validation_data`` is given).
    validation_data : Dataset, optional
        A fresh recording with ``y_ref``.
    bla : BLAIdentification, optional
    sources : mapping, optional
        Input names by role.
    progress : callable, optional
    title : str

    Returns
    -------
    ReportContent
    """
    from hallcal.pipeline import lut_from_artifact, validate

    source = (sources or {}).get("artifact", "artifact")
    setup = setup_from_dict(artifact["setup"], source=f"{source}: setup")
    n_m = int(artifact["pole_pairs"])
    lut = lut_from_artifact(artifact)
    flux = _artifact_flux(artifact, source)
    plant = _artifact_plant(artifact, setup, source)
    diag = artifact.get("diagnostics", {})
    notes: list[str] = []
    cal_traces = _traces(lut, data)
    sem = _resimulate(artifact, setup, flux, plant, data, lut, progress=progress, notes=notes)
    noise_floor, floor_source = _artifact_floor(diag, flux, n_m)
    validation = None
    val_traces = None
    val_source = None
    if validation_data is not None:
        validation_data.require("y_ref")
        val_traces = _traces(lut, validation_data)
        val_source = (sources or {}).get("validation", validation_data.source)
        if lut.bijective:
            validation = validate(lut, validation_data, noise_floor=noise_floor)
    elif cal_traces.y_ref is not None:
        val_traces = cal_traces
        val_source = (sources or {}).get("data", data.source) + " (the calibration recording)"
        if lut.bijective:
            validation = validate(lut, data, noise_floor=noise_floor)
    else:
        notes.insert(0, _no_encoder_note(isinstance(diag.get("constant_speed"), Mapping)))
    if not lut.bijective:
        notes.append(
            "The lookup table is not bijective (the paper's bijectivity condition fails): "
            "f_star is undefined, so only f_init is shown."
        )
    d = data.d
    d_model, label = _model_signals(sem, flux, d, cal_traces)
    t = np.asarray(data["t"], dtype=np.float64) if "t" in data else None
    if t is None:
        # sample_time = 1.0 means time in samples (docs/design.md): plot over the sample index
        t = None if setup.sample_time == 1.0 else setup.sample_time * np.arange(d.shape[0])
    p = artifact.get("plant") if isinstance(artifact.get("plant"), Mapping) else {}
    gain = p.get("gain_correction")
    cs_summary, cs_noise, straight = _constant_speed_parts(
        diag.get("constant_speed") if isinstance(diag.get("constant_speed"), Mapping) else None,
        lut,
        data,
        cal_traces,
    )
    predicted = diag.get("predicted_angle_error_rms")
    timings = diag.get("timings") if isinstance(diag.get("timings"), Mapping) else {}
    return ReportContent(
        title=title,
        setup=setup,
        lut=lut,
        flux=flux,
        sem=sem,
        bla=bla,
        plant=plant,
        gain_correction=None if gain is None else float(gain),
        gain_details=dict(diag["gain_correction"])
        if isinstance(diag.get("gain_correction"), Mapping)
        else None,
        predicted_error=None if predicted is None else float(predicted),
        noise_floor=noise_floor,
        noise_floor_source=floor_source,
        status=str(diag.get("status", "unknown")),
        messages=[str(m) for m in diag.get("messages", [])],
        adequacy=_adequacy_dict(diag.get("adequacy")),
        t=t,
        d=d,
        d_model=d_model,
        d_model_label=label,
        calibration=cal_traces,
        validation=validation,
        validation_traces=val_traces,
        validation_source=val_source,
        eta_std=None if sem is None else _eta_std(flux, sem.covariance, lut),
        sources=dict(sources or {}),
        notes=notes,
        timings={str(k): float(v) for k, v in timings.items()},
        model_info={
            k: v for k, v in artifact.get("model", {}).items() if k not in ("theta", "weights")
        },
        hall_noise_variance=cs_noise,
        constant_speed=cs_summary,
        straight_line=straight,
        cogging=None if sem is None else sem.cogging,
    )


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
    from hallcal.output import plots

    c = content
    n_m = c.pole_pairs
    figs: list[ReportFigure] = []
    vt = c.validation_traces
    if vt is not None and vt.y_ref is not None:
        where = c.validation_source or "the validation recording"
        figs.append(
            ReportFigure(
                "ripple",
                "f_init against the true angle (the paper's Fig. 2)",
                f"Two of the {n_m} pole pairs of {where}: the Clarke + atan2 angle f_init (blue) "
                "against the reference (black dashed); below, the error itself, with f_star (red) "
                "after calibration. The ripple repeats per pole pair and differs slightly from "
                "magnet to magnet.",
                plots.plot_ripple(vt.y_ref, vt.y_init, pole_pairs=n_m, y_star=vt.y_star),
            )
        )
    if c.d_model is not None:
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
        figs.append(
            ReportFigure(
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
        )
    if vt is not None and vt.y_ref is not None:
        figs.append(
            ReportFigure(
                "angle_error",
                "Angle error before and after calibration (the paper's Figs. 5 and 7)",
                f"Error of f_init (blue) and f_star (red) against the reference of "
                f"{c.validation_source}, about its mean. The dashed lines are ±3 times the noise "
                f"floor ({c.noise_floor_source}): white noise alone, and so a calibration at "
                "the noise floor, stays between them.",
                plots.plot_angle_error(vt.y_ref, vt.y_init, vt.y_star, noise_floor=c.noise_floor),
            )
        )
    if c.validation is not None:
        figs.append(
            ReportFigure(
                "spectrum",
                "Cumulative PSD of the angle error (the paper's Fig. 8)",
                f"Cumulative power of the error over spatial frequency. The step of f_init (blue) "
                f"at n_m = {n_m} cycles/rev is the magnet pitch; after calibration (red) the "
                "power grows evenly, as white noise does, towards the noise floor squared.",
                plots.plot_error_spectrum(c.validation, pole_pairs=n_m, noise_floor=c.noise_floor),
            )
        )
    if vt is None or vt.y_ref is None:
        cv = c.calibration
        if cv.y_star is not None:
            figs.append(
                ReportFigure(
                    "correction",
                    "Correction f_star - f_init along the recording (no encoder needed)",
                    "The correction the lookup table adds to f_init along the calibration "
                    "recording: the error the calibration attributes to f_init.",
                    plots.plot_correction(cv.y_init, cv.y_star, pole_pairs=n_m),
                )
            )
    if c.bla is not None:
        figs.append(
            ReportFigure(
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
        )
    if c.sem is not None:
        which = "true" if c.true_noise_variance is not None else "estimated"
        figs.append(
            ReportFigure(
                "sem_cost",
                "SEM cost per iteration (the paper's SEM problem)",
                "Simulation-error cost per accepted Levenberg-Marquardt step. A converged model "
                f"ends at the noise level 3Nσ² ({which} σ², dashed).",
                plots.plot_sem_cost(c.sem, noise_variance=c.true_noise_variance),
            )
        )
    if c.cogging is not None and c.cogging.size:
        figs.append(
            ReportFigure(
                "cogging",
                "Cogging torque identified with the flux (paper sec. Discussion)",
                "The position-periodic torque at the plant input that the closed-loop "
                "simulation needed to reproduce the data, in the unit of the torque command"
                + (
                    ", with its ±2σ band from the covariance"
                    if c.cogging.covariance is not None
                    else ""
                )
                + (
                    " and the virtual bench's torque (black dashed)"
                    if c.true_cogging is not None
                    else ""
                )
                + ". Identified jointly with the flux, it no longer leaks into the lookup "
                "table; subtracted from the torque command it is an anticogging feed-forward.",
                plots.plot_cogging(c.cogging, true_cogging=c.true_cogging),
            )
        )
    figs.append(
        ReportFigure(
            "lut",
            "Lookup table η and its uncertainty (the paper's table correction f_star)",
            "The correction η over one revolution"
            + (" with its ±2σ band from cov(θ)" if c.eta_std is not None else "")
            + (
                " and the true η of the virtual bench (black dashed)"
                if c.true_lut is not None
                else ""
            )
            + (
                "; below, the band on its own scale"
                + (" and the error of the identified table" if c.true_lut is not None else "")
                if (c.eta_std is not None or c.true_lut is not None)
                else ""
            )
            + ".",
            plots.plot_lut(c.lut, eta_std=c.eta_std, true_lut=c.true_lut),
        )
    )
    return figs


# ------------------------------------------------------------------------------------------------
# HTML
# ------------------------------------------------------------------------------------------------

_CSS = """
:root { --blue: #1f77b4; --red: #d62728; --grey: #6b6b6b; --line: #d9d9d9; }
* { box-sizing: border-box; }
body { margin: 0; background: #f6f6f4; color: #1b1b1b;
       font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif; }
main { max-width: 1000px; margin: 0 auto; padding: 24px 28px 48px; background: #fff; }
h1 { font-size: 26px; margin: 0 0 4px; }
h2 { font-size: 19px; margin: 32px 0 10px; padding-bottom: 4px; border-bottom: 1px solid
     var(--line); }
.meta { color: var(--grey); font-size: 13px; margin: 0 0 14px; }
.status { display: inline-block; padding: 3px 10px; border-radius: 4px; font-weight: 600;
          color: #fff; }
.status-ok { background: #2e7d32; } .status-warning { background: #b26a00; }
.status-bad { background: #b71c1c; } .status-unknown { background: #616161; }
.notes { border-left: 4px solid #b26a00; background: #fff8e6; padding: 8px 14px; margin: 12px 0; }
.notes p { margin: 4px 0; }
table { border-collapse: collapse; margin: 8px 0 12px; font-size: 14px; }
th, td { border-bottom: 1px solid var(--line); padding: 5px 12px 5px 0; text-align: left;
         vertical-align: top; }
th { font-weight: 600; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.init td:first-child { color: var(--blue); font-weight: 600; }
tr.star td:first-child { color: var(--red); font-weight: 600; }
.kv th { width: 230px; color: #333; }
figure { margin: 22px 0; }
figure img { display: block; width: 100%; height: auto; border: 1px solid var(--line); }
figcaption { font-size: 13.5px; color: #333; margin-top: 6px; }
pre { background: #f3f3f3; padding: 10px 14px; overflow-x: auto; font-size: 13px; }
footer { color: var(--grey); font-size: 12px; margin-top: 36px; }
"""


def _esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _num(x: Any, fmt: str = ".4g") -> str:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return "–"
    return format(v, fmt) if math.isfinite(v) else "–"


def _tf_text(tf: ContinuousTF) -> str:
    def poly(c: tuple[float, ...]) -> str:
        n = len(c) - 1
        terms = []
        for i, a in enumerate(c):
            if a == 0:
                continue
            p = n - i
            s = "" if p == 0 else ("s" if p == 1 else f"s^{p}")
            coef = f"{a:.4g}"
            terms.append(coef if not s else (s if coef == "1" else f"{coef} {s}"))
        return " + ".join(terms).replace("+ -", "- ") or "0"

    text = f"({poly(tf.num)}) / ({poly(tf.den)})"
    if tf.delay:
        text += f" · exp(-{tf.delay:.4g} s)"
    return text


def _ranges(values: Any) -> str:
    """[1, 2, 3, 5, 33] -> '1..3, 5, 33'."""
    v = sorted(int(x) for x in values)
    out, i = [], 0
    while i < len(v):
        j = i
        while j + 1 < len(v) and v[j + 1] == v[j] + 1:
            j += 1
        out.append(f"{v[i]}..{v[j]}" if j > i + 1 else ", ".join(map(str, v[i : j + 1])))
        i = j + 1
    return ", ".join(out)


def _status_class(status: str) -> str:
    if status == "ok":
        return "status-ok"
    if status in ("warning",):
        return "status-warning"
    if status in ("not-bijective", "inadequate"):
        return "status-bad"
    return "status-unknown"


def _kv(rows: list[tuple[str, str]]) -> str:
    body = "".join(f"<tr><th>{_esc(k)}</th><td>{v}</td></tr>" for k, v in rows)
    return f'<table class="kv">{body}</table>'


def _accuracy_table(c: ReportContent) -> str:
    v = c.validation
    parts = []
    if v is not None:
        ri = v.init.rms / v.star.rms if v.star.rms > 0 else math.nan
        pi = v.init.peak / v.star.peak if v.star.peak > 0 else math.nan
        parts.append(
            "<table><tr><th></th><th>RMS</th><th>peak</th></tr>"
            f'<tr class="init"><td>f_init (before)</td><td class="num">{c.angle(v.init.rms)}</td>'
            f'<td class="num">{c.angle(v.init.peak)}</td></tr>'
            f'<tr class="star"><td>f_star (after)</td><td class="num">{c.angle(v.star.rms)}</td>'
            f'<td class="num">{c.angle(v.star.peak)}</td></tr>'
            f'<tr><td>improvement</td><td class="num">×{_num(ri, ".3g")}</td>'
            f'<td class="num">×{_num(pi, ".3g")}</td></tr>'
            "</table>"
            f'<p class="meta">Against the reference angle y_ref of {_esc(c.validation_source)}; '
            "RMS and peak about the mean error (a constant offset of the angle origin is not a "
            "reconstruction error).</p>"
        )
    elif c.validation_traces is not None and c.validation_traces.y_ref is not None:
        vt = c.validation_traces
        e = vt.y_init - vt.y_ref
        e = e - e.mean()
        parts.append(
            f"<p>f_init against y_ref of {_esc(c.validation_source)}: RMS "
            f"{c.angle(float(np.sqrt(np.mean(e**2))))}, peak {c.angle(float(np.max(np.abs(e))))}; "
            "no f_star (table not bijective).</p>"
        )
    else:
        parts.append("<p><b>Errors against an encoder: unavailable</b> (no y_ref column).</p>")
        sl = c.straight_line
        if sl is not None:
            where = (
                f"the held-out constant-speed samples {sl.start}..{sl.stop} "
                f"({sl.revolutions:.2f} revolutions the calibration did not use)"
                if sl.held_out
                else f"the calibration samples {sl.start}..{sl.stop} (no held-out samples left)"
            )
            ratio = sl.init_rms / sl.star_rms if sl.star_rms > 0 else math.nan
            parts.append(
                "<table><tr><th>straight-line check</th><th>RMS from the best line</th></tr>"
                f'<tr class="init"><td>f_init</td><td class="num">{c.angle(sl.init_rms)}</td>'
                "</tr>"
                f'<tr class="star"><td>f_star</td><td class="num">{c.angle(sl.star_rms)}</td>'
                "</tr>"
                f'<tr><td>improvement</td><td class="num">×{_num(ratio, ".3g")}</td></tr>'
                "</table>"
                f'<p class="meta">At constant speed the true angle is a straight line in the '
                f"sample index, so on {_esc(where)} the residual of the best line bounds the "
                "error from above (the rig's own speed ripple is included).</p>"
            )
        cv = c.calibration
        if cv.y_star is not None:
            corr = cv.y_star - cv.y_init
            parts.append(
                "<p>Correction f_star − f_init along the calibration recording (no encoder "
                f"needed): RMS about the mean {c.angle(float(np.std(corr)))}, peak "
                f"{c.angle(float(np.max(np.abs(corr))))}.</p>"
            )
    rows = [
        (
            "noise floor (RMS)",
            f"{c.angle(c.noise_floor)} <span class='meta'>({_esc(c.noise_floor_source)})</span>",
        ),
        (
            "predicted f_star error (RMS)",
            f"{c.angle(c.predicted_error)} <span class='meta'>"
            + (
                "(the noise floor: what the Hall noise alone leaves; the rig's motion is not "
                "in it)</span>"
                if c.constant_speed is not None
                else "(noise floor and the table's uncertainty from cov(θ))</span>"
            ),
        ),
    ]
    return "".join(parts) + _kv(rows)


def _calibration_rows(c: ReportContent) -> list[tuple[str, str]]:
    rows: list[tuple[str, str]] = []
    rows.append(
        ("status", f'<span class="status {_status_class(c.status)}">{_esc(c.status)}</span>')
    )
    sem = c.sem
    if sem is not None:
        n = int(sem.n_samples)
        s2 = c.true_noise_variance if c.true_noise_variance is not None else sem.noise_variance
        level = 3 * n * float(s2) if s2 is not None else math.nan
        rows += [
            (
                "SEM cost before → after",
                f"{_num(sem.initial_cost)} → {_num(sem.cost)} "
                f"<span class='meta'>(noise level 3Nσ² = {_num(level)}, N = {n})</span>",
            ),
            ("SEM iterations", f"{int(sem.iterations)} ({_esc(sem.status)})"),
            ("SEM solve time", f"{_num(sem.solve_time, '.2f')} s"),
            ("noise variance σ² (from residual)", _num(sem.noise_variance, ".4g")),
        ]
    if c.gain_correction is not None:
        text = _num(c.gain_correction, ".5g")
        g = c.gain_details or {}
        if g.get("c_refined") is not None:
            std = g.get("c_refined_std")
            if std is not None:
                text += f" ± {_num(std, '.2g')}"
            text += (
                " <span class='meta'>(refined jointly with θ in SEM; the gain-correction estimate "
                f"was {_num(g.get('c'), '.5g')})</span>"
            )
        rows.append(("gain correction ĉ (the gain correction c-hat)", text))
    if c.plant is not None:
        rows.append(("plant model used in SEM", f"<code>{_esc(_tf_text(c.plant))}</code>"))
    lut = c.lut
    rows.append(
        (
            "lookup table",
            f"{lut.points} points; bijective: <b>{'yes' if lut.bijective else 'NO'}</b> "
            f"(min slope of y0 → ŷ: {_num(lut.min_slope, '.3g')})",
        )
    )
    info = c.model_info
    if info:
        basis = info.get("basis", "?")
        desc = _esc(basis)
        if "harmonics" in info and basis == "fourier":
            desc += f", mechanical harmonics {_esc(_ranges(info['harmonics']))}"
        elif "points" in info:
            desc += f", {_esc(info['points'])} points"
        rows.append(("flux model", desc))
    if c.adequacy is not None:
        verdict = c.adequacy.get("verdict", "–")
        msg = str(c.adequacy.get("message", "") or "")
        if msg.lower().startswith(str(verdict).lower()):
            msg = msg[len(str(verdict)) :].lstrip(" :,-")
        rows.append(
            ("model adequacy", f"<b>{_esc(verdict)}</b>" + (f": {_esc(msg)}" if msg else ""))
        )
    elif c.constant_speed is not None:
        cs = c.constant_speed
        motion = cs.get("motion_rms")
        floor = cs.get("angle_noise_floor")
        ratio = (
            f" ({_num(motion / floor, '.3g')} × the noise floor)"
            if isinstance(motion, int | float) and isinstance(floor, int | float) and floor > 0
            else ""
        )
        warnings = [str(w) for w in cs.get("warnings", [])]
        rows.append(
            (
                "model adequacy (constant speed)",
                f"<b>{_esc(cs.get('status', '–'))}</b>: rotor motion off the straight line "
                f"{c.angle(motion)} RMS{ratio}; "
                f"{_num(100 * float(cs.get('downweighted_fraction', 0.0)), '.3g')} % of the "
                "samples down-weighted as outliers"
                + (f"; {_esc('; '.join(warnings))}" if warnings else ""),
            )
        )
        rows.append(
            (
                "constant-speed segment",
                f"samples {_esc(cs.get('start'))}..{_esc(cs.get('stop'))}, "
                f"{_num(cs.get('revolutions'), '.3g')} revolutions, Hall noise "
                f"{_num(cs.get('noise_std'), '.3g')} per channel",
            )
        )
    else:
        rows.append(("model adequacy", "<span class='meta'>not assessed</span>"))
    if c.timings:
        rows.append(
            ("time per step", _esc(", ".join(f"{k} {v:.2f} s" for k, v in c.timings.items())))
        )
    return rows


def render_html(content: ReportContent, images: list[tuple[ReportFigure, bytes]]) -> str:
    """The report as one self-contained HTML page (figures as base64 PNG, no scripts, no URLs).

    Parameters
    ----------
    content : ReportContent
    images : list of (ReportFigure, bytes)
        Each figure with its PNG.

    Returns
    -------
    str
    """
    c = content
    created = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    src = "; ".join(f"{k}: {v}" for k, v in c.sources.items()) or "in memory"
    out = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_esc(c.title)}</title><style>{_CSS}</style></head><body><main>",
        f"<h1>{_esc(c.title)}</h1>",
        f'<p class="meta">{c.pole_pairs} pole pairs · '
        + (
            "time in samples (sample_time = 1)"
            if c.setup.sample_time == 1.0
            else f"sample time {_num(c.setup.sample_time, '.4g')} s"
        )
        + " · angle errors in "
        + ("electrical degrees" if c.angle_units == "electrical-deg" else "mechanical mrad")
        + f" · inputs: {_esc(src)} · created {created} · hallcal {_esc(__version__)}</p>",
        f'<p><span class="status {_status_class(c.status)}">status: {_esc(c.status)}</span></p>',
    ]
    if c.messages or c.notes:
        out.append('<div class="notes">')
        out += [f"<p>{_esc(m)}</p>" for m in c.messages]
        out += [f"<p>{_esc(n)}</p>" for n in c.notes]
        out.append("</div>")
    out.append("<h2>Accuracy</h2>")
    out.append(_accuracy_table(c))
    out.append("<h2>Calibration</h2>")
    out.append(_kv(_calibration_rows(c)))
    out.append("<h2>Figures</h2>")
    for i, (fig, png) in enumerate(images, start=1):
        w, h = fig.figure.get_size_inches() * _DPI
        b64 = base64.b64encode(png).decode("ascii")
        out.append(
            f'<figure id="fig-{_esc(fig.key)}"><img src="data:image/png;base64,{b64}" '
            f'alt="{_esc(fig.title)}" width="{int(round(w))}" height="{int(round(h))}">'
            f"<figcaption><b>Figure {i}. {_esc(fig.title)}.</b> {_esc(fig.caption)}"
            "</figcaption></figure>"
        )
    out.append("<h2>Setup</h2>")
    out.append(f"<pre>{_esc(setup_to_toml(c.setup))}</pre>")
    out.append(
        "<footer>hallcal implements van Meer et al., “Self-Calibrating Position Measurements: "
        "Applied to Imperfect Hall Sensors”. Figures are also written as PNG files next to this "
        "report.</footer>"
    )
    out.append("</main></body></html>")
    return "\n".join(out) + "\n"


def _png(fig: Any) -> bytes:
    buf = _io.BytesIO()
    with warnings.catch_warnings():
        # a figure of degenerate data (a flat trace, a tiny run) may not fit constrained layout;
        # matplotlib then draws it without and says so on stderr, which is no news to the user
        warnings.filterwarnings("ignore", message="constrained_layout not applied")
        fig.savefig(buf, format="png", dpi=_DPI, metadata={"Software": None})
    return buf.getvalue()


def _out_dir(out_dir: str | os.PathLike[str]) -> Path:
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise HallcalInputError(f"{out}: exists and is not a directory")
    try:
        (out / FIGURE_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HallcalInputError(f"{out}: cannot create the directory ({exc.strerror})") from None
    return out


def write_report(
    content: ReportContent,
    out_dir: str | os.PathLike[str],
    *,
    progress: Progress = None,
) -> Path:
    """Write the figures (``out_dir/figures/*.png``) and ``out_dir/report.html``, atomically.

    Parameters
    ----------
    content : ReportContent
        What the report shows.
    out_dir : path-like
        Output directory (created if needed).
    progress : callable, keyword-only, optional
        Called with a short message at each step.

    Returns
    -------
    pathlib.Path
        The HTML file.
    """
    out = _out_dir(out_dir)
    _say(progress, "figures")
    figs = make_figures(content)
    images = []
    for f in figs:
        png = _png(f.figure)
        with atomic_write(out / FIGURE_DIR / f"{f.key}.png", "wb") as fh:
            fh.write(png)
        images.append((f, png))
    _say(progress, "HTML report")
    text = render_html(content, images)
    path = out / REPORT_NAME
    with atomic_write(path, "w") as fh:
        fh.write(text)
    return path


# ------------------------------------------------------------------------------------------------
# Entry points of the CLI and the demo
# ------------------------------------------------------------------------------------------------


def write_report_from_files(
    artifact_path: str | os.PathLike[str],
    data_path: str | os.PathLike[str],
    *,
    validation: str | os.PathLike[str] | None = None,
    bla: str | os.PathLike[str] | None = "auto",
    out_dir: str | os.PathLike[str],
    progress: Progress = None,
    units: str = "mrad",
) -> Path:
    """``hallcal report ARTIFACT DATA [--validation VAL] --out DIR [--units U]``.

    Parameters
    ----------
    artifact_path : path-like
        Calibration artifact (JSON).
    data_path : path-like
        The calibration recording.
    validation : path-like, optional
        A fresh recording with ``y_ref`` (encoder) to validate on.
    bla : path-like, "auto" or None
        BLA file (``hallcal bla`` output) to plot; ``"auto"``: ``bla.json`` next to the artifact
        when the artifact's plant came from a BLA (as ``hallcal demo`` writes it); None: none.
    out_dir : path-like
        Folder for ``report.html`` and ``figures/``.
    progress : callable, optional
    units : {"mrad", "electrical-deg"}
        Units of the angle errors in the text (the figures stay in mrad).

    Returns
    -------
    pathlib.Path
        The HTML file.

    Raises
    ------
    HallcalInputError
        Missing or malformed artifact or data (the message names the file and key or column).
    """
    # read and check every input before saying anything: a bad input is one line on stderr
    art = read_artifact(artifact_path)
    data = read_dataset(data_path, required=("d1", "d2", "d3"))
    val = None
    sources = {"artifact": str(artifact_path), "data": str(data_path)}
    if validation is not None:
        val = read_dataset(validation, required=("d1", "d2", "d3", "y_ref"))
        sources["validation"] = str(validation)
    bla_obj = None
    plant = art.get("plant")
    if bla == "auto":
        candidate = Path(artifact_path).parent / "bla.json"
        from_bla = isinstance(plant, Mapping) and plant.get("source") == "bla"
        if from_bla and candidate.is_file():
            try:
                bla_obj = _read_bla(candidate)
                sources["bla"] = str(candidate)
            except HallcalInputError:
                bla_obj = None
    elif bla is not None:
        bla_obj = _read_bla(Path(bla))
        sources["bla"] = str(bla)
    content = content_from_artifact(
        art, data, validation_data=val, bla=bla_obj, sources=sources, progress=progress
    )
    content = dataclasses.replace(content, angle_units=units)
    return write_report(content, out_dir, progress=progress)


def write_demo_report(
    cal: Any,
    val: Any,
    *,
    runs: Mapping[str, Any],
    out_dir: str | os.PathLike[str],
    noise_floor: float | None,
    progress: Progress = None,
) -> Path:
    """The report of ``hallcal demo``: everything in memory, with the virtual bench's truth.

    Parameters
    ----------
    cal : Calibration
    val : Validation
        Errors on the fresh validation run.
    runs : mapping of str to BenchRun
        ``"calibration"`` and ``"validation"`` (``"bla"`` is not needed: ``cal.bla`` has it).
    out_dir : path-like
    noise_floor : float
        RMS angle error of the bench's Hall noise alone [rad].
    progress : callable, optional
        Called with a short message per step.

    Returns
    -------
    pathlib.Path
        The HTML file.
    """
    cal_run, val_run = runs["calibration"], runs["validation"]
    content = content_from_calibration(
        cal,
        Dataset.from_columns(cal_run.columns(), path="calibration.npz"),
        validation_data=Dataset.from_columns(val_run.columns(), path="validation.npz"),
        validation=val,
        noise_floor=noise_floor,
        true_flux=cal_run.truth,
        true_plant=cal_run.config.plant,
        true_noise_variance=cal_run.config.noise_variance,
        sources={
            "calibration": "calibration.npz",
            "validation": "validation.npz (fresh run, true angle)",
            "BLA experiment": "bla.npz",
        },
        title="hallcal demo: the paper's simulation study",
        noise_floor_source="virtual bench: σ·√(2/3)/(A·n_m) with the true σ and A",
    )
    return write_report(content, out_dir, progress=progress)


def write_calibration_report(
    cal: Calibration,
    data: Dataset,
    out_dir: str | os.PathLike[str],
    *,
    validation: Dataset | None = None,
    progress: Progress = None,
    units: str = "mrad",
) -> Path:
    """The report of a calibration object (``Calibration.report``), computed or loaded.

    A calibration computed in this process reports its in-memory results; one loaded from an
    artifact (:attr:`Calibration.artifact`) is reported as ``hallcal report`` does it.

    Parameters
    ----------
    cal : Calibration
    data : Dataset
        The calibration recording.
    out_dir : path-like
    validation : Dataset, optional
        A fresh recording with ``y_ref``.
    progress : callable, optional
        Called with a short message per step.
    units : {"mrad", "electrical-deg"}
        Units of the angle errors in the text.

    Returns
    -------
    pathlib.Path
        The HTML file.
    """
    if cal.artifact is not None:
        content = content_from_artifact(
            cal.artifact, data, validation_data=validation, progress=progress
        )
    else:
        content = content_from_calibration(cal, data, validation_data=validation)
    content = dataclasses.replace(content, angle_units=units)
    return write_report(content, out_dir, progress=progress)
