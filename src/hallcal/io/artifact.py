"""The calibration artifact (JSON, ``docs/design.md`` "Calibration artifact"): one format constant,
one validator, one typed view, reading and writing.

:func:`validate_artifact` is the only place that decides whether an artifact may be used; it
returns an :class:`ArtifactData` (read-only arrays, the parsed :class:`Setup`, and read-only
mapping access to every key) that every consumer (``reconstruct``, ``report``, ``export-c``,
``fleet``, :func:`hallcal.load`) works from; :func:`read_artifact` is the one reader and
:func:`write_artifact` the one writer. It checks the format
and version, the numbers (finite, within :mod:`hallcal.limits`), f_init's projection (rank 2, a
sane condition number, a plausible scale), the lookup table (node count, monotone nodes, bijective
map, corrections below pi), the flux model's shape, the setup and the optional plant.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Literal, NoReturn, overload

import numpy as np
from numpy.typing import NDArray

from hallcal import _version
from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.io.files import (
    _check_parsed,
    _dump_json,
    _read_json_raw,
    atomic_write,
    to_jsonable,
)
from hallcal.io.setup import Setup, _is_int, _is_number, _parse_setup, _show
from hallcal.limits import (
    MAX_ABS_VALUE,
    MAX_DELAY_SAMPLES,
    MAX_HARMONIC,
    MAX_HARMONICS,
    MAX_ITERATIONS,
    MAX_KERNEL_POINTS,
    MAX_LUT_POINTS,
    MAX_POLE_PAIRS,
    MAX_POWERUP_GRID,
    MAX_PROJECTION_CONDITION,
    MAX_SAMPLES,
    MAX_TEXT_FIELD,
    MAX_TF_ORDER,
    MIN_LUT_POINTS,
)
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.lut import LUT
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.lti import ContinuousTF

__all__ = [
    "ARTIFACT_FORMAT",
    "ARTIFACT_STATUSES",
    "RENAMED_VALUES",
    "ArtifactData",
    "TIMING_KEYS",
    "migrate_values",
    "read_artifact",
    "validate_artifact",
    "without_timings",
    "write_artifact",
]

#: The artifact's only wall-clock fields (dotted paths): when it was written and how long steps
#: took. Nothing else depends on the clock, the machine's load or its thread count, so two
#: calibrations of the same input by the same version agree byte for byte once these are
#: removed (:func:`without_timings`; tests/test_determinism.py).
TIMING_KEYS = ("created", "diagnostics.timings", "diagnostics.solve_time")


def without_timings(artifact: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of the artifact without its wall-clock fields (:data:`TIMING_KEYS`).

    Parameters
    ----------
    artifact : mapping
        An artifact as written (JSON object).

    Returns
    -------
    dict
        The same artifact without ``created``, ``diagnostics.timings`` and
        ``diagnostics.solve_time``; equal for two runs of the same input and version.
    """
    out = json.loads(json.dumps(to_jsonable(dict(artifact))))
    for key in TIMING_KEYS:
        *parents, leaf = key.split(".")
        node = out
        for part in parents:
            node = node.get(part, {}) if isinstance(node, dict) else {}
        if isinstance(node, dict):
            node.pop(leaf, None)
    return out


#: Value of the ``"format"`` key of every calibration artifact this version writes and reads.
ARTIFACT_FORMAT = "hallcal-calibration/1"

#: Values of ``diagnostics.status``: those of :class:`hallcal.pipeline.CalibrationStatus`, which
#: lives above this layer (tests/test_limits.py checks that the two agree).
ARTIFACT_STATUSES = ("ok", "warning", "inadequate", "not_bijective")

#: Status values renamed to the one spelling (snake_case) after 0.1.0, old -> new: a file
#: written before (artifact or ``hallcal-bla/1``) is read with the new values
#: (:func:`migrate_values`; CHANGELOG.md states the migration).
RENAMED_VALUES: Mapping[str, str] = {
    "not-bijective": "not_bijective",
    "needs-motion": "needs_motion",
    "not-identifiable": "not_identifiable",
    "weak-positions": "weak_positions",
    "too-uniform": "too_uniform",
    "below-model-uncertainty": "below_model_uncertainty",
    "partial-coverage": "partial_coverage",
    "not-found": "not_found",
    "not-converged": "not_converged",
    "single-realization": "single_realization",
    "single-period": "single_period",
    "single-realization+single-period": "single_realization_and_period",
}

#: Keys whose values :data:`RENAMED_VALUES` renames, at any depth.
_RENAMED_KEYS = ("status", "reason")


