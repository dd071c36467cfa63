"""Each motor's record (``OUT/<motor_id>/fleet.json``): the fingerprint of its inputs and the
SHA-256 of its outputs, so that a rerun reuses what is up to date (module doc of
:mod:`hallcal.fleet`, "Up to date")."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hallcal.errors import HallcalInputError
from hallcal.fleet.manifest import _INPUT_ROLES, MotorSpec
from hallcal.fleet.summary import ARTIFACT_NAME, C_DIR, RECORD_NAME, SUMMARY_COLUMNS
from hallcal.fleet.worker import _Result, _version
from hallcal.io import atomic_write, make_folder, output_set, read_json, write_json

RECORD_FORMAT = "hallcal-fleet-record/1"


def _sha256_file(path: Path) -> str:
    """SHA-256 of a regular file's content, at most the size it had when looked at.

    Raises
    ------
    OSError
        ``EINVAL`` for anything but a regular file (a device such as /dev/zero, a FIFO, a
        folder: hashing one would never end or block), and the errors of opening it.
    """
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise OSError(errno.EINVAL, "not a regular file", str(path))
    h = hashlib.sha256()
    left = st.st_size  # a file that grows while it is hashed is hashed as it was
    with open(path, "rb") as f:
        while left > 0:
            block = f.read(min(left, 1 << 20))
            if not block:
                break
            h.update(block)
            left -= len(block)
    return h.hexdigest()


def fingerprint(spec: MotorSpec, options: Mapping[str, Any]) -> str:
    """SHA-256 of what a motor's result depends on (see "Up to date" in the module docs).

    Parameters
    ----------
    spec : MotorSpec
    options : mapping
        The run options that change the outputs (JSON-serializable).

    Returns
    -------
    str
        Hex digest.
    """
    h = hashlib.sha256()
    head = {"format": RECORD_FORMAT, "hallcal": _version(), "options": dict(options)}
    h.update(json.dumps(head, sort_keys=True).encode())
    for role in _INPUT_ROLES:
        path: Path | None = getattr(spec, role)
        if path is None:
            state = "none"
        else:
            try:
                state = f"{path.suffix.lower()}:{_sha256_file(path)}"
            except FileNotFoundError:
                state = "missing"
            except OSError as exc:
                state = f"unreadable:{exc.errno}"
        h.update(f"\0{role}={state}".encode())
    return h.hexdigest()


def _load_record(folder: Path) -> dict[str, Any] | None:
    path = folder / RECORD_NAME
    if not path.is_file():
        return None
    try:
        rec = read_json(path)
    except HallcalInputError:
        return None
    if not isinstance(rec, dict) or rec.get("format") != RECORD_FORMAT:
        return None
    return rec


def _record_is_current(folder: Path, record: Mapping[str, Any] | None, fp: str) -> bool:
    if record is None or record.get("fingerprint") != fp or record.get("retry", True):
        return False
    row = record.get("row")
    if not isinstance(row, dict) or set(row) != set(SUMMARY_COLUMNS) - {"reused"}:
        return False
    outputs = record.get("outputs")
    if not isinstance(outputs, dict):
        return False
    for rel, digest in outputs.items():
        p = folder / rel
        try:
            if not p.is_file() or _sha256_file(p) != digest:
                return False
        except OSError:
            return False
    return True


def _store(out: Path, spec: MotorSpec, fp: str, result: _Result) -> None:
    """Write one motor's outputs as one set (:func:`hallcal.io.output_set`), then its record.

    The folder holds the previous complete set until the new one is complete; the record,
    written last, vouches for the outputs by their SHA-256, so a batch stopped in between
    (SIGKILL) recomputes this motor."""
    folder = out / spec.motor_id
    outputs: dict[str, str] = {}
    record = {
        "format": RECORD_FORMAT,
        "fingerprint": fp,
        "retry": result.retry,
        "row": {k: v for k, v in result.row.items() if k != "reused"},
        "inputs": {
            role: None if getattr(spec, role) is None else str(getattr(spec, role))
            for role in _INPUT_ROLES
        },
        "outputs": outputs,
    }
    if result.detail:
        record["traceback"] = result.detail
    with output_set():
        make_folder(folder)
        for rel, content in result.files.items():
            target = folder / rel
            make_folder(target.parent)
            with atomic_write(target, "wb") as f:
                f.write(content)
            outputs[rel] = hashlib.sha256(content).hexdigest()
    # outputs of an earlier run that this one does not produce (a motor now refused) must go
    stale = [folder / ARTIFACT_NAME] + sorted((folder / C_DIR).glob("*"))
    wanted = {folder / rel for rel in result.files}
    for p in stale:
        if p not in wanted and p.is_file():
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
    if (folder / C_DIR).is_dir() and not any((folder / C_DIR).iterdir()):
        (folder / C_DIR).rmdir()
    write_json(folder / RECORD_NAME, record)  # last: it vouches for what is there
