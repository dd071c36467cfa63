"""The client side of ``hallcal fleet``: :func:`run_fleet` reuses what is up to date, schedules
the rest on Dask (or one after the other) and writes the records, the summary and the page."""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

from hallcal.errors import HallcalInputError
from hallcal.fleet.manifest import MotorSpec, _specs
from hallcal.fleet.records import _load_record, _record_is_current, _store, fingerprint
from hallcal.fleet.summary import (
    LOCK_NAME,
    REPORT_NAME,
    SUMMARY_CSV,
    SUMMARY_PARQUET,
    SUMMARY_SCHEMA,
    _write_summary,
)
from hallcal.fleet.worker import _failed_result, _Result, _run_motor, _Task, _version
from hallcal.formatting import one_line
from hallcal.io import make_folder

#: How long to wait for an existing scheduler (``scheduler="tcp://..."``) to answer.
_CONNECT_TIMEOUT = "10s"


#: ``progress(row, done, total)``: once with ``row=None, done=0`` when the batch starts, then once
#: per motor as its row is known (reused and unrunnable rows first, then as workers finish).
FleetProgress = Callable[[Mapping[str, Any] | None, int, int], None]


def _local_cluster(workers: int | None) -> Any:
    import dask
    from distributed import LocalCluster

    n = workers if workers is not None else (os.cpu_count() or 1)
    settings = {
        # one retry of a task whose worker died (a transient crash), then it is reported failed
        "distributed.scheduler.allowed-failures": 1,
        # Dask sets MALLOC_TRIM_THRESHOLD_ in its workers to hand memory back to the system
        # early; it also turns off glibc's adaptive mmap threshold, so every large temporary of
        # a calibration is mapped and faulted in anew (twice the system time, measured)
        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    }
    with dask.config.set(settings), _interrupts_ignored():
        # the worker processes inherit SIGINT ignored: Ctrl-C in a terminal reaches the whole
        # process group, and only this process should answer it (one line, no worker traces)
        return LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address="127.0.0.1:0",  # a free port: no clash with other clusters
            # a worker's log of a lost heartbeat under load comes with a traceback at ERROR
            # while the run completes; a crash reaches the user through the task's future
            silence_logs=logging.CRITICAL,
            env={
                "OMP_NUM_THREADS": "1",
                "OPENBLAS_NUM_THREADS": "1",
                "MKL_NUM_THREADS": "1",
                "NUMBA_NUM_THREADS": "1",
            },
        )