def migrate_values(data: Any) -> Any:
    """Rename the old status values of a parsed file in place (:data:`RENAMED_VALUES`).

    Every ``"status"`` and ``"reason"`` key at any depth of nested objects; other values are
    left as they are.

    Parameters
    ----------
    data : object
        Parsed JSON (an artifact or a ``hallcal-bla/1`` document).

    Returns
    -------
    object
        `data`, renamed in place.
    """
    stack = [data]  # no recursion: a hostile file's nesting cannot exhaust the stack
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            for key, value in node.items():
                if key in _RENAMED_KEYS and isinstance(value, str):
                    node[key] = RENAMED_VALUES.get(value, value)
                elif isinstance(value, dict | list):
                    stack.append(value)
        elif node and isinstance(node[0], dict | list):  # lists of numbers are left alone
            stack.extend(node)
    return data


#: Table nodes y_hat_i = y0_i - eta_i with y0_i in [0, 2 pi) and |eta_i| < pi lie in (-pi, 3 pi).
_Y_HAT_RANGE = (-math.pi, 3.0 * math.pi)


def _readonly(a: NDArray[np.float64]) -> NDArray[np.float64]:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class ArtifactData(Mapping[str, Any]):
    """A calibration artifact that passed :func:`validate_artifact`: typed, read-only.

    Also a read-only mapping of the artifact's JSON keys (``art["lut"]["eta"]``,
    ``art.get("plant")``, ``dict(art)``), so that code reading one key needs no second form.

    Attributes
    ----------
    format : str
        :data:`ARTIFACT_FORMAT`.
    version : str
        The hallcal version that wrote it (``hallcal_version``).
    pole_pairs : int
        n_m, in 1 .. :data:`~hallcal.limits.MAX_POLE_PAIRS`.
    projection : ndarray, shape (2, 3)
        f_init's projection P (rank 2, condition number at most
        :data:`~hallcal.limits.MAX_PROJECTION_CONDITION`).
    offset : ndarray, shape (3,)
        Sensor offsets o, subtracted before projecting.
    y_hat, eta : ndarray, shape (M,)
        Table nodes: strictly increasing within one revolution, |eta| < pi, and the map
        y0 = y_hat + eta -> y_hat bijective (eq. recon_biject).
    setup : Setup
        The checked setup the calibration came from.
    model : mapping
        The flux model (``basis``, ``harmonics``, ``theta`` of shape (3, 2 K + 1), ...).
    diagnostics : mapping
        Status, messages, costs, timings (checked for type, not interpreted).
    plant : mapping or None
        The plant G(s) the calibration used (``num``, ``den``, ``delay``), when present.
    data : mapping
        The whole artifact as plain JSON data (what was checked).
    source : str
        Where it came from (the file), for messages.
    file_sha256 : str or None
        SHA-256 of the file's bytes when read from a file (:func:`read_artifact`).
    bijective_checked : bool
        False when validated with ``bijective=False`` (an in-memory refused calibration's
        report): checked again, not passed through, where a usable table is required.
    checked : bool
        False for the artifact of a calibration computed in this process
        (:meth:`in_memory`): :func:`validate_artifact` checks it before it is written or
        reported.
    objects : dict
        The typed objects built so far, by name (:meth:`typed`).
    """

    format: str
    version: str
    pole_pairs: int
    projection: NDArray[np.float64] = field(repr=False)
    offset: NDArray[np.float64] = field(repr=False)
    y_hat: NDArray[np.float64] = field(repr=False)
    eta: NDArray[np.float64] = field(repr=False)
    setup: Setup = field(repr=False)
    model: Mapping[str, Any] = field(repr=False)
    diagnostics: Mapping[str, Any] = field(repr=False)
    plant: Mapping[str, Any] | None = field(repr=False)
    data: Mapping[str, Any] = field(repr=False)
    source: str = "<artifact>"
    file_sha256: str | None = None
    bijective_checked: bool = field(default=True, repr=False)
    checked: bool = field(default=True, repr=False)
    objects: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def in_memory(cls, data: Mapping[str, Any], lut: LUT, typed: Mapping[str, Any]) -> ArtifactData:
        """The artifact of a calibration computed in this process, unchecked.

        Parameters
        ----------
        data : mapping
            Its keys (NumPy data, a :class:`Setup` and NaN allowed: :func:`validate_artifact`
            checks them before they are written or reported).
        lut : LUT
            Its table (``reconstruction`` and ``lut``).
        typed : mapping
            The other objects it was written from, by name (:meth:`typed`).

        Returns
        -------
        ArtifactData
            With ``checked`` False.
        """
        return cls(
            format=data["format"],
            version=data["hallcal_version"],
            pole_pairs=int(data["pole_pairs"]),
            projection=lut.projection,
            offset=lut.offset,
            y_hat=lut.y_hat,
            eta=lut.eta,
            setup=data["setup"],
            model=data["model"],
            diagnostics=data["diagnostics"],
            plant=data.get("plant"),
            data=data,
            source="in memory",
            bijective_checked=False,
            checked=False,
            objects={"lut": lut, **typed},
        )

    def typed(self, name: str, build: Callable[[], Any]) -> Any:
        """A typed object of this artifact, built once.

        Parameters
        ----------
        name : str
            Its name (``"lut"``, ``"flux"``, ...).
        build : callable
            Builds it from the artifact; not called when it exists (or, for a calibration
            computed in this process, is the object the artifact was written from).

        Returns
        -------
        object
        """
        if name not in self.objects:
            self.objects[name] = build()
        return self.objects[name]

    def __getitem__(self, key: str) -> Any:
        return self.data[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.data)

    def __len__(self) -> int:
        return len(self.data)

    @property
    def points(self) -> int:
        """M, table nodes per revolution."""
        return int(self.y_hat.size)

    @property
    def y0(self) -> NDArray[np.float64]:
        """The table's grid y0_i = y_hat_i + eta_i [rad]."""
        return self.y_hat + self.eta

    @cached_property
    def sha256(self) -> str:
        """SHA-256 of the artifact file as read (:func:`read_artifact`: what ``sha256sum``
        prints for it), else of the artifact's canonical JSON (sorted keys, no spaces)."""
        if self.file_sha256 is not None:
            return self.file_sha256
        data = to_jsonable(self.data)  # plain already, unless computed in this process
        canon = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)
        return hashlib.sha256(canon.encode()).hexdigest()

    def lut(self) -> LUT:
        """The lookup table and the f_init it corrects (:class:`hallcal.sensor.lut.LUT`)."""
        return self.typed(
            "lut",
            lambda: LUT.from_arrays(
                self.pole_pairs, self.projection, self.offset, self.y_hat, self.eta
            ),
        )

    def plant_model(self) -> ContinuousTF | None:
        """The plant G(s) the calibration used (``plant``: gain correction applied), or None
        when the artifact has none (open-loop runs, older artifacts)."""
        return self.typed("plant", self._plant_model)

    def _plant_model(self) -> ContinuousTF | None:
        p = self.plant
        if p is None:
            return None
        num, den = (tuple(float(v) for v in p[k]) for k in ("num", "den"))
        return ContinuousTF(num, den, float(p["delay"]))

    def cogging_torque(self) -> CoggingTorque | None:
        """The cogging torque identified with the flux (``cogging``), or None.

        Raises
        ------
        HallcalInputError
            When the model refuses the checked coefficients (the message names the key).
        """
        return self.typed("cogging", self._cogging_torque)

    def _cogging_torque(self) -> CoggingTorque | None:
        if self.data.get("cogging") is None:
            return None
        try:
            return CoggingTorque.from_dict(self.data["cogging"])
        except ValueError as exc:
            raise HallcalInputError(
                f"{self.source}: key 'cogging': {exc}", source=self.source, key="cogging"
            ) from None

    def flux(self) -> FluxModel:
        """The flux model as a Fourier series (a kernel model stores its harmonics and
        coefficients too): :class:`hallcal.sensor.flux.FluxModel`."""
        return self.typed("flux", self._flux)

    def _flux(self) -> FluxModel:
        harmonics = tuple(int(h) for h in self.model["harmonics"])
        return FluxModel(FourierBasis(harmonics), np.array(self.model["theta"], dtype=np.float64))


