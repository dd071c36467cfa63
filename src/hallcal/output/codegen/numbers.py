"""The numbers of the generated C and their stated bounds, float and fixed point.

:func:`_float_numbers` and :func:`_fixed_numbers` turn a :class:`FirmwareDesign` into the
constants each variant's templates need (ranges, windows, seeds, shifts, multipliers) and bound
what the arithmetic adds to the table's own error; the bounds are stated in the files and
checked against Python by the tests.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.output.codegen.c_text import _U32
from hallcal.output.firmware import FirmwareDesign, Plausibility
from hallcal.sensor.firmware_tables import newton_seed

_EPS_F32 = 2.0**-24  # unit roundoff of IEEE single precision
#: The generated code's stated error bound against Python should not exceed this [rad]; a larger
#: table is chosen when the arithmetic would take it above.
MAX_TOTAL_ERROR = 1e-5
#: CORDIC steps of the fixed-point atan2 before the residual is taken as atan(t) ~ t - t^3/3.
CORDIC_STEPS = 5
_TAN_PI_8 = math.tan(math.pi / 8.0)
#: The lean atan2's reciprocal seed from the bit pattern: 1/x ~ float(K - bits(x)) for normal
#: positive floats x (the exponent is negated, the mantissa approximated linearly); two 8-bit
#: chunks, so that ARM builds it in two instructions (0x7EF311C2 is 0.6 % better, four).
RECIPROCAL_MAGIC = 0x7EF30000


#: Largest relative error |1 - x seed(x)| of :data:`RECIPROCAL_MAGIC`'s seed over every normal
#: float x (13/256: the error repeats with the exponent; tests/test_codegen.py computes it over
#: every mantissa, exact in double, instead of each export-c, which took about 0.1 s).
MAGIC_SEED_ERROR = 0.05078125


# --------------------------------------------------------------------------------------------
# Float variant: numbers
# --------------------------------------------------------------------------------------------


def _atan_poly(terms: int = 5) -> tuple[NDArray[np.float64], float]:
    """Odd minimax polynomial of atan on [0, tan(pi/8)] (Lawson iterations) and its max error.

    Computed once per process and number of terms (:func:`_lawson_atan`, 35-50 ms each; an
    export designs the atan2 of the table and of the power-up); the coefficients are a copy.
    """
    coef, err = _lawson_atan(int(terms))
    return coef.copy(), err


@functools.lru_cache(maxsize=8)
def _lawson_atan(terms: int) -> tuple[NDArray[np.float64], float]:
    """:func:`_atan_poly` (the cached computation)."""
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


@dataclass(frozen=True)
class _Atan2Design:
    """A float atan2: the reciprocal's window, seed and Newton steps, the polynomial of atan."""

    x_lo: float
    x_hi: float
    seed: tuple[float, float]  # (0, 0) with the bit-pattern seed
    newton: int
    reciprocal_error: float  # relative, after the Newton steps
    poly: NDArray[np.float64]  # odd powers ascending, rad
    poly_error: float  # rad
    magic: bool = False  # the seed from the bit pattern (RECIPROCAL_MAGIC), not linear


def _float_atan2_design(
    pl: Plausibility,
    *,
    reciprocal_target: float,
    poly_target: float,
    max_newton: int,
    max_terms: int,
    magic: bool = False,
) -> _Atan2Design:
    """The fewest Newton steps (at least 1) and polynomial terms (at least 3) within the targets.

    The reciprocal is of x = max(|a|, |b|) after the rotation (r cos(th), |th| <= pi/8) over the
    radius window; its relative error e turns the angle by at most e t / (1 + t^2) <= 0.354 e.
    Its seed is linear on the window, or with ``magic`` from the bit pattern (relative error
    0.051 wherever x is a normal float, however wide the window; no constant to load but one).
    """
    x_lo = math.cos(math.pi / 8.0) * pl.radius_lo * (1.0 - 1e-6)
    x_hi = pl.radius_hi * (1.0 + 1e-6)
    magic = magic and 2.0**-120 <= x_lo and x_hi <= 2.0**120
    if magic:
        c0, c1, eps = 0.0, 0.0, MAGIC_SEED_ERROR
    else:
        c0, c1, eps = newton_seed(x_lo, x_hi)
    newton, e = 1, eps * eps
    while 0.354 * e > reciprocal_target and newton < max_newton:
        e, newton = e * e, newton + 1
    terms = 3
    coef, poly_err = _atan_poly(terms)
    while poly_err > poly_target and terms < max_terms:
        terms += 1
        coef, poly_err = _atan_poly(terms)
    return _Atan2Design(x_lo, x_hi, (c0, c1), newton, e, coef, poly_err, magic)


