"""What a batch writes and how it went: motor statuses, output names, the summary table."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pyarrow as pa

from hallcal.io import atomic_write
from hallcal.messages import Graded

#: Exit status of ``hallcal fleet`` when at least one motor was refused or failed.
EXIT_INCOMPLETE = 4


ARTIFACT_NAME = "calibration.json"
RECORD_NAME = "fleet.json"
C_DIR = "c"
REPORT_NAME = "fleet.html"
SUMMARY_CSV = "summary.csv"
SUMMARY_PARQUET = "summary.parquet"
#: The output folder's lock (motor ids cannot start with a dot, so none can take it).
LOCK_NAME = ".fleet.lock"


#: Summary columns with their Arrow types. Angles in rad, durations in s.
SUMMARY_SCHEMA = pa.schema(
    [
        pa.field("motor_id", pa.string(), nullable=False),
        pa.field("status", pa.string(), nullable=False),
        pa.field("message", pa.string(), nullable=False),
        pa.field("predicted_error", pa.float64(), metadata={"unit": "rad"}),
        pa.field("f_init_rms", pa.float64(), metadata={"unit": "rad"}),
        pa.field("f_star_rms", pa.float64(), metadata={"unit": "rad"}),
        pa.field("model", pa.string()),
        pa.field("seconds", pa.float64(), metadata={"unit": "s"}),
        pa.field("worker", pa.string()),
        pa.field("reused", pa.bool_(), nullable=False),
        pa.field("computed_at", pa.string()),
        pa.field("artifact", pa.string()),
    ]
)
SUMMARY_COLUMNS: tuple[str, ...] = tuple(SUMMARY_SCHEMA.names)


class MotorStatus(Graded):
    """Outcome of one motor (the ``status`` column).

    ``ok`` and ``warning`` wrote an artifact; ``refused`` and ``failed`` did not.
    """

    OK = "ok"
    WARNING = "warning"
    REFUSED = "refused"
    FAILED = "failed"


def _write_summary(out: Path, table: pa.Table) -> None:
    import csv
    import io

    import pyarrow.parquet as pq

    with atomic_write(out / SUMMARY_PARQUET, "wb") as f:
        pq.write_table(table, f)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(table.column_names)
    for row in table.to_pylist():
        w.writerow([_csv_cell(row[k]) for k in table.column_names])
    with atomic_write(out / SUMMARY_CSV, "w") as f:
        f.write(buf.getvalue())


def _csv_cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def summary_counts(table: pa.Table) -> dict[str, int]:
    """Number of motors per status (every status present, zeros included).

    Parameters
    ----------
    table : pyarrow.Table
        The fleet summary (its ``status`` column).

    Returns
    -------
    dict of str to int
        Status value (``"ok"``, ``"warning"``, ``"refused"``, ``"failed"``) -> motors.
    """
    counts = dict.fromkeys((s.value for s in MotorStatus), 0)
    for s in table.column("status").to_pylist():
        counts[s] = counts.get(s, 0) + 1
    return counts


def all_succeeded(table: pa.Table) -> bool:
    """True when every motor is ok or warning (``hallcal fleet`` then exits 0).

    Parameters
    ----------
    table : pyarrow.Table
        The fleet summary (its ``status`` column).

    Returns
    -------
    bool
    """
    return all(MotorStatus(s).success for s in table.column("status").to_pylist())
