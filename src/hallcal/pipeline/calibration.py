"""The result of a calibration, its artifact, and applying it to a recording.

:class:`Calibration` is what :func:`hallcal.pipeline.calibrate` returns
(:func:`computed_calibration` writes its artifact) and what :func:`calibration_from_artifact`
reads from a JSON artifact: one type, the artifact plus the in-memory :class:`Diagnostics` of a
calibration computed here; :func:`reconstruct` applies it
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
    drift_message,
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
    "Diagnostics",
    "Reconstruction",
    "Validation",
    "calibration_from_artifact",
    "computed_calibration",
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
class Diagnostics:
    """What a calibration computed in this process has beyond its artifact (all optional).

    A calibration loaded from an artifact has none of it: what the artifact keeps of these is
    in its ``diagnostics`` (:attr:`Calibration.diagnostics`).

    Attributes
    ----------
    sem : SEMResult or None
        The SEM solve (closed-loop runs): d_sim, y0_sim, cov(theta), the cost history.
    bla : BLAIdentification or None
    gain : GainCorrection or None
        The BLA's gain correction c-hat (the artifact keeps its value and report).
    adequacy : AdequacyReport or None
    validation : Validation or None
        Errors against ``y_ref`` when the calibration data had it.
    selection : HarmonicSelection or None
        The automatic choice of harmonics (``harmonics = "auto"``).
    kernel : KernelSEMResult or None
        The kernel-basis solve (``basis = "kernel"``).
    constant_speed : ConstantSpeedResult or None
        The open-loop constant-speed fit (``[trajectory] kind = "constant-speed"``).
    cogging_selection : CoggingSelection or None
        How the cogging torque's orders were chosen (evidence and tests).
    """

    sem: SEMResult | None = field(default=None, repr=False)
    bla: BLAIdentification | None = field(default=None, repr=False)
    gain: GainCorrection | None = None
    adequacy: AdequacyReport | None = field(default=None, repr=False)
    validation: Validation | None = None
    selection: HarmonicSelection | None = field(default=None, repr=False)
    kernel: KernelSEMResult | None = field(default=None, repr=False)
    constant_speed: ConstantSpeedResult | None = field(default=None, repr=False)
    cogging_selection: CoggingSelection | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class Calibration:
    """A calibration: its artifact, and what the calibrating process has beyond it.

    The one form of a calibration, computed (:func:`hallcal.pipeline.calibrate`, through
    :func:`computed_calibration`) or loaded (:func:`calibration_from_artifact`): the typed
    artifact that :meth:`save` writes, the report, the C export and the fleet read, with the
    in-memory :class:`Diagnostics` when computed here. Every other attribute is read from the
    artifact (for a computed calibration, the object it was written from).

    Attributes
    ----------
    artifact : ArtifactData
        The artifact (checked when loaded; checked by :meth:`save` when computed here).
    computed : Diagnostics or None
        The solver's results in memory; None when loaded from an artifact.

    Properties read from the artifact: ``setup``; ``flux`` (g_theta*, Fourier coefficients;
    the kernel model in its exact Fourier form); ``lut`` (the table and the f_init it
    corrects); ``status``; ``refusal`` (why the table must not be used, else None);
    ``messages`` (warnings and notes, most important first); ``predicted_error`` (RMS angle
    error of f_star [rad] predicted from the noise floor and cov(theta), in quadrature);
    ``noise_floor`` (RMS angle error [rad] of the Hall noise alone); ``plant`` (G(s) used in
    SEM, gain correction applied; None for open-loop runs) and ``plant_source`` ("setup" or
    "bla"); ``timings`` (seconds per step); ``model_info`` (basis, harmonics, theta, kernel
    hyperparameters); ``cogging`` (the cogging torque identified with the flux, with the
    covariance of its coefficients); ``identifiability`` (the pole pair at power-up from the
    magnets' signatures, :mod:`hallcal.sensor.absolute`); ``observer`` (the model-based
    observer's check: noise variance per channel, whether the three-signal curve is injective,
    :func:`hallcal.pipeline.observe.observer_check`); ``sensors`` (censoring and drift of the
    sensors, :mod:`hallcal.fit.censor`, :mod:`hallcal.fit.drift`); ``diagnostics`` (the
    artifact's ``diagnostics``). Read from :attr:`computed` (None when loaded): ``sem``,
    ``bla``, ``gain``, ``adequacy``, ``validation``, ``selection``, ``kernel``,
    ``constant_speed``, ``cogging_selection``.
    """

    artifact: ArtifactData = field(repr=False)
    computed: Diagnostics | None = field(default=None, repr=False)

    def __repr__(self) -> str:
        shown = "setup flux lut status predicted_error noise_floor refusal messages plant"
        shown += " plant_source gain validation"
        return f"Calibration({', '.join(f'{k}={getattr(self, k)!r}' for k in shown.split())})"

    # read from the artifact (the objects it was written from, when computed here)
    setup = property(lambda self: self.artifact.setup)
    flux = property(lambda self: self.artifact.flux())
    lut = property(lambda self: self.artifact.lut())
    plant = property(lambda self: self.artifact.plant_model())
    cogging = property(lambda self: self.artifact.cogging_torque())
    model_info = property(lambda self: self.artifact.model)
    observer = property(lambda self: self.artifact.get("observer"))
    plant_source = property(lambda self: (self.artifact.plant or {}).get("source"))
    diagnostics = property(lambda self: self.artifact.diagnostics)
    refusal = property(lambda self: self.diagnostics.get("refusal"))
    timings = property(lambda self: self.diagnostics.get("timings", {}))
    sensors = property(lambda self: self.diagnostics.get("sensors", {}))
    predicted_error = property(lambda self: _number(self.diagnostics, "predicted_angle_error_rms"))
    noise_floor = property(lambda self: _number(self.diagnostics, "noise_floor"))
    status = property(  # the validator checked the value (ARTIFACT_STATUSES)
        lambda self: self.artifact.typed(
            "status", lambda: CalibrationStatus(self.diagnostics.get("status", "ok"))
        )
    )
    messages = property(lambda self: self.artifact.typed("messages", lambda: _messages(self)))
    identifiability = property(
        lambda self: self.artifact.typed(
            "identifiability",
            lambda: identifiability_from_artifact(self.artifact, self.artifact.source),
        )
    )
    # the solver's results in memory (None when loaded)
    sem = property(lambda self: self._computed("sem"))
    bla = property(lambda self: self._computed("bla"))
    gain = property(lambda self: self._computed("gain"))
    adequacy = property(lambda self: self._computed("adequacy"))
    validation = property(lambda self: self._computed("validation"))
    selection = property(lambda self: self._computed("selection"))
    kernel = property(lambda self: self._computed("kernel"))
    constant_speed = property(lambda self: self._computed("constant_speed"))
    cogging_selection = property(lambda self: self._computed("cogging_selection"))

    def _computed(self, name: str) -> Any:
        return None if self.computed is None else getattr(self.computed, name)

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

    def to_artifact(self) -> dict[str, Any]:
        """The JSON artifact's keys (a plain dict: :meth:`save` writes it)."""
        return dict(self.artifact.data)

    def with_note(self, note: Message, status: CalibrationStatus) -> Calibration:
        """This calibration with a note first among its messages and another status.

        Parameters
        ----------
        note : Message
        status : CalibrationStatus

        Returns
        -------
        Calibration
        """
        records = [note.record(), *self.diagnostics.get("messages", ())]
        diag = {**self.diagnostics, "status": status.value, "messages": records}
        typed = {**self.artifact.objects, "status": status, "messages": (note, *self.messages)}
        art = dataclasses.replace(
            self.artifact, data={**self.artifact.data, "diagnostics": diag}, diagnostics=diag,
            file_sha256=None, objects=typed,
        )  # fmt: skip
        return dataclasses.replace(self, artifact=art)

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
            Columns d1, d2, d3 (``y_ref``, when present, validates the result).
        y_initial : float, keyword-only
            f_init's angle before the first sample [rad] (the calibration run started at 0).
        absolute : bool, keyword-only
            The recording starts at power-up wherever the rotor stopped (no homing): the pole
            pair is identified from the magnets' signatures and the angles are in the
            calibration's frame, modulo one revolution (``rec.identification`` says when it
            was certain; ``y_initial`` is not used). Raises :class:`CalibrationRefused` when
            :attr:`identifiability` says the pole pair is not identifiable.
        observer : bool, keyword-only
            Also run the model-based observer (:mod:`hallcal.sensor.observer`):
            ``rec["y_obs"]`` (tracking maximum-likelihood angle [rad] with online gain/offset
            adaptation), ``rec["misfit"]`` (windowed chi-square per degree of freedom, about 1
            when the model fits) and ``rec["state"]`` (ok | adapting | stale | degraded |
            fault). A calibration without a table (folding map, :attr:`observer_only`) can
            only be used this way.

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


