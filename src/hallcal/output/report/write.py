"""Writing a report (:func:`write_report`) and the entry points of the CLI, the demo and
:meth:`hallcal.Calibration.report`."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hallcal.errors import HallcalInputError
from hallcal.formatting import AngleUnit
from hallcal.io import (
    Dataset,
    atomic_write,
    make_folder,
    output_set,
    read_artifact,
    read_dataset,
    read_json,
)
from hallcal.io.artifact import migrate_values
from hallcal.output.plots import figure_png
from hallcal.output.report.content import ReportContent, ReportExtras, report_content
from hallcal.output.report.figures import make_figures
from hallcal.output.report.page import _DPI, render_html
from hallcal.pipeline.calibration import Calibration
from hallcal.pipeline.progress import Progress, say
from hallcal.sim.lti import ContinuousTF

REPORT_NAME = "report.html"
FIGURE_DIR = "figures"


def write_report(
    content: ReportContent,
    out_dir: str | os.PathLike[str],
    *,
    progress: Progress = None,
) -> Path:
    """Write the figures (``out_dir/figures/*.png``) and ``out_dir/report.html`` as one set.

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
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise HallcalInputError(f"{out}: exists and is not a directory")
    say(progress, "figures")
    figs = make_figures(content)
    images = [(f, figure_png(f.figure, dpi=_DPI)) for f in figs]
    say(progress, "HTML report")
    text = render_html(content, images)
    path = out / REPORT_NAME
    with output_set():  # the figures and the page appear together, or nothing changes
        make_folder(out / FIGURE_DIR)
        for f, png in images:
            with atomic_write(out / FIGURE_DIR / f"{f.key}.png", "wb") as fh:
                fh.write(png)
        with atomic_write(path, "w") as fh:
            fh.write(text)
    return path


# ------------------------------------------------------------------------------------------------
# Entry points of the CLI and the demo
# ------------------------------------------------------------------------------------------------


def _read_bla(path: Path) -> Any:
    """The BLA of ``hallcal bla``'s file (format ``hallcal-bla/1``), to plot."""
    from hallcal.identify.bla import NonparametricBLA
    from hallcal.identify.parametric import ParametricBLA
    from hallcal.pipeline import BLAIdentification
    from hallcal.pipeline.plant import BLAStatus

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
    status = str(data.get("status", "ok"))
    known = status in BLAStatus._value2member_map_  # an unknown one: usable, look at messages
    return BLAIdentification(npb, par, plant, BLAStatus(status) if known else BLAStatus.WARNING)


def write_report_from_files(
    artifact_path: str | os.PathLike[str],
    data_path: str | os.PathLike[str],
    *,
    validation: str | os.PathLike[str] | None = None,
    bla: str | os.PathLike[str] | None = "auto",
    out_dir: str | os.PathLike[str],
    progress: Progress = None,
    units: str | AngleUnit = AngleUnit.MRAD,
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
    units : AngleUnit or its name ("mrad", "rad", "deg", "electrical-deg")
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
    unit = AngleUnit.parse(units)
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
    content = report_content(
        art,
        data,
        extras=ReportExtras(bla=bla_obj),
        validation_data=val,
        sources=sources,
        progress=progress,
    )
    content = dataclasses.replace(content, angle_units=unit)
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
    extras = ReportExtras(
        validation=val,
        noise_floor=noise_floor,
        noise_floor_source="virtual bench: σ·√(2/3)/(A·n_m) with the true σ and A",
        true_flux=cal_run.truth,
        true_plant=cal_run.config.plant,
        true_noise_variance=cal_run.config.noise_variance,
    )
    content = report_content(
        cal,
        Dataset.from_columns(cal_run.columns(), path="calibration.npz"),
        extras=extras,
        validation_data=Dataset.from_columns(val_run.columns(), path="validation.npz"),
        sources={
            "calibration": "calibration.npz",
            "validation": "validation.npz (fresh run, true angle)",
            "BLA experiment": "bla.npz",
        },
        title="hallcal demo: the paper's simulation study",
    )
    return write_report(content, out_dir, progress=progress)


def write_calibration_report(
    cal: Calibration,
    data: Dataset,
    out_dir: str | os.PathLike[str],
    *,
    validation: Dataset | None = None,
    progress: Progress = None,
    units: str | AngleUnit = AngleUnit.MRAD,
) -> Path:
    """The report of a calibration object (``Calibration.report``), computed or loaded.

    Drawn from the calibration's artifact (:func:`report_content`); a calibration computed in
    this process adds its SEM solve and BLA from memory (:attr:`Calibration.computed`), one
    loaded from an artifact is reported as ``hallcal report`` does it.

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
    units : AngleUnit or its name ("mrad", "rad", "deg", "electrical-deg")
        Units of the angle errors in the text.

    Returns
    -------
    pathlib.Path
        The HTML file.
    """
    unit = AngleUnit.parse(units)  # before the work
    content = report_content(
        cal,
        data,
        validation_data=validation,
        progress=progress,
    )
    content = dataclasses.replace(content, angle_units=unit)
    return write_report(content, out_dir, progress=progress)
