"""Firmware export: eq. (f_final) as lean C99 for microcontrollers, in float and in fixed point.

``export_c(artifact, out_dir)`` writes ``<prefix>.h`` / ``<prefix>.c`` (single-precision float,
for MCUs with an FPU) and ``<prefix>_q.h`` / ``<prefix>_q.c`` (32-bit integers only: no float, no
64-bit arithmetic, no division; for Cortex-M0+/M3 and FPU-less M4). Both compute f_star of
eq. (f_final), y_star = f_init(d) + eta(f_init(d)), with f_init of eq. (fimp) running on its own
unwrap state, and both check each sample for plausibility first. The numbers come from
:func:`hallcal.output.firmware.design_firmware`; this module turns them into C.

What the generated code does per sample (constant worst-case path, no loop, no libm, no double,
no division, no compiler builtin):

1. plausibility of the raw sample: each channel within its calibrated range, then the alpha/beta
   radius within its calibrated window;
2. alpha/beta = P (d - o); the float variant forms d2 - d1 and d3 - d1 when P's rows sum to zero,
   the fixed variant's integer rows sum to exactly zero, so a common mode cancels exactly;
3. the electrical angle: float: octant reduction on the IEEE bit patterns, a rotation by 45
   degrees above 22.5 degrees, a reciprocal by Newton steps from a linear seed valid on the
   radius window, and an odd minimax polynomial of atan on [-tan(pi/8), tan(pi/8)], then Q0.32
   turns; fixed: ``CORDIC_STEPS`` sign-magnitude CORDIC steps in unsigned arithmetic, then
   atan(y/x) ~ t - t^3/3 on the small residual with a 16-bit Newton reciprocal, all scaled to
   mechanical Q0.32 units;
4. the unwrap Gamma of eq. (fimp) (ties to -pi) in integers, then the step limit from the last
   accepted sample (grown for each sample held; none before the first accepted sample);
5. eta from the uniform table of M = n_m 2^k intervals (int16 values, linear, or with int8
   curvatures, quadratic) at f_init's angle within the revolution, found with shifts from the
   turn count and the electrical angle; y_star = revolutions + angle within the revolution;
6. a rejected sample (range, amplitude or step) is counted and the last reading held; after
   ``fault_after`` rejections in a row the fault flag latches until ``_clear_fault``;
7. the reading (revolutions, angle, flags) is published into one of two buffers and a sequence
   counter advanced, so ``_read`` returns a consistent pair from any context (the main loop
   of an ISR's update, or a higher-priority interrupt).

Generated files contain only numbers and comment text that is sanitized so that it cannot end the
comment: file names are reduced to their base name and to the characters ``A-Za-z0-9 ._-+=,:()[]``.
Optional parts are separate :class:`Section` objects added to a variant (see ``_SECTIONS``):
the anticogging feed-forward when the artifact has ``"cogging"``, and the power-up
identification of the pole pair when its ``"identifiability"`` verdict allows it (float variant:
the decoder of :mod:`hallcal.sensor.absolute`, ``init`` without an angle, the identification in
the reading; it fills the variant's insertion points, :data:`FLOAT_HOOKS`, and keeps the lean
path's code; see :func:`_powerup_section`). Without it the generated code keeps the homing API
and its header says why.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import string
import textwrap
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hallcal.errors import HallcalInputError
from hallcal.io import atomic_write
from hallcal.output.firmware import (
    ARTIFACT_FORMAT,
    DEFAULT_FAULT_AFTER,
    DEFAULT_TOLERANCE,
    EXP2_CUT,
    FirmwareDesign,
    PowerUpCode,
    PowerUpFirmware,
    design_firmware,
    design_powerup,
    table_sizes,
)

__all__ = [
    "ARTIFACT_FORMAT",
    "CORDIC_STEPS",
    "ExportResult",
    "Section",
    "comment_text",
    "export_c",
]

TWO_PI = 2.0 * math.pi
_U32 = 1 << 32
_EPS_F32 = 2.0**-24  # unit roundoff of IEEE single precision
#: The generated code's stated error bound against Python should not exceed this [rad]; a larger
#: table is chosen when the arithmetic would take it above.
MAX_TOTAL_ERROR = 1e-5
#: CORDIC steps of the fixed-point atan2 before the residual is taken as atan(t) ~ t - t^3/3.
CORDIC_STEPS = 5
_TAN_PI_8 = math.tan(math.pi / 8.0)
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
        Largest electrical step per sample [turns] before a sample is rejected.
    glitch_safe_speed : float
        Speed up to which one glitch sample cannot make the angle slip [rad per sample,
        mechanical].
    fault_after : int
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


@dataclass(frozen=True)
class Section:
    """An optional piece of a generated variant.

    Attributes
    ----------
    name : str
        Short name (reported in :attr:`ExportResult.sections`).
    header : str
        Declarations for the header (inside ``extern "C"``).
    source : str
        Definitions for the source file.
    notes : tuple of str
        Lines for the banner comment.
    hooks : mapping of str to str
        Text for the variant's insertion points (:data:`FLOAT_HOOKS`; the fixed-point variant
        has none), e.g. members of the state or another ``init``.
    """

    name: str
    header: str
    source: str
    notes: tuple[str, ...] = ()
    hooks: Mapping[str, str] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Text that reaches the C files
# --------------------------------------------------------------------------------------------

_COMMENT_SAFE = re.compile(r"[^A-Za-z0-9 ._+=,:()\[\]-]")


def comment_text(text: str, *, limit: int = 80) -> str:
    """Text safe inside a C block comment on one line.

    Only ``A-Za-z0-9``, space and ``._+=,:()[]-`` survive; anything else (``*``, ``/``, ``\\``,
    ``?``, quotes, control characters, non-ASCII) becomes ``_``. So the result cannot end the
    comment (``*/``), splice a line (backslash-newline), form a trigraph (``??/``) or open a
    nested comment, and has no newline. Truncated to ``limit`` characters.

    Parameters
    ----------
    text : str
        Any text (a file name, a message).
    limit : int, keyword-only
        Maximum length of the result [characters], ``...`` included.

    Returns
    -------
    str
        The sanitized, possibly truncated text.
    """
    out = _COMMENT_SAFE.sub("_", str(text))
    return out if len(out) <= limit else out[: limit - 3] + "..."


def _source_name(source: str | os.PathLike[str] | None) -> str:
    """The base name of the artifact's path, sanitized (never an absolute path)."""
    if source is None:
        return "(in memory)"
    name = os.path.basename(os.fspath(source).replace("\\", "/").rstrip("/")) or "(unnamed)"
    return comment_text(name, limit=60)


def _f32(value: float, what: str) -> float:
    """``value`` as single precision; refuse what float cannot hold (the C would be wrong)."""
    v = float(np.float32(value))
    if not math.isfinite(v) or (v != 0.0 and abs(v) < 1e-30) or abs(v) > 1e30:
        raise HallcalInputError(
            f"the calibration's numbers do not fit single precision ({what} = {value:.3g})"
        )
    return v


def _cf(value: float, what: str = "constant") -> str:
    """A float literal that reads back as the same single-precision number."""
    v = _f32(value, what)
    s = f"{v:.9g}"
    if not any(ch in s for ch in ".e"):
        s += ".0"
    return s + "f"


def _cu(value: int) -> str:
    v = int(value)
    if not 0 <= v < _U32:
        raise ValueError(v)
    return f"{v}u"


def _c_list(values: Sequence[str], per_line: int, indent: str = "    ") -> str:
    return "\n".join(
        indent + ", ".join(values[i : i + per_line]) + "," for i in range(0, len(values), per_line)
    )


def _banner(fname: str, lines: Sequence[str]) -> str:
    body = [comment_text(t, limit=100) for t in lines]
    return (
        "/*\n" + "\n".join((" * " + t).rstrip() for t in [comment_text(fname)] + body) + "\n */\n"
    )


def _version() -> str:
    from hallcal._version import __version__

    return comment_text(__version__, limit=20)


# --------------------------------------------------------------------------------------------
# Float variant: numbers
# --------------------------------------------------------------------------------------------


def _atan_poly(terms: int = 5) -> tuple[NDArray[np.float64], float]:
    """Odd minimax polynomial of atan on [0, tan(pi/8)] (Lawson iterations) and its max error."""
    t = np.sort(np.cos(np.linspace(0.0, math.pi, 4001)) * 0.5 * _TAN_PI_8 + 0.5 * _TAN_PI_8)
    V = np.stack([t ** (2 * k + 1) for k in range(terms)], axis=1)
    f = np.arctan(t)
    w = np.full(t.size, 1.0 / t.size)
    coef = np.zeros(terms)
    for _ in range(300):
        sw = np.sqrt(w)
        coef = np.linalg.lstsq(V * sw[:, None], f * sw, rcond=None)[0]
        e = np.abs(V @ coef - f)
        w = w * e
        w /= w.sum()
    tt = np.linspace(0.0, _TAN_PI_8, 100_001)
    err = float(np.max(np.abs(np.stack([tt ** (2 * k + 1) for k in range(terms)], 1) @ coef
                              - np.arctan(tt))))  # fmt: skip
    return coef, err


def _reciprocal_seed(lo: float, hi: float) -> tuple[float, float, float]:
    """Linear minimax seed c0 - c1 x of 1/x on [lo, hi] (relative error) and that error."""
    c1 = 8.0 / (4.0 * lo * hi + (lo + hi) ** 2)
    c0 = c1 * (lo + hi)
    return c0, c1, abs(1.0 - c1 * lo * hi)


@dataclass(frozen=True)
class _FloatNumbers:
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    r2_lo: float
    r2_hi: float
    seed: tuple[float, float]
    newton: int
    poly: NDArray[np.float64]  # in turns
    atan_bound: float  # rad electrical
    bound: float  # rad mechanical


def _float_numbers(d: FirmwareDesign) -> _FloatNumbers:
    """Constants of the float variant and its stated bounds.

    The atan2 may use a tenth of the budget (electrical: times n_m): the fewest Newton steps
    and polynomial terms within it (at least 1 and 3), so that the hot path does no more work
    than the accuracy needs.
    """
    pl = d.plausibility
    n = d.pole_pairs
    # the reciprocal is of x = max(|a|, |b|) (after the rotation: r cos(th), |th| <= pi/8)
    x_lo = math.cos(math.pi / 8.0) * pl.radius_lo * (1.0 - 1e-6)
    x_hi = pl.radius_hi * (1.0 + 1e-6)
    c0, c1, eps = _reciprocal_seed(x_lo, x_hi)
    target = min(0.25 * d.budget * n, 2e-5)
    # reciprocal: relative error e of t turns the angle by at most e t / (1 + t^2) <= 0.354 e
    newton, e = 1, eps * eps
    while 0.354 * e > 0.5 * target and newton < 5:
        e, newton = e * e, newton + 1
    terms = 3
    coef, poly_err = _atan_poly(terms)
    while poly_err > 0.25 * target and terms < 6:
        terms += 1
        coef, poly_err = _atan_poly(terms)
    # atan2 [rad, electrical]: polynomial; reciprocal; single-precision rounding: about 12
    # roundings of t and the Horner sum (relative to tan(pi/8)) and 2 of the octant assembly
    # on values up to one turn.
    atan_bound = (
        poly_err
        + 0.354 * (e + 4.0 * _EPS_F32)
        + 12.0 * _EPS_F32 * _TAN_PI_8
        + 2.0 * _EPS_F32 * TWO_PI
    )
    # alpha/beta: the float offsets and about 4 roundings of the products and sums, relative
    # to the smallest radius; an error delta of (a, b) turns the angle by delta / r.
    P = d.projection
    span = np.maximum(np.abs(pl.channel_lo), np.abs(pl.channel_hi))
    row = np.abs(P).sum(axis=1)
    # (rows summing to zero: differences d2 - d1, d3 - d1, exact for integer counts below 2^24;
    # otherwise P d - P o, whose roundings are relative to |d|, not to |d - o|)
    ab_err = float(np.max(row)) * (
        _EPS_F32 * float(np.max(np.abs(P @ d.offset))) + 4.0 * _EPS_F32 * float(np.max(span))
    )
    e_el = atan_bound + math.sqrt(2.0) * ab_err / pl.radius_lo
    slope = _table_slope(d)
    m = d.table.points
    # The table position comes from the integer angle, truncated to 2^-16 of an interval: an
    # error there moves both the position and eta (slope). The output in turns: the position
    # converted (1 rounding), scaled by 1/M (1), the sum (1, of at most 1.5 turns: half an ulp
    # is 2^-24 turn), and the reading's conversion to rad (1 rounding and the single-precision
    # 2 pi, 1.7e-7 rad per turn): each 2^-24 turn = 3.7e-7 rad.
    e_pos = e_el / n + TWO_PI / m * 2.0**-16
    e_out = 4.0 * _EPS_F32 * TWO_PI + 1.8e-7
    eta_round = 4.0 * _EPS_F32 * 32768.0 * d.table.lsb_rad
    bound = d.table.error + (1.0 + slope) * e_pos + e_out + eta_round
    return _FloatNumbers(
        lo=pl.channel_lo,
        hi=pl.channel_hi,
        r2_lo=pl.radius_lo**2,
        r2_hi=pl.radius_hi**2,
        seed=(c0, c1),
        newton=newton,
        poly=coef / TWO_PI,
        atan_bound=atan_bound,
        bound=bound,
    )


def _table_slope(d: FirmwareDesign) -> float:
    """Largest |d eta / d x| of the table (rad per rad)."""
    t = d.table
    v = t.values.astype(np.float64)
    c = t.curvature.astype(np.float64) * 2.0**t.curvature_shift
    # derivative of T_i (1-f) + T_(i+1) f + c f (1-f) in f is dT + c (1 - 2f): at most |dT| + |c|
    per_f = np.abs(np.diff(np.append(v, v[0]))) + np.abs(c)
    return float(np.max(per_f)) * t.lsb_rad * t.points / TWO_PI


