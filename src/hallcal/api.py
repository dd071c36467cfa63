"""The front door for notebooks and scripts: :func:`calibrate`, :func:`load`, :class:`Calibration`.

>>> import hallcal
>>> cal = hallcal.calibrate("cal.csv", "setup.toml")           # doctest: +SKIP
>>> cal.status, cal.predicted_error                             # doctest: +SKIP
>>> cal.save("cal.json"); cal.report("report/"); cal.export_c("fw/")   # doctest: +SKIP
>>> angles = hallcal.load("cal.json").reconstruct("run.csv")   # doctest: +SKIP
>>> angles["y_star"]                                            # doctest: +SKIP

Data may be a file path, a :class:`~hallcal.io.Dataset` or a mapping of column name to array;
a setup a path, a :class:`~hallcal.io.Setup` or a mapping with the layout of the TOML file. The
command line is a thin layer over these calls.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from hallcal.errors import HallcalInputError
from hallcal.io.artifact import read_artifact
from hallcal.io.dataset import Dataset, read_dataset
from hallcal.io.setup import Setup, read_setup, setup_from_dict
from hallcal.pipeline import calibrate as _calibrate
from hallcal.pipeline.calibration import Calibration as _Result
from hallcal.pipeline.calibration import Reconstruction, calibration_from_artifact

__all__ = [
    "Calibration",
    "DataLike",
    "SetupLike",
    "as_dataset",
    "as_setup",
    "calibrate",
    "export_c",
    "load",
]

DataLike = str | os.PathLike[str] | Dataset | Mapping[str, Any]
SetupLike = str | os.PathLike[str] | Setup | Mapping[str, Any]


def as_dataset(data: DataLike, *, required: tuple[str, ...] = ("d1", "d2", "d3")) -> Dataset:
    """A :class:`~hallcal.io.Dataset` from a path, a dataset or a mapping of columns.

    Parameters
    ----------
    data : path, Dataset or mapping of columns
        A dataset file (read with :func:`~hallcal.io.read_dataset`), a dataset, or column name
        -> array.
    required : tuple of str, keyword-only
        Columns that must be present.

    Returns
    -------
    Dataset

    Raises
    ------
    HallcalInputError
        Unreadable data, a missing required column, or a type that is none of the above.
    """
    if isinstance(data, Dataset):
        data.require(*required)
        return data
    if isinstance(data, str | os.PathLike):
        return read_dataset(data, required=required)
    if isinstance(data, Mapping):
        return Dataset.from_columns(data, required=required)
    raise HallcalInputError(
        f"data must be a file path, a Dataset or a mapping of columns, not {type(data).__name__}"
    )


def as_setup(setup: SetupLike) -> Setup:
    """A :class:`~hallcal.io.Setup` from a path, a setup or a mapping (the TOML layout).

    Parameters
    ----------
    setup : path, Setup or mapping
        A TOML setup file, a setup, or the parsed TOML as nested mappings.

    Returns
    -------
    Setup

    Raises
    ------
    HallcalInputError
        An invalid setup (the message names the key), or a type that is none of the above.
    """
    if isinstance(setup, Setup):
        return setup
    if isinstance(setup, str | os.PathLike):
        return read_setup(setup)
    if isinstance(setup, Mapping):
        return setup_from_dict(setup)
    raise HallcalInputError(
        f"setup must be a file path, a Setup or a mapping, not {type(setup).__name__}"
    )


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Calibration(_Result):
    """A calibration with the verbs a notebook user needs: :meth:`save`, :meth:`reconstruct`,
    :meth:`report`, :meth:`export_c`.

    A :class:`hallcal.pipeline.Calibration` (its artifact and, when computed in this process,
    its in-memory diagnostics: ``cal.status``, ``cal.lut``, ``cal.predicted_error``,
    ``cal.to_artifact()``, ... see that class) whose methods also take file paths and mappings.
    """

    @property
    def result(self) -> _Result:
        """The pipeline's calibration: this object."""
        return self

    def __repr__(self) -> str:
        return f"hallcal.{super().__repr__()}"

    def reconstruct(
        self,
        data: DataLike,
        *,
        y_initial: float = 0.0,
        absolute: bool = False,
        observer: bool = False,
    ) -> Reconstruction:
        """f_init and f_star over a recording: ``rec["y_init"]``, ``rec["y_star"]`` [rad].

        Parameters
        ----------
        data : path, Dataset or mapping
            Columns d1, d2, d3 (``y_ref``, when present, validates the result: it is checked to
            be in radians first).
        y_initial, absolute, observer : keyword-only
            As :meth:`hallcal.pipeline.Calibration.reconstruct`.

        Returns
        -------
        Reconstruction
        """
        from hallcal.pipeline.checks import check_recording, raise_if_failed

        ds = as_dataset(data)
        # the encoder column validates the result: in degrees its numbers would be nonsense
        checks = check_recording(
            ds, pole_pairs=self.pole_pairs, sample_time=None, angles=("y_ref",)
        )
        raise_if_failed(checks, ds.source)
        return super().reconstruct(ds, y_initial=y_initial, absolute=absolute, observer=observer)

    def report(
        self,
        out_dir: str | os.PathLike[str],
        *,
        data: DataLike | None = None,
        validation: DataLike | None = None,
        units: str = "mrad",
    ) -> Path:
        """Write the figures and the HTML report; returns the HTML file's path.

        Parameters
        ----------
        out_dir : path
            Folder (created if needed).
        data : path, Dataset or mapping
            The calibration recording (the report's figures and model fit are drawn from it;
            required: a HallcalInputError without it).
        validation : path, Dataset or mapping, optional
            A fresh recording with ``y_ref`` to validate on.
        units : {"mrad", "rad", "deg", "electrical-deg"}
            Units of the angle errors in the report's text (:class:`hallcal.formatting.AngleUnit`;
            another name is a :class:`~hallcal.errors.HallcalInputError` naming the valid ones).
        """
        from hallcal.output.report import write_calibration_report

        if data is None:  # the report is drawn from the recording: it cannot be written without
            raise HallcalInputError("report needs data=, the calibration recording")
        return write_calibration_report(
            self,
            as_dataset(data),
            out_dir,
            validation=None if validation is None else as_dataset(validation, required=("y_ref",)),
            units=units,
        )

    def export_c(
        self,
        out_dir: str | os.PathLike[str],
        *,
        adc_scale: float | None = None,
        fixed_point: bool | None = None,
        **options: Any,
    ) -> Any:
        """Generate the C99 sources of f_star for firmware (:func:`export_c`).

        Parameters
        ----------
        out_dir : path-like
            Directory for the ``.h``/``.c`` files.
        adc_scale : float, keyword-only, optional
            ADC counts per unit of the calibration's Hall signals (the fixed-point variant's
            inputs); default: the artifact is in counts when its noise says so.
        fixed_point : bool, keyword-only, optional
            Default: the fixed-point pair whenever it can be made (see :func:`export_c`).
        **options
            The other options of :func:`hallcal.output.codegen.export_c` (``prefix``,
            ``table_points``, ``max_speed``, ...); ``observer=True`` writes the model-based
            observer instead (:func:`hallcal.output.codegen.c_observer.export_observer_c`,
            option ``prefix``).

        Returns
        -------
        ExportResult
            The files written and the table's error figures
            (:class:`hallcal.output.codegen.ExportResult`).
        """
        artifact = self.to_artifact()
        if options.pop("observer", False):
            from hallcal.output.codegen.c_observer import export_observer_c

            return export_observer_c(artifact, out_dir, **options)
        return export_c(artifact, out_dir, adc_scale=adc_scale, fixed_point=fixed_point, **options)