class _Checker:
    """Typed getters whose errors name the artifact and the key."""

    def __init__(self, source: str) -> None:
        self.source = source

    def bad(self, message: str) -> NoReturn:
        raise HallcalInputError(f"{self.source}: {message}")

    def need(self, obj: Mapping[str, Any], key: str, where: str) -> Any:
        if key not in obj:
            self.bad(f"key '{where}' is missing")
        return obj[key]

    def mapping(self, value: Any, where: str) -> Mapping[str, Any]:
        if not isinstance(value, Mapping):
            self.bad(f"key '{where}' must be an object")
        return value

    @overload
    def text(self, value: Any, where: str, *, optional: Literal[False] = False) -> str: ...
    @overload
    def text(self, value: Any, where: str, *, optional: bool) -> str | None: ...
    def text(self, value: Any, where: str, *, optional: bool = False) -> str | None:
        if value is None and optional:
            return None
        if not isinstance(value, str):
            self.bad(f"key '{where}' must be a string")
        if len(value) > MAX_TEXT_FIELD:
            self.bad(
                f"key '{where}' is a string of {len(value)} characters, above the limit of "
                f"{MAX_TEXT_FIELD}"
            )
        return value

    def array(
        self,
        value: Any,
        where: str,
        what: str,
        *,
        shape: tuple[int, ...] | None = None,
        limit: float = MAX_ABS_VALUE,
    ) -> NDArray[np.float64]:
        """Numbers of the given shape (lists of lists), finite, at most `limit` in magnitude."""
        if not _numeric_lists(value):
            self.bad(f"key '{where}' must be {what}")
        try:
            arr = np.array(value, dtype=np.float64)
        except (ValueError, TypeError):  # ragged lists
            self.bad(f"key '{where}' must be {what}")
        if shape is not None and arr.shape != shape:
            self.bad(f"key '{where}' must be {what}")
        if arr.size and not np.all(np.abs(arr) <= limit):
            i = int(np.argmax(~(np.abs(arr) <= limit)))
            self.bad(
                f"key '{where}' holds {arr.flat[i]:.4g}, implausible (above {limit:g} in magnitude)"
            )
        return arr


