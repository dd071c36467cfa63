"""A report's content from a calibration artifact and its recording
(:func:`content_from_artifact`): the closed loop re-simulated with the stored model."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.io import (
    ArtifactData,
    Dataset,
    read_json,
    validate_artifact,
)
from hallcal.io.artifact import migrate_values
from hallcal.output.report.content import (
    _ESTIMATED_FLOOR,
    Progress,
    ReportContent,
    _adequacy_dict,
    _estimated_floor,
    _recording_parts,
    _say,
    _traces,
    _validation_parts,
)
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT
from hallcal.sim.lti import ContinuousTF


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


# ------------------------------------------------------------------------------------------------
# From files
# ------------------------------------------------------------------------------------------------


def _artifact_plant(art: ArtifactData) -> ContinuousTF | None:
    """The plant the calibration used: the artifact's (a BLA's), else the setup's."""
    p = art.plant
    if p is None:
        return art.setup.plant
    return ContinuousTF(
        tuple(float(v) for v in p["num"]), tuple(float(v) for v in p["den"]), float(p["delay"])
    )


def _read_bla(path: Path) -> Any:
    from hallcal.identify.bla import NonparametricBLA
    from hallcal.identify.parametric import ParametricBLA
    from hallcal.pipeline import BLAIdentification

    data = migrate_values(read_json(path))
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
    art: ArtifactData,
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
    from hallcal.fit.sem import SEMResult, SEMStatus
    from hallcal.sim.cogging import CoggingTorque

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
    n = data.n_samples
    s2 = diag.get("noise_variance")
    s2 = math.nan if s2 is None else float(s2)
    setup = art.setup
    cogging = CoggingTorque.from_dict(art.data["cogging"]) if "cogging" in art.data else None
    d_sim = y0_sim = cov = None
    closed = setup.trajectory.kind == "closed-loop"
    if not (closed and plant is not None and setup.controller is not None and "r" in data):
        notes.append(
            "The model fit is shown at the calibrated angle f_star: re-simulating the closed loop "
            "needs a closed-loop trajectory, the plant, the controller and the column 'r'."
        )
    else:
        assert plant is not None
        d_sim, y0_sim, cov, s2 = _closed_loop_fit(
            art, flux, plant, data, lut, cogging, s2, progress=progress, notes=notes
        )
    return SEMResult(
        flux=flux,
        theta0=np.full_like(flux.theta, np.nan),
        cost_history=history,
        iterations=int(diag.get("iterations", history.size - 1)),
        status=str(status),
        solve_time=float(diag.get("solve_time", math.nan)),
        noise_variance=s2,
        covariance=np.full((flux.theta.size,) * 2, np.nan) if cov is None else cov,
        n_samples=int(diag.get("n_samples", n)),
        d_sim=d_sim,
        y0_sim=y0_sim,
        cogging=cogging,
    )


def _closed_loop_fit(
    art: ArtifactData,
    flux: FluxModel,
    plant: ContinuousTF,
    data: Dataset,
    lut: LUT,
    cogging: Any,
    s2: float,
    *,
    progress: Progress,
    notes: list[str],
) -> tuple[Any, Any, Any, float]:
    """The identified model's closed loop on the recording: ``(d_sim, y0_sim, cov, s2)``, the
    covariance (Fourier models) from one Gauss-Newton pass; Nones when it diverges."""
    from hallcal.fit.gauss_newton import ParameterLayout, gauss_newton_system
    from hallcal.sim.loop import ClosedLoop

    setup, diag = art.setup, art.diagnostics
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
    fourier = art.model.get("basis", "fourier") == "fourier"
    if fourier:
        _say(progress, "parameter covariance (one sensitivity pass) for the LUT band")
    gn = gauss_newton_system(loop, layout, x, r, data.d, gram=fourier)
    if not gn.status.success:
        notes.append("Re-simulating the closed loop with the identified model diverged.")
        return None, None, None, s2
    cost = gn.sse
    stored = float(diag.get("cost", cost))
    if not math.isclose(cost, stored, rel_tol=1e-3):
        notes.append(
            f"The data's simulation cost ({cost:.6g}) differs from the artifact's "
            f"({stored:.6g}): the data may not be the calibration recording."
        )
    cov = None
    if fourier:
        if not math.isfinite(s2):
            s2 = cost / max(3 * data.n_samples - layout.size, 1)
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
    return gn.d, gn.y0, cov, s2


def content_from_artifact(
    artifact: Mapping[str, Any] | ArtifactData,
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
    artifact : dict or ArtifactData
        As returned by :func:`hallcal.io.read_artifact` (checked again by
        :func:`hallcal.io.validate_artifact`), or its checked view.
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
    source = (sources or {}).get("artifact", "artifact")
    art = artifact if isinstance(artifact, ArtifactData) else validate_artifact(artifact, source)
    setup, lut, flux, diag = art.setup, art.lut(), art.flux(), art.diagnostics
    plant = _artifact_plant(art)
    notes: list[str] = []
    cal_traces = _traces(lut, data)
    sem = _resimulate(art, flux, plant, data, lut, progress=progress, notes=notes)
    noise_floor, floor_source = _artifact_floor(diag, flux, art.pole_pairs)
    constant_speed = diag.get("constant_speed")
    if not isinstance(constant_speed, Mapping):
        constant_speed = None
    validation, val_traces, val_source = _validation_parts(
        lut, data, cal_traces, validation_data=validation_data, validation=None,
        sources=sources, noise_floor=noise_floor, constant_speed=constant_speed is not None,
        notes=notes,
    )  # fmt: skip
    return ReportContent(
        title=title,
        bla=bla,
        plant=plant,
        noise_floor=noise_floor,
        noise_floor_source=floor_source,
        validation=validation,
        validation_traces=val_traces,
        validation_source=val_source,
        sources=dict(sources or {}),
        notes=notes,
        cogging=None if sem is None else sem.cogging,
        **_artifact_fields(art, lut, flux, sem),
        **_recording_parts(data, setup, lut, flux, sem, cal_traces, constant_speed),
    )


def _artifact_fields(art: ArtifactData, lut: LUT, flux: FluxModel, sem: Any) -> dict[str, Any]:
    """What an artifact says of its calibration (:class:`ReportContent` fields)."""
    diag = art.diagnostics
    gain = (art.plant or {}).get("gain_correction")
    gain_details = diag.get("gain_correction")
    predicted = diag.get("predicted_angle_error_rms")
    timings = diag.get("timings") if isinstance(diag.get("timings"), Mapping) else {}
    return dict(
        setup=art.setup,
        lut=lut,
        flux=flux,
        sem=sem,
        gain_correction=None if gain is None else float(gain),
        gain_details=dict(gain_details) if isinstance(gain_details, Mapping) else None,
        predicted_error=None if predicted is None else float(predicted),
        status=str(diag.get("status", "unknown")),
        messages=[str(m) for m in diag.get("messages", [])],
        adequacy=_adequacy_dict(diag.get("adequacy")),
        timings={str(k): float(v) for k, v in timings.items()},
        model_info={k: v for k, v in art.model.items() if k not in ("theta", "weights")},
    )