@dataclass(frozen=True)
class _FloatNumbers:
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    r2_lo: float
    r2_hi: float
    seed: tuple[float, float]
    newton: int
    magic: bool
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
    target = min(0.25 * d.budget * n, 2e-5)
    at = _float_atan2_design(
        pl, reciprocal_target=0.5 * target, poly_target=0.25 * target, max_newton=5, max_terms=6,
        magic=True,
    )  # fmt: skip
    e, poly_err = at.reciprocal_error, at.poly_error
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
    # eta from the integers: exact but for the floor of the curvature's f (1 - f) 2^fb (at
    # most |C| 2^k units of 2^-fb), the fraction truncated to fb bits (the slope times 2^-fb
    # of an interval) and the conversion to float (half an ulp below 2^31: 2^6 units)
    fb = _table_fraction_bits(d)
    cmax = (
        float(np.max(np.abs(d.table.curvature.astype(np.float64)))) * 2.0**d.table.curvature_shift
    )
    eta_round = (64.0 + cmax) * 2.0**-fb * d.table.lsb_rad + slope * TWO_PI / m * 2.0**-fb
    bound = d.table.error + (1.0 + slope) * e_pos + e_out + eta_round
    return _FloatNumbers(
        lo=pl.channel_lo,
        hi=pl.channel_hi,
        r2_lo=pl.radius_lo**2,
        r2_hi=pl.radius_hi**2,
        seed=at.seed,
        newton=at.newton,
        magic=at.magic,
        poly=at.poly / TWO_PI,
        atan_bound=atan_bound,
        bound=bound,
    )


def _table_fraction_bits(d: FirmwareDesign) -> int:
    """Fraction bits of the integer interpolation (at most 16): the largest with eta 2^fb
    within int32 on every interval (|T| plus a quarter of the curvature, in table units)."""
    t = d.table
    v = np.abs(t.values.astype(np.int64))
    peak = np.maximum(v, np.roll(v, -1)) + (np.abs(t.curvature.astype(np.int64))
                                             << t.curvature_shift) // 4 + 1  # fmt: skip
    fb = 16
    while fb > 8 and int(np.max(peak)) << fb >= 2**31:
        fb -= 1
    return fb


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
class _FixedInputs:
    """The Hall signals as ADC counts: channel ranges, centres and what the rounding costs."""

    lo: list[int]
    hi: list[int]
    centre: list[int]  # the offsets o, rounded to counts
    xr: int  # largest |count - centre| within the ranges (at least 1)
    frac: NDArray[np.float64]  # o adc_scale - centre
    quant_rms: float
    quant_max: float


def _fixed_inputs(d: FirmwareDesign, adc_scale: float) -> _FixedInputs:
    """Channel ranges and centres in counts; refuse an ``adc_scale`` whose counts overflow the
    int32 arithmetic or whose rounding is noisier than the Hall sensors themselves."""
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
    return _FixedInputs(lo, hi, centre, xr, frac, quant_rms, quant_max)


@dataclass(frozen=True)
class _FixedProjection:
    """P 2^(ps + kl) in integers: PH 2^kl + PL (0 <= PL < 2^kl) and the offsets a0."""

    hi_parts: list[list[int]]
    lo_parts: list[list[int]]
    kl: int
    ps: int
    xb: int  # bias making the inputs of the unsigned part non-negative
    a0: list[int]


def _fixed_projection(d: FirmwareDesign, inp: _FixedInputs) -> _FixedProjection:
    """The integer projection; its rows sum to exactly zero when the float rows do."""
    P = d.projection
    xr, frac = inp.xr, inp.frac
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
    return _FixedProjection(hi_parts, lo_parts, kl, ps, xb, a0)


def _fixed_radius(d: FirmwareDesign, scale: float) -> tuple[int, int, float, float]:
    """The radius window on (|a| >> 15, |b| >> 15) for a = alpha ``scale``: its squared bounds
    and the true radii it lets through."""
    pl = d.plausibility
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
    return r2_lo, r2_hi, r_true_lo, r_true_hi


@dataclass(frozen=True)
class _FixedTurns:
    """The electrical period in mechanical Q0.32 units and the constants derived from it."""

    period: int  # 0 for n = 1: 2^32
    half: int
    pe: float  # the period as a float (2^32 for n = 1)
    quarter: int
    eighth: int
    turn_base: list[int]


def _fixed_turns(n: int) -> _FixedTurns:
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
    return _FixedTurns(period, half, pe, quarter, eighth, turn_base)


@dataclass(frozen=True)
class _FixedAtan2:
    """Constants of the fixed-point atan2 (see the template's ``hc_angle``) and its bound."""

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
    atan_bound: float  # rad, electrical


def _fixed_atan2(r_true_lo: float, r_true_hi: float, pe: float) -> _FixedAtan2:
    """CORDIC angles, the reciprocal's seed and shifts, the cube and the scale to mechanical
    units for vectors of radius ``r_true_lo .. r_true_hi``; ``pe`` mechanical units per
    electrical turn."""
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
    c0, c1, eps0 = newton_seed(float(xh_lo), float(xh_hi + 1))
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
    cube_shift, cube_mul, post = _fixed_cube(tau_q_max, e_tau)
    # delta (tau_q units) to mechanical units: delta 2^-e_tau S = (dh * s_mul) >> s_post
    d_shift = max(0, _bitlen(int(tau_q_max)) - 16)
    j = 15 - int(math.floor(math.log2(S)))
    s_mul = int(round(S * 2.0**j))
    s_post = e_tau - d_shift + j
    if s_mul >= 2**16:
        s_mul, s_post = int(round(S * 2.0 ** (j - 1))), s_post - 1
    assert 2**15 <= s_mul < 2**16 and 0 <= s_post < 32, (s_mul, s_post)
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
    return _FixedAtan2(cordic, sx, kr, seed_a, seed_b, seed_shift, sy, cube_shift, cube_mul,
                       post, d_shift, s_mul, s_post, atan_bound)  # fmt: skip


