"""What a report shows (:class:`ReportContent`) and the one place it is gathered
(:func:`report_content`): from the calibration artifact and its recording, plus what a
calibration computed in this process has in memory (:class:`ReportExtras`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.formatting import AngleUnit
from hallcal.io import ArtifactData, Dataset, Setup, validate_artifact
from hallcal.pipeline.calibration import Calibration
from hallcal.pipeline.progress import Progress, say
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sim.lti import ContinuousTF

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
    predicted_error : float
        Predicted RMS error of f_star [rad] (NaN when the artifact has none).
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
    angle_units : AngleUnit
        Units of the angle errors in the text (an unknown name is an error).
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
    predicted_error: float
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
    angle_units: AngleUnit = AngleUnit.MRAD
    cogging: Any = None
    true_cogging: Any = None

    @property
    def pole_pairs(self) -> int:
        return int(self.setup.pole_pairs)

    def angle(self, x: float | None) -> str:
        """An angle error [rad, mechanical] in this report's units."""
        unit = AngleUnit.parse(self.angle_units)
        return unit.text(x, self.pole_pairs, page=True)


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
    cs: Mapping[str, Any] | None, lut: LUT, data: Dataset, traces: Traces
) -> tuple[dict[str, Any] | None, float | None, StraightLineCheck | None]:
    """Summary, Hall noise variance and straight-line check of a constant-speed calibration
    (the artifact's ``diagnostics.constant_speed``)."""
    if cs is None:
        return None, None, None
    summary = dict(cs)
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
    """The noise floor of the model's amplitude (:func:`hallcal.sim.bench.noise_floor`)."""
    from hallcal.sim.bench import noise_floor

    if noise_variance is None or not math.isfinite(noise_variance) or noise_variance < 0:
        return None
    a = _amplitude(flux, n_m)
    return noise_floor(noise_variance, n_m, a) if a > 0 else None


_ESTIMATED_FLOOR = "estimated from the calibration data (model-free Hall noise level)"


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


_NOT_BIJECTIVE_NOTE = (
    "The lookup table is not bijective (the paper's bijectivity condition fails): "
    "f_star is undefined, so only f_init is shown."
)


def _validation_parts(
    lut: LUT,
    data: Dataset,
    cal_traces: Traces,
    *,
    validation_data: Dataset | None,
    validation: Any,
    sources: Mapping[str, str] | None,
    noise_floor: float | None,
    constant_speed: bool,
    notes: list[str],
) -> tuple[Any, Traces | None, str | None]:
    """Errors against an encoder: on ``validation_data``, else on the calibration recording when
    it has ``y_ref`` (a given ``validation`` is kept); else a first note on what is shown instead.

    Returns ``(validation, validation_traces, validation_source)``.
    """
    from hallcal.pipeline import validate
    from hallcal.pipeline.calibration import validation_skipped

    val_traces: Traces | None = None
    val_source: str | None = None
    if validation_data is not None:
        validation_data.require("y_ref")
        val_source = (sources or {}).get("validation", validation_data.source)
        try:
            if validation is None and lut.bijective:
                validation = validate(lut, validation_data, noise_floor=noise_floor)
        except HallcalInputError as exc:  # a standstill run: the calibration's report stands
            notes.insert(0, validation_skipped(exc).record())
            return None, None, None
        val_traces = _traces(lut, validation_data)
    elif cal_traces.y_ref is not None:
        val_traces = cal_traces
        val_source = (sources or {}).get("data", data.source) + " (the calibration recording)"
        if validation is None and lut.bijective:
            validation = validate(lut, data, noise_floor=noise_floor)
    else:
        notes.insert(0, _no_encoder_note(constant_speed))
    if not lut.bijective:
        notes.append(_NOT_BIJECTIVE_NOTE)
    return validation, val_traces, val_source