def computed_calibration(
    setup: Setup,
    flux: FluxModel,
    lut: LUT,
    status: CalibrationStatus,
    predicted_error: float,
    noise_floor: float,
    *,
    refusal: str | None = None,
    messages: tuple[Message, ...] = (),
    plant: ContinuousTF | None = None,
    plant_source: str | None = None,
    timings: Mapping[str, float] | None = None,
    model_info: Mapping[str, Any] | None = None,
    cogging: CoggingTorque | None = None,
    identifiability: IdentifiabilityReport | None = None,
    observer: Mapping[str, Any] | None = None,
    sensors: Mapping[str, Any] | None = None,
    computed: Diagnostics | None = None,
) -> Calibration:
    """A calibration computed in this process: its artifact (the versioned JSON of
    docs/design.md), written once here from the steps' results, and its :class:`Diagnostics`.

    Parameters
    ----------
    setup, flux, lut, status, predicted_error, noise_floor, refusal, messages, plant, \
plant_source, timings, model_info, cogging, identifiability, observer, sensors
        What the artifact records (see :class:`Calibration`).
    computed : Diagnostics, keyword-only, optional
        The steps' results in memory.

    Returns
    -------
    Calibration
        Its artifact: format, pole pairs, f_init's projection and offsets, the model (basis,
        theta), the table, the setup, diagnostics, and where present identifiability, plant,
        cogging and observer; checked when written (:meth:`Calibration.save`).
    """
    x = computed or Diagnostics()
    diag: dict[str, Any] = {
        "status": status.value,
        "refusal": refusal,
        "messages": [m.record() for m in messages],
        "bijective": bool(lut.bijective),
        "min_slope": lut.min_slope,
        "predicted_angle_error_rms": predicted_error,
        "noise_floor": noise_floor,
        "timings": dict(timings or {}),
    }
    sem = x.sem
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
    if x.adequacy is not None:
        diag["adequacy"] = x.adequacy.to_dict()
    if x.validation is not None:
        diag["validation"] = x.validation.to_dict()
    if x.gain is not None:
        diag["gain_correction"] = x.gain.to_dict()
    if x.constant_speed is not None:
        diag["constant_speed"] = x.constant_speed.to_dict()
    if x.cogging_selection is not None:
        diag["cogging"] = x.cogging_selection.to_dict()
    if x.selection is not None:  # without wall times: they live in "timings" only
        diag["model_selection"] = x.selection.to_dict(timings=False)
        del diag["model_selection"]["report"]  # the final fit's is "adequacy"
    if x.kernel is not None:
        diag["model_selection"] = {
            "basis": "kernel",
            "ard_rounds": x.kernel.ard_rounds,
            "settled": bool(x.kernel.settled),
            "budget_hit": not x.kernel.settled,
            "sem_status": str(x.kernel.status),
        }
    if sensors:
        diag["sensors"] = dict(sensors)
    art: dict[str, Any] = {
        "format": ARTIFACT_FORMAT,
        "hallcal_version": __version__,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "pole_pairs": setup.pole_pairs,
        "reconstruction": {
            "method": "f_init (Clarke/projection, atan2, unwrap) + lookup table (f_star)",
            "projection": lut.projection.tolist(),
            "offset": lut.offset.tolist(),
        },
        "model": dict(model_info or {}),
        "lut": lut.to_dict(),
        "setup": setup,
        "diagnostics": diag,
    }
    if identifiability is not None:
        art["identifiability"] = identifiability.to_dict()
    if plant is not None:
        art["plant"] = {
            "num": list(plant.num),
            "den": list(plant.den),
            "delay": plant.delay,
            "gain_correction": None if x.gain is None else x.gain.value,
            "source": plant_source,
        }
    if cogging is not None:
        art["cogging"] = cogging.to_dict()
    if observer is not None:
        art["observer"] = dict(observer)
    typed = {
        "flux": flux,
        "plant": plant,
        "cogging": cogging,
        "status": status,
        "messages": tuple(messages),
        "identifiability": identifiability,
    }
    return Calibration(ArtifactData.in_memory(art, lut, typed), computed)


