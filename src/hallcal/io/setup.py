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
import re
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, NoReturn

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.formatting import one_line
from hallcal.io.files import (
    _check_parsed,
    _closest,
    _decode_text,
    _nested_too_deeply,
    _read_bytes,
    _suggest,
    atomic_write,
    existing_file,
)
from hallcal.limits import (
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
from hallcal.settings import REQUIRED, Setting, render_table, setting, settings_of, toml_value
from hallcal.sim.bench_spec import BenchSpec
from hallcal.sim.lti import ContinuousTF, DiscreteTF

__all__ = [
    "BLASpec",
    "BenchSpec",
    "ModelSpec",
    "Setup",
    "TrajectorySpec",
    "SETUP_SCHEMA",
    "default_setup",
    "read_setup",
    "render_setup_reference",
    "setup_from_dict",
    "setup_to_toml",
    "write_setup",
]


@dataclass(frozen=True)
class ModelSpec:
    """Flux model and solver options (``[model]``; paper, section on the flux model g_theta).

    Every attribute is a setup key, declared on its field with its type, accepted values,
    default and meaning (:func:`hallcal.settings.settings_of`; ``docs/setup-reference.md``).
    ``harmonics`` and ``cogging`` are tuples of int, or a string (``"auto"``, ``"none"``).
    """

    basis: Literal["fourier", "kernel"] = setting(
        "fourier",
        kind="choice",
        choices=("fourier", "kernel"),
        doc="Fourier series in the mechanical angle, or the paper's periodic kernel basis "
        "(closed loop only).",
    )
    harmonics: tuple[int, ...] | Literal["auto"] = setting(
        "auto",
        kind="custom",
        only=("basis", "fourier"),
        limit=MAX_HARMONIC,
        max_length=MAX_HARMONICS,
        type_text="list of integers or string",
        accepts='distinct integers ≥ 1, or `"auto"`',
        doc="Mechanical harmonics of the flux model (the constant term is always included). "
        '`"auto"`: chosen from the data with an adequacy check, then narrowed to the narrowest '
        "band 1..E whose dropped harmonics the run does not need (Wald test on the wide fit), "
        "within a budget of work (SEM fits, Gauss-Newton iterations), never of time (closed "
        "loop); the band 1 .. E n_m, E = 3, 5, 7 or 9, with the least error on a held-out "
        "revolution (constant speed). A search stopped by its budget says "
        "so in a warning and in the artifact's `diagnostics.model_selection`.",
    )
    points: int = setting(
        400,
        kind="integer",
        minimum=8,
        limit=MAX_KERNEL_POINTS,
        only=("basis", "kernel"),
        doc="Number m of kernel centres on one revolution.",
    )
    lengthscale: float | Literal["auto"] = setting(
        "auto",
        kind="custom",
        only=("basis", "kernel"),
        unit="rad",
        type_text="number or string",
        accepts=f'{MIN_LENGTHSCALE:g} .. {MAX_LENGTHSCALE:g} or `"auto"`',
        doc='Length scale of the kernel; `"auto"` chooses it by the evidence.',
    )
    lut_points: int = setting(
        4096,
        kind="integer",
        minimum=MIN_LUT_POINTS,
        limit=MAX_LUT_POINTS,
        doc="Grid points M of the lookup table over one revolution.",
    )
    max_iterations: int = setting(
        50,
        kind="integer",
        minimum=1,
        limit=MAX_ITERATIONS,
        doc="Iteration limit of the simulation-error minimization (and of the constant-speed fit).",
    )
    force: bool = setting(
        False,
        kind="boolean",
        doc="Write the artifact even when the model is judged inadequate (as `--force`). A "
        "table that is not bijective is never written.",
    )
    cogging: tuple[int, ...] | Literal["auto", "none"] = setting(
        "auto",
        kind="custom",
        limit=MAX_HARMONIC,
        max_length=MAX_COGGING_ORDERS,
        type_text="list of integers or string",
        accepts=f"at most {MAX_COGGING_ORDERS} distinct integers 0 .. {MAX_HARMONIC} (periods "
        'per revolution; 0 a constant load torque), `"auto"` or `"none"`; orders only with '
        '`basis = "fourier"`',
        doc="Cogging torque at the plant input, Σ a_k cos(k y0) + b_k sin(k y0) [unit of u], "
        'identified jointly with the flux; order 0 is a constant load torque a_0. `"auto"` '
        "adds the orders the data show (nothing when they show no cogging) and a constant load "
        'torque when it is significant; `"none"` models none. Closed loop only.',
    )

    def __post_init__(self) -> None:
        if self.harmonics != "auto":
            object.__setattr__(self, "harmonics", tuple(int(h) for h in self.harmonics))
        if self.cogging not in ("auto", "none"):
            object.__setattr__(self, "cogging", tuple(int(k) for k in self.cogging))


@dataclass(frozen=True)
class TrajectorySpec:
    """How the true angle moved during the calibration run (``[trajectory]``).

    Every attribute is a setup key declared on its field (:func:`hallcal.settings.settings_of`);
    ``stop`` is None for the end of the data.
    """

    kind: Literal["closed-loop", "constant-speed"] = setting(
        "closed-loop",
        kind="choice",
        choices=("closed-loop", "constant-speed"),
        doc="Closed-loop ramp tracking with f_init feedback (the paper), or an open-loop spin at "
        "constant speed.",
    )
    start: int = setting(
        0,
        kind="integer",
        minimum=0,
        limit=MAX_SAMPLES,
        unit="samples",
        only=("kind", "constant-speed"),
        doc="First sample of the constant-speed part used for calibration. `hallcal inspect` "
        "suggests it.",
    )
    stop: int | None = setting(
        None,
        kind="integer",
        minimum=1,
        limit=MAX_SAMPLES,
        unit="samples",
        only=("kind", "constant-speed"),
        default_text="end of the data",
        accepts="> `start`",
        doc="End (exclusive) of that part. Keep some constant-speed revolutions after it to "
        "check the result (the report's straight-line check uses them).",
    )


@dataclass(frozen=True)
class BLASpec:
    """Multisine experiment for the Best Linear Approximation (``[bla]``; Pintelon & Schoukens).

    Every attribute is a setup key declared on its field (:func:`hallcal.settings.settings_of`).
    ``denominator_order`` counts the poles without the integrator (the paper's G(s) is numerator
    0, denominator 2, integrator; a motor with one mechanical pole is denominator 1).
    """

    period_samples: int = setting(
        kind="integer",
        minimum=8,
        limit=MAX_SAMPLES,
        unit="samples",
        doc="Period N of the multisine: the frequency resolution is 1 / (N Ts).",
    )
    periods: int = setting(
        kind="integer",
        minimum=2,
        limit=MAX_SAMPLES,
        doc="Periods per realization, transient periods included.",
    )
    transient_periods: int = setting(
        1,
        kind="integer",
        minimum=0,
        accepts="≥ 0 and < `periods`",
        doc="Leading periods of each realization dropped (the loop's transient after the "
        "switch). At least 2 steady-state periods are needed for the noise estimate.",
    )
    realizations: int = setting(
        8,
        kind="integer",
        minimum=1,
        limit=MAX_REALIZATIONS,
        doc="Random-phase realizations M (the total variance needs M ≥ 2).",
    )
    band: tuple[float, float] = setting(
        (1.0, 400.0),
        kind="numbers",
        length=2,
        unit="Hz",
        accepts="0 ≤ f_lo < f_hi ≤ Nyquist, holding at least one line",
        doc="Excited frequency band.",
    )
    rms: float = setting(
        0.05, kind="number", positive=True, unit="rad", doc="RMS of the multisine reference."
    )
    lines: Literal["full", "odd", "random-odd"] = setting(
        "random-odd",
        kind="choice",
        choices=("full", "odd", "random-odd"),
        doc="Excited lines in the band (random-odd leaves detection lines for nonlinear "
        "distortion).",
    )
    drift: float = setting(
        1.0,
        kind="number",
        unit="rad/s",
        doc="Speed of the slow ramp under the multisine, so that the rotor turns through many "
        "positions.",
    )
    numerator_order: int = setting(
        0,
        kind="integer",
        minimum=0,
        limit=MAX_TF_ORDER,
        accepts="≥ 0, ≤ `denominator_order` when that is an integer",
        doc="Order of the numerator B(s) of the fitted G(s) = exp(-s τ) B(s) / (s A(s)).",
    )
    denominator_order: int | Literal["auto"] = setting(
        "auto",
        kind="custom",
        limit=MAX_TF_ORDER,
        type_text="integer or string",
        accepts='≥ 0 or `"auto"`',
        doc="Order of A(s), the integrator not counted: 1 for a motor with one mechanical pole "
        '(K / (s (s + a))), 2 for the paper\'s plant. `"auto"` fits 0..3 and keeps the stable '
        "order with the smallest description length; an order that gives an unstable fit is "
        "refused with the order to use named.",
    )
    integrator: bool = setting(
        True,
        kind="boolean",
        doc="Whether G(s) has a pole at s = 0 (a position plant has).",
    )
    fit_delay: bool = setting(
        True,
        kind="boolean",
        doc="Estimate the input delay τ from the BLA's phase (else τ = 0).",
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "band", tuple(float(v) for v in self.band))


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


# ---- The schema ---------------------------------------------------------------------------------


def _tf_settings(what: str, variable: str, proper: str) -> tuple[Setting, ...]:
    """``num``/``den`` of a transfer function (limits.MAX_TF_ORDER: the loop's cost grows with
    the square of its states) and nothing else."""
    longest = MAX_TF_ORDER + 1
    return (
        Setting(
            "num",
            "numbers",
            max_length=longest,
            accepts=f"not all zero, at most as long as `den` ({proper})",
            doc=f"Numerator of {what}, descending powers of {variable}.",
        ),
        Setting(
            "den",
            "numbers",
            max_length=longest,
            accepts="leading coefficient ≠ 0",
            doc=f"Denominator of {what}, descending powers of {variable}"
            + (" (a trailing 0 is the integrator)." if variable == "s" else "."),
        ),
    )


_TOP_LEVEL: tuple[Setting, ...] = (
    Setting(
        "pole_pairs",
        "integer",
        minimum=1,
        limit=MAX_POLE_PAIRS,
        doc="Pole pairs n_m of the rotor: electrical cycles per mechanical revolution. "
        "`hallcal inspect` and `hallcal calibrate` check it against the data and suggest the "
        "right count.",
    ),
    Setting(
        "sample_time",
        "number",
        positive=True,
        unit="s",
        doc='Sample time Ts of every recording. `1.0` means "time in samples" (open-loop '
        "recordings without a known rate).",
    ),
    Setting(
        "controller",
        "table",
        None,
        default_text="required for `closed-loop`",
        doc="The drive's position controller C(q).",
    ),
    Setting(
        "plant",
        "table",
        None,
        default_text="none",
        doc="The plant G(s), when known. A BLA experiment (`--bla-data`) wins over it; "
        "`hallcal simulate` needs it (it is the virtual motor).",
    ),
    Setting(
        "model",
        "table",
        None,
        default_text="all defaults",
        doc="The flux model and the solver.",
    ),
    Setting(
        "trajectory",
        "table",
        None,
        default_text="`closed-loop`",
        doc="How the rotor moved during the calibration run.",
    ),
    Setting(
        "bla",
        "table",
        None,
        default_text="none",
        doc="The multisine experiment for the BLA of the plant (needed by `hallcal bla`, "
        "`--bla-data` and `hallcal simulate --experiment multisine`).",
    ),
    Setting(
        "bench",
        "table",
        None,
        default_text="all defaults",
        doc="The virtual bench of `hallcal simulate` and `hallcal demo`; ignored by calibration.",
    ),
)

#: Every table of the setup file (``""``: the top level) with its keys, in the reference's order.
SETUP_SCHEMA: dict[str, tuple[Setting, ...]] = {
    "": _TOP_LEVEL,
    "controller": _tf_settings("C(q)", "q", "causal"),
    "plant": (
        *_tf_settings("G(s)", "s", "proper"),
        Setting(
            "delay",
            "number",
            0.0,
            minimum=0.0,
            unit="s",
            doc="Input delay (computation and PWM), discretized exactly, any fraction of Ts.",
        ),
    ),
    "model": settings_of(ModelSpec),
    "trajectory": settings_of(TrajectorySpec),
    "bla": settings_of(BLASpec),
    "bench": settings_of(BenchSpec),
}

_SETUP_KEYS: dict[str, tuple[str, ...]] = {
    table: tuple(s.name for s in settings) for table, settings in SETUP_SCHEMA.items()
}
_ALL_SETUP_KEYS: tuple[str, ...] = tuple(
    f"{table}.{key}" if table else key for table, keys in _SETUP_KEYS.items() for key in keys
)
_SCHEMA_BY_NAME: dict[str, dict[str, Setting]] = {
    table: {s.name: s for s in settings} for table, settings in SETUP_SCHEMA.items()
}


# ---- Setup parsing -----------------------------------------------------------------------------


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

    def setting(self, name: str) -> Setting:
        """The schema's declaration of key `name` of this table."""
        return _SCHEMA_BY_NAME[self.table][name]

    def default(self, name: str) -> Any:
        """The declared default of key `name`."""
        return self.setting(name).default

    def get(self, name: str) -> Any:
        """Key `name`, read and checked as the schema declares it (kind, range, limit)."""
        s = self.setting(name)
        if s.kind == "integer":
            low = None if s.minimum is None else int(s.minimum)
            high = None if s.limit is None else int(s.limit)
            return self.integer(name, default=s.default, minimum=low, maximum=high)
        if s.kind == "number":
            return self.number(
                name, default=s.default, minimum=s.minimum, positive=s.positive, maximum=s.limit
            )
        if s.kind == "boolean":
            return self.boolean(name, default=s.default)
        if s.kind == "choice":
            return self.choice(name, s.choices, default=s.default)
        if s.kind == "numbers":
            return self.numbers(
                name, default=s.default, length=s.length, max_length=s.max_length, maximum=s.limit
            )
        raise TypeError(f"key {self.key(name)} ({s.kind}) is read by its table's parser")

    def check_only(self, **values: str) -> None:
        """Refuse a key given where it does not apply (its ``only`` condition is not met)."""
        for s in SETUP_SCHEMA[self.table]:
            if s.only is not None and s.only[0] in values and values[s.only[0]] != s.only[1]:
                if self.has(s.name):
                    self.error(f"key '{self.key(s.name)}' applies only to {s.only_text()}")

    def _read(self, name: str, default: Any, what: str, convert: Callable[[Any], Any]) -> Any:
        """Key `name` converted by `convert` (which checks it), or `default` when not given."""
        if name in self.data:
            return convert(self.data[name])
        if default is REQUIRED:
            self.error(f"key '{self.key(name)}' is missing (it must be {what})")
        return default

    def integer(
        self,
        name: str,
        *,
        default: Any = REQUIRED,
        minimum: int | None = None,
        maximum: int | None = None,
    ) -> Any:
        what = "an integer" + (f" >= {minimum}" if minimum is not None else "")

        def convert(value: Any) -> int:
            if not _is_int(value) or (minimum is not None and value < minimum):
                self.fail(name, what)
            if maximum is not None and value > maximum:
                self.above(name, maximum)
            return int(value)

        return self._read(name, default, what, convert)

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
        default: Any = REQUIRED,
        minimum: float | None = None,
        positive: bool = False,
        maximum: float | None = None,
    ) -> Any:
        what = "a number"
        if positive:
            what += " > 0"
        elif minimum is not None:
            what += f" >= {minimum:g}"

        def convert(value: Any) -> float:
            if not _is_number(value) or not _finite(value):
                self.fail(name, "a finite number" if _is_number(value) else what)
            if (positive and value <= 0) or (minimum is not None and value < minimum):
                self.fail(name, what)
            if maximum is not None and abs(value) > maximum:
                self.above(name, maximum)
            return float(value)

        return self._read(name, default, what, convert)

    def boolean(self, name: str, *, default: Any = REQUIRED) -> Any:
        def convert(value: Any) -> bool:
            if not isinstance(value, bool):
                self.fail(name, "true or false")
            return value

        return self._read(name, default, "true or false", convert)

    def choice(self, name: str, options: Sequence[str], *, default: Any = REQUIRED) -> Any:
        what = "one of " + ", ".join(f'"{o}"' for o in options)

        def convert(value: Any) -> str:
            if not isinstance(value, str) or value not in options:
                self.fail(name, what, _suggest(value, options) if isinstance(value, str) else "")
            return value

        return self._read(name, default, what, convert)

    def numbers(
        self,
        name: str,
        *,
        default: Any = REQUIRED,
        length: int | None = None,
        max_length: int | None = None,
        maximum: float | None = None,
    ) -> Any:
        what = (
            f"a list of {length} numbers" if length is not None else "a non-empty list of numbers"
        )

        def convert(value: Any) -> tuple[float, ...]:
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

        return self._read(name, default, what, convert)

    def distinct_integers(
        self, name: str, value: Any, *, minimum: int, what: str, noun: str, max_count: int
    ) -> tuple[int, ...]:
        """`value` of key `name` as a non-empty list of distinct integers >= `minimum`: at most
        `max_count` of them, none above MAX_HARMONIC (harmonics, cogging orders)."""
        if (
            not isinstance(value, list | tuple)
            or not value
            or not all(_is_int(k) and k >= minimum for k in value)
        ):
            self.fail(name, what)
        if len(value) > max_count:
            self.above(name, max_count, f"a list of {len(value)} {noun}s")
        if max(value) > MAX_HARMONIC:
            self.above(name, MAX_HARMONIC, f"a list with the {noun} {max(value)}")
        if len(set(value)) != len(value):
            article = "an" if noun[0] in "aeiou" else "a"
            self.error(f"key '{self.key(name)}' lists {article} {noun} twice: {_show(value)}")
        return tuple(int(k) for k in value)

    def table_at(self, name: str) -> _Table | None:
        if name not in self.data:
            return None
        value = self.data[name]
        if not isinstance(value, Mapping):
            self.fail(name, "a table")
        return _Table(value, self.source, name, self.prefix)