#: Hall noise variance [signal unit^2] below which an artifact's signals are not ADC counts:
#: rounding to whole counts adds 1/12 count^2 per channel, more than such signals' own noise
#: (the bench's amplitude-1 signals have 7.5e-6).
COUNTS_NOISE_VARIANCE = 1.0 / 12.0


def export_c(
    artifact: Any,
    out_dir: str | os.PathLike[str],
    *,
    adc_scale: float | None = None,
    fixed_point: bool | None = None,
    **options: Any,
) -> Any:
    """The C export with the defaults every entry point shares (CLI, API, fleet).

    The float pair (``hallcal.h``/``.c``) needs no ADC scale and is always written. The
    fixed-point pair takes integer counts: it is written when ``adc_scale`` is given, or when
    the artifact's Hall signals are already counts (their noise variance is at least
    :data:`COUNTS_NOISE_VARIANCE` and the fixed-point design accepts scale 1); otherwise it is
    left out with a note naming the option that writes it.

    Parameters
    ----------
    artifact : mapping or ArtifactData
        The calibration artifact.
    out_dir : path-like
    adc_scale : float, keyword-only, optional
        ADC counts per unit of the artifact's Hall signals.
    fixed_point : bool, keyword-only, optional
        True: the fixed-point pair is required (an unfit scale is an error); False: float only;
        None (default): as above.
    **options
        Passed to :func:`hallcal.output.codegen.export_c`.

    Returns
    -------
    ExportResult
    """
    from hallcal.output.codegen import export_c as _export
    from hallcal.pipeline.calibration import require_table

    require_table(artifact)
    if fixed_point is not None or adc_scale is not None:
        want = True if fixed_point is None else bool(fixed_point)
        scale = 1.0 if adc_scale is None else adc_scale
        return _export(artifact, out_dir, fixed_point=want, adc_scale=scale, **options)
    data = getattr(artifact, "data", artifact)
    variance = (data.get("diagnostics") or {}).get("noise_variance")
    if isinstance(variance, int | float) and variance < COUNTS_NOISE_VARIANCE:
        why = (
            f"the Hall signals are not ADC counts (noise {variance**0.5:.2g} RMS, under one count)"
        )
    else:
        try:
            return _export(artifact, out_dir, fixed_point=True, adc_scale=1.0, **options)
        except HallcalInputError as exc:
            why = str(exc)
    res = _export(artifact, out_dir, fixed_point=False, **options)
    note = (
        f"fixed-point variant (hallcal_q.c) not written: {why}; give the ADC counts per unit "
        "of the Hall signals (--adc-scale, adc_scale=) to write it"
    )
    return dataclasses.replace(res, messages=(*res.messages, note))