def _fixed_cube(tau_q_max: float, e_tau: int) -> tuple[int, int, int]:
    """``(cube_shift, cube_mul, cube_post)``: t^3 / 3 as ``((c^3 >> 8) * mul) >> post`` with
    ``c = tau_q >> cube_shift < 2^10`` and ``tau_q = t 2^e_tau``."""
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
    return cube_shift, cube_mul, post


@dataclass(frozen=True)
class _FixedNumbers:
    """The integer constants of the fixed-point variant (:func:`_fixed_numbers`) and its bounds
    [rad, mechanical]."""

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
    turns: _FixedTurns
    atan: _FixedAtan2
    step_limit: int
    step_growth: int
    step_first: int
    common_mode: tuple[list[int] | None, int, int]  # multipliers (None: the sum), lo, span
    bound: float
    quant_rms: float
    quant_max: float


def _fixed_common_mode(
    d: FirmwareDesign, inp: _FixedInputs, s: float
) -> tuple[list[int] | None, int, int]:
    """The window of the component along P's null vector in the integers of the fixed variant:
    of ``x1 + x2 + x3`` (x = counts - centre) when P's rows sum to zero, else of
    ``sum q_h x_h`` with q = round(null 2^k) (k such that the sum fits in int32; the rounding of
    q widens the window by 1.5 (xr + 1))."""
    pl = d.plausibility
    if d.rejects_common_mode:
        k3 = math.sqrt(3.0)
        extra = float(np.sum(inp.frac))
        lo = math.floor(k3 * s * pl.null_lo + extra) - 1
        hi = math.ceil(k3 * s * pl.null_hi + extra) + 1
        return None, lo, hi - lo
    k = 29 - _bitlen(3 * (inp.xr + 1))
    q = [int(round(float(v) * 2.0**k)) for v in pl.null]
    extra = float(np.dot(q, inp.frac))
    slack = 1.5 * (inp.xr + 1)
    lo = math.floor(2.0**k * s * pl.null_lo + extra - slack) - 1
    hi = math.ceil(2.0**k * s * pl.null_hi + extra + slack) + 1
    return q, lo, hi - lo


def _fixed_numbers(d: FirmwareDesign, adc_scale: float) -> _FixedNumbers:
    """Integer constants of the fixed-point variant and its bounds.

    Raises HallcalInputError when ``adc_scale`` puts the signals outside the int32 arithmetic
    or makes the rounding to counts noisier than the Hall sensors themselves.
    """
    n = d.pole_pairs
    inp = _fixed_inputs(d, adc_scale)
    pj = _fixed_projection(d, inp)
    r2_lo, r2_hi, r_true_lo, r_true_hi = _fixed_radius(d, 2.0**pj.ps * float(adc_scale))
    turns = _fixed_turns(n)
    at = _fixed_atan2(r_true_lo, r_true_hi, turns.pe)
    step_limit = int(math.floor(d.plausibility.step_limit * turns.pe))
    step_growth = int(math.floor(d.plausibility.step_growth * turns.pe))
    step_first = int(math.floor(d.plausibility.step_first * turns.pe))
    # the integer projection: rounding of a0 and the floor of the unsigned part (1.5 units of
    # a), and the rounding of P 2^(ps + kl) (half a unit on each of 3 inputs up to xr)
    proj_err = (1.5 + 1.5 * 3.0 * inp.xr / 2.0**pj.kl) * math.sqrt(2.0) / r_true_lo
    e_el = at.atan_bound + proj_err
    slope = _table_slope(d)
    lsb = TWO_PI / _U32
    e_u = e_el / n + 3.0 * lsb  # turn starts, octant constants
    eta_round = (2.0 + 2.0**-16 * 65536.0) * lsb + 2.0**-16 * 32768.0 * d.table.lsb_rad
    bound = d.table.error + (1.0 + slope) * e_u + eta_round
    return _FixedNumbers(
        lo=inp.lo, hi=inp.hi, centre=inp.centre, proj_hi=pj.hi_parts, proj_lo=pj.lo_parts,
        lo_shift=pj.kl, bias=pj.xb, a0=pj.a0, proj_shift=pj.ps + pj.kl, r2_lo=r2_lo, r2_hi=r2_hi,
        turns=turns, atan=at, step_limit=step_limit, step_growth=step_growth, step_first=step_first,
        common_mode=_fixed_common_mode(d, inp, float(adc_scale)), bound=bound,
        quant_rms=inp.quant_rms, quant_max=inp.quant_max,
    )  # fmt: skip