def _number(diag: Mapping[str, Any], key: str) -> float:
    """``diagnostics[key]`` as a float, NaN when absent or null."""
    value = diag.get(key)
    return float(value) if isinstance(value, int | float) else math.nan


def _messages(cal: Calibration) -> tuple[Message, ...]:
    return tuple(Message.from_record(m) for m in cal.diagnostics.get("messages", ()))


def calibration_from_artifact(artifact: ArtifactData | Mapping[str, Any]) -> Calibration:
    """The :class:`Calibration` of an artifact (:func:`~hallcal.io.read_artifact`'s, or a
    mapping, which is checked by :func:`~hallcal.io.validate_artifact` first).

    Everything the artifact holds is read from it; the solver's results in memory
    (:attr:`Calibration.computed`: SEM iterates, BLA spectra) are None.

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
        The artifact does not pass the validator (which checks ``diagnostics.status``), or its
        ``identifiability`` entry is malformed.
    """
    cal = Calibration(validate_artifact(artifact, "artifact"))
    _ = cal.identifiability  # checked now: a malformed file is refused when read
    return cal


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
    drift = drift_message(cal.identifiability, warning=True)  # the lock's margin, if small
    return Reconstruction(
        out.y_init,
        out.y_star,
        validation,
        out.identification,
        signals=signals,
        messages=notes + (() if drift is None else (drift,)),
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
        A loaded artifact, or its parsed JSON (:func:`calibration_from_artifact`).
    dataset, y_initial, absolute
        As :meth:`Calibration.reconstruct`.

    Returns
    -------
    Reconstruction
    """
    return calibration_from_artifact(artifact).reconstruct(
        dataset, y_initial=y_initial, absolute=absolute
    )
