"""Hostile cases of output safety: one case per recipe.

* an output that is an input (the same file by name, ``..``, a symbolic or a hard link) or
  another output of the same command (``bla --out b.png``), refused before any work;
* output sets (export-c's four files, report's page and figures, bla's JSON and plot,
  simulate's dataset and truth, the demo's folder) under a write error part-way: a file-size
  limit (EFBIG), a full disk (ENOSPC), no permission (EACCES), a read-only file system (EROFS),
  a folder where a file goes, a name over 255 bytes; and Ctrl-C part-way. The previous set
  must stay as it was (the suite checks that a failed command changed no existing file);
* a validation recording that cannot be scored (standstill y_ref): a warning, exit 0;
* artifacts with a lone surrogate or an unknown ``sem_status``;
* limits checked before work (kernel lengthscale, cogging orders, plan's speeds and samples);
* the fleet's edges: inputs that are not regular files, motor ids that are the batch's own
  file names or files in the way, a folder locked by another fleet, a standstill validation.

The worker injects the faults in its own process (``hostile_worker._fault``), so the cases run
in-process like the others: no interpreter start-up per case.
"""

from __future__ import annotations

import copy
import errno
import fcntl
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from hostile_cases import ABORTED, ADC_SCALE, FLEET_INCOMPLETE, INPUT, OK, REFUSED, Base, Case

#: Lock files held for the whole session (a case whose output folder another fleet holds).
_HELD_LOCKS: list[int] = []

#: The inputs every case folder gets (hard links to the suite's base files).
_INPUTS = ("s.toml", "b.toml", "a.json", "cal.npz", "ms.npz")

SAME = r"is the input|same file|holds the input"


def _inputs(folder: Path, base: Base) -> None:
    for name in _INPUTS:
        os.link(base.dir / name, folder / name)


def _old_export(folder: Path, base: Base, name: str = "fw") -> None:
    """A complete previous export in ``folder/name`` (copies: the case may replace them)."""
    shutil.copytree(base.dir / "fw", folder / name)


def _standstill(folder: Path, base: Base) -> None:
    """A recording whose rotor stands still: d and y_ref constant (a validation run that
    cannot be scored)."""
    from hallcal.io import write_dataset

    cols = {k: np.array(v) for k, v in base.columns.items()}
    for k in ("d1", "d2", "d3", "y_ref"):
        cols[k] = np.full_like(cols[k], cols[k][0])
    write_dataset(folder / "still.npz", cols)


def _artifact_with(folder: Path, base: Base, name: str, edit: Callable[[dict], None]) -> None:
    art = copy.deepcopy(base.artifact)
    edit(art)
    (folder / name).write_text(json.dumps(art), encoding="utf-8")


def _setup_with(folder: Path, base: Base, name: str, model: dict[str, Any]) -> None:
    from hostile_cases import BASE_SETUP
    from hostile_support import to_toml

    d = copy.deepcopy(BASE_SETUP)
    d["model"] = {**{"max_iterations": 2}, **model}
    (folder / name).write_text(to_toml(d))


def _manifest(folder: Path, rows: list[tuple[str, str, str]], *, validation: str = "") -> None:
    text = "motor_id,data,setup,validation\n" + "".join(
        f"{m},{d},{s},{validation}\n" for m, d, s in rows
    )
    (folder / "m.csv").write_text(text)


