"""Small shared helpers of the BLA modules: option checks and JSON conversion (no I/O)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hallcal.errors import HallcalInputError


def _int_option(value: int, name: str, *, minimum: int) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < minimum:
        raise HallcalInputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _float_or_none(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _floats(values: np.ndarray) -> list[float | None]:
    return [_float_or_none(v) for v in np.asarray(values, dtype=np.float64).ravel()]


def _complex_pairs(values: np.ndarray) -> list[list[float | None]]:
    z = np.asarray(values, dtype=np.complex128).ravel()
    return [[_float_or_none(v.real), _float_or_none(v.imag)] for v in z]


def _check_kind(data: dict[str, Any], kind: str) -> None:
    if not isinstance(data, dict):
        raise HallcalInputError(f"a {kind} must be a JSON object")
    found = data.get("kind", kind)
    if found != kind:
        raise HallcalInputError(f"key kind: expected {kind!r}, got {found!r}")


def _get(data: dict[str, Any], key: str) -> Any:
    if key not in data:
        raise HallcalInputError(f"missing key {key}")
    return data[key]


def _array_from(data: dict[str, Any], key: str) -> np.ndarray:
    raw = _get(data, key)
    try:
        return np.array([np.nan if v is None else float(v) for v in raw], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise HallcalInputError(f"key {key} must be a list of numbers") from exc


def _complex_from(data: dict[str, Any], key: str) -> np.ndarray:
    raw = _get(data, key)
    try:
        pairs = [
            complex(np.nan if re is None else re, np.nan if im is None else im) for re, im in raw
        ]
    except (TypeError, ValueError) as exc:
        raise HallcalInputError(f"key {key} must be a list of [re, im] pairs") from exc
    return np.array(pairs, dtype=np.complex128)