def _numeric_lists(value: Any) -> bool:
    """Nested lists whose leaves are all numbers (no strings, booleans or None)."""
    stack = [value]
    while stack:
        v = stack.pop()
        if isinstance(v, list):
            stack.extend(v)
        elif not _is_number(v):
            return False
    return isinstance(value, list)


def _check_projection(c: _Checker, rec: Mapping[str, Any]) -> tuple[NDArray, NDArray]:
    P = c.array(
        c.need(rec, "projection", "reconstruction.projection"),
        "reconstruction.projection",
        "a 2x3 array of numbers",
        shape=(2, 3),
    )
    o = c.array(
        c.need(rec, "offset", "reconstruction.offset"),
        "reconstruction.offset",
        "a list of 3 numbers",
        shape=(3,),
    )
    s = np.linalg.svd(P, compute_uv=False)
    if s[0] == 0.0:
        c.bad("key 'reconstruction.projection' is all zero: f_init needs a rank-2 projection")
    # alpha, beta = P (d - o) must stay far from overflow and underflow, also in single precision
    if not 1.0 / MAX_ABS_VALUE <= s[0] <= MAX_ABS_VALUE:
        c.bad(
            f"key 'reconstruction.projection' has the scale {s[0]:.3g}, implausible (outside "
            f"{1.0 / MAX_ABS_VALUE:g} .. {MAX_ABS_VALUE:g})"
        )
    kappa = s[0] / s[1] if s[1] > 0.0 else math.inf
    if kappa > MAX_PROJECTION_CONDITION:
        rank = "rank 1, " if s[1] <= s[0] * 1e-15 else ""
        c.bad(
            f"key 'reconstruction.projection' has {rank}condition number {kappa:.3g}, above the "
            f"limit of {MAX_PROJECTION_CONDITION:g}: the sensors' directions do not span a "
            "plane, no angle can be read"
        )
    return P, o


def _check_lut(
    c: _Checker, lut: Mapping[str, Any], pole_pairs: int, *, folding: bool = False
) -> tuple[NDArray, NDArray]:
    what = f"a list of at least {MIN_LUT_POINTS} numbers"
    y_hat = c.need(lut, "y_hat", "lut.y_hat")
    eta = c.need(lut, "eta", "lut.eta")
    for key, value in (("y_hat", y_hat), ("eta", eta)):
        if not (isinstance(value, list) and len(value) >= MIN_LUT_POINTS):
            c.bad(f"key 'lut.{key}' must be {what}")
        if len(value) > MAX_LUT_POINTS:
            c.bad(f"key 'lut.{key}' has {len(value)} nodes, above the limit of {MAX_LUT_POINTS}")
    y_hat = c.array(y_hat, "lut.y_hat", what)
    eta = c.array(eta, "lut.eta", what)
    if y_hat.ndim != 1 or eta.ndim != 1:
        c.bad(f"key 'lut.{'y_hat' if y_hat.ndim != 1 else 'eta'}' must be {what}")
    if y_hat.size != eta.size:
        c.bad(
            f"keys 'lut.y_hat' and 'lut.eta' have different lengths ({y_hat.size} and {eta.size})"
        )
    m = y_hat.size
    if "points" in lut and (not _is_int(lut["points"]) or lut["points"] != m):
        c.bad(f"key 'lut.points' is {_show(lut['points'])} but 'lut.y_hat' has {m} nodes")
    if np.max(np.abs(eta)) >= math.pi:
        c.bad("key 'lut.eta' has corrections of pi rad or more: not a table of this f_init")
    lo, hi = _Y_HAT_RANGE
    if not (np.all(y_hat > lo) and np.all(y_hat < hi)):
        c.bad("key 'lut.y_hat' has nodes outside one revolution (-pi .. 3 pi)")
    if "y0" in lut:
        y0 = c.array(lut["y0"], "lut.y0", f"a list of {m} numbers", shape=(m,))
        if np.max(np.abs(y0 - (y_hat + eta))) > 1e-9:
            c.bad("key 'lut.y0' differs from 'lut.y_hat' + 'lut.eta': the table is corrupt")
    # eq. (recon_biject): the nodes strictly increasing within one revolution, and the map
    # y0 -> y_hat monotone (checked on the nodes themselves, so reordered nodes are refused)
    monotone = bool(np.all(np.diff(y_hat) > 0) and y_hat[-1] < y_hat[0] + TWO_PI)
    table = LUT.from_arrays(pole_pairs, np.eye(2, 3), np.zeros(3), y_hat, eta)
    if not (monotone and table.bijective) and not folding:
        c.bad(
            f"key 'lut' is not bijective (min slope {table.min_slope:.3g}): the table would give "
            "wrong angles"
        )
    return y_hat, eta


