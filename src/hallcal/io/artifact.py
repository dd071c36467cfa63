"""The calibration artifact (JSON, ``docs/design.md`` "Calibration artifact"): one format constant,
one validator, reading and writing."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NoReturn

from hallcal import _version
from hallcal.errors import HallcalInputError
from hallcal.io.files import _dump_json, atomic_write, read_json
from hallcal.io.setup import _is_int, _is_number, _parse_setup, _show

__all__ = ["ARTIFACT_FORMAT", "read_artifact", "write_artifact"]

#: Value of the ``"format"`` key of every calibration artifact this version writes and reads.
ARTIFACT_FORMAT = "hallcal-calibration/1"


def _validate_artifact(data: Any, source: str) -> None:
    def bad(message: str) -> NoReturn:
        raise HallcalInputError(f"{source}: {message}")

    if not isinstance(data, Mapping):
        bad("not a hallcal calibration artifact (not a JSON object)")
    if "format" not in data:
        bad("not a hallcal calibration artifact (format key missing)")
    if data["format"] != ARTIFACT_FORMAT:
        bad(f"unsupported format {_show(data['format'])} (this hallcal reads '{ARTIFACT_FORMAT}')")
    for key in ("pole_pairs", "reconstruction", "lut", "model", "setup", "diagnostics"):
        if key not in data:
            bad(f"key '{key}' is missing")
    if "hallcal_version" not in data:
        bad("key 'hallcal_version' is missing")
    if not isinstance(data["hallcal_version"], str):
        bad("key 'hallcal_version' must be a string")
    if not _is_int(data["pole_pairs"]) or data["pole_pairs"] < 1:
        bad(f"key 'pole_pairs' must be an integer >= 1, got {_show(data['pole_pairs'])}")
    for key in ("reconstruction", "lut", "model", "diagnostics"):
        if not isinstance(data[key], Mapping):
            bad(f"key '{key}' must be an object")

    def vector(value: Any, length: int | None = None) -> bool:
        return (
            isinstance(value, list)
            and (length is None or len(value) == length)
            and all(_is_number(v) for v in value)
        )

    rec = data["reconstruction"]
    for key in ("projection", "offset"):
        if key not in rec:
            bad(f"key 'reconstruction.{key}' is missing")
    projection = rec["projection"]
    if not (isinstance(projection, list) and len(projection) == 2):
        bad("key 'reconstruction.projection' must be a 2x3 array of numbers")
    if not all(vector(row, 3) for row in projection):
        bad("key 'reconstruction.projection' must be a 2x3 array of numbers")
    if not vector(rec["offset"], 3):
        bad("key 'reconstruction.offset' must be a list of 3 numbers")
    lut = data["lut"]
    for key in ("y_hat", "eta"):
        if key not in lut:
            bad(f"key 'lut.{key}' is missing")
    for key in ("y_hat", "eta"):
        if not vector(lut[key]) or len(lut[key]) < 16:
            bad(f"key 'lut.{key}' must be a list of at least 16 numbers")
    n_hat, n_eta = len(lut["y_hat"]), len(lut["eta"])
    if n_hat != n_eta:
        bad(f"keys 'lut.y_hat' and 'lut.eta' have different lengths ({n_hat} and {n_eta})")
    if "cogging" in data:
        _check_cogging(data["cogging"], bad, vector)
    setup = _parse_setup(data["setup"], source, prefix="setup.")
    if setup.pole_pairs != data["pole_pairs"]:
        bad(
            f"key 'pole_pairs' ({data['pole_pairs']}) differs from 'setup.pole_pairs' "
            f"({setup.pole_pairs})"
        )


def _check_cogging(cog: Any, bad: Any, vector: Any) -> None:
    """The optional ``"cogging"`` entry: T_c(y0) = sum a_k cos(k y0) + b_k sin(k y0)."""
    if not isinstance(cog, Mapping):
        bad("key 'cogging' must be an object")
    orders = cog.get("orders")
    if not isinstance(orders, list) or not all(_is_int(k) and k >= 1 for k in orders):
        bad("key 'cogging.orders' must be a list of integers >= 1")
    for key in ("a", "b"):
        if not vector(cog.get(key), len(orders)):
            bad(f"key 'cogging.{key}' must be a list of {len(orders)} numbers (one per order)")


def write_artifact(path: str | os.PathLike[str], artifact: Mapping[str, Any]) -> None:
    """Write a calibration artifact (JSON, ``docs/design.md`` "Calibration artifact"), atomically.

    ``"format"`` (:data:`ARTIFACT_FORMAT`) and ``"hallcal_version"`` are filled in when absent;
    a :class:`Setup` under ``"setup"`` is converted with :meth:`Setup.to_dict`; NumPy data are
    converted to lists and numbers. The result is checked like :func:`read_artifact` checks it
    before anything is written.

    Raises
    ------
    ValueError
        NaN or inf anywhere (the message names the key); nothing is written.
    HallcalInputError
        The artifact does not have the structure :func:`read_artifact` requires, or the file
        cannot be written.
    """
    p = Path(path)
    data = dict(artifact)
    data.setdefault("format", ARTIFACT_FORMAT)
    data.setdefault("hallcal_version", _version.__version__)
    ordered = {"format": data.pop("format"), **data}
    text = _dump_json(p, ordered)
    _validate_artifact(json.loads(text), str(p))
    with atomic_write(p, "w") as f:
        f.write(text)


def read_artifact(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read and check a calibration artifact.

    Checks: valid JSON; ``"format" == ARTIFACT_FORMAT``; ``pole_pairs`` (integer >= 1, equal to
    ``setup.pole_pairs``); ``reconstruction.projection`` (2x3) and ``reconstruction.offset``
    (3); ``lut.y_hat`` and ``lut.eta`` (lists of numbers of equal length >= 16); ``model`` and
    ``diagnostics`` (objects); ``setup`` (a valid setup, see :func:`setup_from_dict`);
    ``hallcal_version`` (string).

    Returns
    -------
    dict
        The artifact as parsed JSON (lists, not arrays). ``setup_from_dict(a["setup"])`` gives
        the :class:`Setup`.

    Raises
    ------
    HallcalInputError
        Missing file, invalid JSON, not an artifact, unsupported format, or a missing or
        malformed key (named in the message).
    """
    data = read_json(path)
    _validate_artifact(data, str(Path(path)))
    return data
