"""Each motor's record (``OUT/<motor_id>/fleet.json``): the fingerprint of its inputs and the
SHA-256 of its outputs, so that a rerun reuses what is up to date (module doc of
:mod:`hallcal.fleet`, "Up to date")."""

from __future__ import annotations

import contextlib
import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hallcal.errors import HallcalInputError
from hallcal.fleet.manifest import _INPUT_ROLES, MotorSpec
from hallcal.fleet.summary import ARTIFACT_NAME, C_DIR, RECORD_NAME, SUMMARY_COLUMNS
from hallcal.fleet.worker import _Result, _version
from hallcal.io import atomic_write, read_json, write_json

RECORD_FORMAT = "hallcal-fleet-record/1"


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
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
    """Write one motor's outputs then its record (the record last, so it vouches for them)."""
    folder = out / spec.motor_id
    folder.mkdir(parents=True, exist_ok=True)
    with contextlib.suppress(FileNotFoundError):
        (folder / RECORD_NAME).unlink()
    # outputs of an earlier run that this one does not produce (a motor now refused) must go
    stale = [folder / ARTIFACT_NAME] + sorted((folder / C_DIR).glob("*"))
    wanted = {folder / rel for rel in result.files}
    for p in stale:
        if p not in wanted and p.is_file():
            p.unlink()
    if (folder / C_DIR).is_dir() and not any((folder / C_DIR).iterdir()):
        (folder / C_DIR).rmdir()
    outputs: dict[str, str] = {}
    for rel, content in result.files.items():
        target = folder / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(target, "wb") as f:
            f.write(content)
        outputs[rel] = hashlib.sha256(content).hexdigest()
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
    write_json(folder / RECORD_NAME, record)