def _check_model(c: _Checker, model: Mapping[str, Any]) -> None:
    basis = c.need(model, "basis", "model.basis")
    if basis not in ("fourier", "kernel"):
        c.bad(f'key \'model.basis\' must be "fourier" or "kernel", got {_show(basis)}')
    harmonics = c.need(model, "harmonics", "model.harmonics")
    limit = MAX_HARMONICS if basis == "fourier" else MAX_KERNEL_POINTS // 2
    if not (isinstance(harmonics, list) and all(_is_int(h) and h >= 1 for h in harmonics)):
        c.bad("key 'model.harmonics' must be a list of integers >= 1")
    if len(harmonics) > limit:
        c.bad(f"key 'model.harmonics' lists {len(harmonics)} harmonics, above the limit of {limit}")
    if harmonics and max(harmonics) > MAX_HARMONIC:
        c.bad(
            f"key 'model.harmonics' has the harmonic {max(harmonics)}, above the limit of "
            f"{MAX_HARMONIC}"
        )
    if len(set(harmonics)) != len(harmonics):
        c.bad("key 'model.harmonics' lists a harmonic twice")
    m = 2 * len(harmonics) + 1
    c.array(
        c.need(model, "theta", "model.theta"),
        "model.theta",
        f"a 3x{m} array of numbers (3 sensors, 2 x {len(harmonics)} + 1 coefficients)",
        shape=(3, m),
    )
    if basis == "kernel" and "points" in model:
        points = model["points"]
        if not _is_int(points) or not 3 <= points <= MAX_KERNEL_POINTS:
            c.bad(f"key 'model.points' must be an integer in 3 .. {MAX_KERNEL_POINTS}")
        if "weights" in model:
            c.array(model["weights"], "model.weights", f"a 3x{points} array", shape=(3, points))


#: Optional diagnostics read by the report and :func:`hallcal.load`, and their types.
_DIAGNOSTIC_NUMBERS = (
    "cost",
    "cost_initial",
    "solve_time",
    "noise_variance",
    "min_slope",
    "predicted_angle_error_rms",
    "noise_floor",
)
_DIAGNOSTIC_COUNTS = ("iterations", "n_samples")
_DIAGNOSTIC_OBJECTS = ("adequacy", "validation", "gain_correction", "constant_speed", "timings")


def _check_diagnostics(c: _Checker, diag: Mapping[str, Any]) -> None:
    for key in ("status", "sem_status"):
        if key in diag:
            c.text(diag[key], f"diagnostics.{key}")
    if diag.get("status", "ok") not in ARTIFACT_STATUSES:
        options = ", ".join(f'"{v}"' for v in ARTIFACT_STATUSES)
        c.bad(f"key 'diagnostics.status' must be one of {options}, got {_show(diag['status'])}")
    if "refusal" in diag:
        c.text(diag["refusal"], "diagnostics.refusal", optional=True)
    for key in _DIAGNOSTIC_NUMBERS:
        value = diag.get(key)
        if value is not None and not _is_number(value):
            c.bad(f"key 'diagnostics.{key}' must be a number or null")
    for key in _DIAGNOSTIC_COUNTS:
        if key in diag and not (_is_int(diag[key]) and diag[key] >= 0):
            c.bad(f"key 'diagnostics.{key}' must be an integer >= 0")
    for key in _DIAGNOSTIC_OBJECTS:
        if diag.get(key) is not None:
            c.mapping(diag[key], f"diagnostics.{key}")
    if "bijective" in diag and not isinstance(diag["bijective"], bool):
        c.bad("key 'diagnostics.bijective' must be true or false")
    if "cost_history" in diag:
        history = diag["cost_history"]
        if not (isinstance(history, list) and all(_is_number(v) for v in history)):
            c.bad("key 'diagnostics.cost_history' must be a list of numbers")
        if len(history) > MAX_ITERATIONS + 1:
            c.bad(
                f"key 'diagnostics.cost_history' has {len(history)} entries, above the limit of "
                f"{MAX_ITERATIONS + 1} (one per SEM iteration)"
            )
    if "messages" in diag:
        messages = diag["messages"]
        if not isinstance(messages, list):
            c.bad("key 'diagnostics.messages' must be a list of strings")
        for i, m in enumerate(messages):
            c.text(m, f"diagnostics.messages[{i}]")
    for key in ("predicted_angle_error_rms", "noise_floor", "noise_variance"):
        value = diag.get(key)
        if value is not None and value < 0:
            c.bad(f"key 'diagnostics.{key}' must be a number >= 0 or null")
    timings = diag.get("timings", {})
    if not all(_is_number(v) for v in timings.values()):
        c.bad("key 'diagnostics.timings' must be an object of numbers")