@contextlib.contextmanager
def _interrupts_ignored() -> Iterator[None]:
    """SIGINT ignored while child processes are started (main thread only)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _crash_message(exc: BaseException) -> tuple[str, bool]:
    name = type(exc).__name__
    if name == "KilledWorker":
        return (
            "worker crashed while calibrating this motor (the task killed its worker; retried once)"
        ), True
    if name in ("CancelledError", "FutureCancelledError"):
        return "the task was cancelled (scheduler or worker lost)", True
    return f"worker error: {name}: {exc}", True


def run_fleet(
    manifest_or_rows: str | os.PathLike[str] | Iterable[Mapping[str, Any] | MotorSpec],
    out: str | os.PathLike[str],
    *,
    scheduler: Any = None,
    workers: int | None = None,
    export_c: bool = False,
    adc_scale: float | None = None,
    recompute: bool = False,
    report: bool = True,
    base: str | os.PathLike[str] | None = None,
    progress: FleetProgress | None = None,
    _task: Callable[[_Task], _Result] | None = None,
) -> pa.Table:
    """Calibrate every motor of a manifest on Dask; write the artifacts and the summary.

    Parameters
    ----------
    manifest_or_rows : path-like or iterable of mapping or MotorSpec
        A manifest file (CSV or Parquet), or rows with the manifest's keys (``motor_id``,
        ``data``, ``setup``, optional ``bla_data`` and ``validation``).
    out : path-like
        Output folder (created if missing).
    scheduler : str or distributed.Client, optional
        None: a local cluster in this machine, one single-threaded worker process per core
        (``workers`` to change), closed at the end. A string: the address of an existing Dask
        scheduler (``"tcp://host:8786"``); its workers need hallcal (same version) and read access
        to the inputs. A ``distributed.Client``: used as it is. ``"sequential"``: no Dask, the
        motors one after the other in this process (debugging, the benchmarks' baseline).
    workers : int, optional
        Number of workers of the local cluster (default: ``os.cpu_count()``).
    export_c : bool
        Also write each artifact's C99 sources (:func:`hallcal.api.export_c`: the float pair
        always) to ``OUT/<motor_id>/c/``.
    adc_scale : float, optional
        ADC counts per Hall signal unit for the fixed-point C export (default: the fixed-point
        pair only for artifacts in counts).
    recompute : bool
        Ignore the records of earlier runs and calibrate every motor again.
    report : bool
        Write ``OUT/fleet.html``.
    base : path-like, optional
        Folder that relative paths in `manifest_or_rows` rows are relative to (default: the
        current directory; a manifest file's own folder for a manifest).
    progress : callable, optional
        ``progress(row, done, total)``: once with ``row=None`` at the start, then after each
        motor (see :data:`FleetProgress`).

    Returns
    -------
    pyarrow.Table
        The summary (:data:`SUMMARY_COLUMNS`, one row per manifest row, in manifest order), as
        written to ``OUT/summary.parquet`` and ``OUT/summary.csv``. ``table.to_pylist()`` gives
        the rows as dicts; :func:`summary_counts` the number per status. Angles in rad.

    Raises
    ------
    HallcalInputError
        The manifest is unusable (missing file or column, no motors), the output folder cannot
        be created, or the scheduler cannot be reached. Problems of single motors do not raise:
        they are in their rows.
    Notes
    -----
    The default local cluster spawns worker processes, which import the calling script's main
    module: a script (not a notebook) that calls this needs the usual
    ``if __name__ == "__main__":`` guard, as with any Dask process cluster.

    Examples
    --------
    >>> table = run_fleet("manifest.csv", "batch")  # doctest: +SKIP
    >>> [r["motor_id"] for r in table.to_pylist() if r["status"] == "failed"]  # doctest: +SKIP
    """
    specs, source = _specs(manifest_or_rows, base)
    if adc_scale is not None and not (
        isinstance(adc_scale, int | float) and math.isfinite(adc_scale) and adc_scale > 0
    ):
        raise HallcalInputError(f"adc_scale must be a positive number, got {adc_scale!r}")
    _check_names(specs, Path(out), source)
    out_dir = make_folder(out)
    with _locked(out_dir):
        return _run_locked(
            specs, source, out_dir, scheduler=scheduler, workers=workers, export_c=export_c,
            adc_scale=adc_scale, recompute=recompute, report=report, progress=progress,
            task=_task,
        )  # fmt: skip


#: The names of a batch's own files in its output folder: no motor_id may take one.
RESERVED_NAMES = frozenset({SUMMARY_CSV, SUMMARY_PARQUET, REPORT_NAME, LOCK_NAME})


def _check_names(specs: Sequence[MotorSpec], out: Path, source: str) -> None:
    """Before any work: no motor_id is one of the batch's own file names or a file already in
    the output folder, and no output is an input (the manifest, a motor's files)."""
    from hallcal.io import check_outputs

    for spec in specs:
        if spec.motor_id.lower() in RESERVED_NAMES:
            raise HallcalInputError(
                f"{source}: row {spec.row}: motor_id '{spec.motor_id}' is the name of a file the "
                f"batch writes ({', '.join(sorted(RESERVED_NAMES))}): rename the motor"
            )
        folder = out / spec.motor_id
        if spec.problem is None and (folder.exists() or folder.is_symlink()):
            if not folder.is_dir() or folder.is_symlink():
                raise HallcalInputError(
                    f"{source}: row {spec.row}: motor_id '{spec.motor_id}': {folder} exists and "
                    "is not a folder of this batch: rename the motor or move the file"
                )
    inputs: list[Path | str] = [] if source == "<rows>" else [source]
    inputs += [p for s in specs for p in (s.data, s.setup, s.bla_data, s.validation) if p]
    check_outputs(
        [out / SUMMARY_CSV, out / SUMMARY_PARQUET, out / REPORT_NAME],
        inputs,
        folders=[out / s.motor_id for s in specs if s.problem is None],
    )


@contextlib.contextmanager
def _locked(out_dir: Path) -> Iterator[None]:
    """Hold the output folder's lock (``OUT/.fleet.lock``, released when this process ends
    however it ends): a second fleet on the same folder is refused with one line."""
    import fcntl

    path = out_dir / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise HallcalInputError(f"{path}: cannot create the lock ({exc.strerror})") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise HallcalInputError(
                f"{out_dir}: another hallcal fleet is writing to this folder (it holds "
                f"{path}): wait for it to finish or choose another --out"
            ) from None
        yield
    finally:
        os.close(fd)


def _run_locked(
    specs: list[MotorSpec],
    source: str,
    out_dir: Path,
    *,
    scheduler: Any,
    workers: int | None,
    export_c: bool,
    adc_scale: float | None,
    recompute: bool,
    report: bool,
    progress: FleetProgress | None,
    task: Callable[[_Task], _Result] | None,
) -> pa.Table:
    scale = None if adc_scale is None else float(adc_scale)
    options = {"export_c": bool(export_c), "adc_scale": scale if export_c else None}
    batch = _Batch(out_dir, [None] * len(specs), progress)
    pending = batch.reuse(specs, options, recompute=recompute)

    task_of = functools.partial(
        _Task.of, export_c=bool(export_c), adc_scale=scale, version=_version()
    )
    work = task or _run_motor
    if pending:
        if isinstance(scheduler, str) and scheduler == "sequential":
            for i, spec, fp in pending:
                batch.accept(i, spec, fp, work(task_of(spec)))
        else:
            with _client(scheduler, workers) as client:
                _run_on_dask(client, pending, task_of, batch.accept, work)

    table = pa.Table.from_pylist([r for r in batch.rows if r is not None], schema=SUMMARY_SCHEMA)
    from hallcal.io import output_set

    with output_set():  # summary.csv, summary.parquet and fleet.html of the same batch
        _write_summary(out_dir, table)
        if report:
            from hallcal.output.fleet_report import write_fleet_report

            write_fleet_report(table, out_dir / REPORT_NAME, source=source)
    return table


@dataclass
class _Batch:
    """The summary rows of a batch as they become known (manifest order), the motors' outputs
    stored as their results arrive, and the progress calls."""

    out: Path
    rows: list[dict[str, Any] | None]
    progress: FleetProgress | None
    done: int = 0

    def __post_init__(self) -> None:
        if self.progress is not None:  # the batch starts
            self.progress(None, 0, len(self.rows))

    def finish(self, i: int, row: dict[str, Any]) -> None:
        self.rows[i] = row
        self.done += 1
        if self.progress is not None:
            self.progress(row, self.done, len(self.rows))

    def accept(self, i: int, spec: MotorSpec, fp: str, result: _Result) -> None:
        """A worker's result: its outputs and record written, its row known."""
        _store(self.out, spec, fp, result)
        self.finish(i, result.row)

    def reuse(
        self, specs: Sequence[MotorSpec], options: Mapping[str, Any], *, recompute: bool
    ) -> list[tuple[int, MotorSpec, str]]:
        """Finish the rows that cannot run and those whose record is up to date; return the
        motors to calibrate as ``(index, spec, fingerprint)``."""
        pending: list[tuple[int, MotorSpec, str]] = []
        for i, spec in enumerate(specs):
            if spec.problem is not None:
                self.finish(i, _failed_result(spec.motor_id, spec.problem, retry=False).row)
                continue
            fp = fingerprint(spec, options)
            folder = self.out / spec.motor_id
            record = None if recompute else _load_record(folder)
            if _record_is_current(folder, record, fp):
                assert record is not None
                self.finish(i, {**record["row"], "reused": True})
            else:
                pending.append((i, spec, fp))
        return pending


@contextlib.contextmanager
def _client(scheduler: Any, workers: int | None) -> Iterator[Any]:
    from distributed import Client

    if scheduler is None:
        cluster = _local_cluster(workers)
        try:
            with Client(cluster, set_as_default=False) as client:
                yield client
        finally:
            cluster.close()
    elif isinstance(scheduler, str):
        try:
            client = Client(scheduler, timeout=_CONNECT_TIMEOUT, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            why = one_line(exc) or type(exc).__name__
            raise HallcalInputError(f"scheduler {scheduler}: cannot connect ({why})") from None
        with client:
            yield client
    else:
        yield scheduler  # a Client the caller owns


def _run_on_dask(
    client: Any,
    pending: Sequence[tuple[int, MotorSpec, str]],
    task_of: Callable[[MotorSpec], _Task],
    accept: Callable[[int, MotorSpec, str, _Result], None],
    work: Callable[[_Task], _Result],
) -> None:
    from distributed import as_completed

    futures = {}
    for i, spec, fp in pending:
        fut = client.submit(
            work,
            task_of(spec),
            key=f"hallcal-fleet-{spec.motor_id}-{fp[:16]}",
            pure=False,
            retries=0,
        )
        futures[fut] = (i, spec, fp)
    try:
        for fut in as_completed(list(futures), loop=client.loop):
            i, spec, fp = futures.pop(fut)
            try:
                result = fut.result()
            except Exception as exc:  # the worker died, or the task was lost with it
                message, retry = _crash_message(exc)
                result = _failed_result(spec.motor_id, message, retry=retry)
            accept(i, spec, fp, result)
            fut.release()
    finally:
        for fut in futures:
            fut.cancel()