def _parse_tf(t: _Table, *, continuous: bool) -> tuple[tuple[float, ...], tuple[float, ...]]:
    num = t.get("num")
    den = t.get("den")
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


def _parse_model(t: _Table | None) -> ModelSpec:
    if t is None:
        return ModelSpec()
    t.check_keys()
    basis = t.get("basis")
    t.check_only(basis=basis)
    harmonics: tuple[int, ...] | str = t.default("harmonics")
    points = t.default("points")
    lengthscale: float | str = t.default("lengthscale")
    if basis == "fourier":
        value = t.data.get("harmonics", harmonics)
        if not (isinstance(value, str) and value == "auto"):
            harmonics = t.distinct_integers(
                "harmonics", value, minimum=1, what='a list of distinct integers >= 1 or "auto"',
                noun="harmonic", max_count=MAX_HARMONICS,
            )  # fmt: skip
    else:
        points = t.get("points")
        value = t.data.get("lengthscale", lengthscale)
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
        lut_points=t.get("lut_points"),
        max_iterations=t.get("max_iterations"),
        force=t.get("force"),
        cogging=_parse_cogging(t, basis),  # type: ignore[arg-type]
    )


def _parse_cogging(t: _Table, basis: str) -> tuple[int, ...] | str:
    """``cogging = "auto" | "none" | [orders]`` (distinct integers >= 0, 0 a constant load
    torque; Fourier basis)."""
    value = t.data.get("cogging", t.default("cogging"))
    if isinstance(value, str) and value in ("auto", "none"):
        return value
    if basis != "fourier":
        t.error(f"key '{t.key('cogging')}' with orders applies only to basis = \"fourier\"")
    what = ('a list of distinct integers >= 0 (periods per revolution, 0 a constant load '
            'torque), "auto" or "none"')  # fmt: skip
    return t.distinct_integers(
        "cogging", value, minimum=0, what=what, noun="order", max_count=MAX_COGGING_ORDERS
    )