def _check_loop(c: _Checker, key: str, num: Any, den: Any, delay: float, setup: Setup) -> None:
    """The plant can close a loop through f_init: no direct feedthrough without delay.

    The exact ZOH of G(s) (hallcal.sim.lti.c2d_zoh) keeps the feedthrough D = num[0] / den[0]
    of a biproper G only when the delay is below 1e-12 samples; then y[k] would depend on u[k],
    which depends on y[k], and the loop cannot be simulated (the report re-simulates it). Checked
    here in plain Python, so that reading an artifact does not load the simulator.
    """
    trimmed = list(num)
    while len(trimmed) > 1 and trimmed[0] == 0:
        trimmed = trimmed[1:]
    if len(trimmed) == len(den) and trimmed[0] != 0 and delay < 1e-12 * setup.sample_time:
        c.bad(
            f"key '{key}' has a direct feedthrough (as many zeros as poles and no delay): the "
            "loop through f_init would be algebraic"
        )


def _check_identifiability(c: _Checker, entry: Any, pole_pairs: int) -> None:
    """The sizes in the power-up entry (its meaning is hallcal.sensor.absolute's to check)."""
    entry = c.mapping(entry, "identifiability")
    if "pole_pairs" in entry and entry["pole_pairs"] != pole_pairs:
        c.bad(
            f"key 'identifiability.pole_pairs' ({_show(entry['pole_pairs'])}) differs from "
            f"'pole_pairs' ({pole_pairs})"
        )
    grid = entry.get("grid")
    if grid is not None and not (_is_int(grid) and 4 <= grid <= MAX_POWERUP_GRID):
        c.bad(f"key 'identifiability.grid' must be an integer in 4 .. {MAX_POWERUP_GRID}")
    for key in ("standstill_budget", "motion_budget"):
        value = entry.get(key)
        if value is not None and not (_is_int(value) and 0 <= value <= MAX_SAMPLES):
            c.bad(f"key 'identifiability.{key}' must be an integer in 0 .. {MAX_SAMPLES}")
    if "message" in entry:
        c.text(entry["message"], "identifiability.message")


def _check_plant(c: _Checker, plant: Mapping[str, Any], setup: Setup) -> None:
    for key in ("num", "den"):
        value = c.need(plant, key, f"plant.{key}")
        c.array(value, f"plant.{key}", "a list of numbers", limit=math.inf)
        if not (isinstance(value, list) and 1 <= len(value) <= MAX_TF_ORDER + 1):
            c.bad(f"key 'plant.{key}' must be a list of 1 .. {MAX_TF_ORDER + 1} numbers")
    num = [v for v in plant["num"]]
    den = [v for v in plant["den"]]
    while len(num) > 1 and num[0] == 0:
        num = num[1:]
    if den[0] == 0 or all(v == 0 for v in num) or len(num) > len(den):
        c.bad("keys 'plant.num' and 'plant.den' are not a proper transfer function")
    delay = c.need(plant, "delay", "plant.delay")
    if not (_is_number(delay) and delay >= 0):
        c.bad("key 'plant.delay' must be a number >= 0")
    if delay / setup.sample_time > MAX_DELAY_SAMPLES:
        c.bad(
            f"key 'plant.delay' is {delay / setup.sample_time:.4g} samples, above the limit of "
            f"{MAX_DELAY_SAMPLES}"
        )
    if setup.controller is not None:
        _check_loop(c, "plant", plant["num"], plant["den"], delay, setup)
    gain = plant.get("gain_correction")
    if gain is not None and not (_is_number(gain) and gain > 0):
        c.bad("key 'plant.gain_correction' must be a number > 0 or null")
    if "source" in plant:
        c.text(plant["source"], "plant.source", optional=True)