def safety_cases() -> list[Case]:
    """The cases (ids ``safety-...``)."""
    cases: list[Case] = []

    def c(
        id: str,
        prepare: Callable[[Path, Base], Any] | None,
        args: list[str],
        expect: tuple[int, ...] = (INPUT,),
        msg: str | None = None,
        **kw: Any,
    ) -> None:
        def build(folder: Path, base: Base) -> list[str]:
            _inputs(folder, base)
            if prepare is not None:
                prepare(folder, base)
            return list(args)

        cases.append(Case(f"safety-{id}", build, expect, msg, **kw))

    cal = ["calibrate", "cal.npz", "--setup", "s.toml"]
    rec = ["reconstruct", "a.json", "cal.npz"]
    bla = ["bla", "ms.npz", "--setup", "b.toml"]
    export = ["export-c", *ADC_SCALE, "a.json", "--out", "fw"]
    report = ["report", "a.json", "cal.npz", "--out", "rep"]

    # -- an output that is an input, or another output: refused before any work ----------------
    c("out-is-data-calibrate", None, [*cal, "--out", "cal.npz"], msg=SAME)
    c("out-is-setup-calibrate", None, [*cal, "--out", "s.toml"], msg=SAME)
    c("out-dotdot-calibrate", lambda f, b: (f / "sub").mkdir(), [*cal, "--out", "sub/../cal.npz"],
      msg=SAME)  # fmt: skip
    c("out-symlink-calibrate", lambda f, b: (f / "l.json").symlink_to("cal.npz"),
      [*cal, "--out", "l.json"], msg=SAME)  # fmt: skip
    c("out-hardlink-calibrate", lambda f, b: os.link(f / "cal.npz", f / "h.json"),
      [*cal, "--out", "h.json"], msg=SAME)  # fmt: skip
    c("out-is-data-reconstruct", None, [*rec, "--out", "cal.npz"], msg=SAME)
    c("out-is-data-bla", None, [*bla, "--out", "ms.npz"], msg=SAME)
    c("out-is-setup-bla", None, [*bla, "--out", "b.toml"], msg=SAME)
    c("out-png-collides-bla", None, [*bla, "--out", "b.png"], msg=SAME)
    c(
        "out-holds-artifact-export-c",
        lambda f, b: (f / "fw").mkdir() or os.link(f / "a.json", f / "fw" / "hallcal.h"),
        ["export-c", *ADC_SCALE, "fw/hallcal.h", "--out", "fw"],
        msg=SAME,
    )
    c(
        "out-holds-input-report",
        lambda f, b: (f / "figures").mkdir() or os.link(f / "a.json", f / "figures" / "a.json"),
        ["report", "figures/a.json", "cal.npz", "--out", "."],
        msg=SAME,
    )
    c(
        "sidecar-is-setup-simulate",
        lambda f, b: os.link(f / "s.toml", f / "x.truth.json"),
        ["simulate", "--setup", "x.truth.json", "--out", "x.npz"],
        msg=SAME,
    )

    # -- write errors part-way through an output set: nothing partial, the old set intact ------
    enospc, eacces, erofs = errno.ENOSPC, errno.EACCES, errno.EROFS
    c("efbig-export-c", _old_export, export, msg="File too large", fault={"fsize": 20000})
    c("enospc-export-c", _old_export, export, msg="No space left",
      fault={"at_write": 3, "errno": enospc})  # fmt: skip
    c("eacces-export-c", _old_export, export, msg="Permission denied",
      fault={"at_write": 2, "errno": eacces})  # fmt: skip
    c("erofs-export-c", _old_export, export, msg="Read-only file system",
      fault={"at_write": 4, "errno": erofs})  # fmt: skip
    c("folder-in-the-way-export-c",
      lambda f, b: _old_export(f, b) or (f / "fw" / "hallcal.c").unlink()
      or (f / "fw" / "hallcal.c").mkdir(), export, msg="Is a directory")  # fmt: skip
    c("ctrl-c-export-c", _old_export, export, (ABORTED,),
      fault={"at_write": 2, "interrupt": True})  # fmt: skip
    c("efbig-report", None, report, msg="File too large", fault={"fsize": 150000})
    c("ctrl-c-report", None, report, (ABORTED,), fault={"at_write": 3, "interrupt": True})
    c("enospc-bla", None, [*bla, "--out", "o.json"], msg="No space left",
      fault={"at_write": 2, "errno": enospc})  # fmt: skip
    c("ctrl-c-bla", None, [*bla, "--out", "o.json"], (ABORTED,),
      fault={"at_write": 2, "interrupt": True})  # fmt: skip
    c("png-is-a-folder-bla", lambda f, b: (f / "o.png").mkdir(), [*bla, "--out", "o.json"],
      msg="Is a directory")  # fmt: skip
    c("enospc-simulate", None, ["simulate", "--setup", "s.toml", "--out", "o.npz"],
      msg="No space left", fault={"at_write": 2, "errno": enospc})  # fmt: skip
    c("efbig-calibrate", None, [*cal, "--out", "o.json"], msg="File too large",
      fault={"fsize": 10000})  # fmt: skip
    c("ctrl-c-calibrate", None, [*cal, "--out", "o.json"], (ABORTED,),
      fault={"at_write": 1, "interrupt": True})  # fmt: skip
    c("efbig-reconstruct", None, [*rec, "--out", "o.csv"], msg="File too large",
      fault={"fsize": 10000})  # fmt: skip
    c("enospc-demo", None, ["demo", "--no-report", "--out", "d"], msg="No space left",
      fault={"at_write": 3, "errno": enospc})  # fmt: skip
    c("name-256-reconstruct", None, [*rec, "--out", "x" * 252 + ".csv"], msg="above the limit")
    c("name-255-reconstruct", None, [*rec, "--out", "x" * 251 + ".csv"], (OK,))
    c("name-256-export-c", None, ["export-c", *ADC_SCALE, "a.json", "--out", "f" * 256],
      msg="above the limit")  # fmt: skip

    # -- a validation run that cannot be scored: a warning, the result stands -----------------
    c("standstill-reconstruct", _standstill, ["reconstruct", "a.json", "still.npz", "--out",
      "o.npz"], (OK,))  # fmt: skip
    # every sample the first one, its noise frozen too: a residual with a mean, which the
    # power-up gate's bias half refuses ("do not match this calibration", exit 3)
    c("standstill-absolute-reconstruct", _standstill,
      ["reconstruct", "a.json", "still.npz", "--absolute", "--out", "o.npz"],
      (OK, REFUSED))  # fmt: skip
    c("standstill-report", _standstill,
      ["report", "a.json", "cal.npz", "--validation", "still.npz", "--out", "rep"], (OK,),
      html_dir="rep")  # fmt: skip

    # -- artifacts ------------------------------------------------------------------------------
    def surrogate(f: Path, b: Base) -> None:
        (f / "u.json").write_text(
            json.dumps(
                {
                    **b.artifact,
                    "diagnostics": {**b.artifact["diagnostics"], "messages": ["x \ud800 y"]},
                }
            ),  # fmt: skip
            encoding="utf-8",
        )

    def sem_status(f: Path, b: Base) -> None:
        _artifact_with(f, b, "u.json", lambda a: a["diagnostics"].update(sem_status="weird"))

    c("surrogate-report", surrogate, ["report", "u.json", "cal.npz", "--out", "rep"],
      msg="surrogate")  # fmt: skip
    c("surrogate-reconstruct", surrogate, ["reconstruct", "u.json", "cal.npz", "--out", "o.npz"],
      msg="surrogate")  # fmt: skip
    c("sem-status-report", sem_status, ["report", "u.json", "cal.npz", "--out", "rep"],
      msg="sem_status")  # fmt: skip
    c("empty-objects-report",  # 2 GB of Python objects parsed from a 3 MB file
      lambda f, b: (f / "u.json").write_text("[" + "{}," * 1_000_001 + "{}]"),
      ["report", "u.json", "cal.npz", "--out", "rep"], msg="above the limit")  # fmt: skip

    # -- limits before work ---------------------------------------------------------------------
    for name, model in {
        "lengthscale-1e-300": {"basis": "kernel", "points": 64, "lengthscale": 1e-300},
        "lengthscale-1e300": {"basis": "kernel", "points": 64, "lengthscale": 1e300},
        "cogging-1-512": {"harmonics": list(range(1, 12)), "cogging": list(range(1, 513))},
        "cogging-1-600": {"harmonics": list(range(1, 12)), "cogging": list(range(1, 601))},
    }.items():
        c(f"{name}-calibrate",
          lambda f, b, model=model: _setup_with(f, b, "x.toml", model),
          ["calibrate", "cal.npz", "--setup", "x.toml", "--out", "o.json"],
          msg="above the limit|outside")  # fmt: skip
    c("harmonics-2000-2048-calibrate",
      lambda f, b: _setup_with(f, b, "x.toml", {"harmonics": [2000, 2048]}),
      ["calibrate", "cal.npz", "--setup", "x.toml", "--out", "o.json"],
      (INPUT, REFUSED))  # fmt: skip
    c("revolutions-1e6-plan", None, ["plan", "a.json", "--revolutions", "1e6"],
      msg="above the limit")  # fmt: skip
    speeds = ",".join(f"{1 + 0.01 * i:.2f}" for i in range(10000))
    c("speeds-10000-plan", None, ["plan", "a.json", "--speeds", speeds], msg="above the limit")

    # -- the fleet ------------------------------------------------------------------------------
    fleet = ["fleet", "m.csv", "--out", "batch", "--scheduler", "sequential", "--quiet"]

    def devzero(f: Path, b: Base) -> None:
        (f / "z.npz").symlink_to("/dev/zero")
        _manifest(f, [("m1", "z.npz", "s.toml")])

    def fifo(f: Path, b: Base) -> None:
        os.mkfifo(f / "p.npz")
        _manifest(f, [("m1", "p.npz", "s.toml")])

    def reserved(name: str) -> Callable[[Path, Base], None]:
        return lambda f, b: _manifest(f, [(name, "cal.npz", "s.toml")])

    def in_the_way(f: Path, b: Base) -> None:
        (f / "batch").mkdir()
        (f / "batch" / "m1").write_text("a file of the user")
        _manifest(f, [("m1", "cal.npz", "s.toml")])

    def locked(f: Path, b: Base) -> None:
        (f / "batch").mkdir()
        fd = os.open(f / "batch" / ".fleet.lock", os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        _HELD_LOCKS.append(fd)  # held by the test process while the worker runs the case
        _manifest(f, [("m1", "cal.npz", "s.toml")])

    def manifest_in_out(f: Path, b: Base) -> None:
        (f / "batch").mkdir()
        _manifest(f, [("m1", "cal.npz", "s.toml")])
        os.replace(f / "m.csv", f / "batch" / "summary.csv")

    def standstill_validation(f: Path, b: Base) -> None:
        _standstill(f, b)
        _manifest(f, [("m1", "cal.npz", "s.toml")], validation="still.npz")

    c("dev-zero-fleet", devzero, fleet, (FLEET_INCOMPLETE,))
    c("fifo-fleet", fifo, fleet, (FLEET_INCOMPLETE,))
    for name in ("summary.csv", "summary.parquet", "fleet.html"):
        c(f"motor-id-{name}-fleet", reserved(name), fleet, msg="the name of a file the batch")
    c("motor-id-in-the-way-fleet", in_the_way, fleet, msg="is not a folder of this batch")
    c("locked-fleet", locked, fleet, msg="another hallcal fleet")
    c("manifest-in-out-fleet", manifest_in_out,
      ["fleet", "batch/summary.csv", "--out", "batch", "--scheduler", "sequential", "--quiet"],
      msg=SAME)  # fmt: skip
    c("standstill-validation-fleet", standstill_validation, fleet, (OK,))
    return cases