def calibrate(
    data: DataLike,
    setup: SetupLike,
    *,
    bla_data: DataLike | None = None,
    progress: Callable[[str], None] | None = None,
) -> Calibration:
    """Calibrate the Hall sensors of one motor (Algorithm 1 of van Meer et al.).

    Parameters
    ----------
    data : path, Dataset or mapping of columns
        The calibration run: r, y, d1..d3 (closed loop) or d1..d3 (constant speed).
    setup : path, Setup or mapping
        The setup (TOML layout): pole pairs, sample time, controller, plant or ``[bla]``, model.
    bla_data : path, Dataset or mapping, optional
        Multisine experiment (r, u, y, realization) for the plant's BLA.
    progress : callable, optional
        Called with one short message per step.

    Returns
    -------
    Calibration
        Look at ``cal.status`` (``cal.refusal`` says why a refused one must not be used),
        ``cal.predicted_error`` and ``cal.messages``.

    Raises
    ------
    HallcalInputError
        A file, column or setup key that cannot be used (the message names it).
    """
    s = as_setup(setup)
    closed = s.trajectory.kind == "closed-loop"
    ds = as_dataset(data, required=("r", "d1", "d2", "d3") if closed else ("d1", "d2", "d3"))
    bla_ds = None
    if bla_data is not None:
        bla_ds = as_dataset(bla_data, required=("r", "u", "y", "realization"))
    result = _calibrate(ds, s, bla_dataset=bla_ds, progress=progress)
    return Calibration(result.artifact, result.computed)


def load(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration artifact (JSON) written by :meth:`Calibration.save` or the CLI.

    Parameters
    ----------
    path : path-like
        The artifact file.

    Returns
    -------
    Calibration
        With its status, lookup table, flux model and messages as saved.

    Raises
    ------
    HallcalInputError
        Missing file or an invalid artifact (the message names the key).
    """
    return Calibration(calibration_from_artifact(read_artifact(path)).artifact)
