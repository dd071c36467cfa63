"""Writing the files: :func:`export_c` and what it returns, :class:`ExportResult`.

The steps: check the options and the artifact (the one validator), design the numbers (a larger
table when the arithmetic would take the stated bound above :data:`MAX_TOTAL_ERROR`), decide the
power-up identification, assemble each variant with its optional sections and banner, and write
the files atomically.
"""

from __future__ import annotations

import builtins
import dataclasses
import math
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from hallcal._constants import DEFAULT_C_PREFIX
from hallcal.errors import HallcalInputError
from hallcal.io import ArtifactData, atomic_write, make_folder, output_set, validate_artifact
from hallcal.output.codegen.anticogging import _anticogging_section
from hallcal.output.codegen.c_fixed import _fixed_header, _fixed_source
from hallcal.output.codegen.c_float import _float_header, _float_source, _float_subs
from hallcal.output.codegen.c_powerup import _homing_note, _powerup_section
from hallcal.output.codegen.c_text import _banner, _source_name, _version
from hallcal.output.codegen.numbers import (
    MAX_TOTAL_ERROR,
    TWO_PI,
    _fixed_numbers,
    _FixedNumbers,
    _float_numbers,
    _FloatNumbers,
)
from hallcal.output.codegen.sections import Section, _Context
from hallcal.output.firmware import (
    DEFAULT_FAULT_AFTER,
    DEFAULT_TOLERANCE,
    FirmwareDesign,
    PowerUpCode,
    PowerUpFirmware,
    design_firmware,
    design_powerup,
    table_sizes,
)