def validate_artifact(
    artifact: Mapping[str, Any], source: str = "<artifact>", *, bijective: bool = True
) -> ArtifactData:
    """Check a calibration artifact and return its typed view: the one validator.

    Accepts the parsed JSON (:func:`~hallcal.io.read_json`) or the in-memory artifact of a
    calibration (NumPy arrays, a :class:`Setup`), which is converted to plain JSON data first;
    an :class:`ArtifactData` (already checked) is returned as it is.

    Checks, each with a one-line message naming `source` and the key:

    * ``format`` is :data:`ARTIFACT_FORMAT`; ``hallcal_version`` a short string;
    * every number finite, every integer within 64 bits, nesting at most
      :data:`~hallcal.limits.MAX_JSON_DEPTH` levels;
    * ``pole_pairs`` an integer in 1 .. :data:`~hallcal.limits.MAX_POLE_PAIRS`, equal to
      ``setup.pole_pairs``;
    * ``reconstruction.projection`` 2x3, not all zero, of plausible scale, rank 2 with a
      condition number at most :data:`~hallcal.limits.MAX_PROJECTION_CONDITION`;
      ``reconstruction.offset`` 3 numbers at most :data:`~hallcal.limits.MAX_ABS_VALUE`;
    * ``lut.y_hat``, ``lut.eta``: equal lengths in :data:`~hallcal.limits.MIN_LUT_POINTS` ..
      :data:`~hallcal.limits.MAX_LUT_POINTS` (``lut.points`` and ``lut.y0`` consistent when
      present), |eta| < pi, nodes strictly increasing within one revolution, the map bijective;
    * ``model``: basis, harmonics within the limits, ``theta`` of shape (3, 2 K + 1);
    * ``setup``: a valid setup (:func:`~hallcal.io.setup_from_dict`, limits included);
    * ``diagnostics``: an object with string status, messages and refusal;
    * ``plant`` (optional): a proper G(s) of order at most :data:`~hallcal.limits.MAX_TF_ORDER`
      with a delay of at most :data:`~hallcal.limits.MAX_DELAY_SAMPLES` samples.

    Parameters
    ----------
    artifact : mapping
        The artifact.
    source : str
        Its name for messages (normally the file).
    bijective : bool, keyword-only
        False also accepts a table that is not bijective: the in-memory artifact of a
        calibration refused as not bijective, for its report (such an artifact is never
        written: :func:`write_artifact` keeps the default).

    Returns
    -------
    ArtifactData

    Raises
    ------
    HallcalInputError
        The first problem found.
    """
    if isinstance(artifact, ArtifactData):
        if artifact.checked and (artifact.bijective_checked or not bijective):
            return artifact
        artifact = artifact.data
    c = _Checker(source)
    if not isinstance(artifact, Mapping):
        c.bad("not a hallcal calibration artifact (not a JSON object)")
    try:
        data = to_jsonable(artifact)
    except (ValueError, TypeError) as exc:
        c.bad(str(exc))
    _check_parsed(source, data)
    migrate_values(data)
    if "format" not in data:
        c.bad("not a hallcal calibration artifact (format key missing)")
    if data["format"] != ARTIFACT_FORMAT:
        c.bad(
            f"unsupported format {_show(data['format'])} (this hallcal reads '{ARTIFACT_FORMAT}')"
        )
    for key in ("pole_pairs", "reconstruction", "lut", "model", "setup", "diagnostics"):
        c.need(data, key, key)
    version = c.text(c.need(data, "hallcal_version", "hallcal_version"), "hallcal_version")
    if len(version) > 64 or not version.isprintable():
        c.bad("key 'hallcal_version' must be a version string")
    n = data["pole_pairs"]
    if not _is_int(n) or n < 1:
        c.bad(f"key 'pole_pairs' must be an integer >= 1, got {_show(n)}")
    if n > MAX_POLE_PAIRS:
        c.bad(f"key 'pole_pairs' is {n}, above the limit of {MAX_POLE_PAIRS}")
    for key in ("reconstruction", "lut", "model", "diagnostics"):
        c.mapping(data[key], key)
    projection, offset = _check_projection(c, data["reconstruction"])
    folding = not bijective
    if data.get("observer") is not None:
        injective = _check_observer(c, data["observer"])
        folding |= injective and data["diagnostics"].get("status") == "not_bijective"
    y_hat, eta = _check_lut(c, data["lut"], int(n), folding=folding)
    _check_model(c, data["model"])
    if data.get("cogging") is not None:
        _check_cogging(c, data["cogging"])
    setup = _parse_setup(data["setup"], source, prefix="setup.")
    if setup.pole_pairs != n:
        c.bad(f"key 'pole_pairs' ({n}) differs from 'setup.pole_pairs' ({setup.pole_pairs})")
    if setup.plant is not None and setup.controller is not None:
        p = setup.plant
        _check_loop(c, "setup.plant", p.num, p.den, p.delay, setup)
    _check_diagnostics(c, data["diagnostics"])
    plant = None
    if data.get("plant") is not None:
        plant = c.mapping(data["plant"], "plant")
        _check_plant(c, plant, setup)
    if "created" in data:
        c.text(data["created"], "created")
    if data.get("identifiability") is not None:
        _check_identifiability(c, data["identifiability"], int(n))
    return ArtifactData(
        format=data["format"],
        version=version,
        pole_pairs=int(n),
        projection=_readonly(projection),
        offset=_readonly(offset),
        y_hat=_readonly(y_hat),
        eta=_readonly(eta),
        setup=setup,
        model=data["model"],
        diagnostics=data["diagnostics"],
        plant=plant,
        data=data,
        source=source,
        bijective_checked=bijective,
    )