def _parse_trajectory(t: _Table | None) -> TrajectorySpec:
    if t is None:
        return TrajectorySpec()
    t.check_keys()
    kind = t.get("kind")
    t.check_only(kind=kind)
    if kind == "closed-loop":
        return TrajectorySpec(kind=kind)
    start = t.get("start")
    stop = t.get("stop")
    if stop is not None and stop <= start:
        t.error(
            f"key '{t.key('stop')}' must be greater than '{t.key('start')}' ({start}), got {stop}"
        )
    return TrajectorySpec(kind=kind, start=start, stop=stop)


def _parse_bla(t: _Table | None, sample_time: float) -> BLASpec | None:
    if t is None:
        return None
    t.check_keys()
    period_samples = t.get("period_samples")
    periods = t.get("periods")
    transient = t.get("transient_periods")
    if transient >= periods:
        t.error(
            f"key '{t.key('transient_periods')}' must be less than '{t.key('periods')}' "
            f"({periods}), got {transient}"
        )
    band = t.get("band")
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
    realizations = t.get("realizations")
    total = period_samples * periods * realizations
    if total > MAX_SAMPLES:
        t.error(
            f"keys '{t.key('period_samples')}' x '{t.key('periods')}' x "
            f"'{t.key('realizations')}' = {total} samples, above the limit of {MAX_SAMPLES} "
            "samples of one experiment"
        )
    numerator_order = t.get("numerator_order")
    denominator_order: int | str = t.default("denominator_order")
    value = t.data.get("denominator_order", denominator_order)
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
        rms=t.get("rms"),
        lines=t.get("lines"),
        drift=t.get("drift"),
        numerator_order=numerator_order,
        denominator_order=denominator_order,  # type: ignore[arg-type]
        integrator=t.get("integrator"),
        fit_delay=t.get("fit_delay"),
    )


