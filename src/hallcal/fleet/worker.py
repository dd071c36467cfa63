"""The work of one motor, in a Dask worker: the front-door calibration, the artifact and C
sources as bytes, the summary row; a problem of the motor goes into its row, never raised."""

from __future__ import annotations

import contextlib
import datetime as _dt
import math
import os
import tempfile
import time
import traceback
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hallcal.errors import HallcalInputError
from hallcal.fleet.manifest import MotorSpec
from hallcal.fleet.summary import ARTIFACT_NAME, C_DIR, SUMMARY_COLUMNS, MotorStatus
from hallcal.formatting import finite, one_line, ranges
from hallcal.messages import Message, MessageCode

if TYPE_CHECKING:
    from hallcal.api import Calibration


def _version() -> str:
    from hallcal._version import __version__

    return __version__


@dataclass(frozen=True)
class _Task:
    """What a worker needs for one motor (sent through Dask; paths as strings)."""

    motor_id: str
    data: str
    setup: str
    bla_data: str | None
    validation: str | None
    export_c: bool
    adc_scale: float | None
    version: str

    @classmethod
    def of(cls, spec: MotorSpec, *, export_c: bool, adc_scale: float | None, version: str) -> _Task:
        return cls(
            motor_id=spec.motor_id,
            data=str(spec.data),
            setup=str(spec.setup),
            bla_data=None if spec.bla_data is None else str(spec.bla_data),
            validation=None if spec.validation is None else str(spec.validation),
            export_c=export_c,
            adc_scale=adc_scale,
            version=version,
        )


@dataclass
class _Result:
    """What a worker sends back: the summary row, the output files and whether to retry."""

    row: dict[str, Any]
    files: dict[str, bytes] = field(default_factory=dict)
    retry: bool = False
    detail: str | None = None


def _calibrate(data: str, setup: str, bla_data: str | None) -> Calibration:
    """The one call into the calibration: the front door, as ``hallcal calibrate`` uses it.

    Returns a :class:`hallcal.api.Calibration`; errors name the file at fault (the numeric
    layers say "setup:", replaced here by the setup file's path, as the CLI does).
    """
    from hallcal.api import calibrate

    try:
        return calibrate(data, setup, bla_data=bla_data)
    except HallcalInputError as exc:
        msg = str(exc)
        if msg.startswith("setup:"):
            raise HallcalInputError(setup + msg[len("setup") :]) from None
        raise


def _model_text(model: Mapping[str, Any]) -> str:
    basis = model.get("basis")
    if basis == "fourier":
        return "fourier " + ranges(model.get("harmonics", []), to="-", sep=",")
    if basis == "kernel":
        text = f"kernel m={model.get('points')}"
        ls = model.get("lengthscale")
        if isinstance(ls, int | float) and math.isfinite(ls):
            text += f" l={ls:.3g}"
        return text
    return str(basis or "")


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"local pid {os.getpid()}"


@contextlib.contextmanager
def _single_threaded() -> Iterator[None]:
    """BLAS (threadpoolctl) and numba at one thread, so n workers use n cores, not n^2."""
    from threadpoolctl import threadpool_limits

    previous: int | None = None
    try:
        import numba

        previous = numba.get_num_threads()
        numba.set_num_threads(1)
    except (ImportError, ValueError, RuntimeError):  # pragma: no cover - numba always present
        previous = None
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        if previous is not None:
            numba.set_num_threads(previous)


def _empty_row(motor_id: str) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(SUMMARY_COLUMNS)
    row.update(motor_id=motor_id, message="", reused=False)
    return row