def _check_observer(c: _Checker, entry: Any) -> bool:
    """The ``observer`` entry (:mod:`hallcal.pipeline.observe`); True when it says the
    three-signal curve is injective, which lets a folding map's table (status "not_bijective")
    be stored for the observer."""
    entry = c.mapping(entry, "observer")
    nv = c.array(c.need(entry, "noise_variance", "observer.noise_variance"),
                 "observer.noise_variance", "a list of 3 numbers > 0", shape=(3,))  # fmt: skip
    if not np.all(nv > 0):
        c.bad("key 'observer.noise_variance' must be a list of 3 numbers > 0")
    injective = c.need(entry, "injective", "observer.injective")
    if not isinstance(injective, bool):
        c.bad("key 'observer.injective' must be true or false")
    for key in ("separation", "margin", "worst_std", "rms_std"):
        if key in entry and not _is_number(entry[key]):
            c.bad(f"key 'observer.{key}' must be a number")
    return injective


def _check_cogging(c: _Checker, cog: Any) -> None:
    """The optional ``"cogging"`` entry: T_c(y0) = sum a_k cos(k y0) + b_k sin(k y0)."""
    cog = c.mapping(cog, "cogging")
    orders = cog.get("orders")
    if not isinstance(orders, list) or not all(_is_int(k) and k >= 0 for k in orders):
        c.bad("key 'cogging.orders' must be a list of integers >= 0")
    if len(orders) > MAX_HARMONICS or (orders and max(orders) > MAX_HARMONIC):
        c.bad(
            f"key 'cogging.orders' must hold at most {MAX_HARMONICS} orders up to "
            f"{MAX_HARMONIC} (the limits of the flux model's harmonics)"
        )
    if len(set(orders)) != len(orders):
        c.bad("key 'cogging.orders' lists an order twice")
    m = len(orders)
    for key in ("a", "b"):
        what = f"a list of {m} numbers (one per order)"
        c.array(cog.get(key), f"cogging.{key}", what, shape=(m,), limit=math.inf)
    for key in ("std_a", "std_b"):  # null where a standard deviation is unknown
        value = cog.get(key)
        if value is not None and not (
            isinstance(value, list)
            and len(value) == m
            and all(v is None or (_is_number(v) and v >= 0) for v in value)
        ):
            c.bad(f"key 'cogging.{key}' must be a list of {m} numbers >= 0 or nulls")
    if cog.get("covariance") is not None:
        what = f"a {2 * m}x{2 * m} array of numbers"
        c.array(cog["covariance"], "cogging.covariance", what, shape=(2 * m, 2 * m), limit=math.inf)


def write_artifact(path: str | os.PathLike[str], artifact: Mapping[str, Any]) -> None:
    """Write a calibration artifact (JSON, ``docs/design.md`` "Calibration artifact"), atomically.

    ``"format"`` (:data:`ARTIFACT_FORMAT`) and ``"hallcal_version"`` are filled in when absent;
    a :class:`Setup` under ``"setup"`` is converted with :meth:`Setup.to_dict`; NumPy data are
    converted to lists and numbers. The result is checked by :func:`validate_artifact`, as
    :func:`read_artifact` checks it, before anything is written.

    Parameters
    ----------
    path : path-like
        Destination file; its directory must exist.
    artifact : mapping
        The artifact's keys (e.g. from
        :meth:`hallcal.pipeline.Calibration.to_artifact`).

    Raises
    ------
    ValueError
        NaN or inf anywhere (the message names the key); nothing is written.
    HallcalInputError
        The artifact does not pass :func:`validate_artifact`, or the file cannot be written.
    """
    p = Path(path)
    data = dict(artifact)
    data.setdefault("format", ARTIFACT_FORMAT)
    data.setdefault("hallcal_version", _version.__version__)
    ordered = {"format": data.pop("format"), **data}
    text = _dump_json(p, ordered)
    validate_artifact(json.loads(text), str(p))
    with atomic_write(p, "w") as f:
        f.write(text)


def read_artifact(path: str | os.PathLike[str]) -> ArtifactData:
    """Read a calibration artifact and return its checked, typed view: the one reader.

    Parameters
    ----------
    path : path-like
        The artifact (JSON) written by ``hallcal calibrate`` or :func:`write_artifact`.

    Returns
    -------
    ArtifactData
        The validated content: pole pairs, f_init's projection and offsets and the table
        nodes as arrays, the setup as a :class:`Setup`, every key as a read-only mapping
        (``art["plant"]``), and the SHA-256 of the file's bytes.

    Raises
    ------
    HallcalInputError
        Missing file, invalid JSON, not an artifact, unsupported format, or a missing, malformed
        or implausible key (named in the message): anything :func:`validate_artifact` refuses.
    """
    data, raw = _read_json_raw(path)
    data = migrate_values(data)
    art = validate_artifact(data, str(Path(path)))
    return replace(art, file_sha256=hashlib.sha256(raw).hexdigest())