_C_KEYWORDS = frozenset(
    "auto break case char const continue default do double else enum extern float for goto if "
    "inline int long register restrict return short signed sizeof static struct switch typedef "
    "union unsigned void volatile while _Bool _Complex _Imaginary".split()
)


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_c` wrote and the accuracy it states.

    Bounds are mechanical rad of ``|y_C - y_python|``, y_python being ``hallcal reconstruct``
    (:meth:`hallcal.sensor.lut.LUT.f_star` in double precision) on the same input samples.

    Attributes
    ----------
    paths : tuple of Path
        Files written (``.h`` then ``.c``, float variant first).
    pole_pairs : int
        n_m.
    table_points : int
        M, intervals of the uniform table per revolution.
    table_bytes : int
        Bytes of the correction table (int16 values and int8 curvatures).
    table_error : float
        Largest difference of the table to the artifact's interpolant [rad] (exact).
    budget : float
        What the table may differ [rad]: a tenth of the noise floor, at most 1e-5 rad.
    noise_floor : float or None
        From the artifact [rad].
    float_bound : float
        Bound of the float variant (table error included).
    atan2_bound : float
        Bound of the float variant's atan2 [rad, electrical].
    fixed_bound : float or None
        Bound of the fixed-point variant on the same integer samples (table error included).
    fixed_atan2_bound : float or None
        Bound of the fixed-point atan2 [rad, electrical].
    quantization_rms, quantization_max : float or None
        What rounding the artifact's signals to integer counts (``adc_scale``) adds [rad].
    adc_scale : float
    step_limit : float
        Largest electrical step from the last accepted sample [turns] with none held (w + m;
        w more per sample held).
    glitch_safe_speed : float
        The speed limit w [rad per sample, mechanical]: up to it nothing slips and one glitch
        sample is absorbed; from it to twice it a slip cannot happen without the fault flag
        (``<PREFIX>_SPEED_LIMIT`` in the headers).
    fault_after : int
        Rejected samples in a row that latch the fault flag (the requested count, or fewer
        when a longer hold could alias at twice the speed limit).
    sha256 : str
        SHA-256 of the artifact's canonical JSON (also written into the files).
    sections : tuple of str
        Optional parts emitted (e.g. ``"anticogging"``).
    messages : tuple of str
        Warnings and notes.
    design : FirmwareDesign
        The numbers behind the files.
    identifies_pole_pair : bool
        Whether the float variant identifies the pole pair after init by itself (section
        ``"powerup"``; init takes no angle); otherwise both variants need the calibration's
        starting position (homing).
    powerup_message : str
        The artifact's identifiability verdict, or why there is no decoder.
    powerup_table_bytes : int
        Flash of the decoder's tables R and Z (0 without a decoder).
    powerup : PowerUpFirmware or None
        The decoder's numbers.
    """

    paths: tuple[Path, ...]
    pole_pairs: int
    table_points: int
    table_bytes: int
    table_error: float
    budget: float
    noise_floor: float | None
    float_bound: float
    atan2_bound: float
    fixed_bound: float | None
    fixed_atan2_bound: float | None
    quantization_rms: float | None
    quantization_max: float | None
    adc_scale: float
    step_limit: float
    glitch_safe_speed: float
    fault_after: int
    sha256: str
    sections: tuple[str, ...] = ()
    messages: tuple[str, ...] = ()
    design: FirmwareDesign | None = field(default=None, repr=False, compare=False)
    identifies_pole_pair: bool = False
    powerup_message: str = ""
    powerup_table_bytes: int = 0
    powerup: PowerUpFirmware | None = field(default=None, repr=False, compare=False)


#: Optional sections: (artifact key, builder). A builder returns a Section for a variant, or
#: None when it has nothing for that variant.
_SECTIONS: list[tuple[str, Callable[[_Context], Section | None]]] = [
    ("cogging", _anticogging_section),
    ("identifiability", _powerup_section),
]


def _sections(ctx: _Context) -> list[Section]:
    out = []
    for key, build in _SECTIONS:
        if key in ctx.artifact:
            sec = build(ctx)
            if sec is not None:
                out.append(sec)
    return out


def _check_options(prefix: str, adc_scale: float) -> None:
    if not isinstance(prefix, str) or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]{0,30}", prefix):
        raise HallcalInputError(
            f"prefix {str(prefix)[:40]!r} is not a C identifier (at most 31 letters, digits and "
            "underscores, starting with a letter)"
        )
    if prefix in _C_KEYWORDS:
        raise HallcalInputError(f"prefix {prefix!r} is a C keyword")
    if isinstance(adc_scale, bool) or not isinstance(adc_scale, int | float):
        raise HallcalInputError("adc_scale must be a positive number")
    if not (math.isfinite(adc_scale) and adc_scale > 0):
        raise HallcalInputError(f"adc_scale must be a positive number, got {adc_scale!r}")


@dataclass(frozen=True)
class _Numbers:
    """A design and the numbers of its variants (no fixed point: ``fixed`` is None)."""

    design: FirmwareDesign
    float: _FloatNumbers
    fixed: _FixedNumbers | None

    @property
    def worst(self) -> builtins.float:  # the field ``float`` shadows the builtin here
        """The larger stated bound of the two variants [rad]."""
        return max(self.float.bound, self.fixed.bound if self.fixed is not None else 0.0)


def _choose_numbers(
    art: ArtifactData, source: str, adc_scale: float | None, table_points: int | None,
    **options: object,
) -> _Numbers:  # fmt: skip
    """The design of ``table_points`` (default: the cheapest table within its budget), or a
    larger table when the arithmetic would take the stated bound above 1e-5 rad."""

    def numbers(points: int | None) -> _Numbers:
        design = design_firmware(art, source=source, table_points=points, sha256=art.sha256,
                                 **options)  # type: ignore[arg-type]  # fmt: skip
        fixed = _fixed_numbers(design, adc_scale) if adc_scale is not None else None
        return _Numbers(design, _float_numbers(design), fixed)

    best = numbers(table_points)
    if best.worst > MAX_TOTAL_ERROR and table_points is None:
        # the table within its budget, but with the arithmetic above 1e-5 rad: a larger table
        for m in table_sizes(best.design.pole_pairs):
            if m <= best.design.table.points:
                continue
            bigger = numbers(m)
            if bigger.worst < best.worst:
                best = bigger
            if best.worst <= MAX_TOTAL_ERROR:
                break
    return best


def _bound_messages(design: FirmwareDesign, worst: float) -> list[str]:
    """What to say about the table's size and the stated bound; refuse an implausible bound."""
    t = design.table
    out = []
    if t.nbytes > 4096 and not any("bytes" in m for m in design.messages):
        out.append(
            f"the table has {t.points} intervals ({t.nbytes} bytes): the calibration needs more "
            "than 4 kB for a stated bound within 1e-5 rad"
        )
    limit = design.noise_floor if design.noise_floor is not None else 1e-3
    if worst > limit:
        raise HallcalInputError(
            f"the generated code would differ from the calibration by up to {worst:.2g} rad, more "
            f"than the noise floor {limit:.2g} rad: the calibration's numbers are implausible"
        )
    if worst > MAX_TOTAL_ERROR:
        out.append(
            f"stated error bound {worst:.2g} rad is above {MAX_TOTAL_ERROR:g} rad (the table "
            f"alone differs by {t.error:.2g} rad)"
        )
    return out


def _powerup(
    art: ArtifactData, design: FirmwareDesign, source: str, wanted: bool
) -> PowerUpFirmware:
    if not wanted:
        return PowerUpFirmware(PowerUpCode.DISABLED, "left out on request (powerup=False)")
    return design_powerup(art, design, source=source)


def _powerup_messages(pu: PowerUpFirmware, prefix: str, fixed_point: bool) -> list[str]:
    if pu.emitted:
        return [
            f"the float variant identifies the pole pair at power-up by itself ({prefix}_init "
            f"takes no angle; tables {pu.table_bytes} bytes); the fixed-point variant needs "
            "the calibration's starting position as before"
            if fixed_point
            else f"the float variant identifies the pole pair at power-up by itself "
            f"({prefix}_init takes no angle; tables {pu.table_bytes} bytes)"
        ]
    if pu.status is not PowerUpCode.SINGLE_POLE_PAIR:
        return [f"no power-up identification in the C (homing needed): {pu.message}"]
    return []


def _glitch_safe_speed(design: FirmwareDesign) -> float:
    """The speed limit w [rad per sample, mechanical]: nothing slips below it."""
    return design.plausibility.speed * TWO_PI / design.pole_pairs


def _common_banner(design: FirmwareDesign, source: str, sha: str) -> list[str]:
    """The banner lines both variants share: origin, method, table, plausibility."""
    n, t, pl = design.pole_pairs, design.table, design.plausibility
    ts = design.sample_time
    safe = _glitch_safe_speed(design)
    speed_text = (
        f"{safe / ts:.4g} rad/s, {safe:.4g} rad per sample" if ts != 1.0
        else f"{safe:.4g} rad per sample"
    )  # fmt: skip
    return [
        f"generated by hallcal {_version()} (hallcal.output.codegen). Do not edit.",
        "",
        f"Source artifact : {source}",
        f"  sha256        : {sha}",
        f"Pole pairs n_m  : {n}",
        'Method: van Meer et al., "Self-Calibrating Position Measurements: Applied to Imperfect',
        'Hall Sensors": f_init (Clarke + atan2 + unwrap) and y_star = y + eta(mod(y, 2 pi)).',
        "",
        f"Table: {t.points} uniform intervals per revolution, "
        + (
            "piecewise quadratic (int16 values, int8 curvatures),"
            if t.quadratic
            else "piecewise linear (int16 values),"
        ),
        f"  {t.nbytes} bytes; differs from the calibration's table by at most",
        f"  {t.error:.2e} rad (RMS {t.rms_error:.2e}); budget {design.budget:.2e} rad = "
        + (
            f"min(0.1 x noise floor {design.noise_floor:.2e}, 1e-5)"
            if design.noise_floor is not None
            else "no noise floor in the artifact"
        ),
        "Plausibility: channel ranges and alpha/beta radius window "
        f"[{pl.radius_lo:.6g}, {pl.radius_hi:.6g}]",
        f"  (calibrated {pl.radius_model[0]:.6g} .. {pl.radius_model[1]:.6g}, tolerance "
        f"{pl.tolerance:g}, {6:d} noise sigmas).",
        f"Step rule: speed limit w = {pl.speed:.4g} electrical turn per sample",
        f"  ({speed_text}); f_init's step from the last accepted sample within",
        f"  s w + m = {pl.step_limit:.4g} turn (s = {pl.slope:.3f}: f_init's steepest slope; m = "
        f"{pl.step_noise:.2g}: six noise sigmas), s w more per sample held;",
        f"  the fault flag when {pl.fault_after} samples were rejected or unconfirmed (each "
        "confirmed one forgives one), then re-acquired"
        + (
            f" (not {pl.requested_fault_after}: a longer hold could alias at 2 w)."
            if pl.fault_after < pl.requested_fault_after
            else "."
        ),
        "  Up to w nothing slips, whatever one glitch sample reads; from w to 2 w a slip cannot",
        "  happen without the fault flag (tests/test_codegen_slip.py, benchmarks/bench_slip.py).",
    ]


def _float_files(
    ctx: _Context, fn: _FloatNumbers, common: list[str]
) -> tuple[list[tuple[str, str]], list[Section]]:
    """``<prefix>.h`` and ``<prefix>.c`` (name, text) and the sections they hold."""
    ctx = dataclasses.replace(ctx, subs=_float_subs(ctx, fn))
    secs = _sections(ctx)
    pu = ctx.powerup
    lines = (
        common
        + [
            "",
            "Float variant: single precision, no libm, no double, no division.",
            "  inputs: the Hall signals in the calibration's unit; ADC counts times "
            f"{ctx.PFX}_UNIT_PER_COUNT",
            f"  (this export: {ctx.adc_scale:g} counts per unit)",
            f"  stated bound vs hallcal reconstruct: {fn.bound:.2e} rad (mechanical)",
            f"  atan2: |error| <= {fn.atan_bound:.2e} rad (electrical)",
        ]
        + ([] if pu.emitted else _homing_note(pu))
        + [note for s in secs for note in s.notes]
    )
    pfx = ctx.pfx
    return [
        (f"{pfx}.h", _float_header(ctx, _banner(f"{pfx}.h", lines), secs)),
        (f"{pfx}.c", _float_source(ctx, _banner(f"{pfx}.c", lines), secs)),
    ], secs


def _fixed_files(
    ctx: _Context, q: _FixedNumbers, pu: PowerUpFirmware, common: list[str], adc_scale: float
) -> list[tuple[str, str]]:
    """``<prefix>_q.h`` and ``<prefix>_q.c`` (name, text)."""
    secs = _sections(ctx)
    lines = (
        common
        + [
            "",
            "Fixed-point variant: 32-bit integers only (no float, no 64-bit, no division).",
            f"  inputs: ADC counts, adc_scale {adc_scale:g} counts per artifact unit",
            f"  stated bound vs hallcal reconstruct on the same counts: {q.bound:.2e} rad",
            f"  atan2: |error| <= {q.atan.atan_bound:.2e} rad (electrical)",
            f"  rounding the artifact's signals to counts adds {q.quant_rms:.2e} rad RMS "
            f"(at most {q.quant_max:.2e})",
        ]
        + _homing_note(pu, fixed=True)
        + [note for s in secs for note in s.notes]
    )
    pfx = ctx.pfx
    defs = "".join(s.source for s in secs)
    return [
        (f"{pfx}_q.h", _fixed_header(ctx, _banner(f"{pfx}_q.h", lines), secs)),
        (f"{pfx}_q.c", _fixed_source(ctx, q, _banner(f"{pfx}_q.c", lines), defs)),
    ]


def _write(path: Path, text: str) -> None:
    try:
        text.encode("ascii")
    except UnicodeEncodeError:  # pragma: no cover - comment_text keeps everything ASCII
        raise AssertionError("generated C must be ASCII") from None
    with atomic_write(path, "w", encoding="ascii") as fh:
        fh.write(text)


def _write_files(out_dir: str | os.PathLike[str], texts: list[tuple[str, str]]) -> tuple[Path, ...]:
    """Write the files as one set (:func:`hallcal.io.output_set`): a failure part-way leaves
    the previous export complete, never a header of one calibration beside another's source."""
    out = Path(out_dir)
    with output_set():
        make_folder(out)
        for name, text in texts:
            _write(out / name, text)
    return tuple(out / name for name, _ in texts)


def _result(
    paths: tuple[Path, ...], nums: _Numbers, pu: PowerUpFirmware, adc_scale: float, sha: str,
    sections: list[Section], messages: list[str],
) -> ExportResult:  # fmt: skip
    design, fn, q = nums.design, nums.float, nums.fixed
    t, pl = design.table, design.plausibility
    return ExportResult(
        paths=paths,
        pole_pairs=design.pole_pairs,
        table_points=t.points,
        table_bytes=t.nbytes,
        table_error=t.error,
        budget=design.budget,
        noise_floor=design.noise_floor,
        float_bound=fn.bound,
        atan2_bound=fn.atan_bound,
        fixed_bound=q.bound if q is not None else None,
        fixed_atan2_bound=q.atan.atan_bound if q is not None else None,
        quantization_rms=q.quant_rms if q is not None else None,
        quantization_max=q.quant_max if q is not None else None,
        adc_scale=float(adc_scale),
        step_limit=pl.step_limit,
        glitch_safe_speed=_glitch_safe_speed(design),
        fault_after=pl.fault_after,
        sha256=sha,
        sections=tuple(dict.fromkeys(s.name for s in sections)),
        messages=tuple(messages),
        design=design,
        identifies_pole_pair=pu.emitted,
        powerup_message=pu.message,
        powerup_table_bytes=pu.table_bytes,
        powerup=pu,
    )


def export_c(
    artifact: Mapping | ArtifactData,
    out_dir: str | os.PathLike[str],
    *,
    prefix: str = DEFAULT_C_PREFIX,
    fixed_point: bool = True,
    source: str | os.PathLike[str] | None = None,
    adc_scale: float = 1.0,
    table_points: int | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
    max_speed: float | None = None,
    fault_after: int = DEFAULT_FAULT_AFTER,
    powerup: bool = True,
) -> ExportResult:
    """Generate lean C99 sources of f_star (eq. (f_final)) from a calibration artifact.

    Writes ``<prefix>.h`` and ``<prefix>.c`` (float) and, with ``fixed_point``,
    ``<prefix>_q.h`` and ``<prefix>_q.c`` (32-bit integers only), each atomically, with the
    usual permissions (``0666 & ~umask``). The C API (default prefix)::

        void hallcal_init(hallcal_state *s);  /* after power-up: angle acquired */
        uint32_t hallcal_set_angle(hallcal_state *s, int32_t revolutions, float angle);
        uint32_t hallcal_update(hallcal_state *s, float d1, float d2, float d3);  /* flags */
        void hallcal_read(const hallcal_state *s, hallcal_reading *r);  /* consistent */
        void hallcal_clear_fault(hallcal_state *s);
        /* hallcal_q_...: the same with int32 counts in and Q0.32 turns out */

    The same signatures for every export (DESIGN.md: one ``init`` for every variant). With the
    power-up identification (the artifact's identifiability verdict allows it; float variant
    only) ``init`` also starts the identification of the pole pair and the reading has
    ``identified`` and ``pole_pair`` (see
    :func:`~hallcal.output.codegen.c_powerup._powerup_section`); ``set_angle`` (a homed axis)
    ends it.

    Parameters
    ----------
    artifact : mapping or ArtifactData
        The calibration artifact as read from JSON (``"format": "hallcal-calibration/1"``),
        checked here by :func:`hallcal.io.validate_artifact`, or its checked view; the export
        reads ``pole_pairs``, ``reconstruction``, ``lut``, ``model``, ``setup.sample_time``,
        ``diagnostics.noise_floor`` and the optional ``cogging`` and ``identifiability``.
    out_dir : path
        Directory for the files (created if missing).
    prefix : str, keyword-only
        C identifier prefix of files, types, functions and macros (lower case recommended).
    fixed_point : bool, keyword-only
        Also write the fixed-point variant.
    source : str or path, keyword-only
        The artifact's file; only its sanitized base name goes into the comments.
    adc_scale : float, keyword-only
        ADC counts per unit of the artifact's Hall signals (fixed point: its inputs are
        ``round(adc_scale * d)``); 1 when the artifact is in counts.
    table_points : int, keyword-only
        Size of the uniform table (power of two); default from the error budget.
    tolerance : float, keyword-only
        Relative widening of the calibrated amplitude windows (default 0.25).
    max_speed : float, keyword-only
        Largest mechanical speed [rad/s] for the step rule; default 22.5 electrical degrees per
        sample.
    fault_after : int, keyword-only
        Rejected samples in a row before the fault flag (default 8).
    powerup : bool, keyword-only
        Put the power-up identification of the pole pair into the float variant when the
        artifact's identifiability verdict allows it (then ``<prefix>_init(s)`` takes no angle;
        see :data:`~hallcal.output.codegen.c_powerup._PU_C`); False keeps the homing API (and
        saves the decoder's tables).

    Returns
    -------
    ExportResult

    Raises
    ------
    HallcalInputError
        A malformed artifact (the message names the key), a table that is not bijective,
        numbers the generated C could not represent, an ``adc_scale`` outside what the
        fixed-point variant can take, or an option out of range. Nothing is written then.
    """
    _check_options(prefix, adc_scale)
    src = _source_name(source)
    art = validate_artifact(artifact, src)
    nums = _choose_numbers(art, src, adc_scale if fixed_point else None, table_points,
                           tolerance=tolerance, max_speed=max_speed,
                           fault_after=fault_after)  # fmt: skip
    design = nums.design
    messages = list(design.messages) + _bound_messages(design, nums.worst)
    pu = _powerup(art, design, src, powerup)
    messages += _powerup_messages(pu, prefix, fixed_point)
    common = _common_banner(design, src, art.sha256)
    ctx = _Context(art.data, design, prefix, prefix.upper(), "float", powerup=pu,
                   adc_scale=float(adc_scale))  # fmt: skip
    texts, sections = _float_files(ctx, nums.float, common)
    if nums.fixed is not None:
        ctx_q = _Context(art.data, design, prefix, prefix.upper(), "fixed",
                         adc_scale=float(adc_scale))  # fmt: skip
        texts += _fixed_files(ctx_q, nums.fixed, pu, common, adc_scale)
    paths = _write_files(out_dir, texts)
    return _result(paths, nums, pu, adc_scale, art.sha256, sections, messages)
