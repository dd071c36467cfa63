"""Calibrate a fleet of motors on Dask (``hallcal fleet``): end-of-line production.

One manifest lists the motors; each motor is calibrated by the same front-door calibration as
``hallcal calibrate`` (Algorithm 1 of van Meer et al.), in a Dask worker, independently of the
others: a bad file, a refused model or a crashed worker gives that motor's row a status and a
one-line reason, and the batch goes on.

Manifest
--------
A CSV (header row, UTF-8) or Parquet table, one row per motor:

``motor_id``
    Name of the motor; also the name of its output folder, so it may hold letters, digits,
    ``.``, ``_`` and ``-`` only (at most 128 characters, not starting with ``.``), and must be
    unique in the manifest.
``data``
    The calibration recording (any dataset format of :func:`hallcal.io.read_dataset`).
``setup``
    The setup file (TOML).
``bla_data`` (optional)
    A multisine experiment for the BLA, for setups without ``[plant]``.
``validation`` (optional)
    A second recording with ``y_ref`` (an encoder, or the virtual bench's truth) on which the
    RMS errors of f_init and f_star are measured. Validation only: never used to calibrate.

An empty cell means "none". Relative paths are relative to the manifest's folder. Other columns
are ignored, except a name that looks like a misspelling of one of these (an error).

Outputs
-------
``OUT/<motor_id>/calibration.json``
    The calibration artifact (``"hallcal-calibration/1"``), when the motor's status is ok or
    warning; with ``export_c`` also its C99 sources in ``OUT/<motor_id>/c/``.
``OUT/<motor_id>/fleet.json``
    The motor's record: its summary row, the fingerprint of its inputs and the SHA-256 of each
    output. A rerun skips a motor whose record is up to date (see below).
``OUT/summary.parquet``, ``OUT/summary.csv``
    One row per manifest row, in manifest order, columns :data:`SUMMARY_COLUMNS`.
``OUT/fleet.html``
    A self-contained page for a quality engineer: the distributions of the predicted error and
    of f_init versus f_star, the outliers and every motor that did not succeed.

Every file is written atomically (:func:`hallcal.io.atomic_write`); the workers return their
outputs to the client, which alone writes to ``OUT``, so the workers of an existing cluster need
to read the inputs (a shared file system, as usual with Dask) but not to write anywhere.

Up to date
----------
A motor's result is reused when its record exists and holds the same fingerprint, every output
it lists exists with the recorded SHA-256, and the result was not a transient failure (a crashed
worker or an unexpected error is always retried). The fingerprint is a SHA-256 over the
record format, the hallcal version, the options that change the outputs (``export_c``,
``adc_scale``) and, for each input role (data, setup, bla_data, validation), the file's
extension and the SHA-256 of its contents (or that it is absent or missing). Paths themselves do
not count: moving a batch keeps it up to date; editing, replacing or adding any input, or a new
hallcal version, does not. Inputs are hashed when the batch starts; a file replaced while the
batch runs is seen at the next run (its recorded hash is the old one).

Status
------
``ok``
    Artifact written, nothing to report.
``warning``
    Artifact written, with a caveat in the message (model adequacy warning, the validation run
    unusable or f_star worse than f_init on it, the C export refused (for instance an
    ``adc_scale`` too coarse for the signals), or an inadequate model written because the setup
    says ``[model] force = true``).
``refused``
    The calibration ran but its result must not be used (model inadequate, or the lookup table
    not bijective): no artifact.
``failed``
    No result: a bad input file (named in the message), a crashed worker or an unexpected error.

``hallcal fleet`` exits 0 when every motor is ok or warning and :data:`EXIT_INCOMPLETE` (4) when
at least one was refused or failed; 2 when the manifest itself is unusable.

Modules
-------
:mod:`~hallcal.fleet.manifest` (reading the manifest), :mod:`~hallcal.fleet.worker` (the work of
one motor, in a worker), :mod:`~hallcal.fleet.records` (fingerprints and each motor's record),
:mod:`~hallcal.fleet.summary` (statuses, the output names, the summary table) and
:mod:`~hallcal.fleet.run` (:func:`run_fleet`: scheduling on Dask and writing the outputs).
"""

from __future__ import annotations

from hallcal.fleet.manifest import MANIFEST_COLUMNS, MotorSpec, read_manifest
from hallcal.fleet.records import fingerprint
from hallcal.fleet.run import FleetProgress, run_fleet
from hallcal.fleet.summary import (
    ARTIFACT_NAME,
    C_DIR,
    EXIT_INCOMPLETE,
    RECORD_NAME,
    REPORT_NAME,
    SUMMARY_COLUMNS,
    MotorStatus,
    all_succeeded,
    summary_counts,
)

__all__ = [
    "ARTIFACT_NAME",
    "C_DIR",
    "EXIT_INCOMPLETE",
    "MANIFEST_COLUMNS",
    "RECORD_NAME",
    "REPORT_NAME",
    "SUMMARY_COLUMNS",
    "FleetProgress",
    "MotorSpec",
    "MotorStatus",
    "all_succeeded",
    "fingerprint",
    "read_manifest",
    "run_fleet",
    "summary_counts",
]
