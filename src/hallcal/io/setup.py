"""The setup file (TOML, ``docs/design.md`` "Setup file"): typed specs, strict parsing, writing.

Every table and key is checked; an unknown key is an error with a did-you-mean suggestion (a
misspelled key must never fall back to a default), and every message names the file and the
dotted key.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, NoReturn

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.formatting import one_line
from hallcal.io.files import (
    _check_parsed,
    _closest,
    _decode_text,
    _existing_file,
    _nested_too_deeply,
    _read_bytes,
    _suggest,
    atomic_write,
)
from hallcal.limits import (
    MAX_ABS_VALUE,
    MAX_BENCH_ELECTRICAL_HARMONICS,
    MAX_COGGING_ORDERS,
    MAX_DELAY_SAMPLES,
    MAX_HARMONIC,
    MAX_HARMONICS,
    MAX_ITERATIONS,
    MAX_KERNEL_POINTS,
    MAX_LENGTHSCALE,
    MAX_LUT_POINTS,
    MAX_POLE_PAIRS,
    MAX_REALIZATIONS,
    MAX_SAMPLES,
    MAX_SETUP_BYTES,
    MAX_TF_ORDER,
    MIN_LENGTHSCALE,
    MIN_LUT_POINTS,
)
from hallcal.sim.lti import ContinuousTF, DiscreteTF

__all__ = [
    "BLASpec",
    "BenchSpec",
    "ModelSpec",
    "Setup",
    "TrajectorySpec",
    "default_setup",
    "read_setup",
    "setup_from_dict",
    "setup_to_toml",
    "write_setup",
]


def _tuple_of_floats(values: Iterable[Any]) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


@dataclass(frozen=True)
class ModelSpec:
    """Flux model and solver options (``[model]``; paper, section on the flux model g_theta).

    Attributes
    ----------
    basis : {"fourier", "kernel"}
        Fourier series in the mechanical angle, or the periodic kernel basis.
    harmonics : tuple of int or "auto"
        Fourier basis: mechanical harmonics (the constant term is always included); ``"auto"``
        leaves the choice to the calibration.
    points : int
        Kernel basis: number of kernel centres on [0, 2 pi).
    lengthscale : float or "auto"
        Kernel basis: length scale l of the kernel.
    lut_points : int
        Number M of grid points of the lookup table.
    max_iterations : int
        Iteration limit of the simulation-error minimization.
    force : bool
        Write the artifact even when the adequacy check fails.
    cogging : tuple of int, "auto" or "none"
        Cogging torque ``sum_k a_k cos(k y0) + b_k sin(k y0)`` at the plant input, identified
        jointly with the flux: its orders k (periods per revolution), chosen from the data
        (``"auto"``: nothing is added when the data show no cogging), or none. Identified with
        the Fourier basis; the kernel basis accepts "auto" and "none" and models no cogging.
    """

    basis: Literal["fourier", "kernel"] = "fourier"
    harmonics: tuple[int, ...] | Literal["auto"] = "auto"
    points: int = 400
    lengthscale: float | Literal["auto"] = "auto"
    lut_points: int = 4096
    max_iterations: int = 50
    force: bool = False
    cogging: tuple[int, ...] | Literal["auto", "none"] = "auto"

    def __post_init__(self) -> None:
        if self.harmonics != "auto":
            object.__setattr__(self, "harmonics", tuple(int(h) for h in self.harmonics))
        if self.cogging not in ("auto", "none"):
            object.__setattr__(self, "cogging", tuple(int(k) for k in self.cogging))


@dataclass(frozen=True)
class TrajectorySpec:
    """How the true angle moved during the calibration run (``[trajectory]``).

    Attributes
    ----------
    kind : {"closed-loop", "constant-speed"}
        Closed-loop ramp tracking (the paper), or an open-loop spin at constant speed.
    start, stop : int, int or None
        Constant speed: sample indices of the constant-speed part, ``stop`` exclusive
        (``None``: end of the data).
    """

    kind: Literal["closed-loop", "constant-speed"] = "closed-loop"
    start: int = 0
    stop: int | None = None


@dataclass(frozen=True)
class BLASpec:
    """Multisine experiment for the Best Linear Approximation (``[bla]``; Pintelon & Schoukens).

    Attributes
    ----------
    period_samples : int
        Samples per multisine period (>= 8).
    periods : int
        Periods per realization, including the transient ones (>= 2).
    transient_periods : int
        Leading periods discarded in each realization (< periods).
    realizations : int
        Number of random-phase realizations.
    band : tuple of float
        ``(f_lo, f_hi)`` excited frequency band in Hz.
    rms : float
        RMS of the multisine in rad.
    lines : {"full", "odd", "random-odd"}
        Which frequency lines in the band are excited.
    drift : float
        Speed in rad/s of the slow ramp the multisine rides on.
    numerator_order : int
        Order of the numerator of the parametric model fitted to the BLA.
    denominator_order : int or "auto"
        Order of its denominator, the integrator pole excluded (the paper's G(s) is numerator
        0, denominator 2, integrator; a motor with one mechanical pole is denominator 1);
        ``"auto"`` chooses 0..3 from the data (stable fits only, minimum description length).
    integrator : bool
        Whether the parametric model has a pole at s = 0.
    fit_delay : bool
        Whether the parametric model has an input delay estimated from the data.
    """

    period_samples: int
    periods: int
    transient_periods: int = 1
    realizations: int = 8
    band: tuple[float, float] = (1.0, 400.0)
    rms: float = 0.05
    lines: Literal["full", "odd", "random-odd"] = "random-odd"
    drift: float = 1.0
    numerator_order: int = 0
    denominator_order: int | Literal["auto"] = "auto"
    integrator: bool = True
    fit_delay: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "band", _tuple_of_floats(self.band))


@dataclass(frozen=True)
class BenchSpec:
    """Virtual bench used by ``hallcal simulate`` (``[bench]``); defaults are the paper's.

    Attributes
    ----------
    experiment : {"ramp", "multisine"}
        Calibration ramp, or the BLA multisine experiment of ``[bla]``.
    seed : int
        Seed of the random generator (noise, flux variations, multisine phases).
    noise_variance : float
        Variance of the white noise on each Hall channel.
    ramp_end : float
        Final value of the ramp reference in rad.
    duration : float
        Duration of the ramp experiment in s.
    amplitude : float
        Amplitude A of the Hall signals.
    magnet_variation : float
        Relative size of the per-magnet flux variations (mechanical harmonics
        1 .. pole_pairs - 1).
    pole_modulation : float
        Relative size of per-pole amplitude differences (amplitude modulation by mechanical
        harmonics 1..3: sidebands k pole_pairs +- j).
    shape_variation : float
        Per-magnet shape variation s: every pole pair's flux waveform gets its own smooth random
        deformation of RMS s times the amplitude (mechanical harmonics 1 .. shape_harmonics *
        pole_pairs, every sideband; :func:`hallcal.sim.bench.shape_deformation`). 0 = none.
    shape_harmonics : int
        Electrical bandwidth of that deformation (highest electrical harmonic).
    misalignment_deg : tuple of 3 float
        Electrical degrees added to each sensor's nominal 0/120/240 degrees.
    gain_mismatch : tuple of 3 float
        Relative gain error of each sensor (gain ``1 + g``).
    offset : tuple of 3 float
        Offset of each sensor.
    electrical_harmonics : tuple of (int, float)
        ``(harmonic >= 2, relative amplitude)`` pairs of electrical harmonics of the flux.
    torque_disturbance : float
        Standard deviation of a random low-frequency torque at the plant input.
    cogging : float
        Amplitude of a cogging torque at the plant input.
    cogging_periods : int
        Cogging periods per revolution; 0 means ``6 * pole_pairs`` (the bench's
        :class:`~hallcal.sim.bench.BenchConfig` resolves it).
    """

    experiment: Literal["ramp", "multisine"] = "ramp"
    seed: int = 0
    noise_variance: float = 7.5e-6
    ramp_end: float = 13.0
    duration: float = 26.0
    amplitude: float = 1.0
    magnet_variation: float = 0.04
    pole_modulation: float = 0.0
    shape_variation: float = 0.0
    shape_harmonics: int = 5
    misalignment_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gain_mismatch: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    electrical_harmonics: tuple[tuple[int, float], ...] = ()
    torque_disturbance: float = 0.0
    cogging: float = 0.0
    cogging_periods: int = 0

    def __post_init__(self) -> None:
        for name in ("misalignment_deg", "gain_mismatch", "offset"):
            object.__setattr__(self, name, _tuple_of_floats(getattr(self, name)))
        pairs = tuple((int(h), float(a)) for h, a in self.electrical_harmonics)
        object.__setattr__(self, "electrical_harmonics", pairs)


@dataclass(frozen=True)
class Setup:
    """Everything the setup file says (``docs/design.md``, "Setup file").

    Build it with :func:`read_setup` or :func:`setup_from_dict`, which check it; constructing it
    directly checks nothing (``setup_from_dict(s.to_dict())`` does).

    Attributes
    ----------
    pole_pairs : int
        Number of pole pairs n_m.
    sample_time : float
        Sample time Ts in s (1.0 means "time in samples").
    controller : DiscreteTF or None
        The known feedback controller C(q); ``None`` only for constant-speed trajectories.
    plant : ContinuousTF or None
        The plant G(s) when known; ``None`` when a BLA experiment replaces it.
    model : ModelSpec
    trajectory : TrajectorySpec
    bla : BLASpec or None
    bench : BenchSpec
    """

    pole_pairs: int
    sample_time: float
    controller: DiscreteTF | None
    plant: ContinuousTF | None = None
    model: ModelSpec = field(default_factory=ModelSpec)
    trajectory: TrajectorySpec = field(default_factory=TrajectorySpec)
    bla: BLASpec | None = None
    bench: BenchSpec = field(default_factory=BenchSpec)

    def to_dict(self) -> dict[str, Any]:
        """Return the setup as plain JSON-serializable data (the layout of the TOML file).

        Every option is written explicitly (defaults included); options that do not apply
        (kernel options of a Fourier model, ``start``/``stop`` of a closed-loop trajectory) and
        absent tables are left out, so ``setup_from_dict(s.to_dict()) == s``.
        """
        out: dict[str, Any] = {"pole_pairs": self.pole_pairs, "sample_time": self.sample_time}
        if self.controller is not None:
            out["controller"] = {"num": list(self.controller.num), "den": list(self.controller.den)}
        if self.plant is not None:
            out["plant"] = {
                "num": list(self.plant.num),
                "den": list(self.plant.den),
                "delay": self.plant.delay,
            }
        m = self.model
        model: dict[str, Any] = {"basis": m.basis}
        if m.basis == "fourier":
            model["harmonics"] = m.harmonics if m.harmonics == "auto" else list(m.harmonics)
        else:
            model["points"] = m.points
            model["lengthscale"] = m.lengthscale
        model.update(lut_points=m.lut_points, max_iterations=m.max_iterations, force=m.force)
        model["cogging"] = m.cogging if m.cogging in ("auto", "none") else list(m.cogging)
        out["model"] = model
        t = self.trajectory
        trajectory: dict[str, Any] = {"kind": t.kind}
        if t.kind == "constant-speed":
            trajectory["start"] = t.start
            if t.stop is not None:
                trajectory["stop"] = t.stop
        out["trajectory"] = trajectory
        if self.bla is not None:
            bla = dataclasses.asdict(self.bla)
            bla["band"] = list(self.bla.band)
            out["bla"] = bla
        b = self.bench
        bench = dataclasses.asdict(b)
        for name in ("misalignment_deg", "gain_mismatch", "offset"):
            bench[name] = list(getattr(b, name))
        bench["electrical_harmonics"] = [[h, a] for h, a in b.electrical_harmonics]
        out["bench"] = bench
        return out


def default_setup() -> Setup:
    """Return the setup of the paper's simulation study (section "Simulation results").

    11 pole pairs, Ts = 1/4000 s, the paper's C(q) and G(s) (input delay 1.2e-4 s), a Fourier
    flux model with mechanical harmonics 1..11, a BLA experiment of 4 periods of 4000 samples
    (1 transient) and the default virtual bench (ramp 0 -> 13 rad in 26 s, noise variance
    7.5e-6). Equal to parsing the example setup file of ``docs/design.md``.

    Returns
    -------
    Setup
        A fresh setup object (with the plant G(s), so it can drive the virtual bench).
    """
    return Setup(
        pole_pairs=11,
        sample_time=2.5e-4,
        controller=DiscreteTF((2.94, -3.29, -2.10, 2.45), (1.0, -3.45, 4.52, -2.68, 0.61)),
        plant=ContinuousTF((1.663e5,), (1.0, 632.6, 2702.0, 0.0), delay=1.2e-4),
        model=ModelSpec(basis="fourier", harmonics=tuple(range(1, 12))),
        trajectory=TrajectorySpec(),
        bla=BLASpec(period_samples=4000, periods=4, transient_periods=1),
        bench=BenchSpec(),
    )


# ---- Setup parsing -----------------------------------------------------------------------------

_SETUP_KEYS: dict[str, tuple[str, ...]] = {
    "": ("pole_pairs", "sample_time", "controller", "plant", "model", "trajectory", "bla", "bench"),
    "controller": ("num", "den"),
    "plant": ("num", "den", "delay"),
    "model": (
        "basis",
        "harmonics",
        "points",
        "lengthscale",
        "lut_points",
        "max_iterations",
        "force",
        "cogging",
    ),
    "trajectory": ("kind", "start", "stop"),
    "bla": tuple(f.name for f in dataclasses.fields(BLASpec)),
    "bench": tuple(f.name for f in dataclasses.fields(BenchSpec)),
}
_ALL_SETUP_KEYS: tuple[str, ...] = tuple(
    f"{table}.{key}" if table else key for table, keys in _SETUP_KEYS.items() for key in keys
)

_REQUIRED: Any = object()


def _show(value: Any) -> str:
    """Render a setup value the way it looks in TOML, shortened."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, Mapping):
        text = "a table"
    elif isinstance(value, str | list | tuple):
        try:
            text = json.dumps(value, default=str)
        except (TypeError, ValueError):
            text = repr(value)
    else:
        text = repr(value) if isinstance(value, float) else str(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_int(value: Any) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def _is_number(value: Any) -> bool:
    return _is_int(value) or (isinstance(value, float | np.floating))


def _finite(value: Any) -> bool:
    """A number that converts to a finite float (an integer of 400 digits does not)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


class _Table:
    """One table of the setup, with typed getters whose errors name the key."""

    def __init__(self, data: Mapping[str, Any], source: str, table: str, prefix: str) -> None:
        self.data = data
        self.source = source
        self.table = table  # schema name: "", "model", ...
        self.prefix = prefix  # shown before key names: "", "setup.", ...

    def key(self, name: str) -> str:
        return f"{self.prefix}{self.table}.{name}" if self.table else f"{self.prefix}{name}"

    def error(self, message: str) -> NoReturn:
        raise HallcalInputError(f"{self.source}: {message}")

    def fail(self, name: str, what: str, hint: str = "") -> NoReturn:
        self.error(f"key '{self.key(name)}' must be {what}, got {_show(self.data[name])}{hint}")

    def check_keys(self) -> None:
        allowed = _SETUP_KEYS[self.table]
        for name in self.data:
            if name in allowed:
                continue
            guess = _closest(str(name), allowed)
            hint = ""
            if guess is not None:
                hint = f" (did you mean '{self.key(guess)}'?)"
            else:
                elsewhere = [k for k in _ALL_SETUP_KEYS if k.rsplit(".", 1)[-1] == name]
                if elsewhere:
                    hint = f" (did you mean '{self.prefix}{elsewhere[0]}'?)"
            self.error(f"unknown key '{self.key(str(name))}'{hint}")

    def has(self, name: str) -> bool:
        return name in self.data

    def _get(self, name: str, default: Any, what: str) -> Any:
        if name in self.data:
            return self.data[name]
        if default is _REQUIRED:
            self.error(f"key '{self.key(name)}' is missing (it must be {what})")
        return default

    def integer(
        self,
        name: str,
        *,
        default: Any = _REQUIRED,
        minimum: int | None = None,
        maximum: int | None = None,
    ) -> Any:
        what = "an integer" + (f" >= {minimum}" if minimum is not None else "")
        value = self._get(name, default, what)
        if value is default and name not in self.data:
            return value
        if not _is_int(value) or (minimum is not None and value < minimum):
            self.fail(name, what)
        if maximum is not None and value > maximum:
            self.above(name, maximum)
        return int(value)

    def above(self, name: str, maximum: float, what: str = "") -> NoReturn:
        """The value of `name` exceeds hallcal's limit `maximum` (:mod:`hallcal.limits`)."""
        shown = what or _show(self.data[name])
        exact = float(maximum).is_integer() and maximum < 1e15
        limit = str(int(maximum)) if exact else f"{maximum:g}"
        self.error(f"key '{self.key(name)}' is {shown}, above the limit of {limit}")

    def number(
        self,
        name: str,
        *,
        default: Any = _REQUIRED,
        minimum: float | None = None,
        positive: bool = False,
        maximum: float | None = None,
    ) -> Any:
        what = "a number"
        if positive:
            what += " > 0"
        elif minimum is not None:
            what += f" >= {minimum:g}"
        value = self._get(name, default, what)
        if value is default and name not in self.data:
            return value
        if not _is_number(value) or not _finite(value):
            self.fail(name, "a finite number" if _is_number(value) else what)
        if (positive and value <= 0) or (minimum is not None and value < minimum):
            self.fail(name, what)
        if maximum is not None and abs(value) > maximum:
            self.above(name, maximum)
        return float(value)

    def boolean(self, name: str, *, default: Any = _REQUIRED) -> Any:
        value = self._get(name, default, "true or false")
        if not isinstance(value, bool):
            self.fail(name, "true or false")
        return value

    def choice(self, name: str, options: Sequence[str], *, default: Any = _REQUIRED) -> Any:
        what = "one of " + ", ".join(f'"{o}"' for o in options)
        value = self._get(name, default, what)
        if not isinstance(value, str) or value not in options:
            self.fail(name, what, _suggest(value, options) if isinstance(value, str) else "")
        return value

    def numbers(
        self,
        name: str,
        *,
        default: Any = _REQUIRED,
        length: int | None = None,
        max_length: int | None = None,
        maximum: float | None = None,
    ) -> Any:
        what = (
            f"a list of {length} numbers" if length is not None else "a non-empty list of numbers"
        )
        value = self._get(name, default, what)
        if value is default and name not in self.data:
            return value
        if (
            not isinstance(value, list | tuple)
            or not value
            or (length is not None and len(value) != length)
            or not all(_is_number(v) for v in value)
        ):
            self.fail(name, what)
        if not all(_finite(v) for v in value):
            self.fail(name, "a list of finite numbers")
        if max_length is not None and len(value) > max_length:
            self.above(name, max_length, f"a list of {len(value)} numbers")
        if maximum is not None and any(abs(v) > maximum for v in value):
            self.above(name, maximum, "a list with " + _show(max(value, key=abs)))
        return tuple(float(v) for v in value)

    def table_at(self, name: str) -> _Table | None:
        if name not in self.data:
            return None
        value = self.data[name]
        if not isinstance(value, Mapping):
            self.fail(name, "a table")
        return _Table(value, self.source, name, self.prefix)


def _parse_tf(t: _Table, *, continuous: bool) -> tuple[tuple[float, ...], tuple[float, ...]]:
    # limits.MAX_TF_ORDER: the loop's cost grows with the square of its states
    num = t.numbers("num", max_length=MAX_TF_ORDER + 1)
    den = t.numbers("den", max_length=MAX_TF_ORDER + 1)
    if den[0] == 0.0:
        t.error(f"key '{t.key('den')}' must have a nonzero leading coefficient, got {_show(den)}")
    stripped = num
    while len(stripped) > 1 and stripped[0] == 0.0:
        stripped = stripped[1:]
    if len(stripped) > len(den):
        what = "proper" if continuous else "causal"
        t.error(
            f"key '{t.key('num')}' has more coefficients than '{t.key('den')}' (the transfer "
            f"function must be {what})"
        )
    if all(v == 0.0 for v in num):
        t.error(f"key '{t.key('num')}' must not be all zero")
    return num, den


def _only_for(t: _Table, names: Sequence[str], condition: str) -> None:
    for name in names:
        if t.has(name):
            t.error(f"key '{t.key(name)}' applies only to {condition}")


def _parse_model(t: _Table | None) -> ModelSpec:
    if t is None:
        return ModelSpec()
    t.check_keys()
    basis = t.choice("basis", ("fourier", "kernel"), default="fourier")
    harmonics: tuple[int, ...] | str = "auto"
    points = 400
    lengthscale: float | str = "auto"
    if basis == "fourier":
        _only_for(t, ("points", "lengthscale"), 'basis = "kernel"')
        value = t.data.get("harmonics", "auto")
        what = 'a list of distinct integers >= 1 or "auto"'
        if not (isinstance(value, str) and value == "auto"):
            if (
                not isinstance(value, list | tuple)
                or not value
                or not all(_is_int(h) and h >= 1 for h in value)
            ):
                t.fail("harmonics", what)
            if len(value) > MAX_HARMONICS:
                t.above("harmonics", MAX_HARMONICS, f"a list of {len(value)} harmonics")
            if max(value) > MAX_HARMONIC:
                t.above("harmonics", MAX_HARMONIC, f"a list with the harmonic {max(value)}")
            if len(set(value)) != len(value):
                t.error(f"key '{t.key('harmonics')}' lists a harmonic twice: {_show(value)}")
            harmonics = tuple(int(h) for h in value)
    else:
        _only_for(t, ("harmonics",), 'basis = "fourier"')
        points = t.integer("points", default=400, minimum=8, maximum=MAX_KERNEL_POINTS)
        value = t.data.get("lengthscale", "auto")
        if not (isinstance(value, str) and value == "auto"):
            if not _is_number(value) or not math.isfinite(value) or value <= 0:
                t.fail("lengthscale", 'a number > 0 or "auto"')
            if not MIN_LENGTHSCALE <= value <= MAX_LENGTHSCALE:
                t.error(
                    f"key '{t.key('lengthscale')}' is {value:g}, outside {MIN_LENGTHSCALE:g} .. "
                    f"{MAX_LENGTHSCALE:g} rad (the kernel's distances are at most 2)"
                )
            lengthscale = float(value)
    return ModelSpec(
        basis=basis,
        harmonics=harmonics,  # type: ignore[arg-type]
        points=points,
        lengthscale=lengthscale,  # type: ignore[arg-type]
        lut_points=t.integer(
            "lut_points", default=4096, minimum=MIN_LUT_POINTS, maximum=MAX_LUT_POINTS
        ),
        max_iterations=t.integer("max_iterations", default=50, minimum=1, maximum=MAX_ITERATIONS),
        force=t.boolean("force", default=False),
        cogging=_parse_cogging(t, basis),  # type: ignore[arg-type]
    )


def _parse_cogging(t: _Table, basis: str) -> tuple[int, ...] | str:
    """``cogging = "auto" | "none" | [orders]`` (distinct integers >= 0, 0 a constant load
    torque; Fourier basis)."""
    value = t.data.get("cogging", "auto")
    if isinstance(value, str) and value in ("auto", "none"):
        return value
    if basis != "fourier":
        t.error(f"key '{t.key('cogging')}' with orders applies only to basis = \"fourier\"")
    if (
        not isinstance(value, list | tuple)
        or not value
        or not all(_is_int(k) and k >= 0 for k in value)
    ):
        t.fail("cogging", 'a list of distinct integers >= 0 (periods per revolution, 0 a '
               'constant load torque), "auto" or "none"')  # fmt: skip
    if len(set(value)) != len(value):
        t.error(f"key '{t.key('cogging')}' lists an order twice: {_show(value)}")
    if len(value) > MAX_COGGING_ORDERS:
        t.above("cogging", MAX_COGGING_ORDERS, f"a list of {len(value)} orders")
    if max(value) > MAX_HARMONIC:
        t.above("cogging", MAX_HARMONIC, f"a list with the order {max(value)}")
    return tuple(int(k) for k in value)


def _parse_trajectory(t: _Table | None) -> TrajectorySpec:
    if t is None:
        return TrajectorySpec()
    t.check_keys()
    kind = t.choice("kind", ("closed-loop", "constant-speed"), default="closed-loop")
    if kind == "closed-loop":
        _only_for(t, ("start", "stop"), 'kind = "constant-speed"')
        return TrajectorySpec(kind=kind)
    start = t.integer("start", default=0, minimum=0, maximum=MAX_SAMPLES)
    stop = t.integer("stop", default=None, minimum=1, maximum=MAX_SAMPLES)
    if stop is not None and stop <= start:
        t.error(
            f"key '{t.key('stop')}' must be greater than '{t.key('start')}' ({start}), got {stop}"
        )
    return TrajectorySpec(kind=kind, start=start, stop=stop)


def _parse_bla(t: _Table | None, sample_time: float) -> BLASpec | None:
    if t is None:
        return None
    t.check_keys()
    period_samples = t.integer("period_samples", minimum=8, maximum=MAX_SAMPLES)
    periods = t.integer("periods", minimum=2, maximum=MAX_SAMPLES)
    transient = t.integer("transient_periods", default=1, minimum=0)
    if transient >= periods:
        t.error(
            f"key '{t.key('transient_periods')}' must be less than '{t.key('periods')}' "
            f"({periods}), got {transient}"
        )
    band = t.numbers("band", default=(1.0, 400.0), length=2)
    nyquist = 0.5 / sample_time
    if not 0.0 <= band[0] < band[1]:
        t.fail("band", "[f_lo, f_hi] with 0 <= f_lo < f_hi")
    if band[1] > nyquist:
        t.error(
            f"key '{t.key('band')}' must stay below the Nyquist frequency {nyquist:g} Hz, "
            f"got {_show(list(band))}"
        )
    f0 = 1.0 / (period_samples * sample_time)
    first = max(1, math.ceil(band[0] / f0 - 1e-9))
    if first * f0 > band[1] * (1 + 1e-12):
        t.error(
            f"key '{t.key('band')}' holds no frequency line (lines are multiples of "
            f"1/(period_samples*sample_time) = {f0:g} Hz), got {_show(list(band))}"
        )
    realizations = t.integer("realizations", default=8, minimum=1, maximum=MAX_REALIZATIONS)
    total = period_samples * periods * realizations
    if total > MAX_SAMPLES:
        t.error(
            f"keys '{t.key('period_samples')}' x '{t.key('periods')}' x "
            f"'{t.key('realizations')}' = {total} samples, above the limit of {MAX_SAMPLES} "
            "samples of one experiment"
        )
    numerator_order = t.integer("numerator_order", default=0, minimum=0, maximum=MAX_TF_ORDER)
    denominator_order: int | str = "auto"
    value = t.data.get("denominator_order", "auto")
    if not (isinstance(value, str) and value == "auto"):
        if not _is_int(value) or value < 0:
            t.fail("denominator_order", 'an integer >= 0 or "auto"')
        if value > MAX_TF_ORDER:
            t.above("denominator_order", MAX_TF_ORDER)
        denominator_order = int(value)
    if denominator_order != "auto" and numerator_order > int(denominator_order):
        t.error(
            f"key '{t.key('numerator_order')}' must not exceed "
            f"'{t.key('denominator_order')}' ({denominator_order}), got {numerator_order}"
        )
    return BLASpec(
        period_samples=period_samples,
        periods=periods,
        transient_periods=transient,
        realizations=realizations,
        band=band,
        rms=t.number("rms", default=0.05, positive=True),
        lines=t.choice("lines", ("full", "odd", "random-odd"), default="random-odd"),
        drift=t.number("drift", default=1.0),
        numerator_order=numerator_order,
        denominator_order=denominator_order,  # type: ignore[arg-type]
        integrator=t.boolean("integrator", default=True),
        fit_delay=t.boolean("fit_delay", default=True),
    )


def _parse_bench(t: _Table | None, pole_pairs: int) -> BenchSpec:
    if t is None:
        return BenchSpec()
    t.check_keys()
    gain = t.numbers("gain_mismatch", default=(0.0, 0.0, 0.0), length=3)
    if any(g <= -1.0 for g in gain):
        t.fail("gain_mismatch", "a list of 3 numbers > -1")
    pairs: list[tuple[int, float]] = []
    value = t.data.get("electrical_harmonics", [])
    what = "a list of [harmonic >= 2, relative amplitude] pairs"
    if not isinstance(value, list | tuple):
        t.fail("electrical_harmonics", what)
    if len(value) > MAX_BENCH_ELECTRICAL_HARMONICS:
        t.above("electrical_harmonics", MAX_BENCH_ELECTRICAL_HARMONICS, f"{len(value)} pairs")
    for pair in value:
        if (
            not isinstance(pair, list | tuple)
            or len(pair) != 2
            or not _is_int(pair[0])
            or pair[0] < 2
            or not _is_number(pair[1])
            or not _finite(pair[1])
        ):
            t.fail("electrical_harmonics", what)
        pairs.append((int(pair[0]), float(pair[1])))
    if len({h for h, _ in pairs}) != len(pairs):
        t.error(f"key '{t.key('electrical_harmonics')}' lists a harmonic twice: {_show(value)}")
    if pairs and max(h for h, _ in pairs) * pole_pairs > MAX_HARMONIC:
        highest = max(h for h, _ in pairs)
        t.error(
            f"key '{t.key('electrical_harmonics')}' has the electrical harmonic {highest}, "
            f"mechanical harmonic {highest * pole_pairs}, above the limit of {MAX_HARMONIC}"
        )
    return BenchSpec(
        experiment=t.choice("experiment", ("ramp", "multisine"), default="ramp"),
        seed=t.integer("seed", default=0, minimum=0),
        noise_variance=t.number("noise_variance", default=7.5e-6, minimum=0.0),
        ramp_end=t.number("ramp_end", default=13.0),
        duration=t.number("duration", default=26.0, positive=True),
        amplitude=t.number("amplitude", default=1.0, positive=True, maximum=MAX_ABS_VALUE),
        magnet_variation=t.number("magnet_variation", default=0.04, minimum=0.0),
        pole_modulation=t.number("pole_modulation", default=0.0, minimum=0.0),
        shape_variation=t.number("shape_variation", default=0.0, minimum=0.0),
        shape_harmonics=t.integer("shape_harmonics", default=5, minimum=1),
        misalignment_deg=t.numbers("misalignment_deg", default=(0.0, 0.0, 0.0), length=3),
        gain_mismatch=gain,
        offset=t.numbers("offset", default=(0.0, 0.0, 0.0), length=3, maximum=MAX_ABS_VALUE),
        electrical_harmonics=tuple(pairs),
        torque_disturbance=t.number("torque_disturbance", default=0.0, minimum=0.0),
        cogging=t.number("cogging", default=0.0, minimum=0.0),
        cogging_periods=t.integer("cogging_periods", default=0, minimum=0),
    )


def _parse_setup(data: Mapping[str, Any], source: str, prefix: str = "") -> Setup:
    if not isinstance(data, Mapping):
        what = f"key '{prefix.rstrip('.')}'" if prefix else "the setup"
        raise HallcalInputError(f"{source}: {what} must be a table")
    top = _Table(data, source, "", prefix)
    top.check_keys()
    pole_pairs = top.integer("pole_pairs", minimum=1, maximum=MAX_POLE_PAIRS)
    sample_time = top.number("sample_time", positive=True)
    controller_t = top.table_at("controller")
    plant_t = top.table_at("plant")
    model_t = top.table_at("model")
    trajectory_t = top.table_at("trajectory")
    bla_t = top.table_at("bla")
    bench_t = top.table_at("bench")
    for sub in (controller_t, plant_t, model_t, trajectory_t, bla_t, bench_t):
        if sub is not None:
            sub.check_keys()  # a misspelled key is reported before anything it might cause

    trajectory = _parse_trajectory(trajectory_t)
    controller = None
    if controller_t is not None:
        controller_t.check_keys()
        controller = DiscreteTF(*_parse_tf(controller_t, continuous=False))
    elif trajectory.kind == "closed-loop":
        top.error(
            f"key '{prefix}controller' is missing (a [controller] table with num and den is "
            'needed unless trajectory.kind = "constant-speed")'
        )
    plant = None
    if plant_t is not None:
        plant_t.check_keys()
        num, den = _parse_tf(plant_t, continuous=True)
        delay = plant_t.number("delay", default=0.0, minimum=0.0)
        if delay / sample_time > MAX_DELAY_SAMPLES:
            plant_t.error(
                f"key '{plant_t.key('delay')}' is {delay / sample_time:.4g} samples "
                f"({_show(delay)} s at sample_time {_show(sample_time)} s), above the limit of "
                f"{MAX_DELAY_SAMPLES} samples"
            )
        plant = ContinuousTF(num, den, delay)
    bla = _parse_bla(bla_t, sample_time)
    bench = _parse_bench(bench_t, pole_pairs)
    if bench.experiment == "multisine" and bla is None:
        top.error(f"key '{prefix}bench.experiment' is \"multisine\" but there is no [bla] table")
    return Setup(
        pole_pairs=pole_pairs,
        sample_time=sample_time,
        controller=controller,
        plant=plant,
        model=_parse_model(model_t),
        trajectory=trajectory,
        bla=bla,
        bench=bench,
    )


def setup_from_dict(d: Mapping[str, Any], *, source: str = "<setup>") -> Setup:
    """Check a setup given as nested dictionaries (the layout of the TOML file).

    Parameters
    ----------
    d : mapping
        As parsed from the TOML file, or as returned by :meth:`Setup.to_dict`.
    source : str
        Name used in error messages (normally the file name).

    Returns
    -------
    Setup

    Raises
    ------
    HallcalInputError
        Unknown key (with a did-you-mean suggestion), missing required key, wrong type, value
        out of range, or above one of the resource limits of :mod:`hallcal.limits`; the message
        names `source` and the dotted key (and the limit).
    """
    return _parse_setup(d, source)


def read_setup(path: str | os.PathLike[str]) -> Setup:
    """Read and check a setup file (TOML, ``docs/design.md`` "Setup file").

    Parameters
    ----------
    path : path-like
        The ``.toml`` file.

    Returns
    -------
    Setup

    Raises
    ------
    HallcalInputError
        Missing file, a file above :data:`~hallcal.limits.MAX_SETUP_BYTES` or nested deeper than
        :data:`~hallcal.limits.MAX_JSON_DEPTH`, invalid UTF-8, malformed TOML (with its line), a
        number out of range, or any problem :func:`setup_from_dict` reports.
    """
    p = _existing_file(path)
    text = _decode_text(p, _read_bytes(p, limit=MAX_SETUP_BYTES, what="a setup file"))
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        message = one_line(exc)
        raise HallcalInputError(f"{p}: invalid TOML: {message}") from None
    except RecursionError:
        raise _nested_too_deeply(p) from None
    _check_parsed(p, data)
    return _parse_setup(data, str(p))


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def setup_to_toml(setup: Setup) -> str:
    """Return the text of a setup file that :func:`read_setup` reads back as `setup`.

    Parameters
    ----------
    setup : Setup
        The setup to serialize.

    Returns
    -------
    str
        TOML text: top-level keys first, then one table per section.
    """
    data = setup.to_dict()
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for name, table in data.items():
        if isinstance(table, dict):
            lines.append("")
            lines.append(f"[{name}]")
            lines.extend(f"{k} = {_toml_value(v)}" for k, v in table.items())
    return "\n".join(lines) + "\n"


def write_setup(path: str | os.PathLike[str], setup: Setup) -> None:
    """Write `setup` as a TOML setup file (atomically); see :func:`setup_to_toml`.

    Parameters
    ----------
    path : path-like
        Destination file; its directory must exist.
    setup : Setup
        The setup to write.
    """
    text = setup_to_toml(setup)
    with atomic_write(path, "w") as f:
        f.write(text)