def _parse_bench(t: _Table | None, pole_pairs: int) -> BenchSpec:
    if t is None:
        return BenchSpec()
    t.check_keys()
    gain = t.get("gain_mismatch")
    if any(g <= -1.0 for g in gain):
        t.fail("gain_mismatch", "a list of 3 numbers > -1")
    pairs: list[tuple[int, float]] = []
    value = t.data.get("electrical_harmonics", t.default("electrical_harmonics"))
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
    custom = {"gain_mismatch": gain, "electrical_harmonics": tuple(pairs)}
    # the other keys in the table's order (the order their errors are reported in)
    values = {
        s.name: custom[s.name] if s.name in custom else t.get(s.name) for s in SETUP_SCHEMA["bench"]
    }
    return BenchSpec(**values)


def _parse_setup(data: Mapping[str, Any], source: str, prefix: str = "") -> Setup:
    if not isinstance(data, Mapping):
        what = f"key '{prefix.rstrip('.')}'" if prefix else "the setup"
        raise HallcalInputError(f"{source}: {what} must be a table")
    top = _Table(data, source, "", prefix)
    top.check_keys()
    pole_pairs = top.get("pole_pairs")
    sample_time = top.get("sample_time")
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
        delay = plant_t.get("delay")
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
    p = existing_file(path)
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
    lines = [f"{k} = {toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for name, table in data.items():
        if isinstance(table, dict):
            lines.append("")
            lines.append(f"[{name}]")
            lines.extend(f"{k} = {toml_value(v)}" for k, v in table.items())
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


_GENERATED = re.compile(
    r"(<!-- generated from the schema: \[(\w*)\] -->\n).*?(\n<!-- end of generated table -->)",
    re.S,
)


def render_setup_reference(text: str) -> str:
    """`text` (``docs/setup-reference.md``) with its key tables rendered from the schema.

    Each table sits between ``<!-- generated from the schema: [model] -->`` (``[]``: the top
    level) and ``<!-- end of generated table -->``; the prose around them is kept. The committed
    reference equals its rendering (``tests/test_docs.py``), so the tables cannot drift from the
    parser.

    Parameters
    ----------
    text : str
        The reference as committed.

    Returns
    -------
    str
        The same text with every generated table rendered from :data:`SETUP_SCHEMA`.
    """
    return _GENERATED.sub(
        lambda m: m.group(1) + render_table(SETUP_SCHEMA[m.group(2)]) + m.group(3), text
    )