def _run_motor(task: _Task) -> _Result:
    """Calibrate one motor: never raises for a problem of the motor (it goes in the row)."""
    t0 = time.perf_counter()
    row = _empty_row(task.motor_id)
    row["worker"] = _worker_name()
    row["computed_at"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    result = _Result(row)
    try:
        if task.version != _version():
            raise HallcalInputError(
                f"worker {row['worker']} runs hallcal {_version()}, the client {task.version}: "
                "install the same version on every worker"
            )
        with _single_threaded():
            _calibrate_into(task, result)
    except HallcalInputError as exc:
        row.update(status=MotorStatus.FAILED.value, message=one_line(str(exc)))
    except MemoryError:
        row.update(status=MotorStatus.FAILED.value, message="out of memory in the worker")
        result.retry = True
    except Exception as exc:  # a bug or an unforeseen input: report it, go on with the others
        row.update(
            status=MotorStatus.FAILED.value,
            message=one_line(f"internal error: {type(exc).__name__}: {exc}"),
        )
        result.retry = True
        result.detail = traceback.format_exc()
        result.files.clear()
    row["seconds"] = time.perf_counter() - t0
    return result


def _calibrate_into(task: _Task, result: _Result) -> None:
    from hallcal.api import export_c  # the export defaults every entry point shares
    from hallcal.io import read_artifact, read_dataset
    from hallcal.pipeline.calibration import CalibrationStatus
    from hallcal.pipeline.verdict import refusal

    row = result.row
    cal = _calibrate(task.data, task.setup, task.bla_data)
    row["predicted_error"] = finite(cal.predicted_error)
    row["model"] = _model_text(cal.model_info)
    force = bool(cal.setup.model.force)  # as `hallcal calibrate` honours [model] force = true
    notes = list(cal.messages)
    refused = refusal(
        cal.status, cal.refusal or (notes[0].record() if notes else None), force=force
    )
    if refused is not None:
        row.update(status=MotorStatus.REFUSED.value, message=one_line(refused.text))
        return
    status = MotorStatus.OK if cal.status is CalibrationStatus.OK else MotorStatus.WARNING
    if cal.status.refused:
        forced = f"model inadequate, written because [model] force = true: {cal.refusal}"
        notes.insert(0, Message.note(MessageCode.FORCED, forced))
    elif cal.status is CalibrationStatus.WARNING and not notes:
        notes.append(Message.warning(MessageCode.SEE_DIAGNOSTICS, "see the artifact's diagnostics"))
    with tempfile.TemporaryDirectory(prefix="hallcal-fleet-") as tmp:
        cal.save(Path(tmp) / ARTIFACT_NAME, force=force)
        result.files[ARTIFACT_NAME] = (Path(tmp) / ARTIFACT_NAME).read_bytes()
        if task.export_c:
            cdir = Path(tmp) / C_DIR
            try:
                # from the saved file: the banner's sha256 is the artifact file's
                art = read_artifact(Path(tmp) / ARTIFACT_NAME)
                res = export_c(art, cdir, adc_scale=task.adc_scale)
            except HallcalInputError as exc:  # the artifact stands; its C sources do not
                status = MotorStatus.WARNING
                notes.insert(0, Message.warning(MessageCode.C_EXPORT, f"no C export: {exc}"))
            else:
                notes += [
                    Message.note(MessageCode.C_EXPORT, f"C export: {m}")
                    for m in getattr(res, "messages", [])
                ]
                for p in sorted(cdir.iterdir()):
                    result.files[f"{C_DIR}/{p.name}"] = p.read_bytes()
    if task.validation is not None:
        try:
            ds = read_dataset(task.validation, required=("d1", "d2", "d3", "y_ref"))
            rec = cal.reconstruct(ds)
            v = rec.validation
            if v is None:  # y_ref cannot be scored (a standstill run): the calibration stands
                raise HallcalInputError(rec.messages[0].text.removeprefix("validation skipped: "))
            row["f_init_rms"] = finite(v.init.rms)
            row["f_star_rms"] = finite(v.star.rms)
            if v.star.rms > v.init.rms:
                status = MotorStatus.WARNING
                notes.insert(
                    0,
                    Message.warning(
                        MessageCode.VALIDATION_WORSE,
                        f"on the validation run f_star ({1e3 * v.star.rms:.3f} mrad RMS) is "
                        f"worse than f_init ({1e3 * v.init.rms:.3f} mrad)",
                    ),
                )
        except HallcalInputError as exc:
            status = MotorStatus.WARNING
            warning = f"validation run unusable: {exc}"
            notes.insert(0, Message.warning(MessageCode.VALIDATION_SKIPPED, warning))
    row["status"] = status.value
    row["artifact"] = f"{task.motor_id}/{ARTIFACT_NAME}"
    row["message"] = one_line(notes[0].record()) if notes else ""


def _failed_result(motor_id: str, message: str, *, retry: bool) -> _Result:
    row = _empty_row(motor_id)
    row.update(
        status=MotorStatus.FAILED.value,
        message=one_line(message),
        computed_at=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    )
    return _Result(row, retry=retry)
