"""The result of a calibration, its artifact, and applying it to a recording.

:class:`Calibration` is what :func:`hallcal.pipeline.calibrate` returns and what
:func:`calibration_from_artifact` rebuilds from a JSON artifact; :func:`reconstruct` applies it
(f_init then the table, the paper's eq. for f_star), :func:`validate` measures it against an
encoder or the bench's truth (step 5 of Algorithm 1).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hallcal._version import __version__
from hallcal.errors import CalibrationRefused, HallcalInputError
from hallcal.io.artifact import ARTIFACT_FORMAT, ArtifactData, validate_artifact, write_artifact
from hallcal.io.dataset import Dataset
from hallcal.io.setup import Setup
from hallcal.limits import check_command_samples
from hallcal.messages import Message, MessageCode
from hallcal.pipeline.powerup import (
    SignalCheck,
    SignalStatus,
    check_signals,
    decoder_for,
    identifiability_from_artifact,
    identification_check,
    same_revolution,
)
from hallcal.pipeline.verdict import CalibrationStatus, refusal
from hallcal.sensor.absolute import (
    IdentifiabilityReport,
    PowerUpIdentification,
    absolute_reconstruction,
)
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT
from hallcal.sensor.metrics import AngleError, SpatialSpectrum, angle_error, spatial_spectrum
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.lti import ContinuousTF

if TYPE_CHECKING:  # result types of the steps, for annotations only (keeps the import light)
    from hallcal.fit.adequacy import AdequacyReport
    from hallcal.fit.cogging_search import CoggingSelection
    from hallcal.fit.constant_speed import ConstantSpeedResult
    from hallcal.fit.kernel import KernelSEMResult
    from hallcal.fit.order import HarmonicSelection
    from hallcal.fit.sem import SEMResult
    from hallcal.pipeline.plant import BLAIdentification, GainCorrection
    from hallcal.sensor.observer import ObserverRun

__all__ = [
    "Calibration",
    "CalibrationStatus",
    "Reconstruction",
    "Validation",
    "artifact_from_calibration",
    "calibration_from_artifact",
    "reconstruct",
    "require_table",
    "validate",
]


@dataclass(frozen=True)
class Validation:
    """Angle errors of f_init and f_star against an encoder (y_ref) or the bench's truth.

    Attributes
    ----------
    init, star : AngleError
        RMS and peak error [rad] of f_init and f_star about zero (``rms`` = ``rms_raw``; the
        constant offset, ``mean``, included; about the mean for a constant-speed calibration,
        whose frame is arbitrary): what the predicted error predicts
        (:mod:`hallcal.pipeline.verdict`). ``y_ref`` is taken in the calibration's frame (zero
        at the rotor's position at the calibration run's first sample, as the bench's truth).
    spectrum_init, spectrum_star : SpatialSpectrum
        Cumulative spatial PSD of the errors (cycles per revolution).
    noise_floor : float or None
        The angle noise floor [rad RMS] the errors are compared with, when known.
    """

    init: AngleError
    star: AngleError
    spectrum_init: SpatialSpectrum = field(repr=False)
    spectrum_star: SpatialSpectrum = field(repr=False)
    noise_floor: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "f_init": self.init.to_dict(),
            "f_star": self.star.to_dict(),
            "noise_floor": self.noise_floor,
            "improvement_rms": self.init.rms / self.star.rms if self.star.rms > 0 else None,
        }


def validate(
    lut: LUT,
    dataset: Dataset,
    *,
    noise_floor: float | None = None,
    angles: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    remove_mean: bool = False,
) -> Validation:
    """Errors of f_init and f_star on a dataset with ``y_ref`` (encoder or bench truth).

    The validation of the paper's section "Experimental results" (figures exp_eta and
    exp_spectrum): RMS and peak error about zero (the constant offset included, as the
    predicted error) and the cumulative spatial PSD.

    Parameters
    ----------
    lut : LUT
        The table to validate.
    dataset : Dataset
        A recording with d1, d2, d3 and ``y_ref`` [rad].
    noise_floor : float, keyword-only, optional
        Angle noise floor [rad RMS] to compare with.
    angles : (ndarray, ndarray), keyword-only, optional
        The recording's (y_init, y_star) already computed with `lut` [rad].
    remove_mean : bool, keyword-only
        Errors about their means instead of about zero: for a table whose frame the calibration
        does not fix (a constant-speed spin has no start at rest at y0 = 0).

    Returns
    -------
    Validation
        Errors and spatial spectra of f_init and f_star against ``y_ref``.

    Raises
    ------
    HallcalInputError
        When ``y_ref`` does not move (a recording at standstill cannot be scored).
    """
    y_ref = dataset["y_ref"]
    if not np.ptp(y_ref) > 0:  # no spatial spectrum and no error over position to score
        where = dataset.source
        raise HallcalInputError(
            f"{where}: y_ref does not move (a recording at standstill): nothing to validate "
            "against; record the validation run while the rotor turns",
            source=str(where),
            key="y_ref",
        )
    if angles is None:
        angles = lut.reconstruct(dataset["d1"], dataset["d2"], dataset["d3"])
    yi, ys = angles
    # about zero, as the predicted error: the table's offset is part of what reconstruct outputs
    ei = angle_error(yi, y_ref, remove_mean=remove_mean)
    es = angle_error(ys, y_ref, remove_mean=remove_mean)
    return Validation(
        ei,
        es,
        spatial_spectrum(yi - y_ref, y_ref),
        spatial_spectrum(ys - y_ref, y_ref),
        noise_floor,
    )


@dataclass(frozen=True)
class Reconstruction:
    """f_init and f_star over a recording, run sequentially from y = y_initial.

    A small table: ``rec["y_init"]``, ``rec["y_star"]`` or :attr:`columns`.

    Attributes
    ----------
    y_init, y_star : ndarray (N,)
        The angles [rad], mechanical.
    validation : Validation or None
        Against the recording's ``y_ref`` when it has one.
    identification : PowerUpIdentification or None
        With ``absolute=True``: which pole pair the recording started in, when the sequential
        test was certain, with what posterior probability.
    signals : SignalCheck or None
        Whether the signals fit the calibration's model at all (a remounted ring, swapped or
        rewired sensors do not): :func:`hallcal.pipeline.powerup.check_signals`.
    observer : ObserverRun or None
        With ``observer=True``: the model-based observer's y_obs [rad], misfit and state per
        sample (:mod:`hallcal.sensor.observer`).
    observer_error : AngleError or None
        y_obs against the recording's ``y_ref``, when it has one.

    ``y_star`` is None when the calibration has no table (a folding map, observer only).
    messages : tuple of Message
        Warnings: a ``y_ref`` that cannot be scored (a recording at standstill) leaves
        ``validation`` None and says so here; the angles stand.
    """

    y_init: NDArray[np.float64] = field(repr=False)
    y_star: NDArray[np.float64] | None = field(repr=False)
    validation: Validation | None = None
    identification: PowerUpIdentification | None = None
    observer: ObserverRun | None = field(default=None, repr=False)
    observer_error: AngleError | None = None
    signals: SignalCheck | None = None
    messages: tuple[Message, ...] = ()

    @property
    def status(self) -> SignalStatus:
        """``fits``, ``mismatch`` (recalibrate), ``wiring`` (another order of d1..d3 fits) or
        ``unchecked``; :attr:`signals` has the one-line message."""
        return SignalStatus.UNCHECKED if self.signals is None else self.signals.status

    @property
    def columns(self) -> dict[str, NDArray[Any]]:
        """``{"y_init": ..., "y_star": ...}`` (the columns ``hallcal reconstruct`` writes), with
        ``y_obs``, ``misfit`` and ``state`` from the observer (``reconstruct --observer``)."""
        cols: dict[str, NDArray[Any]] = {"y_init": self.y_init}
        if self.y_star is not None:
            cols["y_star"] = self.y_star
        if self.observer is not None:
            cols["y_obs"] = self.observer.y_obs
            cols["misfit"] = self.observer.misfit
            cols["state"] = self.observer.state
        return cols

    def __getitem__(self, name: str) -> NDArray[Any]:
        return self.columns[name]

    def __len__(self) -> int:
        return int(self.y_init.size)


@dataclass(frozen=True)
class Calibration:
    """Result of a calibration (Algorithm 1), or one rebuilt from its artifact.

    Attributes
    ----------
    setup : Setup
    flux : FluxModel
        Identified g_theta* (Fourier coefficients; the kernel model in its exact Fourier form).
    lut : LUT
        The table and the f_init it corrects.
    status : CalibrationStatus
    refusal : str or None
        Why the table must not be used (``status.refused``), else None.
    messages : tuple of Message
        Warnings and notes for the user, most important first.
    predicted_error : float
        Predicted RMS angle error of f_star [rad]: the noise floor and the table's uncertainty
        from cov(theta), in quadrature (:class:`~hallcal.fit.adequacy.AdequacyReport`).
    noise_floor : float
        RMS angle error [rad] that the Hall noise alone causes with this sensor map.
    plant : ContinuousTF or None
        The plant model used in SEM (gain correction applied); None for open-loop runs.
    plant_source : {"setup", "bla"} or None
    gain : GainCorrection or None
    sem : SEMResult or None
        The SEM solve (closed-loop runs computed in this process).
    bla : BLAIdentification or None
    adequacy : AdequacyReport or None
    validation : Validation or None
        Errors against ``y_ref`` when the calibration data had it (validation only).
    timings : dict
        Seconds per step.
    model_info : dict
        Basis description for the artifact (basis, harmonics, theta, kernel hyperparameters).
    selection : HarmonicSelection or None
        The automatic choice of harmonics (``harmonics = "auto"``).
    kernel : KernelSEMResult or None
        The kernel-basis solve (``basis = "kernel"``).
    constant_speed : ConstantSpeedResult or None
        The open-loop constant-speed fit (``[trajectory] kind = "constant-speed"``).
    cogging : CoggingTorque or None
        The cogging torque identified jointly with the flux (``[model] cogging``), with the
        covariance of its coefficients; None when none was modelled or found.
    cogging_selection : CoggingSelection or None
        How its orders were chosen (evidence and tests).
    identifiability : IdentifiabilityReport or None
        How well the pole pair can be identified at power-up from the magnets' signatures
        (:mod:`hallcal.sensor.absolute`); None without a bijective table or for artifacts
        made before it existed.
    observer : mapping or None
        The model-based observer's check at calibration time (the artifact's ``observer``
        entry: noise variance per channel, whether the three-signal curve is injective with
        its margin; :func:`hallcal.pipeline.observe.observer_check`); None when not checked.
    sensors : dict
        What the data say about the sensors themselves (:mod:`hallcal.fit.censor`,
        :mod:`hallcal.fit.drift`): ``censoring`` (censored samples per sensor, rails,
        quantization step) and ``drift`` when found; the artifact's ``diagnostics.sensors``.
    artifact : dict or None
        The artifact this calibration was loaded from (None when computed here).
    """

    setup: Setup
    flux: FluxModel
    lut: LUT
    status: CalibrationStatus
    predicted_error: float
    noise_floor: float
    refusal: str | None = None
    messages: tuple[Message, ...] = ()
    plant: ContinuousTF | None = None
    plant_source: str | None = None
    gain: GainCorrection | None = None
    sem: SEMResult | None = field(default=None, repr=False)
    bla: BLAIdentification | None = field(default=None, repr=False)
    adequacy: AdequacyReport | None = field(default=None, repr=False)
    validation: Validation | None = None
    timings: Mapping[str, float] = field(default_factory=dict, repr=False)
    model_info: Mapping[str, Any] = field(default_factory=dict, repr=False)
    selection: HarmonicSelection | None = field(default=None, repr=False)
    kernel: KernelSEMResult | None = field(default=None, repr=False)
    constant_speed: ConstantSpeedResult | None = field(default=None, repr=False)
    cogging: CoggingTorque | None = field(default=None, repr=False)
    cogging_selection: CoggingSelection | None = field(default=None, repr=False)
    identifiability: IdentifiabilityReport | None = field(default=None, repr=False)
    observer: Mapping[str, Any] | None = field(default=None, repr=False)
    sensors: Mapping[str, Any] = field(default_factory=dict, repr=False)
    artifact: Mapping[str, Any] | None = field(default=None, repr=False)

    @property
    def pole_pairs(self) -> int:
        """n_m."""
        return self.setup.pole_pairs

    @property
    def observer_only(self) -> bool:
        """No table can exist (folding map), but the model fits and the observer can track the
        angle (the artifact's ``observer.injective``, set only then for a folding map)."""
        return (
            self.status is CalibrationStatus.NOT_BIJECTIVE
            and self.observer is not None
            and self.observer.get("injective") is True
        )

    @property
    def diagnostics(self) -> Mapping[str, Any]:
        """The artifact's ``diagnostics`` (status, costs, noise variance, ...): as loaded, or as
        :meth:`save` writes them; the same keys whichever way this calibration was made."""
        if self.artifact is not None:
            return self.artifact["diagnostics"]
        return _diagnostics(self)

    def to_artifact(self) -> dict[str, Any]:
        """The JSON artifact (a plain dict; see :func:`artifact_from_calibration`); for a
        calibration loaded from an artifact, that artifact."""
        if self.artifact is not None:
            return dict(self.artifact)
        return artifact_from_calibration(self)

    def save(self, path: str | os.PathLike[str], *, force: bool = False) -> None:
        """Write the JSON artifact atomically.

        Parameters
        ----------
        path : path-like
            Destination file; its directory must exist.
        force : bool, keyword-only
            Write a calibration refused as inadequate anyway (never one that is not
            bijective).

        Raises
        ------
        CalibrationRefused
            When the table is not bijective (unless the observer can use the model:
            :attr:`observer_only`), or the model was judged inadequate and ``force`` is False;
            nothing is written.
        """
        if self.observer_only:
            write_artifact(path, self.to_artifact())
            return
        refused = refusal(self.status, self.refusal, force=force)
        if refused is not None:
            hint = (
                ""
                if refused.code is MessageCode.NOT_BIJECTIVE
                else " (use --force, or force=True, to write it anyway)"
            )
            raise CalibrationRefused(f"{refused.text}; no artifact written{hint}")
        write_artifact(path, self.to_artifact())

    def reconstruct(
        self,
        data: Dataset,
        *,
        y_initial: float = 0.0,
        absolute: bool = False,
        observer: bool = False,
    ) -> Reconstruction:
        """Apply the calibration to a recording (``hallcal reconstruct [--absolute|--observer]``).

        Parameters
        ----------
        data : Dataset
        y_initial : float, keyword-only
            f_init's angle before the first sample [rad] (the calibration run started at 0).
        absolute : bool, keyword-only
            The recording starts at power-up anywhere: identify the pole pair from the
            magnets' signatures and give the angles in the calibration's frame (modulo one
            revolution; ``y_initial`` is not used). Raises :class:`CalibrationRefused` when
            the calibration says the pole pair is not identifiable.
        observer : bool, keyword-only
            Also run the model-based observer (:mod:`hallcal.sensor.observer`): columns
            y_obs, misfit and state. The only way to use a calibration without a table
            (:attr:`observer_only`).

        Returns
        -------
        Reconstruction
            y_init, y_star; its ``status`` says whether the signals fit the calibration's
            model at all (:func:`hallcal.pipeline.powerup.check_signals`; ``hallcal
            reconstruct`` exits 3 when they do not).
        """
        if observer:
            return _reconstruct_observer(self, data, y_initial=y_initial)
        if absolute:
            return _reconstruct_absolute(self, data)
        if self.observer_only:
            raise CalibrationRefused(
                "no lookup table can exist for this motor (the sensor map folds); the "
                "calibration is for the model-based observer: use 'reconstruct --observer'"
            )
        rec = reconstruct_with(self.lut, data, y_initial=y_initial)
        decoder = None
        if self.identifiability is not None:
            decoder = self.identifiability.decoder(self.flux, self.lut)
        return dataclasses.replace(rec, signals=check_signals(decoder, data))


def _diagnostics(cal: Calibration) -> dict[str, Any]:
    diag: dict[str, Any] = {
        "status": cal.status.value,
        "refusal": cal.refusal,
        "messages": [m.record() for m in cal.messages],
        "bijective": bool(cal.lut.bijective),
        "min_slope": cal.lut.min_slope,
        "predicted_angle_error_rms": cal.predicted_error,
        "noise_floor": cal.noise_floor,
        "timings": dict(cal.timings),
    }
    sem = cal.sem
    if sem is not None:
        diag.update(
            {
                "cost_initial": sem.initial_cost,
                "cost": sem.cost,
                "cost_history": sem.cost_history.tolist(),
                "iterations": sem.iterations,
                "sem_status": str(sem.status),
                "solve_time": sem.solve_time,
                "noise_variance": sem.noise_variance,
                "n_samples": sem.n_samples,
            }
        )
    if cal.adequacy is not None:
        diag["adequacy"] = cal.adequacy.to_dict()
    if cal.validation is not None:
        diag["validation"] = cal.validation.to_dict()
    if cal.gain is not None:
        diag["gain_correction"] = cal.gain.to_dict()
    if cal.constant_speed is not None:
        diag["constant_speed"] = cal.constant_speed.to_dict()
    if cal.cogging_selection is not None:
        diag["cogging"] = cal.cogging_selection.to_dict()
    if cal.selection is not None:  # without wall times: they live in "timings" only
        diag["model_selection"] = cal.selection.to_dict(timings=False)
        del diag["model_selection"]["report"]  # the final fit's is "adequacy"
    if cal.kernel is not None:
        diag["model_selection"] = {
            "basis": "kernel",
            "ard_rounds": cal.kernel.ard_rounds,
            "settled": bool(cal.kernel.settled),
            "budget_hit": not cal.kernel.settled,
            "sem_status": str(cal.kernel.status),
        }
    if cal.sensors:
        diag["sensors"] = dict(cal.sensors)
    return diag


def artifact_from_calibration(cal: Calibration) -> dict[str, Any]:
    """The versioned JSON calibration artifact of docs/design.md (a plain dict).

    Parameters
    ----------
    cal : Calibration
        The result of a calibration.

    Returns
    -------
    dict
        Format, pole pairs, f_init's projection and offsets, the model (basis, theta), the
        table, the setup, diagnostics, and where present identifiability, plant and cogging;
        ready for :func:`~hallcal.io.write_artifact`.
    """
    art: dict[str, Any] = {
        "format": ARTIFACT_FORMAT,
        "hallcal_version": __version__,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "pole_pairs": cal.setup.pole_pairs,
        "reconstruction": {
            "method": "f_init (Clarke/projection, atan2, unwrap) + lookup table (f_star)",
            "projection": cal.lut.projection.tolist(),
            "offset": cal.lut.offset.tolist(),
        },
        "model": dict(cal.model_info),
        "lut": cal.lut.to_dict(),
        "setup": cal.setup,
        "diagnostics": _diagnostics(cal),
    }
    if cal.identifiability is not None:
        art["identifiability"] = cal.identifiability.to_dict()
    if cal.plant is not None:
        art["plant"] = {
            "num": list(cal.plant.num),
            "den": list(cal.plant.den),
            "delay": cal.plant.delay,
            "gain_correction": None if cal.gain is None else cal.gain.value,
            "source": cal.plant_source,
        }
    if cal.cogging is not None:
        art["cogging"] = cal.cogging.to_dict()
    if cal.observer is not None:
        art["observer"] = dict(cal.observer)
    return art


def _float_or_nan(value: Any) -> float:
    return float(value) if isinstance(value, int | float) else math.nan


def calibration_from_artifact(artifact: ArtifactData | Mapping[str, Any]) -> Calibration:
    """Rebuild a :class:`Calibration` from an artifact (:func:`~hallcal.io.read_artifact`'s, or
    a mapping, which is checked by :func:`~hallcal.io.validate_artifact` first).

    The flux model, table, setup, status, messages, predicted error and plant come back; the
    solver's internals (SEM iterates, BLA spectra) stay in :attr:`Calibration.artifact`.

    Parameters
    ----------
    artifact : ArtifactData or mapping
        A loaded artifact, or its parsed JSON.

    Returns
    -------
    Calibration

    Raises
    ------
    HallcalInputError
        The artifact does not pass the validator, or its ``diagnostics.status`` is not one of
        :class:`CalibrationStatus`.
    """
    art = validate_artifact(artifact, "artifact")
    diag = art.diagnostics
    try:
        status = CalibrationStatus(diag.get("status", "ok"))
    except ValueError:
        options = ", ".join(f'"{s.value}"' for s in CalibrationStatus)
        raise HallcalInputError(
            f"{art.source}: key 'diagnostics.status' must be one of {options}",
            source=art.source,
            key="diagnostics.status",
        ) from None
    try:
        identifiability = identifiability_from_artifact(art.data)
    except HallcalInputError as exc:  # it says "artifact:"; name the file
        text = str(exc).removeprefix("artifact:").strip()
        raise HallcalInputError(
            f"{art.source}: {text}", source=art.source, key=exc.key or "identifiability"
        ) from None
    return Calibration(
        setup=art.setup,
        flux=art.flux(),
        lut=art.lut(),
        status=status,
        predicted_error=_float_or_nan(diag.get("predicted_angle_error_rms")),
        noise_floor=_float_or_nan(diag.get("noise_floor")),
        refusal=diag.get("refusal"),
        messages=tuple(Message.from_record(m) for m in diag.get("messages", ())),
        plant=art.plant_model(),
        plant_source=None if art.plant is None else art.plant.get("source"),
        timings=dict(diag.get("timings", {})),
        model_info=dict(art.model),
        identifiability=identifiability,
        observer=art.data.get("observer"),
        artifact=art.data,
        cogging=art.cogging_torque(),
    )


def require_table(artifact: ArtifactData | Mapping[str, Any], source: str = "artifact") -> None:
    """Refuse (exit 3) a calibration kept for the observer only (no table can exist).

    Parameters
    ----------
    artifact : ArtifactData or mapping
        A loaded artifact, or its parsed JSON.
    source : str
        Its name in the message (the file).

    Raises
    ------
    CalibrationRefused
        When the artifact's table is not bijective (a folding map written for the observer).
    """
    if not validate_artifact(artifact, "artifact").lut().bijective:
        raise CalibrationRefused(
            f"{source}: no lookup table can exist for this motor (the sensor map folds); the "
            "calibration is for the model-based observer ('reconstruct --observer')"
        )


def reconstruct_with(lut: LUT, dataset: Dataset, *, y_initial: float = 0.0) -> Reconstruction:
    """f_init and f_star of a recording with a table, validated when it has ``y_ref``.

    Raises
    ------
    CalibrationRefused
        When the table is not bijective.
    """
    if not lut.bijective:
        raise CalibrationRefused("the lookup table is not bijective; refusing to use it")
    dataset.require("d1", "d2", "d3")
    _within_budget(dataset, "reconstruct" if "y_ref" in dataset else "reconstruct without y_ref")
    yi, ys = lut.reconstruct(dataset["d1"], dataset["d2"], dataset["d3"], y_initial=y_initial)
    val: Validation | None = None
    notes: tuple[Message, ...] = ()
    if "y_ref" in dataset:
        val, notes = _scored(lambda: validate(lut, dataset, angles=(yi, ys)))
    return Reconstruction(yi, ys, val, messages=notes)


def validation_skipped(exc: Exception) -> Message:
    """The warning when ``y_ref`` cannot be scored (a standstill run): the result stands.

    Parameters
    ----------
    exc : Exception
        Why it cannot be scored.

    Returns
    -------
    Message
    """
    return Message.warning(MessageCode.VALIDATION_SKIPPED, f"validation skipped: {exc}")


def _scored(score: Any) -> tuple[Validation | None, tuple[Message, ...]]:
    """The validation, or None and a warning when ``y_ref`` cannot be scored."""
    try:
        return score(), ()
    except HallcalInputError as exc:
        return None, (validation_skipped(exc),)


def _within_budget(dataset: Dataset, command: str) -> None:
    """The recording fits the command's memory budget (:data:`~hallcal.limits.BYTES_PER_SAMPLE`)."""
    try:
        check_command_samples(dataset.n_samples, command)
    except ValueError as exc:
        raise HallcalInputError(f"{dataset.source}: {exc}", source=dataset.source) from None


def _reconstruct_observer(
    cal: Calibration, dataset: Dataset, *, y_initial: float = 0.0
) -> Reconstruction:
    """``Calibration.reconstruct(observer=True)``: the table's angles when it exists, and the
    observer's (see :mod:`hallcal.pipeline.observe`)."""
    from hallcal.pipeline.observe import run_on  # numba kernels: loaded for the observer only

    dataset.require("d1", "d2", "d3")
    if cal.lut.bijective:
        rec = reconstruct_with(cal.lut, dataset, y_initial=y_initial)
    else:
        y_init = cal.lut.f_init(dataset.d, y_initial=y_initial)
        rec = Reconstruction(y_init, None)
    obs = run_on(cal, np.ascontiguousarray(dataset.d), y_initial=y_initial)
    err = angle_error(obs.y_obs, dataset["y_ref"]) if "y_ref" in dataset else None
    return Reconstruction(
        rec.y_init,
        rec.y_star,
        rec.validation,
        observer=obs,
        observer_error=err,
        messages=rec.messages,
    )


def _reconstruct_absolute(cal: Calibration, dataset: Dataset) -> Reconstruction:
    """``Calibration.reconstruct(absolute=True)``: see :mod:`hallcal.pipeline.powerup`."""
    _within_budget(dataset, "reconstruct --absolute")
    decoder = decoder_for(cal.flux, cal.lut, cal.identifiability)
    out = absolute_reconstruction(decoder, cal.lut, dataset.d)
    validation: Validation | None = None
    notes: tuple[Message, ...] = ()
    if "y_ref" in dataset:
        ref = same_revolution(out.y_star, dataset["y_ref"])
        moved = dataclasses.replace(dataset, columns={**dataset.columns, "y_ref": ref})
        validation, notes = _scored(
            lambda: validate(cal.lut, moved, angles=(out.y_init, out.y_star))
        )
    signals = identification_check(decoder, dataset, out)
    return Reconstruction(
        out.y_init,
        out.y_star,
        validation,
        out.identification,
        signals=signals,
        messages=notes,
    )


def reconstruct(
    artifact: ArtifactData | Mapping[str, Any],
    dataset: Dataset,
    *,
    y_initial: float = 0.0,
    absolute: bool = False,
) -> Reconstruction:
    """Apply a calibration artifact to a recording (``hallcal reconstruct [--absolute]``).

    Parameters
    ----------
    artifact : ArtifactData or mapping
        A loaded artifact, or its parsed JSON.
    dataset : Dataset
        The recording (d1, d2, d3; ``y_ref`` is used for validation when present).
    y_initial : float, keyword-only
        f_init's estimate before the first sample [rad] (ignored with ``absolute``).
    absolute : bool, keyword-only
        Identify the pole pair at power-up and give the angles in the calibration's frame.

    Returns
    -------
    Reconstruction
        y_init and y_star [rad] per sample, the validation against ``y_ref`` when present, and
        the power-up identification with ``absolute``.

    Raises
    ------
    HallcalInputError
        The artifact does not pass :func:`~hallcal.io.validate_artifact` (a table that is not
        bijective included).
    CalibrationRefused
        (``absolute``) When the pole pair is not identifiable with this motor's sensors.
    """
    return calibration_from_artifact(artifact).reconstruct(
        dataset, y_initial=y_initial, absolute=absolute
    )