# --------------------------------------------------------------------------------------------
# Fixed variant: numbers
# --------------------------------------------------------------------------------------------


def _bitlen(v: int) -> int:
    return int(v).bit_length()


@dataclass(frozen=True)
class _FixedNumbers:
    lo: list[int]
    hi: list[int]
    centre: list[int]
    proj_hi: list[list[int]]
    proj_lo: list[list[int]]
    lo_shift: int
    bias: int
    a0: list[int]
    proj_shift: int
    r2_lo: int
    r2_hi: int
    period: int  # electrical period in mechanical Q0.32 units (0 for n = 1: 2^32)
    half: int
    quarter: int
    eighth: int
    turn_base: list[int]
    cordic: list[int]
    sx: int
    kr: int
    seed_a: int
    seed_b: int
    seed_shift: int
    sy: int
    cube_shift: int
    cube_mul: int
    cube_post: int
    d_shift: int
    s_mul: int
    s_post: int
    step_limit: int
    atan_bound: float
    bound: float
    quant_rms: float
    quant_max: float


def _fixed_numbers(d: FirmwareDesign, adc_scale: float) -> _FixedNumbers:
    """Integer constants of the fixed-point variant and its bounds.

    Raises HallcalInputError when ``adc_scale`` puts the signals outside the int32 arithmetic
    or makes the rounding to counts noisier than the Hall sensors themselves.
    """
    pl = d.plausibility
    n = d.pole_pairs
    s = float(adc_scale)
    P = d.projection
    lo_f = np.floor(pl.channel_lo * s)
    hi_f = np.ceil(pl.channel_hi * s)
    limit = 2.0**30
    if not (np.all(np.abs(lo_f) < limit) and np.all(np.abs(hi_f) < limit)):
        raise HallcalInputError(
            f"adc_scale {adc_scale:g} puts the Hall signals at {np.max(np.abs(hi_f)):.3g} counts; "
            "the fixed-point variant takes signals up to 2^30 counts"
        )
    # input rounding to counts: worst case and RMS angle error [rad, mechanical]
    row1 = float(np.max(np.abs(P).sum(axis=1)))
    quant_max = 0.5 * row1 * math.sqrt(2.0) / (s * pl.radius_model[0]) / n
    r_mean = 0.5 * sum(pl.radius_model)
    quant_rms = (
        (1.0 / math.sqrt(12.0)) * float(np.linalg.norm(P)) / (math.sqrt(2.0) * s * r_mean) / n
    )
    if d.noise_floor is not None:
        if quant_rms > d.noise_floor:
            raise HallcalInputError(
                f"adc_scale {adc_scale:g}: rounding the signals to counts adds {quant_rms:.2g} rad "
                f"RMS, more than the Hall noise floor {d.noise_floor:.2g} rad (the artifact is "
                "not in ADC counts: give the counts per unit)"
            )
    elif s * pl.radius_model[0] / row1 < 64.0:
        raise HallcalInputError(
            f"adc_scale {adc_scale:g}: the Hall amplitude would be "
            f"{s * pl.radius_model[0] / row1:.3g} counts, under 64 (give the counts per unit)"
        )
    centre = [int(round(v * s)) for v in d.offset]
    lo = [int(v) for v in lo_f]
    hi = [int(v) for v in hi_f]
    xr = max(max(h - c, c - lo_) for lo_, h, c in zip(lo, hi, centre, strict=True))
    xr = max(xr, 1)
    frac = np.array([v * s - c for v, c in zip(d.offset, centre, strict=True)])
    # Projection P 2^(ps + kl) in two parts, PA = PH 2^kl + PL with 0 <= PL < 2^kl:
    # a = sum PH x + ((sum PL (x + xb)) >> kl) - a0, with x + xb >= 0 (unsigned, no shift of a
    # negative number) and every partial sum within 32 bits:
    #   sum |PH| x_max < 2^29 (signed part), 3 2^kl 2 xb < 2^32 (unsigned part).
    xb = xr
    kl = int(math.floor(math.log2(2.0**32 / (3.0 * (2 * xb + 1))))) - 1
    kl = max(0, min(kl, 20))
    ps = 60
    while ps > -60:
        if all(float(np.abs(P[r]).sum()) * 2.0**ps * (xr + 2.0) < 2.0**28 for r in range(2)):
            break
        ps -= 1
    proj = []
    for r in range(2):
        qa = [int(round(v)) for v in P[r] * 2.0 ** (ps + kl)]
        if d.rejects_common_mode:  # make the integer row sum exactly zero
            j = int(np.argmax([abs(v) for v in qa]))
            qa[j] -= sum(qa)
        proj.append(qa)
    hi_parts = [[v >> kl for v in row] for row in proj]  # floor: PL = PA - PH 2^kl in [0, 2^kl)
    lo_parts = [[v - (h << kl) for v, h in zip(row, hrow, strict=True)]
                for row, hrow in zip(proj, hi_parts, strict=True)]  # fmt: skip
    # a0 (units of a): the fractional offsets and the bias of the unsigned part
    a0 = [
        int(round(float(np.dot(proj[r], frac)) / 2.0**kl + sum(lo_parts[r]) * xb / 2.0**kl))
        for r in range(2)
    ]
    scale = 2.0**ps * s
    r_lo_a = pl.radius_lo * scale
    r_hi_a = pl.radius_hi * scale
    if r_hi_a >= 2.0**30.5 or r_lo_a < 2.0**24:
        raise HallcalInputError(
            "the fixed-point variant cannot scale this sensor map"
        )  # pragma: no cover
    # radius check on (|a| >> 15, |b| >> 15): r_s in [r / 2^15 - sqrt 2, r / 2^15]
    r2_lo = int(math.floor((r_lo_a / 2.0**15) ** 2))
    r2_hi = int(math.ceil((r_hi_a / 2.0**15) ** 2))
    # what the check lets through, in true radius
    r_true_lo = math.sqrt(r2_lo) * 2.0**15
    r_true_hi = (math.sqrt(r2_hi) + math.sqrt(2.0)) * 2.0**15
    # electrical period in mechanical Q0.32 units
    if n == 1:
        period, half = 0, 1 << 31
        pe = float(_U32)
    else:
        period = _U32 // n
        half = period // 2
        pe = float(period)
    quarter = int(round(pe / 4.0))
    eighth = int(round(pe / 8.0))
    turn_base = [(t * _U32) // n for t in range(n)]
    S = pe / TWO_PI  # mechanical units per electrical rad
    cordic = [int(round(math.atan(2.0**-i) * S)) for i in range(CORDIC_STEPS)]
    # after the steps: x = K r cos(theta), |theta| <= sum_{i >= N} atan(2^-i) < 2^-(N-1)
    K = math.prod(math.sqrt(1.0 + 4.0**-i) for i in range(CORDIC_STEPS))
    theta_max = 2.0 ** -(CORDIC_STEPS - 1) * 1.01
    x8_hi = K * r_true_hi * (1.0 + 1e-6) + 16.0
    x8_lo = K * r_true_lo * math.cos(theta_max) - 16.0 * CORDIC_STEPS
    sx = _bitlen(int(math.ceil(x8_hi))) - 16
    xh_hi = int(math.ceil(x8_hi)) >> sx
    xh_lo = max(1, (int(math.floor(x8_lo)) >> sx) - 1)
    if xh_lo < 2**12:
        raise HallcalInputError(
            "the amplitude window is too wide for the fixed-point reciprocal (lower the tolerance)"
        )
    kr = 15 + int(math.floor(math.log2(xh_lo)))  # R ~ 2^kr / xh < 2^16
    c0, c1, eps0 = _reciprocal_seed(float(xh_lo), float(xh_hi + 1))
    seed_shift = 15 - int(math.floor(math.log2(c1 * 2.0**kr)))
    seed_b = int(round(c1 * 2.0**kr * 2.0**seed_shift))
    seed_a = int(round(c0 * 2.0**kr))
    assert 2**15 <= seed_b < 2**16 and seed_a < 2**17, (seed_a, seed_b)
    # y after the steps: |y| <= x tan(theta_max)
    y8_hi = x8_hi * math.tan(theta_max) + 16.0 * CORDIC_STEPS
    sy = max(0, _bitlen(int(math.ceil(y8_hi))) - 16)
    e_tau = kr + sx - sy  # tau_q = yh R = tau 2^e_tau
    tau_q_max = math.tan(theta_max) * 2.0**e_tau * 1.01
    assert tau_q_max < 2.0**32
    # cube: c = tau_q >> cube_shift < 2^10; tau^3 / 3 in tau_q units = c^3 2^(3 cs - 2 e) / 3
    cube_shift = max(0, _bitlen(int(tau_q_max)) - 10)
    fexp = 3 * cube_shift - 2 * e_tau  # c^3 2^fexp / 3
    # ((c^3 >> 8) * mul) >> post with mul in [2^7, 2^8)
    f = 2.0 ** (fexp + 8) / 3.0
    post = 7 - int(math.floor(math.log2(f)))
    cube_mul = int(round(f * 2.0**post))
    if cube_mul >= 256:
        cube_mul, post = int(round(f * 2.0 ** (post - 1))), post - 1
    assert post >= 0 and 2**7 <= cube_mul < 2**8, (post, cube_mul)
    # delta (tau_q units) to mechanical units: delta 2^-e_tau S = (dh * s_mul) >> s_post
    d_shift = max(0, _bitlen(int(tau_q_max)) - 16)
    j = 15 - int(math.floor(math.log2(S)))
    s_mul = int(round(S * 2.0**j))
    s_post = e_tau - d_shift + j
    if s_mul >= 2**16:
        s_mul, s_post = int(round(S * 2.0 ** (j - 1))), s_post - 1
    assert 2**15 <= s_mul < 2**16 and 0 <= s_post < 32, (s_mul, s_post)
    step = pl.step_limit * pe
    step_limit = int(math.floor(step))
    # --- bounds ---
    # atan2 [rad, electrical]: the reciprocal's relative error (two Newton steps of a 16-bit
    # product: eps^4 plus 3 truncations of 2^-15) times tan(theta_max); the truncation of y to
    # 16 bits; the residual of atan(t) ~ t - t^3/3 and the 8-bit cube; the CORDIC shifts (one
    # unit per step on vectors of at least r_lo); the rounded constants (half a unit each, plus
    # the 16-bit scale to mechanical units).
    eps2 = eps0**4 + 3.0 * 2.0**-15
    tau_max = math.tan(theta_max)
    atan_bound = (
        tau_max * eps2
        + 2.0**sy / x8_lo
        + tau_max**5 / 5.0
        + tau_max**3 / 3.0 * 2.0**-6
        + 2.0 * CORDIC_STEPS / (r_true_lo * 0.5)
        + (0.5 * CORDIC_STEPS + 2.0) / S
        + tau_max * 2.0**-15
    )
    # the integer projection: rounding of a0 and the floor of the unsigned part (1.5 units of
    # a), and the rounding of P 2^(ps + kl) (half a unit on each of 3 inputs up to xr)
    proj_err = (1.5 + 1.5 * 3.0 * xr / 2.0**kl) * math.sqrt(2.0) / r_true_lo
    e_el = atan_bound + proj_err
    slope = _table_slope(d)
    lsb = TWO_PI / _U32
    e_u = e_el / n + 3.0 * lsb  # turn starts, octant constants
    eta_round = (2.0 + 2.0**-16 * 65536.0) * lsb + 2.0**-16 * 32768.0 * d.table.lsb_rad
    bound = d.table.error + (1.0 + slope) * e_u + eta_round
    return _FixedNumbers(
        lo=lo, hi=hi, centre=centre, proj_hi=hi_parts, proj_lo=lo_parts, lo_shift=kl, bias=xb,
        a0=a0,
        proj_shift=ps + kl, r2_lo=r2_lo, r2_hi=r2_hi,
        period=period, half=half, quarter=quarter, eighth=eighth, turn_base=turn_base,
        cordic=cordic, sx=sx, kr=kr, seed_a=seed_a, seed_b=seed_b, seed_shift=seed_shift, sy=sy,
        cube_shift=cube_shift, cube_mul=cube_mul, cube_post=post, d_shift=d_shift, s_mul=s_mul,
        s_post=s_post, step_limit=step_limit,
        atan_bound=atan_bound, bound=bound, quant_rms=quant_rms, quant_max=quant_max,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# C templates: float variant
# --------------------------------------------------------------------------------------------

_FLOAT_H = string.Template(
    r"""$banner
#ifndef ${PFX}_H
#define ${PFX}_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define ${PFX}_POLE_PAIRS ${n}
#define ${PFX}_TABLE_POINTS ${m}
#define ${PFX}_FAULT_AFTER ${fault_after}
${api_macros}
/* Flags of a reading (bit mask). */
#define ${PFX}_HELD 1u           /* this sample was rejected: the reading is the last accepted */
#define ${PFX}_FAULT 2u          /* ${PFX}_FAULT_AFTER rejected in a row; latched until cleared */
#define ${PFX}_REJ_RANGE 4u      /* a channel outside its calibrated range, or not a number */
#define ${PFX}_REJ_AMPLITUDE 8u  /* alpha/beta radius outside its calibrated window */
#define ${PFX}_REJ_STEP 16u      /* step from the last accepted angle above the limit */

/* One consistent reading: y_star = 2 pi revolutions + angle [rad]. */
typedef struct {
    int32_t revolutions; /* whole revolutions (wraps after 2^31) */
    float angle;         /* within the revolution, [0, 2 pi) rad */
    uint32_t flags;      /* of the last sample: ${PFX}_HELD, ${PFX}_FAULT, ${PFX}_REJ_... */
    uint32_t rejected;   /* rejected samples since init (saturates) */
${reading_members}} ${pfx}_reading;

/* State of one sensor set; its members are private (use the functions). No dynamic memory. */
typedef struct {
    int32_t rev;       /* f_init: whole revolutions of its own (uncorrected) unwrap state */
    int32_t turn;      /* f_init: electrical turn within the revolution, 0 .. n_m - 1 */
    uint32_t phase;    /* f_init: electrical angle within the turn, Q0.32 turns */
    uint32_t limit;    /* step limit for the next sample, Q0.32 electrical turns */
    uint32_t held;     /* rejected samples in a row */
    volatile uint32_t rejected; /* rejected samples since init */
    uint32_t fault;    /* ${PFX}_FAULT once ${PFX}_FAULT_AFTER samples in a row were rejected */
    volatile uint32_t seq; /* readings published; the last one is pub[seq & 1] */
    volatile struct {
        int32_t revolutions;
        float turns; /* y_star within the revolution [turns] */
        uint32_t flags;
    } pub[2];
${state_members}} ${pfx}_state;

${init_decl}
/* One sample of the three Hall signals in the calibration's unit. Returns the flags of the
 * reading it publishes (0: accepted). Constant worst-case time, no library call. */
uint32_t ${pfx}_update(${pfx}_state *s, float d1, float d2, float d3);

/* The last reading, consistent (revolutions and angle of the same sample) from any context:
 * the main loop while ${pfx}_update runs in an ISR, or an ISR that interrupts ${pfx}_update.
 * Single core only (one writer). */
void ${pfx}_read(const ${pfx}_state *s, ${pfx}_reading *r);

/* Clear the latched fault flag (after the cause is removed and the angle re-referenced). */
void ${pfx}_clear_fault(${pfx}_state *s);
$section_decls
#ifdef __cplusplus
}
#endif

#endif /* ${PFX}_H */
"""
)

_FLOAT_C = string.Template(
    r"""$banner
#include <stdint.h>

#include "${header}"

/* The sign, absolute value and range checks read the IEEE 754 binary32 pattern of a float
 * through a union (MISRA C:2012 Rule 19.2, advisory, deviated here: hc_bits and hc_float). The
 * patterns of non-negative floats are ordered as the numbers are, so a range [lo, hi] of
 * positive numbers is one unsigned comparison: bits(x) - bits(lo) <= bits(hi) - bits(lo);
 * negative numbers and NaN fall outside. */
typedef char hc_float_is_binary32[(sizeof(float) == sizeof(uint32_t)) ? 1 : -1];

${table_decl}

/* atan2 from the first-octant angle th: base +- th (Q0.32 turns), by octant (a < 0, b < 0,
 * |b| > |a|) and by the 45-degree rotation (which adds 1/8 turn to th); th is subtracted in the
 * octants of bit mask 0x96. */
static const uint32_t hc_base[16] = {
    0x00000000u, 0x20000000u, 0x40000000u, 0x20000000u, 0x00000000u, 0xE0000000u, 0xC0000000u,
    0xE0000000u, 0x80000000u, 0x60000000u, 0x40000000u, 0x60000000u, 0x80000000u, 0xA0000000u,
    0xC0000000u, 0xA0000000u,
};

static uint32_t hc_bits(float f)
{
    union {
        float f;
        uint32_t u;
    } c;
    c.f = f;
    return c.u;
}

static float hc_float(uint32_t u)
{
    union {
        uint32_t u;
        float f;
    } c;
    c.u = u;
    return c.f;
}

static int32_t hc_s32(uint32_t u) /* two's complement without implementation-defined casts */
{
    int32_t v;
    if (u <= 0x7FFFFFFFu) {
        v = (int32_t)u;
    } else {
        v = (int32_t)(u - 0x80000000u) - 0x7FFFFFFF - 1;
    }
    return v;
}

${atan2_fn}
static void hc_publish(${pfx}_state *s, int32_t rev, float turns, uint32_t flags)
{
    const uint32_t q = s->seq + 1u;
    s->pub[q & 1u].revolutions = rev;
    s->pub[q & 1u].turns = turns;
    s->pub[q & 1u].flags = flags;
    s->seq = q;
}

${init_def}
${before_update}${update_def}
void ${pfx}_read(const ${pfx}_state *s, ${pfx}_reading *r)
{
    uint32_t before;
    uint32_t after;
    float turns;
${read_locals}    do {
        before = s->seq;
        r->revolutions = s->pub[before & 1u].revolutions;
        turns = s->pub[before & 1u].turns;
        r->flags = s->pub[before & 1u].flags;
${read_copy}        after = s->seq;
    } while ((after - before) > 1u);
    r->rejected = s->rejected;${read_after}
    if (turns < 0.0f) { /* update keeps y_star in (-1/2, 3/2) turns of its revolution */
        turns = turns + 1.0f;
        r->revolutions = hc_s32((uint32_t)r->revolutions - 1u);
    } else if (turns >= 1.0f) {
        turns = turns - 1.0f;
        r->revolutions = hc_s32((uint32_t)r->revolutions + 1u);
    } else {
        /* within the revolution */
    }
    r->angle = turns * 6.28318548f;
    if (r->angle >= 6.28318548f) {
        r->angle = 0.0f; /* rounded up to 2 pi: the start of the next revolution */
        r->revolutions = hc_s32((uint32_t)r->revolutions + 1u);
    }
}

void ${pfx}_clear_fault(${pfx}_state *s)
{
    s->fault = 0u;
}
$section_defs"""
)

#: The float variant's atan2 (the lean path's ``hc_angle``; the power-up decoder has a finer
#: one for its table positions).
_FLOAT_ATAN2 = string.Template(
    r"""/* Electrical angle atan2(b, a) in Q0.32 turns${purpose}. Octant reduction, a rotation by
 * -45 degrees above 22.5 degrees, 1/x from a linear seed valid for x in [${x_lo}, ${x_hi}]
 * and ${newton} Newton step(s), an odd minimax polynomial of atan on [-tan(pi/8), tan(pi/8)]. For
 * vectors in the radius window: |error| <= ${atan_bound} rad (electrical). */
static uint32_t ${name}(float a, float b)
{
    const uint32_t ua = hc_bits(a);
    const uint32_t ub = hc_bits(b);
    const uint32_t ma = ua & 0x7FFFFFFFu; /* |a|: non-negative floats order as their bits do */
    const uint32_t mb = ub & 0x7FFFFFFFu; /* |b| */
    const uint32_t sw = (mb > ma) ? 1u : 0u;
    /* octant: a < 0, b < 0, |b| > |a| */
    const uint32_t o = ((ua >> 31) << 2) | ((ub >> 31) << 1) | sw;
    uint32_t k = o << 1;
    float x = hc_float((sw != 0u) ? mb : ma); /* max(|a|, |b|) */
    float y = hc_float((sw != 0u) ? ma : mb); /* min(|a|, |b|) */
    float rc;
    float t;
    float t2;
    uint32_t th;
    if (y > (${tan8} * x)) {
        const float xr = (x + y) * ${rsqrt2};
        y = (y - x) * ${rsqrt2};
        x = xr;
        k = k | 1u;
    }
    rc = ${c0} - (${c1} * x);
${newton_steps}
    t = y * rc;
    t2 = t * t;
    th = (uint32_t)(int32_t)(t * ${poly}); /* atan(t) 2^32 / (2 pi), |.| <= 2^29 */
    return hc_base[k] + ((((0x96u >> o) & 1u) != 0u) ? (0u - th) : th);
}
"""
)

_FLOAT_INIT = string.Template(
    r"""void ${pfx}_init(${pfx}_state *s, int32_t revolutions, float angle)
{
    float a = angle * 0.159154943f; /* turns */
    float e;
    int32_t t;
    if (!((a >= 0.0f) && (a < 1.0f))) {
        a = 0.0f;
    }
    e = a * ${n}.0f; /* electrical turns within the revolution */
    t = (int32_t)e;
    if (t > ${n_minus_1}) {
        t = ${n_minus_1};
    }
    s->rev = revolutions;
    s->turn = t;
    s->phase = (uint32_t)((e - (float)t) * 4294967296.0f);
    s->limit = 0xFFFFFFFFu; /* no step limit before the first accepted sample */
    s->held = 0u;
    s->rejected = 0u;
    s->fault = 0u;
    s->seq = 0u;
    hc_publish(s, revolutions, a, 0u);
    hc_publish(s, revolutions, a, 0u);
}
"""
)

_INIT_DECL = """\
/* Start at y = 2 pi revolutions + angle (angle in [0, 2 pi) rad, else 0); 0, 0 by convention. */
void ${pfx}_init(${pfx}_state *s, int32_t revolutions, float angle);
"""

#: The lean sample path (with the power-up decoder, it runs once the pole pair is identified).
_FLOAT_UPDATE = string.Template(
    r"""uint32_t ${pfx}_update(${pfx}_state *s, float d1, float d2, float d3)
{
    uint32_t flags;
    /* f_init: alpha, beta = P (d - o) */
${projection}
    const float r2 = (a * a) + (b * b);
    /* plausibility: each channel in its calibrated range (NaN is not), then the radius */
    if (${range_check}) {
        flags = ${PFX}_REJ_RANGE;
    } else if ((hc_bits(r2) - ${r2_lo_bits}u) <= ${r2_span_bits}u) {
        /* r2 in [${r2_lo}, ${r2_hi}] */
        const uint32_t p = hc_angle(a, b); /* electrical angle, Q0.32 turns */
        const int32_t step = hc_s32(p - s->phase);         /* wrapped into [-1/2, 1/2) turn */
        const uint32_t mag = (step < 0) ? (0u - (uint32_t)step) : (uint32_t)step;
        int32_t turn = s->turn;
        int32_t rev = s->rev;
        /* the unwrap of f_init: crossing the start of the turn moves the turn count */
        if ((step >= 0) && (p < s->phase)) {
            if (turn == ${n_minus_1}) {
                turn = 0;
                rev = hc_s32((uint32_t)rev + 1u);
            } else {
                turn = turn + 1;
            }
        } else if ((step < 0) && (p > s->phase)) {
            if (turn == 0) {
                turn = ${n_minus_1};
                rev = hc_s32((uint32_t)rev - 1u);
            } else {
                turn = turn - 1;
            }
        } else {
            /* no turn boundary crossed */
        }
        /* step limit from the last accepted sample (grown while samples are held) */
        if (mag <= s->limit) {
            /* eta from the table at f_init's angle within the revolution: interval i of
             * ${per_turn} per electrical turn, position i + f in Q16.16 */
${index}
            const float f = (float)(uint16_t)x * 1.52587891e-5f; /* 2^-16 */
            const int32_t t0 = (int32_t)hc_t[i];
            const int32_t dt = (int32_t)hc_t[i + 1u] - t0;
            /* y_star within the revolution [turns], in (-1/2, 3/2): _read brings it to [0, 1) */
            const float y = ((float)x * ${inv_m16})
                            + ((((float)t0 + (f * (float)dt))${curv}) * ${lsb});
            s->phase = p;
            s->turn = turn;
            s->rev = rev;
            s->limit = ${step_limit}u;
            s->held = 0u;
            flags = s->fault; /* 0 or ${PFX}_FAULT (latched) */
            hc_publish(s, rev, y, flags);
        } else {
            flags = ${PFX}_REJ_STEP;
        }
    } else {
        flags = ${PFX}_REJ_AMPLITUDE;
    }
    if (flags > ${PFX}_FAULT) { /* rejected: count it and hold the last reading */
        const uint32_t last = s->seq & 1u;
        if (s->rejected < 0xFFFFFFFFu) {
            s->rejected = s->rejected + 1u;
        }
        if (s->held < ${PFX}_FAULT_AFTER) {
            s->held = s->held + 1u;
        }
        if (s->held >= ${PFX}_FAULT_AFTER) {
            s->fault = ${PFX}_FAULT;
        }
        if (s->limit < 0x80000000u) {
            s->limit = s->limit + ${step_limit}u;
        }
        flags = flags | ${PFX}_HELD | s->fault;
        hc_publish(s, s->pub[last].revolutions, s->pub[last].turns, flags);
    }
    return flags;
}
"""
)

# --------------------------------------------------------------------------------------------
# C templates: fixed-point variant
# --------------------------------------------------------------------------------------------

_FIXED_H = string.Template(
    r"""$banner
#ifndef ${PFX}_Q_H
#define ${PFX}_Q_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define ${PFX}_Q_POLE_PAIRS ${n}
#define ${PFX}_Q_TABLE_POINTS ${m}
#define ${PFX}_Q_FAULT_AFTER ${fault_after}
/* Angles are Q0.32 turns: 2^32 = one revolution = 2 pi rad; one unit is this many rad: */
#define ${PFX}_Q_RAD_PER_LSB 1.4629180792671596e-9

/* Flags of a reading (bit mask). */
#define ${PFX}_Q_HELD 1u           /* this sample was rejected: the reading is the last accepted */
#define ${PFX}_Q_FAULT 2u          /* ${PFX}_Q_FAULT_AFTER rejected in a row; latched */
#define ${PFX}_Q_REJ_RANGE 4u      /* a channel outside its calibrated range */
#define ${PFX}_Q_REJ_AMPLITUDE 8u  /* alpha/beta radius outside its calibrated window */
#define ${PFX}_Q_REJ_STEP 16u      /* step from the last accepted angle above the limit */

/* One consistent reading: y_star = revolutions turns + angle / 2^32 turn. */
typedef struct {
    int32_t revolutions; /* whole revolutions (wraps after 2^31) */
    uint32_t angle;      /* within the revolution, Q0.32 turns */
    uint32_t flags;      /* of the last sample: ${PFX}_Q_HELD, ${PFX}_Q_FAULT, ${PFX}_Q_REJ_... */
    uint32_t rejected;   /* rejected samples since init (saturates) */
} ${pfx}_q_reading;

/* State of one sensor set; its members are private (use the functions). No dynamic memory. */
typedef struct {
    int32_t rev;       /* f_init: whole revolutions of its own (uncorrected) unwrap state */
    int32_t turn;      /* f_init: electrical turn within the revolution, 0 .. n_m - 1 */
    uint32_t phase;    /* f_init: electrical angle within the turn, Q0.32 mechanical turns */
    uint32_t limit;    /* step limit for the next sample, Q0.32 mechanical turns */
    uint32_t held;     /* rejected samples in a row */
    volatile uint32_t rejected; /* rejected samples since init */
    uint32_t fault;    /* ${PFX}_Q_FAULT once ${PFX}_Q_FAULT_AFTER samples in a row were rejected */
    volatile uint32_t seq; /* readings published; the last one is pub[seq & 1] */
    volatile struct {
        int32_t revolutions;
        uint32_t angle; /* Q0.32 turns */
        uint32_t flags;
    } pub[2];
} ${pfx}_q_state;

/* Start at y = revolutions + angle / 2^32 turns (0, 0 by convention). */
void ${pfx}_q_init(${pfx}_q_state *s, int32_t revolutions, uint32_t angle);

/* One sample of the three Hall signals as raw ADC counts (any int32 is safe). Returns the flags
 * of the reading it publishes (0: accepted). Constant worst-case time, 32-bit integers only. */
uint32_t ${pfx}_q_update(${pfx}_q_state *s, int32_t d1, int32_t d2, int32_t d3);

/* The last reading, consistent (revolutions and angle of the same sample) from any context:
 * the main loop while ${pfx}_q_update runs in an ISR, or an ISR that interrupts it.
 * Single core only (one writer). */
void ${pfx}_q_read(const ${pfx}_q_state *s, ${pfx}_q_reading *r);

/* Clear the latched fault flag (after the cause is removed and the angle re-referenced). */
void ${pfx}_q_clear_fault(${pfx}_q_state *s);
$section_decls
#ifdef __cplusplus
}
#endif

#endif /* ${PFX}_Q_H */
"""
)

_FIXED_C = string.Template(
    r"""$banner
#include <stdint.h>

#include "${header}"

${fixed_table}
/* floor(t 2^32 / n_m): start of electrical turn t, Q0.32 mechanical turns. */
static const uint32_t hc_turn[${n}] = {
${turn_base}
};

static int32_t hc_s32(uint32_t u) /* two's complement without implementation-defined casts */
{
    int32_t v;
    if (u <= 0x7FFFFFFFu) {
        v = (int32_t)u;
    } else {
        v = (int32_t)(u - 0x80000000u) - 0x7FFFFFFF - 1;
    }
    return v;
}

static uint32_t hc_abs(int32_t v) /* |v| for |v| < 2^31 */
{
    return (v < 0) ? (0u - (uint32_t)v) : (uint32_t)v;
}

/* Electrical angle atan2(b, a) in mechanical Q0.32 units, [0, ${period_text}) (one electrical
 * turn). Octant reduction; ${steps} CORDIC steps on magnitudes (x, |y|) with the sign of y apart,
 * so every shift is of an unsigned number; the residual angle t = y / x (|t| < 2^-${last}) as
 * t - t^3/3 with 1/x from a linear seed and two Newton steps in 16-bit products. For vectors in
 * the radius window: |error| <= ${atan_bound} rad (electrical). */
static uint32_t hc_angle(int32_t a, int32_t b)
{
    const uint32_t ua = hc_abs(a);
    const uint32_t ub = hc_abs(b);
    uint32_t x = ua;
    uint32_t y = ub;
    uint32_t neg = 0u; /* sign of the CORDIC's y: 0 positive, 0xFFFFFFFF negative */
    uint32_t z = 0u;   /* angle turned so far, mechanical units, modulo 2^32 */
    uint32_t xs;
    uint32_t ys;
    uint32_t xh;
    uint32_t r;
    uint32_t w;
    uint32_t tq;
    uint32_t c;
    uint32_t dq;
    uint32_t dm;
    int32_t th;
    uint32_t p;
    if (ub > ua) {
        x = ub;
        y = ua;
    }
${cordic_steps}
    /* residual t = (+-) y / x: 1/x on xh = x >> ${sx} in [${xh_lo}, ${xh_hi}], R ~ 2^${kr} / xh */
    xh = x >> ${sx};
    r = ${seed_a}u - ((${seed_b}u * xh) >> ${seed_shift});
    w = ${two_kr1}u - (xh * r);
    r = (r * (w >> ${kr_15})) >> 15;
    w = ${two_kr1}u - (xh * r);
    r = (r * (w >> ${kr_15})) >> 15;
    tq = (y >> ${sy}) * r;                       /* t 2^${e_tau} */
    c = tq >> ${cube_shift};
    dq = tq - ((((c * c * c) >> 8) * ${cube_mul}u) >> ${cube_post}); /* t - t^3 / 3 */
    dm = ((dq >> ${d_shift}) * ${s_mul}u) >> ${s_post};         /* in mechanical units */
    th = hc_s32((neg != 0u) ? (z - dm) : (z + dm));
    if (th < 0) {
        th = 0;
    }
    if (th > ${eighth}) {
        th = ${eighth};
    }
    p = (uint32_t)th;
    if (ub > ua) {
        p = ${quarter}u - p;
    }
    if (a < 0) {
        p = ${half_turn}u - p;
    }
    if (b < 0) {
        p = ${period}u - p;
    }
${wrap_period}
    return p;
}

static void hc_publish(${pfx}_q_state *s, int32_t rev, uint32_t angle, uint32_t flags)
{
    const uint32_t q = s->seq + 1u;
    s->pub[q & 1u].revolutions = rev;
    s->pub[q & 1u].angle = angle;
    s->pub[q & 1u].flags = flags;
    s->seq = q;
}

void ${pfx}_q_init(${pfx}_q_state *s, int32_t revolutions, uint32_t angle)
{
    uint32_t t = ((angle >> 16) * ${n}u) >> 16; /* at or below the turn of angle */
    if (t > ${n_minus_1}u) {
        t = ${n_minus_1}u;
    }
    if ((t < ${n_minus_1}u) && (hc_turn[t + 1u] <= angle)) {
        t = t + 1u;
    }
    s->rev = revolutions;
    s->turn = (int32_t)t;
    s->phase = angle - hc_turn[t];
${init_wrap}
    s->limit = 0xFFFFFFFFu; /* no step limit before the first accepted sample */
    s->held = 0u;
    s->rejected = 0u;
    s->fault = 0u;
    s->seq = 0u;
    hc_publish(s, revolutions, angle, 0u);
    hc_publish(s, revolutions, angle, 0u);
}

uint32_t ${pfx}_q_update(${pfx}_q_state *s, int32_t d1, int32_t d2, int32_t d3)
{
    uint32_t flags;
    /* plausibility: each channel in its calibrated range (unsigned: no overflow for any int32) */
    if ((((uint32_t)d1 - ${lo1}u) > ${span1}u) || (((uint32_t)d2 - ${lo2}u) > ${span2}u)
        || (((uint32_t)d3 - ${lo3}u) > ${span3}u)) {
        flags = ${PFX}_Q_REJ_RANGE;
    } else {
        /* f_init: alpha, beta = P (d - o) 2^${pshift}, with
         * P 2^${pshift} = PH 2^${kl} + PL (PL >= 0 acts on the shifted, non-negative inputs);
         * its rows sum to ${rowsum} */
        /* in unsigned (modular) arithmetic: the true values fit in int32, so no product or
         * sum can overflow anything, and hc_s32 recovers the signed results */
        const uint32_t x1 = (uint32_t)d1 - ${c1}u;
        const uint32_t x2 = (uint32_t)d2 - ${c2}u;
        const uint32_t x3 = (uint32_t)d3 - ${c3}u;
        const uint32_t y1 = x1 + ${xb}u; /* x + xb >= 0: x is within the channel range */
        const uint32_t y2 = x2 + ${xb}u;
        const uint32_t y3 = x3 + ${xb}u;
        const uint32_t la = (((${l00}u * y1) + (${l01}u * y2)) + (${l02}u * y3)) >> ${kl};
        const uint32_t lb = (((${l10}u * y1) + (${l11}u * y2)) + (${l12}u * y3)) >> ${kl};
        const uint32_t ha = ((${p00}u * x1) + (${p01}u * x2)) + (${p02}u * x3);
        const uint32_t hb = ((${p10}u * x1) + (${p11}u * x2)) + (${p12}u * x3);
        const int32_t a = hc_s32((ha + la) - ${a0}u);
        const int32_t b = hc_s32((hb + lb) - ${b0}u);
        const uint32_t as = hc_abs(a) >> 15;
        const uint32_t bs = hc_abs(b) >> 15;
        const uint32_t r2 = (as * as) + (bs * bs);
        if ((r2 < ${r2_lo}u) || (r2 > ${r2_hi}u)) {
            flags = ${PFX}_Q_REJ_AMPLITUDE;
        } else {
            const uint32_t p = hc_angle(a, b);
            int32_t turn = s->turn;
            int32_t rev = s->rev;
            uint32_t mag;
${unwrap}
            /* step limit from the last accepted sample (grown while samples are held) */
            if (mag <= s->limit) {
                /* eta(u) from the table at f_init's angle u within the revolution */
                const uint32_t u = hc_turn[turn] + p;
${fixed_index}
${fixed_eta}
                const uint32_t out = (u + (acc >> ${eshift})) - ${ebias}u;
                int32_t out_rev = rev;
                if (acc >= 0x80000000u) {
                    if (out < u) {
                        out_rev = hc_s32((uint32_t)out_rev + 1u);
                    }
                } else if (out > u) {
                    out_rev = hc_s32((uint32_t)out_rev - 1u);
                } else {
                    /* within the revolution */
                }
                s->phase = p;
                s->turn = turn;
                s->rev = rev;
                s->limit = ${step_limit}u;
                s->held = 0u;
                flags = s->fault; /* 0 or ${PFX}_Q_FAULT (latched) */
                hc_publish(s, out_rev, out, flags);
            } else {
                flags = ${PFX}_Q_REJ_STEP;
            }
        }
    }
    if (flags > ${PFX}_Q_FAULT) { /* rejected: count it and hold the last reading */
        const uint32_t last = s->seq & 1u;
        if (s->rejected < 0xFFFFFFFFu) {
            s->rejected = s->rejected + 1u;
        }
        if (s->held < ${PFX}_Q_FAULT_AFTER) {
            s->held = s->held + 1u;
        }
        if (s->held >= ${PFX}_Q_FAULT_AFTER) {
            s->fault = ${PFX}_Q_FAULT;
        }
        if (s->limit < ${limit_cap}u) {
            s->limit = s->limit + ${step_limit}u;
        }
        flags = flags | ${PFX}_Q_HELD | s->fault;
        hc_publish(s, s->pub[last].revolutions, s->pub[last].angle, flags);
    }
    return flags;
}

void ${pfx}_q_read(const ${pfx}_q_state *s, ${pfx}_q_reading *r)
{
    uint32_t before;
    uint32_t after;
    do {
        before = s->seq;
        r->revolutions = s->pub[before & 1u].revolutions;
        r->angle = s->pub[before & 1u].angle;
        r->flags = s->pub[before & 1u].flags;
        after = s->seq;
    } while ((after - before) > 1u);
    r->rejected = s->rejected;
}

void ${pfx}_q_clear_fault(${pfx}_q_state *s)
{
    s->fault = 0u;
}
$section_defs"""
)

_CORDIC_STEP = """\
    /* step {i}: rotate by -+atan(2^-{i}) towards the x axis */
    xs = x >> {i}u;
    ys = y >> {i}u;
    x = x + ys;
    z = (neg != 0u) ? (z - {atan}u) : (z + {atan}u);
    if (y >= xs) {{
        y = y - xs;
    }} else {{
        y = xs - y;
        neg = ~neg;
    }}"""

_UNWRAP_N = """\
            /* the unwrap of f_init: the step wrapped into [-1/2, 1/2) electrical turn */
            int32_t step = hc_s32(p - s->phase);
            if (step >= {half}) {{
                step = step - {period};
                if (turn == 0) {{
                    turn = {n_minus_1};
                    rev = hc_s32((uint32_t)rev - 1u);
                }} else {{
                    turn = turn - 1;
                }}
            }} else if (step < -{half}) {{
                step = step + {period};
                if (turn == {n_minus_1}) {{
                    turn = 0;
                    rev = hc_s32((uint32_t)rev + 1u);
                }} else {{
                    turn = turn + 1;
                }}
            }} else {{
                /* no turn boundary crossed */
            }}
            mag = hc_abs(step);"""

_UNWRAP_1 = """\
            /* the unwrap of f_init for one pole pair: the step modulo 2^32 in [-1/2, 1/2) turn */
            const int32_t step = hc_s32(p - s->phase);
            if ((step >= 0) && (p < s->phase)) {
                rev = hc_s32((uint32_t)rev + 1u);
            } else if ((step < 0) && (p > s->phase)) {
                rev = hc_s32((uint32_t)rev - 1u);
            } else {
                /* no revolution boundary crossed */
            }
            mag = (step < 0) ? (0u - (uint32_t)step) : (uint32_t)step;"""


# --------------------------------------------------------------------------------------------
# Assembling the variants
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Context:
    """What every piece of a variant needs."""

    artifact: Mapping[str, Any]
    design: FirmwareDesign
    pfx: str
    PFX: str
    variant: str  # "float" or "fixed"
    subs: Mapping[str, Any] = field(default_factory=dict)  # the lean templates' substitutions
    powerup: Any = None  # hallcal.output.firmware.PowerUpFirmware


def _int_sub(var: str, value: int) -> str:
    """``var - value`` for 0 < value <= 2^31 without a literal outside int32."""
    if value >= 2**31:
        return f"({var} - 2147483647) - 1"
    return f"{var} - {value}"


def _int_add(var: str, value: int) -> str:
    if value >= 2**31:
        return f"({var} + 2147483647) + 1"
    return f"{var} + {value}"


def _f32_down(v: float) -> np.float32:
    x = np.float32(v)
    return x if float(x) <= v else np.nextafter(x, np.float32(-np.inf))


def _f32_up(v: float) -> np.float32:
    x = np.float32(v)
    return x if float(x) >= v else np.nextafter(x, np.float32(np.inf))


def _bits(x: np.float32) -> int:
    return int(np.array(x, dtype=np.float32).view(np.uint32))


def _range_check(lo: NDArray, hi: NDArray) -> str:
    """C expression, true when a channel is outside its range (or not a number).

    Ranges of positive numbers compare the IEEE bit patterns as unsigned integers (their order
    is the numbers' order; negative numbers and NaN fall outside); ranges about zero compare
    the magnitude's bit pattern (the range is widened to be symmetric when its centre is within
    5 % of its half width); other ranges compare as floats.
    """
    parts = []
    for h in range(3):
        d = f"d{h + 1}"
        lo_f, hi_f = _f32_down(lo[h]), _f32_up(hi[h])
        mid, half = 0.5 * (lo[h] + hi[h]), 0.5 * (hi[h] - lo[h])
        for v in (lo_f, hi_f):
            _f32(float(v), "channel range")
        if lo_f > 0:
            lob = _bits(lo_f)
            parts.append(f"((hc_bits({d}) - {lob}u) > {_bits(hi_f) - lob}u)")
        elif lo_f < 0 < hi_f and abs(mid) <= 0.05 * half:
            m = _f32_up(max(-float(lo_f), float(hi_f)))
            parts.append(f"((hc_bits({d}) & 0x7FFFFFFFu) > {_bits(m)}u)")
        else:
            parts.append(f"(!(({d} >= {_cf(float(lo_f))}) && ({d} <= {_cf(float(hi_f))})))")
    return "\n        || ".join(parts)


def _atan2_c(
    name: str, purpose: str, x_lo: float, x_hi: float, seed: tuple[float, float], newton: int,
    poly_turns: NDArray[np.float64], atan_bound: float,
) -> str:  # fmt: skip
    """A float atan2 (Q0.32 turns out) with its own reciprocal seed, Newton steps and polynomial
    (coefficients of atan in turns, odd powers ascending)."""
    steps = "\n".join(
        ["    {", "        float u;"]
        + ["        u = 1.0f - (x * rc);\n        rc = rc + (rc * u);"] * newton
        + ["    }"]
    )
    scaled = poly_turns * 2.0**32
    poly = _cf(scaled[-1])
    for c in scaled[-2::-1]:
        poly = f"({_cf(c)} + (t2 * {poly}))"
    return _FLOAT_ATAN2.substitute(
        name=name,
        purpose=purpose,
        x_lo=f"{x_lo:.6g}",
        x_hi=f"{x_hi:.6g}",
        newton=newton,
        atan_bound=f"{atan_bound:.2e}",
        tan8=_cf(_TAN_PI_8),
        rsqrt2=_cf(math.sqrt(0.5)),
        c0=_cf(seed[0], "reciprocal seed"),
        c1=_cf(seed[1], "reciprocal seed"),
        newton_steps=steps,
        poly=poly,
    )


#: Insertion points of the float variant's templates an optional Section may fill (``hooks``;
#: ``state_members`` go after the lean members, whose offsets stay those of the lean build).
#: ``init_decl`` and ``init_def`` replace the default ``init`` (angle given: homing);
#: ``update_dispatch`` is ``(condition, function)``-like text "cond|name": while the condition
#: holds, ``update`` hands the sample to that function instead of running the lean path.
FLOAT_HOOKS = (
    "api_macros", "reading_members", "state_members", "init_decl", "init_def",
    "read_locals", "read_copy", "read_after", "before_update", "update_dispatch",
)  # fmt: skip


def _float_subs(ctx: _Context, fn: _FloatNumbers) -> dict[str, Any]:
    """The substitutions of the lean float templates (shared with the optional sections)."""
    d = ctx.design
    n, m = d.pole_pairs, d.table.points
    P, o = d.projection, d.offset
    if d.rejects_common_mode:
        ab0 = P @ o
        projection = "\n".join(
            [
                "    const float e1 = d2 - d1; /* the rows of P sum to zero: P (d - o) = "
                "P01 e1 + P02 e2 - P o */",
                "    const float e2 = d3 - d1;",
                f"    const float a = (({_cf(P[0, 1])} * e1) + ({_cf(P[0, 2])} * e2)) - "
                f"{_cf(ab0[0], 'P o')};",
                f"    const float b = (({_cf(P[1, 1])} * e1) + ({_cf(P[1, 2])} * e2)) - "
                f"{_cf(ab0[1], 'P o')};",
            ]
        )
    else:
        ab0 = P @ o
        projection = "\n".join(
            [
                f"    const float a = ((({_cf(P[0, 0])} * d1) + ({_cf(P[0, 1])} * d2)) + "
                f"({_cf(P[0, 2])} * d3)) - {_cf(ab0[0], 'P o')};",
                f"    const float b = ((({_cf(P[1, 0])} * d1) + ({_cf(P[1, 1])} * d2)) + "
                f"({_cf(P[1, 2])} * d3)) - {_cf(ab0[1], 'P o')};",
            ]
        )
    t = d.table
    pl = d.plausibility
    kbits = (m // n).bit_length() - 1  # M = n 2^k
    values = list(t.values) + [t.values[0]]  # T[M] = T[0]: the wrap-around without a branch
    if t.quadratic:
        table_decl = (
            f"/* eta table of f_star: value T[i] (int16) at mechanical angle i / {m} turn and "
            f"curvature\n * C[i] (int8) of interval i: eta = (T[i] (1 - f) + T[i+1] f + "
            f"2^{t.curvature_shift} C[i] f (1 - f)) 2^-{t.shift} turn\n"
            " * (T[M] = T[0]). */\n"
            f"static const int16_t hc_t[{m + 1}] = {{\n"
            + _c_list([str(int(v)) for v in values], 12)
            + f"\n}};\nstatic const int8_t hc_c[{m}] = {{\n"
            + _c_list([str(int(v)) for v in t.curvature], 16)
            + "\n};"
        )
        curv = (
            "\n                 + ((f - (f * f)) * "
            f"((float)hc_c[i] * {_cf(2.0**t.curvature_shift, 'table unit')}))"
        )
    else:
        table_decl = (
            f"/* eta table of f_star: value T[i] (int16) at mechanical angle i / {m} turn, "
            f"linear in\n * between: eta = (T[i] (1 - f) + T[i+1] f) 2^-{t.shift} turn "
            "(T[M] = T[0]). */\n"
            f"static const int16_t hc_t[{m + 1}] = {{\n"
            + _c_list([str(int(v)) for v in values], 12)
            + "\n};"
        )
        curv = ""
    index = (
        f"            const uint32_t x = ((uint32_t)turn << {kbits + 16}) + (p >> {16 - kbits});\n"
        "            const uint32_t i = x >> 16;"
    )
    curv = curv.replace("\n                 + ", "\n                             + ")
    x_lo = math.cos(math.pi / 8.0) * pl.radius_lo
    return dict(
        header=f"{ctx.pfx}.h",
        pfx=ctx.pfx,
        PFX=ctx.PFX,
        m=m,
        m1=m + 1,
        table_decl=table_decl,
        atan2_fn=_atan2_c(
            "hc_angle", "", x_lo, pl.radius_hi, fn.seed, fn.newton, fn.poly, fn.atan_bound
        ),  # fmt: skip
        n=n,
        n_minus_1=n - 1,
        projection=projection,
        range_check=_range_check(fn.lo, fn.hi),
        r2_lo=_cf(float(_f32_down(fn.r2_lo)), "radius window"),
        r2_hi=_cf(float(_f32_up(fn.r2_hi)), "radius window"),
        r2_lo_bits=_bits(_f32_down(fn.r2_lo)),
        r2_span_bits=_bits(_f32_up(fn.r2_hi)) - _bits(_f32_down(fn.r2_lo)),
        step_limit=int(math.floor(pl.step_limit * 2.0**32)),
        per_turn=m // n,
        index=index,
        curv=curv,
        lsb=_cf(2.0**-t.shift, "table unit"),
        inv_m16=_cf(1.0 / m / 65536.0),
    )


def _hooks(secs: Sequence[Section], names: Sequence[str]) -> dict[str, str]:
    """The sections' texts per insertion point (concatenated; empty where none fills it)."""
    out = dict.fromkeys(names, "")
    for sec in secs:
        for key, text in sec.hooks.items():
            if key not in out:
                raise ValueError(f"unknown hook {key!r} of section {sec.name!r}")
            out[key] += text
    return out


def _float_header(ctx: _Context, banner: str, secs: Sequence[Section]) -> str:
    d = ctx.design
    hooks = _hooks(secs, FLOAT_HOOKS)
    init_decl = hooks["init_decl"] or string.Template(_INIT_DECL).substitute(
        pfx=ctx.pfx, PFX=ctx.PFX
    )
    return _FLOAT_H.substitute(
        banner=banner,
        pfx=ctx.pfx,
        PFX=ctx.PFX,
        n=d.pole_pairs,
        m=d.table.points,
        fault_after=d.plausibility.fault_after,
        section_decls="".join(s.header for s in secs),
        api_macros=hooks["api_macros"],
        reading_members=hooks["reading_members"],
        state_members=hooks["state_members"],
        init_decl=init_decl,
    )


def _float_source(ctx: _Context, banner: str, secs: Sequence[Section]) -> str:
    subs = dict(ctx.subs)
    hooks = _hooks(secs, FLOAT_HOOKS)
    update = _FLOAT_UPDATE.substitute(subs)
    if hooks["update_dispatch"]:
        # the lean path in an else branch; while the condition holds, the other function
        cond, func = hooks["update_dispatch"].split("|")
        head, rest = update.split("    uint32_t flags;\n", 1)
        body, tail = rest.rsplit("    return flags;\n", 1)
        update = (
            head
            + "    uint32_t flags;\n"
            + f"    if ({cond}) {{\n"
            + f"        flags = {func}(s, d1, d2, d3);\n"
            + "    } else {\n"
            + "\n".join(("    " + line) if line else line for line in body.split("\n"))
            + "    }\n    return flags;\n"
            + tail
        )
    return _FLOAT_C.substitute(
        subs,
        banner=banner,
        init_def=hooks["init_def"] or _FLOAT_INIT.substitute(subs),
        before_update=hooks["before_update"],
        update_def=update,
        read_locals=hooks["read_locals"],
        read_copy=hooks["read_copy"],
        read_after=hooks["read_after"],
        section_defs="".join(s.source for s in secs),
    )


def _fixed_source(ctx: _Context, q: _FixedNumbers, banner: str, defs: str) -> str:
    d = ctx.design
    n, t = d.pole_pairs, d.table
    m = t.points
    kbits = (m // n).bit_length() - 1  # M = n 2^k
    steps = "\n".join(_CORDIC_STEP.format(i=i, atan=q.cordic[i]) for i in range(CORDIC_STEPS))
    if n == 1:
        unwrap = _UNWRAP_1
        wrap_period = "    /* one pole pair: the electrical turn is the whole 2^32 */"
        init_wrap = "    /* one pole pair: the phase is the angle */"
        period_text = "2^32"
    else:
        unwrap = (
            _UNWRAP_N.format(half=q.half, period=q.period, n_minus_1=n - 1)
            .replace(f"step - {q.period};", _int_sub("step", q.period) + ";")
            .replace(f"step + {q.period};", _int_add("step", q.period) + ";")
        )
        wrap_period = f"    if (p >= {q.period}u) {{\n        p = p - {q.period}u;\n    }}"
        init_wrap = (
            f"    if (s->phase >= {q.period}u) {{\n        s->phase = {q.period - 1}u;\n    }}"
        )
        period_text = str(q.period)
    eshift = t.shift - 16
    rowsum = "zero" if d.rejects_common_mode else "the float rows' sums"
    values = list(t.values) + [t.values[0]]  # T[M] = T[0]
    tb = _c_list([f"{int(v) + 32768}u" for v in values], 12)
    if t.quadratic:
        fixed_table = (
            "/* eta table of f_star, offset binary: value TB[i] - 32768 at mechanical angle "
            f"i / {m} turn\n * and curvature CB[i] - 128 of interval i, in units of 2^-{t.shift} "
            f"turn (curvature 2^{t.curvature_shift}\n * units): eta = (T[i] (1 - f) + T[i+1] f + "
            f"2^{t.curvature_shift} C[i] f (1 - f)) 2^-{t.shift} turn, T[M] = T[0]. */\n"
            f"static const uint16_t hc_t[{m + 1}] = {{\n{tb}\n}};\n"
            f"static const uint8_t hc_c[{m}] = {{\n"
            + _c_list([f"{int(v) + 128}u" for v in t.curvature], 16)
            + "\n};"
        )
        fixed_eta = (
            "                const uint32_t g = (f * (65536u - f)) >> 16;\n"
            "                const uint32_t acc = ((((uint32_t)hc_t[i] * (65536u - f))\n"
            "                                       + ((uint32_t)hc_t[i + 1u] * f))\n"
            "                                      + (((uint32_t)hc_c[i] * g) << "
            f"{t.curvature_shift}))\n"
            f"                                     - (g << {t.curvature_shift + 7});"
        )
    else:
        fixed_table = (
            "/* eta table of f_star, offset binary: value TB[i] - 32768 at mechanical angle "
            f"i / {m} turn,\n * in units of 2^-{t.shift} turn, linear in between: eta = (T[i] "
            f"(1 - f) + T[i+1] f) 2^-{t.shift} turn,\n * T[M] = T[0]. */\n"
            f"static const uint16_t hc_t[{m + 1}] = {{\n{tb}\n}};"
        )
        fixed_eta = (
            "                const uint32_t acc = ((uint32_t)hc_t[i] * (65536u - f))\n"
            "                                     + ((uint32_t)hc_t[i + 1u] * f);"
        )
    # interval i = turn 2^k + the electrical fraction's top k bits; the electrical fraction is
    # p n / 2^32 (p < 2^32 / n: no overflow), f its next 16 bits
    if kbits == 0:
        fixed_index = (
            f"                const uint32_t e = p * {n}u; /* electrical angle, Q0.32 turns */\n"
            "                const uint32_t i = (uint32_t)turn;\n"
            "                const uint32_t f = e >> 16;"
        )
    else:
        fixed_index = (
            f"                const uint32_t e = p * {n}u; /* electrical angle, Q0.32 turns */\n"
            f"                const uint32_t i = ((uint32_t)turn << {kbits})"
            f" + (e >> {32 - kbits});\n"
            f"                const uint32_t f = (e >> {16 - kbits}) & 0xFFFFu;"
        )
    return _FIXED_C.substitute(
        banner=banner,
        header=f"{ctx.pfx}_q.h",
        pfx=ctx.pfx,
        PFX=ctx.PFX,
        m=m,
        mask=m - 1,
        n=n,
        n_minus_1=n - 1,
        tshift=t.shift,
        kc=t.curvature_shift,
        kc7=t.curvature_shift + 7,
        table=_c_list([f"{int(v) + 32768}u" for v in t.values], 12),
        curv=_c_list([f"{int(v) + 128}u" for v in t.curvature], 16),
        turn_base=_c_list([_cu(v) for v in q.turn_base], 6),
        period_text=period_text,
        steps=CORDIC_STEPS,
        last=CORDIC_STEPS - 1,
        atan_bound=f"{q.atan_bound:.2e}",
        cordic_steps=steps,
        sx=q.sx,
        xh_lo="computed",
        xh_hi="2^16",
        kr=q.kr,
        seed_a=q.seed_a,
        seed_b=q.seed_b,
        seed_shift=q.seed_shift,
        two_kr1=1 << (q.kr + 1),
        kr_15=q.kr - 15,
        sy=q.sy,
        e_tau=q.kr + q.sx - q.sy,
        cube_shift=q.cube_shift,
        cube_mul=q.cube_mul,
        cube_post=q.cube_post,
        d_shift=q.d_shift,
        s_mul=q.s_mul,
        s_post=q.s_post,
        eighth=q.eighth,
        quarter=q.quarter,
        half_turn=q.half if n > 1 else 1 << 31,
        period=q.period,
        wrap_period=wrap_period,
        init_wrap=init_wrap,
        lo1=q.lo[0] % _U32,
        span1=q.hi[0] - q.lo[0],
        lo2=q.lo[1] % _U32,
        span2=q.hi[1] - q.lo[1],
        lo3=q.lo[2] % _U32,
        span3=q.hi[2] - q.lo[2],
        limit_cap=(q.half if n > 1 else 1 << 31),
        pshift=q.proj_shift,
        rowsum=rowsum,
        c1=q.centre[0] % _U32,
        c2=q.centre[1] % _U32,
        c3=q.centre[2] % _U32,
        p00=q.proj_hi[0][0] % _U32,
        p01=q.proj_hi[0][1] % _U32,
        p02=q.proj_hi[0][2] % _U32,
        p10=q.proj_hi[1][0] % _U32,
        p11=q.proj_hi[1][1] % _U32,
        p12=q.proj_hi[1][2] % _U32,
        l00=q.proj_lo[0][0],
        l01=q.proj_lo[0][1],
        l02=q.proj_lo[0][2],
        l10=q.proj_lo[1][0],
        l11=q.proj_lo[1][1],
        l12=q.proj_lo[1][2],
        a0=q.a0[0] % _U32,
        b0=q.a0[1] % _U32,
        kl=q.lo_shift,
        xb=q.bias,
        r2_lo=q.r2_lo,
        r2_hi=q.r2_hi,
        unwrap=unwrap,
        step_limit=q.step_limit,
        fixed_table=fixed_table,
        fixed_index=fixed_index,
        fixed_eta=fixed_eta,
        eshift=eshift,
        ebias=(1 << 31) >> eshift,
        section_defs=defs,
    )


# --------------------------------------------------------------------------------------------
# Optional sections
# --------------------------------------------------------------------------------------------

_ANTICOGGING_C = string.Template(
    r"""
/* Anticogging feed-forward (artifact key "cogging"): T_c(y0) = sum_k a_k cos(k y0) + b_k sin(k y0)
 * [${unit}], k = ${orders}; ${points} values over one revolution, cubic interpolation
 * through the four nearest (T[-1] and T[N], T[N+1] repeat the other end). Largest |T_c|:
 * ${scale}; |table - map| <= ${error} (${relative} relative). In single precision the table
 * position carries the angle's rounding, 2^-24 of a revolution (3.7e-7 rad), which moves T_c by
 * up to ${slope_error} (its largest slope times that), and the sum about 1e-7 relative. */
static const float hc_cog[${points3}] = {
${values}
};

float ${pfx}_anticogging(float angle)
{
    float a = angle;
    float q;
    float u;
    int32_t r;
    uint32_t i;
    float t;
    if (!((a > -1.0e5f) && (a < 1.0e5f))) { /* NaN, infinite or far beyond one revolution */
        a = 0.0f;
    }
    /* to one revolution: a - 2 pi floor(a / 2 pi), with 2 pi = 6.28125 + 1.93530717e-3 (the
     * first part has 8 significant bits, so r times it is exact) */
    q = a * 0.159154937f;
    r = (int32_t)q;
    if (q < (float)r) {
        r = r - 1; /* floor */
    }
    a = (a - ((float)r * 6.28125f)) - ((float)r * 1.93530717e-3f);
    u = a * ${n_over_2pi}; /* table position, ${points} per revolution */
    if (!((u >= 0.0f) && (u < ${points}.0f))) {
        u = 0.0f; /* rounding at the revolution boundary */
    }
    i = (uint32_t)u;
    t = u - (float)i;
    {
        const float tm = t - 1.0f;
        const float tp = t + 1.0f;
        const float t2 = t - 2.0f;
        return (((-0.166666672f * t) * (tm * t2)) * hc_cog[i])
               + (((0.5f * tp) * (tm * t2)) * hc_cog[i + 1u])
               + (((-0.5f * tp) * (t * t2)) * hc_cog[i + 2u])
               + (((0.166666672f * tp) * (t * tm)) * hc_cog[i + 3u]);
    }
}
"""
)


def _anticogging_section(ctx: _Context) -> Section | None:
    """``<prefix>_anticogging(angle)`` in the float variant when the artifact has "cogging"."""
    if ctx.variant != "float":
        return None
    from hallcal.output.firmware import cogging_table

    tab = cogging_table(ctx.artifact["cogging"], source="calibration artifact")
    m = tab.points
    vals = list(tab.values)
    ext = [vals[-1], *vals, vals[0], vals[1]]
    orders = ", ".join(str(int(k)) for k in tab.orders[:12]) + (
        ", ..." if tab.orders.size > 12 else ""
    )
    unit = comment_text(tab.unit or "artifact unit", limit=40)
    source = _ANTICOGGING_C.substitute(
        unit=unit,
        orders=orders,
        points=m,
        points3=m + 3,
        scale=f"{tab.scale:.6g}",
        error=f"{tab.error:.2e}",
        relative=f"{tab.error / tab.scale:.1e}",
        slope_error=f"{tab.slope * 2.0 * TWO_PI * 2.0**-24:.1e}",
        values=_c_list([_cf(float(v), "anticogging table") for v in ext], 6),
        pfx=ctx.pfx,
        n_over_2pi=_cf(m / TWO_PI),
    )
    header = (
        "\n/* Anticogging feed-forward T_c(y0) [" + unit + "] at the mechanical angle y0 [rad]\n"
        " * (the reading's angle within the revolution; other values are reduced to it), from a\n"
        f" * table of {m} floats in flash: within {tab.error / tab.scale:.1e} of the calibration's "
        "map\n * relative to its largest value. */\n"
        f"float {ctx.pfx}_anticogging(float angle);\n"
    )
    notes = (
        f"Anticogging: {ctx.pfx}_anticogging(angle), {m} floats ({4 * (m + 3)} bytes), "
        f"{tab.error / tab.scale:.1e} relative to the map",
    )
    return Section("anticogging", header, source, notes)


# --------------------------------------------------------------------------------------------
# Optional section: power-up identification of the pole pair (float variant)
# --------------------------------------------------------------------------------------------

#: Largest error of the decoder's own atan2 polynomial [rad, electrical]; with the conversion to
#: Q0.32 turns the table position is within about 1e-7 rad (the lean atan2 may be 100 times
#: coarser: its error moves a hypothesis's cost by up to 3e-3 per sample at the bench's slopes).
POWERUP_ATAN2_POLY = 1e-8
#: Stated relative error of one term exp(-v / 2) of the lock rule as the C computes it (the
#: rounding of v / (2 ln 2), 6e-8 relative on exponents up to ~30, i.e. 1.2e-6; the polynomial
#: 2.5e-9; Horner and the product 3 roundings), checked by tests/test_codegen_powerup.py.
POWERUP_TERM_ERROR = 2e-6

_PU_INIT = string.Template(
    r"""static void hc_publish_id(${pfx}_state *s, int32_t rev, float turns, uint32_t flags,
                          uint32_t ident)
{
    const uint32_t q = s->seq + 1u;
    s->pub[q & 1u].revolutions = rev;
    s->pub[q & 1u].turns = turns;
    s->pub[q & 1u].flags = flags;
    s->pub_ident[q & 1u] = ident;
    s->seq = q;
}

void ${pfx}_init(${pfx}_state *s)
{
    s->rev = 0; /* f_init from y = 0 before the first sample, as the calibration run */
    s->turn = 0;
    s->phase = 0u;
    s->limit = 0xFFFFFFFFu; /* no step limit before the first accepted sample */
    s->held = 0u;
    s->rejected = 0u;
    s->fault = 0u;
    s->locked = 0u;
    s->best = 0u;
    s->samples = 0u; /* lam is set by the first sample of evidence (no loop: no memset) */
    s->seq = 0u;
    hc_publish_id(s, 0, 0.0f, 0u, 0u);
    hc_publish_id(s, 0, 0.0f, 0u, 0u);
}
"""
)

_PU_C = string.Template(
    r"""
/* ---- Power-up identification of the pole pair (artifact key "identifiability") ----
 * The decoder of hallcal.sensor.absolute (module doc, "Decoder specification"; the Python
 * reference is PowerUpIdentifier), in noise-sigma units (sigma = ${sigma} artifact units): R[q] and
 * Z[q] are the model flux's alpha/beta radius and its component along the projection's null
 * vector at the calibration frame's f_init angle 2 pi q / M, M = ${n} x ${grid}, divided by sigma;
 * R[M] = R[0], Z[M] = Z[0] (the wrap-around without a branch). ${table_bytes} bytes. */
static const float hc_pu_r[${m1}] = {
${radius}
};
static const float hc_pu_z[${m1}] = {
${zero}
};

${atan2_fine}
/* 2^-x for x >= 0: the integer part k goes into the exponent bits (exact), 2^-f of the fraction
 * f = x - k is a polynomial (relative error ${exp2_error}); 0 for x >= ${cut} (below 2^-${cut}). */
static float hc_exp2m(float x)
{
    float r = 0.0f;
    if (x < ${cut}.0f) {
        const uint32_t k = (uint32_t)x; /* floor: x >= 0 */
        const float f = x - (float)k;   /* exact: x < 2^7 has at most 17 fraction bits */
        r = ${exp2_poly} * hc_float((127u - k) << 23);
    }
    return r;
}

/* The lock rule (step 7): 1 when W = sum_(j != best) exp(-lam_j / 2) <= alpha / (1 - alpha), i.e.
 * the posterior 1 / (1 + W) of the best pole pair is at least 1 - alpha = ${confidence}. exp is
 * taken in base 2, exp(-v / 2) = 2^-(v / (2 ln 2)), with hc_exp2m: each term within ${term_error}
 * relative, so the rule differs from the exact one only when W is within that of the threshold
 * (ln W within it of ln(alpha / (1 - alpha))). */
static uint32_t hc_lock_rule(const float lam[${n}], uint32_t best)
{
    float w = 0.0f;
    uint32_t j;
    for (j = 0u; j < ${n}u; j = j + 1u) {
        if (j != best) {
            w = w + hc_exp2m(lam[j] * 0.72134752f);
        }
    }
    return (w <= ${theta}) ? 1u : 0u;
}

/* One sample of evidence (steps 4 to 7 of the specification): the cost of every pole-pair
 * hypothesis j (squared Mahalanobis distance of the sample to the model curve of j, the tangent
 * projected out, censored at ${cap_text}), the maximum-likelihood choice, and the lock rule
 * sum_(j != best) exp(-Lambda_j / 2) <= alpha / (1 - alpha) = ${theta_text}, evaluated in base 2
 * (exp(-L / 2) = 2^-(L / (2 ln 2))): no library call. a, b: alpha/beta; r2 = a^2 + b^2 (in the
 * amplitude window); zeta in sigmas; turn, p: f_init's electrical turn and angle (the fine atan2).
 * n_m hypotheses: a loop of ${n} iterations, no other data-dependent work. */
static void hc_evidence(${pfx}_state *s, float a, float b, float r2, float zeta, uint32_t turn,
                        uint32_t p)
{
    float y = ${rs_c0} - (${rs_c1} * r2); /* 1/sqrt(r2): linear seed, Newton */
    float c;
    float sn;
    float rho;
${gram_decls}    float f;
    float lmin;
    uint32_t e;
    uint32_t lo;
    uint32_t j;
    uint32_t best = 0u;
${rsqrt_steps}
    c = a * y; /* cos and sin of the electrical angle */
    sn = b * y;
    rho = (r2 * y) * ${inv_sigma}; /* radius in sigmas */
    /* the metric S in the frame (u, v, n) of this angle${gram_note} */
${gram_calc}
    /* table position of hypothesis j: electrical turn (turn + j) mod n_m, then the angle */
    e = turn;
    lo = p >> ${g_shift};                             /* interval within the turn */
    f = (float)((p << ${g}) >> 8) * 5.96046448e-8f; /* fraction, 2^-24 */
    for (j = 0u; j < ${n}u; j = j + 1u) {
        const uint32_t i = (e << ${g}) + lo;
        const float r0 = hc_pu_r[i];
        const float z0 = hc_pu_z[i];
        const float dr = hc_pu_r[i + 1u] - r0;
        const float dz = hc_pu_z[i + 1u] - z0;
        const float rj = r0 + (f * dr);    /* R_j, Z_j */
        const float zj = z0 + (f * dz);
        const float tr = dr * ${slope};    /* dR_j, dZ_j per electrical rad */
        const float tz = dz * ${slope};
        const float ea = rho - rj;         /* residual r = ea u + eb n */
        const float eb = zeta - zj;
        /* tangent t = dR u + R v + dZ n: <t, u>, <t, v>, <t, n> in the metric S */
${tangent_calc}
        float q = ${tt_c0} - (${tt_c1} * tt); /* 1/tt: seed on [${tt_lo}, ${tt_hi}], Newton */
        float cost;
${tt_steps}
        cost = rr - ((rt * rt) * q);
        if (cost > ${cap}) {
            cost = ${cap};
        }
        s->lam[j] = (s->samples != 0u) ? (s->lam[j] + cost) : cost; /* 0 + cost, exactly */
        e = (e == ${n_minus_1}u) ? 0u : (e + 1u);
    }
    s->samples = s->samples + 1u;
    lmin = s->lam[0];
    for (j = 1u; j < ${n}u; j = j + 1u) {
        if (s->lam[j] < lmin) {
            lmin = s->lam[j];
            best = j;
        }
    }
    for (j = 0u; j < ${n}u; j = j + 1u) {
        s->lam[j] = s->lam[j] - lmin;
    }
    s->best = best;
    s->locked = hc_lock_rule(s->lam, best);
}

"""
)


def _pu_newton(var: str, expr: str, steps: int, indent: str) -> str:
    return "\n".join(f"{indent}{var} = {expr};" for _ in range(steps))


def _powerup_identify(ctx: _Context) -> str:
    """``<prefix>_identify_sample``: the lean sample path with the evidence and the output in
    the frame of the current maximum-likelihood pole pair, derived from the lean template's
    text (so the checks, the unwrap and the table are literally the lean path's)."""
    n = ctx.design.pole_pairs
    text = _FLOAT_UPDATE.template

    def swap(old: str, new: str) -> None:
        nonlocal text
        if text.count(old) != 1:  # pragma: no cover - guards the template's shape
            raise AssertionError(f"the lean update template changed: {old[:60]!r}")
        text = text.replace(old, new)

    swap(
        "uint32_t ${pfx}_update(${pfx}_state *s, float d1, float d2, float d3)\n{",
        "/* The sample path until the pole pair is identified: the lean path's checks and f_init,\n"
        " * the evidence of every hypothesis, and the output in the frame of the current\n"
        " * maximum-likelihood pole pair; once identified, the state moves to that frame for good\n"
        " * and the lean path takes over. */\n"
        "uint32_t ${pfx}_identify_sample(${pfx}_state *s, float d1, float d2, float d3)\n{",
    )
    swap(
        "        if (mag <= s->limit) {\n",
        "        if (mag <= s->limit) {\n"
        "            /* zeta: along the projection's null vector, in sigmas */\n"
        "            const float zeta = ${zeta};\n"
        "            int32_t oturn;\n"
        "            int32_t orev = rev;\n"
        "            uint32_t ident;\n"
        "            hc_evidence(s, a, b, r2, zeta, (uint32_t)turn, p);\n"
        "            ident = s->best;\n"
        "            oturn = turn + (int32_t)ident; /* the output in the frame of the best */\n"
        "            if (oturn > ${n_minus_1}) {\n"
        "                oturn = oturn - ${n};\n"
        "                orev = hc_s32((uint32_t)rev + 1u);\n"
        "            }\n",
    )
    swap("${index}\n", "${index_o}\n")
    # the decoder's finer atan2 for f_init too (the table positions need it; hc_angle stays
    # called once, so compilers keep it inlined in the lean path, whose cycles must not change)
    swap(
        "const uint32_t p = hc_angle(a, b); /* electrical angle, Q0.32 turns */",
        "const uint32_t p = hc_angle_fine(a, b); /* electrical angle, Q0.32 turns */",
    )
    swap(
        "            s->phase = p;\n"
        "            s->turn = turn;\n"
        "            s->rev = rev;\n"
        "            s->limit = ${step_limit}u;\n"
        "            s->held = 0u;\n"
        "            flags = s->fault; /* 0 or ${PFX}_FAULT (latched) */\n"
        "            hc_publish(s, rev, y, flags);\n",
        "            s->phase = p;\n"
        "            s->limit = ${step_limit}u;\n"
        "            s->held = 0u;\n"
        "            flags = s->fault; /* 0 or ${PFX}_FAULT (latched) */\n"
        "            if (s->locked != 0u) {\n"
        "                /* identified: f_init moves to the calibration's frame for good; both\n"
        "                 * buffers get the identification (a reader of the older one retries) */\n"
        "                s->turn = oturn;\n"
        "                s->rev = orev;\n"
        "                ident = ident | 0x10000u;\n"
        "                hc_publish_id(s, orev, y, flags, ident);\n"
        "            } else {\n"
        "                s->turn = turn;\n"
        "                s->rev = rev;\n"
        "            }\n"
        "            hc_publish_id(s, orev, y, flags, ident);\n",
    )
    swap(
        "        hc_publish(s, s->pub[last].revolutions, s->pub[last].turns, flags);\n",
        "        hc_publish_id(s, s->pub[last].revolutions, s->pub[last].turns, flags,\n"
        "                      s->pub_ident[last]);\n",
    )
    swap(
        "    if (flags > ${PFX}_FAULT) { /* rejected: count it and hold the last reading */",
        "    if (flags > ${PFX}_FAULT) { /* rejected: counted, last reading held, no evidence */",
    )
    pu = ctx.powerup
    nv = pu.null
    subs = dict(ctx.subs)
    subs["index_o"] = subs["index"].replace("(uint32_t)turn <<", "(uint32_t)oturn <<")
    assert subs["index_o"] != subs["index"]
    subs["zeta"] = (
        f"((({_cf(nv[0], 'null vector')} * d1) + ({_cf(nv[1], 'null vector')} * d2)) + "
        f"({_cf(nv[2], 'null vector')} * d3)) - {_cf(pu.null_offset, 'null offset')}"
        if pu.null_offset != 0.0
        else f"(({_cf(nv[0], 'null vector')} * d1) + ({_cf(nv[1], 'null vector')} * d2)) + "
        f"({_cf(nv[2], 'null vector')} * d3)"
    )
    return string.Template(text).substitute(subs, n=n, n_minus_1=n - 1)


def _sum_c(terms: Sequence[tuple[float | None, str]], what: str) -> str:
    """C sum of ``coef * expr`` terms (coef None: the bare expression), zero coefficients left
    out, left to right: ``((t1 + t2) + t3)``; ``0.0f`` when nothing is left."""
    parts = []
    for coef, expr in terms:
        if coef is None:
            parts.append(expr)
        elif coef != 0.0:
            parts.append(f"({_cf(coef, what)} * {expr})")
    if not parts:
        return "0.0f"
    out = parts[0]
    for p in parts[1:]:
        out = f"({out} + {p})"
    return out


def _powerup_metric(pu: PowerUpFirmware) -> tuple[str, str, str, str]:
    """Declarations and computation of the metric terms and of the per-hypothesis tangent
    products, with the terms that vanish for this projection (e.g. all cross terms of the
    Clarke rows with isotropic noise) left out; entries below 1e-12 of the largest count as
    zero (their effect on a cost is below 1e-12 relative)."""
    A, B, C = pu.gram_a, pu.gram_b, pu.gram_c
    big = max(float(np.max(np.abs(A))), float(np.max(np.abs(B))), abs(C))

    def z(v: float) -> float:
        return 0.0 if abs(v) <= 1e-12 * big else float(v)

    a00, a01, a11, b0, b1 = z(A[0, 0]), z(A[0, 1]), z(A[1, 1]), z(B[0]), z(B[1])
    d = z(A[1, 1] - A[0, 0])
    has_uv = a01 != 0.0 or d != 0.0
    has_n = b0 != 0.0 or b1 != 0.0
    w = "Gram"
    lines = [
        f"    guu = {_sum_c([(a00, '(c * c)'), (2 * a01, '(c * sn)'), (a11, '(sn * sn)')], w)};",
        f"    gvv = {_sum_c([(a00, '(sn * sn)'), (-2 * a01, '(c * sn)'), (a11, '(c * c)')], w)};",
    ]
    decls = ["    float guu;", "    float gvv;"]
    if has_uv:
        decls.append("    float guv;")
        lines.append(f"    guv = {_sum_c([(d, '(c * sn)'), (a01, '((c * c) - (sn * sn))')], w)};")
    if has_n:
        decls += ["    float gun;", "    float gvn;"]
        lines.append(f"    gun = {_sum_c([(b0, 'c'), (b1, 'sn')], w)};")
        lines.append(f"    gvn = {_sum_c([(b1, 'c'), (-b0, 'sn')], w)};")

    def prod(coef: str, var: str, present: bool) -> tuple[float | None, str]:
        return (None if present else 0.0, f"({coef} * {var})")

    cnn = _cf(C, w)
    tu = _sum_c([prod("tr", "guu", True), prod("rj", "guv", has_uv), prod("tz", "gun", has_n)], w)
    tv = _sum_c([prod("tr", "guv", has_uv), prod("rj", "gvv", True), prod("tz", "gvn", has_n)], w)
    tn = _sum_c([prod("tr", "gun", has_n), prod("rj", "gvn", has_n), (C, "tz")], w)
    cross = "(((2.0f * ea) * eb) * gun)"
    rr = _sum_c([(None, "((ea * ea) * guu)"), (None if has_n else 0.0, cross),
                 (None, f"((eb * eb) * {cnn})")], w)  # fmt: skip
    tangent = "\n".join(
        [
            f"        const float tu = {tu};",
            f"        const float tv = {tv};",
            f"        const float tn = {tn};",
            "        const float tt = ((tr * tu) + (rj * tv)) + (tz * tn);",
            "        const float rt = (ea * tu) + (eb * tn);",
            f"        const float rr = {rr};",
        ]
    )
    note = (
        ""
        if has_uv and has_n
        else (
            ": "
            + ", ".join(
                ([] if has_uv else ["<u, v> = 0"]) + ([] if has_n else ["<u, n> = <v, n> = 0"])
            )
            + " here"
        )
    )
    return "\n".join(decls) + "\n", "\n".join(lines), tangent, note


def _powerup_section(ctx: _Context) -> Section | None:
    """Pole-pair identification at power-up in the float variant (see :data:`_PU_C`) when the
    artifact's identifiability verdict allows it; the fixed-point variant keeps the homing API."""
    pu = ctx.powerup
    if ctx.variant != "float" or pu is None or not pu.emitted:
        return None
    d = ctx.design
    n, L = d.pole_pairs, pu.grid
    g = L.bit_length() - 1
    pfx, PFX = ctx.pfx, ctx.PFX
    pl = d.plausibility
    # the finer atan2: same octant reduction, more Newton steps and polynomial terms
    x_lo = math.cos(math.pi / 8.0) * pl.radius_lo * (1.0 - 1e-6)
    x_hi = pl.radius_hi * (1.0 + 1e-6)
    c0, c1, eps = _reciprocal_seed(x_lo, x_hi)
    newton, e = 1, eps * eps
    while 0.354 * e > POWERUP_ATAN2_POLY and newton < 6:
        e, newton = e * e, newton + 1
    terms = 3
    coef, poly_err = _atan_poly(terms)
    while poly_err > POWERUP_ATAN2_POLY and terms < 8:
        terms += 1
        coef, poly_err = _atan_poly(terms)
    # float rounding: 12 roundings relative to tan(pi/8), and t * poly to Q0.32 (2^29: 64 units)
    fine_bound = poly_err + 0.354 * e + 12.0 * _EPS_F32 * _TAN_PI_8 + 64.0 * TWO_PI / _U32
    atan2_fine = _atan2_c("hc_angle_fine", " (the decoder's, finer than the lean path's)",
                          x_lo, x_hi, (c0, c1), newton, coef / TWO_PI, fine_bound)  # fmt: skip
    exp2 = pu.exp2
    poly = f"{_cf(exp2[-1], 'exp2')}"
    for cf in exp2[-2::-1]:
        poly = f"({_cf(cf, 'exp2')} + (f * {poly}))"
    gram_decls, gram_calc, tangent_calc, gram_note = _powerup_metric(pu)
    source = _PU_C.substitute(
        pfx=pfx,
        PFX=PFX,
        n=n,
        n_minus_1=n - 1,
        grid=L,
        g=g,
        g_shift=32 - g,
        m1=n * L + 1,
        sigma=f"{pu.sigma:.6g}",
        table_bytes=pu.table_bytes,
        radius=_c_list([_cf(float(v), "power-up table") for v in pu.radius], 6),
        zero=_c_list(
            [_cf(float(v), "power-up table") if abs(v) >= 1e-30 else "0.0f" for v in pu.zero], 6
        ),  # fmt: skip
        atan2_fine=atan2_fine,
        exp2_error=f"{pu.exp2_error:.1e}",
        cut=EXP2_CUT,
        exp2_poly=poly,
        cap_text=f"{pu.cost_cap:.4g}",
        theta_text=f"{pu.threshold:.4g}",
        rs_c0=_cf(pu.rsqrt_seed[0], "rsqrt seed"),
        rs_c1=_cf(pu.rsqrt_seed[1], "rsqrt seed"),
        rsqrt_steps=_pu_newton(
            "y", "y * (1.5f - ((0.5f * r2) * (y * y)))", pu.rsqrt_steps, "    "
        ),  # fmt: skip
        inv_sigma=_cf(1.0 / pu.sigma, "1 / sigma"),
        gram_decls=gram_decls,
        gram_calc=gram_calc,
        gram_note=gram_note,
        tangent_calc=tangent_calc,
        slope=_cf(pu.slope, "grid"),
        tt_c0=_cf(pu.tangent_seed[0], "tangent seed"),
        tt_c1=_cf(pu.tangent_seed[1], "tangent seed"),
        tt_lo=f"{pu.tangent_window[0]:.4g}",
        tt_hi=f"{pu.tangent_window[1]:.4g}",
        tt_steps=_pu_newton("q", "q * (2.0f - (tt * q))", pu.tangent_steps, "        "),
        cap=_cf(pu.cost_cap, "cost cap"),
        theta=_cf(pu.threshold, "lock threshold"),
        confidence=f"{1.0 - pu.report.error_target:g}",
        term_error=f"{POWERUP_TERM_ERROR:.0e}",
    )
    source += _powerup_identify(ctx) + "\n"
    rep = pu.report
    hooks = {
        "api_macros": (
            f"/* This code identifies the pole pair at power-up by itself: {pfx}_init takes no\n"
            f" * angle, reading.identified says when the angle is in the calibration's frame. */\n"
            f"#define {PFX}_POWERUP 1\n"
            f"#define {PFX}_POWERUP_GRID {L}\n"
        ),
        "reading_members": (
            "    uint32_t identified; /* 1 once the pole pair is identified (the test locked) */\n"
            "    uint32_t pole_pair;  /* j: the calibration frame is f_init's + j pole pitches;\n"
            "                          * the current maximum-likelihood j until identified */\n"
        ),
        "state_members": (
            "    /* power-up identification (after the lean path's members: their offsets, and so\n"
            "     * the lean path's code, are those of the build without it) */\n"
            "    volatile uint32_t pub_ident[2]; /* of pub[i]: pole pair j, + 0x10000 once\n"
            "                                     * identified */\n"
            "    uint32_t locked;   /* pole pair identified: the lean path runs */\n"
            "    uint32_t best;     /* maximum-likelihood pole-pair offset j */\n"
            "    uint32_t samples;  /* samples of evidence so far (until identified) */\n"
            f"    float lam[{n}];    /* Lambda_j - min Lambda [noise sigma^2] */\n"
        ),
        "init_decl": (
            f"/* Until the pole pair is identified, {pfx}_update hands each sample to this\n"
            " * function; it has external linkage only so that compilers keep it out of the lean\n"
            f" * path (whose cycles it would lengthen). Call {pfx}_update, not this. */\n"
            f"uint32_t {pfx}_identify_sample({pfx}_state *s, float d1, float d2, float d3);\n\n"
            "/* Start after power-up wherever the rotor is: no angle and no homing. The first\n"
            " * readings are in the frame of the current maximum-likelihood pole pair (angle\n"
            " * right within the electrical period from the first sample); reading.identified\n"
            " * becomes 1 when the probability of a wrong pole pair is below "
            f"{rep.error_target:g}. */\n"
            f"void {pfx}_init({pfx}_state *s);\n"
        ),
        "init_def": _PU_INIT.substitute(pfx=pfx, n=n),
        "read_locals": "    uint32_t ident;\n",
        "read_copy": "        ident = s->pub_ident[before & 1u];\n",
        "read_after": "\n    r->pole_pair = ident & 0xFFFFu;\n    r->identified = ident >> 16;",
        "before_update": source,
        "update_dispatch": f"s->locked == 0u|{pfx}_identify_sample",
    }
    notes = (
        "",
        f"Power-up: the pole pair is identified after {pfx}_init (no angle, no homing): maximum",
        f"  likelihood over the {n} pole pairs from the magnets' signatures, sequential test to a",
        f"  wrong-pole-pair probability below {rep.error_target:g} (hallcal.sensor.absolute,",
        f"  PowerUpIdentifier). Until identified each sample evaluates all {n} hypotheses (bounded",
        "  loop), then the lean path runs alone. Verdict: "
        + comment_text(rep.status.value, limit=30)
        + f"; tables {pu.table_bytes} bytes.",
    )
    return Section("powerup", "", "", notes, hooks)


def _homing_note(pu: PowerUpFirmware, *, fixed: bool = False) -> list[str]:
    """Banner lines of a variant that does not identify the pole pair (homing API)."""
    if pu.status is PowerUpCode.SINGLE_POLE_PAIR:
        text = comment_text("Power-up: " + pu.message.replace("'", ""), limit=600)
        return ["", *textwrap.wrap(text, 90, subsequent_indent="  ")]
    if fixed and pu.emitted:
        why = (
            "the decoder needs single precision (24-bit mantissa arithmetic on every hypothesis, "
            "see the firmware guide), the float variant of this export identifies it"
        )
    else:
        why = pu.message
    why = comment_text(why.replace("'", "").replace(";", ","), limit=600)
    return [
        "",
        "Power-up: this code does NOT identify the pole pair. Init it with the calibration run",
        "  starting position (the same rotor position, or a homed axis). Why:",
        *("  " + line for line in textwrap.wrap(why, 88)),
    ]


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


# --------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------


def _canonical_sha256(artifact: Mapping) -> str:
    def default(obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            return obj.tolist()
        if isinstance(obj, np.generic):
            return obj.item()
        if hasattr(obj, "to_dict"):
            return obj.to_dict()
        return str(obj)

    try:
        canon = json.dumps(artifact, sort_keys=True, separators=(",", ":"), default=default)
    except (TypeError, ValueError, RecursionError):
        raise HallcalInputError("the calibration artifact cannot be serialized") from None
    return hashlib.sha256(canon.encode("utf-8", "surrogatepass")).hexdigest()


def _write(path: Path, text: str) -> None:
    try:
        text.encode("ascii")
    except UnicodeEncodeError:  # pragma: no cover - comment_text keeps everything ASCII
        raise AssertionError("generated C must be ASCII") from None
    with atomic_write(path, "w", encoding="ascii") as fh:
        fh.write(text)


def export_c(
    artifact: Mapping,
    out_dir: str | os.PathLike[str],
    *,
    prefix: str = "hallcal",
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

        void hallcal_init(hallcal_state *s, int32_t revolutions, float angle);
        uint32_t hallcal_update(hallcal_state *s, float d1, float d2, float d3);  /* flags */
        void hallcal_read(const hallcal_state *s, hallcal_reading *r);  /* consistent */
        void hallcal_clear_fault(hallcal_state *s);
        /* hallcal_q_...: the same with int32 counts in and Q0.32 turns out */

    With the power-up identification (the artifact's identifiability verdict allows it; float
    variant only) ``void hallcal_init(hallcal_state *s);`` takes no angle and the reading has
    ``identified`` and ``pole_pair`` (see :func:`_powerup_section`).

    Parameters
    ----------
    artifact : mapping
        The calibration artifact as read from JSON (``"format": "hallcal-calibration/1"``,
        ``pole_pairs``, ``reconstruction``, ``lut``, ``model``; ``diagnostics.noise_floor`` and
        ``setup.sample_time`` when present).
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
        Largest mechanical speed [rad/s] for the step limit; default 45 electrical degrees per
        sample.
    fault_after : int, keyword-only
        Rejected samples in a row before the fault flag (default 8).
    powerup : bool, keyword-only
        Put the power-up identification of the pole pair into the float variant when the
        artifact's identifiability verdict allows it (then ``<prefix>_init(s)`` takes no angle;
        see :data:`_PU_C`); False keeps the homing API (and saves the decoder's tables).

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
    src = _source_name(source)
    sha = _canonical_sha256(artifact) if isinstance(artifact, Mapping) else ""
    design = design_firmware(
        artifact,
        source=src,
        table_points=table_points,
        tolerance=tolerance,
        max_speed=max_speed,
        fault_after=fault_after,
        sha256=sha,
    )
    fn = _float_numbers(design)
    q = _fixed_numbers(design, adc_scale) if fixed_point else None
    worst = max(fn.bound, q.bound if q is not None else 0.0)
    if worst > MAX_TOTAL_ERROR and table_points is None:
        # the table within its budget, but with the arithmetic above 1e-5 rad: a larger table
        for m in table_sizes(design.pole_pairs):
            if m <= design.table.points:
                continue
            bigger = design_firmware(
                artifact, source=src, table_points=m, tolerance=tolerance,
                max_speed=max_speed, fault_after=fault_after, sha256=sha,
            )  # fmt: skip
            fn2 = _float_numbers(bigger)
            q2 = _fixed_numbers(bigger, adc_scale) if fixed_point else None
            worst2 = max(fn2.bound, q2.bound if q2 is not None else 0.0)
            if worst2 < worst:
                design, fn, q, worst = bigger, fn2, q2, worst2
            if worst <= MAX_TOTAL_ERROR:
                break
    n, t, pl = design.pole_pairs, design.table, design.plausibility
    messages = list(design.messages)
    if t.nbytes > 4096 and not any("bytes" in m for m in messages):
        messages.append(
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
        messages.append(
            f"stated error bound {worst:.2g} rad is above {MAX_TOTAL_ERROR:g} rad (the table "
            f"alone differs by {t.error:.2g} rad)"
        )
    pfx, PFX = prefix, prefix.upper()
    version = _version()
    ts = design.sample_time
    safe = pl.glitch_safe_step * TWO_PI / n  # rad per sample
    speed_text = (
        f"{safe / ts:.4g} rad/s" if ts is not None and ts != 1.0 else f"{safe:.4g} rad/sample"
    )
    common = [
        f"generated by hallcal {version} (hallcal.output.codegen). Do not edit.",
        "",
        f"Source artifact : {src}",
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
        f"{pl.tolerance:g}, {6:d} noise sigmas); step limit {pl.step_limit:.4g} electrical turn",
        f"  per sample (grows while samples are held); fault after {pl.fault_after} in a row.",
        f"  One glitch sample cannot make the angle slip up to {speed_text}.",
    ]
    paths: list[Path] = []
    texts: list[tuple[str, str]] = []
    section_names: list[str] = []
    pu = (
        design_powerup(artifact, design, source=src)
        if powerup
        else PowerUpFirmware(PowerUpCode.DISABLED, "left out on request (powerup=False)")
    )
    if pu.emitted:
        messages.append(
            f"the float variant identifies the pole pair at power-up by itself ({prefix}_init "
            f"takes no angle; tables {pu.table_bytes} bytes); the fixed-point variant needs "
            "the calibration's starting position as before"
            if fixed_point
            else f"the float variant identifies the pole pair at power-up by itself "
            f"({prefix}_init takes no angle; tables {pu.table_bytes} bytes)"
        )
    elif pu.status is not PowerUpCode.SINGLE_POLE_PAIR:
        messages.append(f"no power-up identification in the C (homing needed): {pu.message}")
    ctx_f = _Context(artifact, design, pfx, PFX, "float", powerup=pu)
    ctx_f = dataclasses.replace(ctx_f, subs=_float_subs(ctx_f, fn))
    secs = _sections(ctx_f)
    section_names += [s.name for s in secs]
    lines_f = (
        common
        + [
            "",
            "Float variant: single precision, no libm, no double, no division.",
            f"  stated bound vs hallcal reconstruct: {fn.bound:.2e} rad (mechanical)",
            f"  atan2: |error| <= {fn.atan_bound:.2e} rad (electrical)",
        ]
        + ([] if pu.emitted else _homing_note(pu))
        + [note for s in secs for note in s.notes]
    )
    texts.append((f"{pfx}.h", _float_header(ctx_f, _banner(f"{pfx}.h", lines_f), secs)))
    texts.append((f"{pfx}.c", _float_source(ctx_f, _banner(f"{pfx}.c", lines_f), secs)))
    if q is not None:
        ctx_q = _Context(artifact, design, pfx, PFX, "fixed")
        secs_q = _sections(ctx_q)
        lines_q = (
            common
            + [
                "",
                "Fixed-point variant: 32-bit integers only (no float, no 64-bit, no division).",
                f"  inputs: ADC counts, adc_scale {adc_scale:g} counts per artifact unit",
                f"  stated bound vs hallcal reconstruct on the same counts: {q.bound:.2e} rad",
                f"  atan2: |error| <= {q.atan_bound:.2e} rad (electrical)",
                f"  rounding the artifact's signals to counts adds {q.quant_rms:.2e} rad RMS "
                f"(at most {q.quant_max:.2e})",
            ]
            + _homing_note(pu, fixed=True)
            + [note for s in secs_q for note in s.notes]
        )
        texts.append(
            (
                f"{pfx}_q.h",
                _FIXED_H.substitute(
                    banner=_banner(f"{pfx}_q.h", lines_q),
                    pfx=pfx,
                    PFX=PFX,
                    n=n,
                    m=t.points,
                    fault_after=pl.fault_after,
                    section_decls="".join(s.header for s in secs_q),
                ),
            )
        )
        texts.append(
            (
                f"{pfx}_q.c",
                _fixed_source(
                    ctx_q, q, _banner(f"{pfx}_q.c", lines_q), "".join(s.source for s in secs_q)
                ),
            )
        )
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HallcalInputError(
            f"cannot create the output folder ({exc.strerror or type(exc).__name__})"
        ) from None
    for name, text in texts:
        _write(out / name, text)
        paths.append(out / name)
    return ExportResult(
        paths=tuple(paths),
        pole_pairs=n,
        table_points=t.points,
        table_bytes=t.nbytes,
        table_error=t.error,
        budget=design.budget,
        noise_floor=design.noise_floor,
        float_bound=fn.bound,
        atan2_bound=fn.atan_bound,
        fixed_bound=q.bound if q is not None else None,
        fixed_atan2_bound=q.atan_bound if q is not None else None,
        quantization_rms=q.quant_rms if q is not None else None,
        quantization_max=q.quant_max if q is not None else None,
        adc_scale=float(adc_scale),
        step_limit=pl.step_limit,
        glitch_safe_speed=safe,
        fault_after=pl.fault_after,
        sha256=sha,
        sections=tuple(dict.fromkeys(section_names)),
        messages=tuple(messages),
        design=design,
        identifies_pole_pair=pu.emitted,
        powerup_message=pu.message,
        powerup_table_bytes=pu.table_bytes,
        powerup=pu,
    )