def _recording_parts(
    data: Dataset,
    setup: Setup,
    lut: LUT,
    flux: FluxModel,
    sem: Any,
    cal_traces: Traces,
    constant_speed: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """What the report shows of the calibration recording: the signals and the model's, the
    time axis, the table's uncertainty and the constant-speed check (:class:`ReportContent`
    fields)."""
    d = np.asarray(data.d, dtype=np.float64)
    d_model, label = _model_signals(sem, flux, d, cal_traces)
    t = np.asarray(data["t"], dtype=np.float64) if "t" in data else None
    if t is None:
        # sample_time = 1.0 means time in samples (docs/design.md): plot over the sample index
        t = (
            None
            if setup.sample_time == 1.0
            else np.arange(d.shape[0], dtype=np.float64) * float(setup.sample_time)
        )
    cs_summary, cs_noise, straight = _constant_speed_parts(constant_speed, lut, data, cal_traces)
    return dict(
        t=t,
        d=d,
        d_model=d_model,
        d_model_label=label,
        calibration=cal_traces,
        eta_std=None if sem is None else _eta_std(flux, sem.covariance, lut),
        hall_noise_variance=cs_noise,
        constant_speed=cs_summary,
        straight_line=straight,
    )


@dataclass(frozen=True)
class ReportExtras:
    """What a report can show beyond the artifact and its recording (all optional).

    Attributes
    ----------
    bla : BLAIdentification or None
        The BLA read from ``hallcal bla``'s file (a calibration computed in this process has
        its own).
    validation : Validation or None
        Errors already computed on the report's ``validation_data`` (recomputed when None).
    noise_floor : float or None
        RMS angle error of Hall noise alone [rad]; default: the artifact's.
    noise_floor_source : str
        Where a given ``noise_floor`` comes from, for the summary table.
    true_flux, true_plant, true_noise_variance, true_cogging : optional
        The virtual bench's truth, drawn for comparison.
    """

    bla: Any = None
    validation: Any = None
    noise_floor: float | None = None
    noise_floor_source: str = "given"
    true_flux: FluxModel | None = None
    true_plant: ContinuousTF | None = None
    true_noise_variance: float | None = None
    true_cogging: Any = None


def _artifact_floor(cal: Calibration, flux: FluxModel) -> tuple[float | None, str]:
    """The artifact's noise floor (the calibration's own), or for artifacts written before it
    was stored, the estimate from the SEM's noise variance."""
    if math.isfinite(cal.noise_floor):
        return float(cal.noise_floor), _ESTIMATED_FLOOR
    return (
        _estimated_floor(cal.diagnostics.get("noise_variance"), flux, cal.pole_pairs),
        "estimated from the SEM residual",
    )


def _replayed_sem(
    art: ArtifactData,
    flux: FluxModel,
    plant: ContinuousTF | None,
    data: Dataset,
    lut: LUT,
    cogging: Any,
    *,
    progress: Progress,
    notes: list[str],
) -> Any:
    """The SEM result of an artifact: cost history as stored, d_sim, y0_sim and cov(theta)
    from the loop replayed on the recording (:func:`hallcal.fit.replay.replay_closed_loop`)."""
    from hallcal.fit.sem import SEMResult, SEMStatus

    diag = art.diagnostics
    status = diag.get("sem_status", "unknown")
    if status not in SEMStatus._value2member_map_:
        known = ", ".join(f'"{v.value}"' for v in SEMStatus)
        raise HallcalInputError(
            f"{art.source}: key 'diagnostics.sem_status' must be one of {known}, got "
            f"{str(status)[:40]!r}",
            source=art.source,
            key="diagnostics.sem_status",
        )
    history = np.asarray(diag.get("cost_history", []), dtype=np.float64)
    if history.size == 0:
        return None
    s2 = diag.get("noise_variance")
    s2 = math.nan if s2 is None else float(s2)
    setup = art.setup
    d_sim = y0_sim = cov = None
    closed = setup.trajectory.kind == "closed-loop"
    if not (closed and plant is not None and setup.controller is not None and "r" in data):
        notes.append(
            "The model fit is shown at the calibrated angle f_star: re-simulating the closed loop "
            "needs a closed-loop trajectory, the plant, the controller and the column 'r'."
        )
    else:
        from hallcal.fit.replay import replay_closed_loop

        say(progress, "re-simulating the closed loop with the identified model")
        fourier = art.model.get("basis", "fourier") == "fourier"
        if fourier:
            say(progress, "parameter covariance (one sensitivity pass) for the LUT band")
        run = replay_closed_loop(
            flux, lut, plant, setup.controller, setup.sample_time, data["r"], data.d,
            cogging=cogging, noise_variance=s2, covariance=fourier,
        )  # fmt: skip
        if not run.status.success:
            notes.append("Re-simulating the closed loop with the identified model diverged.")
        else:
            d_sim, y0_sim, cov, s2 = run.d_sim, run.y0_sim, run.covariance, run.noise_variance
            stored = float(diag.get("cost", run.sse))
            if not math.isclose(run.sse, stored, rel_tol=1e-3):
                notes.append(
                    f"The data's simulation cost ({run.sse:.6g}) differs from the artifact's "
                    f"({stored:.6g}): the data may not be the calibration recording."
                )
            if not fourier:
                notes.append(
                    "No uncertainty band for the lookup table: the covariance of a kernel "
                    "model is only available in the calibrating process."
                )
    return SEMResult(
        flux=flux,
        theta0=np.full_like(flux.theta, np.nan),
        cost_history=history,
        iterations=int(diag.get("iterations", history.size - 1)),
        status=SEMStatus(status),
        solve_time=float(diag.get("solve_time", math.nan)),
        noise_variance=s2,
        covariance=np.full((flux.theta.size,) * 2, np.nan) if cov is None else cov,
        n_samples=int(diag.get("n_samples", data.n_samples)),
        # not re-simulated: NaN signals, which the plots read as "no model trace"
        d_sim=np.full(data.d.shape, np.nan) if d_sim is None else d_sim,
        y0_sim=np.full(data.n_samples, np.nan) if y0_sim is None else y0_sim,
        cogging=cogging,
    )


def report_content(
    calibration: Calibration | ArtifactData | Mapping[str, Any],
    data: Dataset,
    *,
    extras: ReportExtras | None = None,
    validation_data: Dataset | None = None,
    sources: Mapping[str, str] | None = None,
    progress: Progress = None,
    title: str = "hallcal calibration report",
) -> ReportContent:
    """Gather a report's content: the one builder (``hallcal report``, ``demo``,
    :meth:`hallcal.Calibration.report`).

    The lookup table, the flux model, the plant and the diagnostics come from the artifact
    (through :class:`~hallcal.pipeline.Calibration`'s properties). The model fit (Fig. 4) and
    the table's uncertainty band need the SEM's simulated signals and cov(theta): from the
    calibration's SEM solve when it was computed in this process, else the closed loop is
    replayed with the stored plant and controller. The noise floor is
    the calibration's own (``diagnostics.noise_floor``) unless ``extras`` gives one.

    Parameters
    ----------
    calibration : Calibration, ArtifactData or mapping
        A :class:`~hallcal.pipeline.Calibration` (computed in this process: its SEM solve and
        BLA are shown from memory; a table that is not bijective is accepted, so that a
        calibration refused as such can still be reported), or an artifact as returned by
        :func:`hallcal.io.read_artifact`, or a mapping (checked by
        :func:`hallcal.io.validate_artifact`).
    data : Dataset
        The calibration recording (d1..d3; r for the replay; y_ref validates when no
        ``validation_data`` is given).
    extras : ReportExtras, keyword-only, optional
        What the caller has beyond the calibration (validation, noise floor, the truth).
    validation_data : Dataset, keyword-only, optional
        A fresh recording with ``y_ref``.
    sources : mapping, keyword-only, optional
        Input names by role, listed in the report.
    progress : callable, keyword-only, optional
    title : str, keyword-only

    Returns
    -------
    ReportContent
    """
    x = extras or ReportExtras()
    if isinstance(calibration, Calibration):
        art = validate_artifact(calibration.artifact, "in memory", bijective=False)
        cal = Calibration(art, calibration.computed)
    else:
        art = validate_artifact(calibration, (sources or {}).get("artifact", "artifact"))
        cal = Calibration(art)
    setup, lut, flux, diag = cal.setup, cal.lut, cal.flux, cal.diagnostics
    cogging = cal.cogging
    plant = cal.plant or setup.plant  # the calibration's (a BLA's), else the setup's
    notes: list[str] = []
    cal_traces = _traces(lut, data)
    sem = cal.sem
    if sem is None:
        sem = _replayed_sem(art, flux, plant, data, lut, cogging, progress=progress, notes=notes)
    noise_floor, floor_source = x.noise_floor, x.noise_floor_source
    if noise_floor is None:
        noise_floor, floor_source = _artifact_floor(cal, flux)
    constant_speed = diag.get("constant_speed")
    if not isinstance(constant_speed, Mapping):
        constant_speed = None
    validation, val_traces, val_source = _validation_parts(
        lut, data, cal_traces, validation_data=validation_data, validation=x.validation,
        sources=sources, noise_floor=noise_floor, constant_speed=constant_speed is not None,
        notes=notes,
    )  # fmt: skip
    true_lut = None
    if x.true_flux is not None:
        true_lut = build_lut(
            x.true_flux, setup.pole_pairs, points=lut.points, projection=lut.projection,
            offset=lut.offset,
        )  # fmt: skip
    return ReportContent(
        title=title,
        bla=x.bla if cal.bla is None else cal.bla,
        plant=plant,
        noise_floor=noise_floor,
        noise_floor_source=floor_source,
        validation=validation,
        validation_traces=val_traces,
        validation_source=val_source,
        true_lut=true_lut,
        true_plant=x.true_plant,
        true_noise_variance=x.true_noise_variance,
        true_cogging=x.true_cogging,
        sources=dict(sources or {}),
        notes=notes,
        cogging=cogging,
        **_artifact_fields(cal, lut, flux, sem),
        **_recording_parts(data, setup, lut, flux, sem, cal_traces, constant_speed),
    )


def _artifact_fields(cal: Calibration, lut: LUT, flux: FluxModel, sem: Any) -> dict[str, Any]:
    """What an artifact says of its calibration (:class:`ReportContent` fields).

    An artifact without ``diagnostics.status`` (the validator reads it as "ok") is reported
    with status "unknown": the report does not vouch for what the file does not say.
    """
    art, diag = cal.artifact, cal.diagnostics
    gain = (art.plant or {}).get("gain_correction")
    gain_details = diag.get("gain_correction")
    adequacy = diag.get("adequacy")
    return dict(
        setup=art.setup,
        lut=lut,
        flux=flux,
        sem=sem,
        gain_correction=None if gain is None else float(gain),
        gain_details=dict(gain_details) if isinstance(gain_details, Mapping) else None,
        predicted_error=cal.predicted_error,
        status=cal.status.value if "status" in diag else "unknown",
        messages=[m.record() for m in cal.messages],
        adequacy=dict(adequacy) if isinstance(adequacy, Mapping) else None,
        timings={str(k): float(v) for k, v in cal.timings.items()},
        model_info={k: v for k, v in cal.model_info.items() if k not in ("theta", "weights")},
    )
