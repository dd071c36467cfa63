"""The float variant (``<prefix>.h``, ``<prefix>.c``): single precision, for MCUs with an FPU.

Templates of the header, the source, the atan2, ``init`` and the lean sample path, and the code
that fills them from a :class:`_Context` and the :class:`_FloatNumbers`. Optional sections add
declarations and definitions and may fill the insertion points :data:`FLOAT_HOOKS`.
"""

from __future__ import annotations

import math
import string
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hallcal.output.codegen import c_common
from hallcal.output.codegen.c_text import (
    _bits,
    _c_list,
    _cf,
    _f32,
    _f32_down,
    _f32_up,
    _speed_text,
)
from hallcal.output.codegen.numbers import (
    _TAN_PI_8,
    RECIPROCAL_MAGIC,
    TWO_PI,
    _FloatNumbers,
    _table_fraction_bits,
)
from hallcal.output.codegen.sections import Section, _Context
from hallcal.output.firmware import FirmwareDesign

_FLOAT_H = string.Template(
    c_common.variant(c_common.HEADER_OPEN, fixed=False)
    + r"""
#define ${PFX}_FAULT_AFTER ${fault_after} /* rejected samples: fault latched, angle re-acquired */
/* Speed limit [rad per sample, mechanical]${speed_text}: up to it nothing slips (one glitch
 * sample included); from it to twice it a slip cannot happen without ${PFX}_FAULT. */
#define ${PFX}_SPEED_LIMIT ${speed_limit}
/* Inputs: the Hall signals in the calibration's unit. This export's ADC scale is ${adc_scale}
 * counts per unit: pass ${PFX}_UNIT_PER_COUNT * (float)count (1.0f: counts are the unit). */
#define ${PFX}_UNIT_PER_COUNT ${unit_per_count}
${api_macros}
/* Flags of a reading (bit mask). */
#define ${PFX}_HELD 1u           /* this sample was rejected: the reading is the last accepted */
#define ${PFX}_FAULT 2u          /* ${PFX}_FAULT_AFTER rejected (or unconfirmed) samples, or a
                                  * corrupt state; latched until cleared */
#define ${PFX}_REJ_RANGE 4u      /* a channel outside its calibrated range, or not a number, or
                                  * the three inconsistent (along P's null vector) */
#define ${PFX}_REJ_AMPLITUDE 8u  /* alpha/beta radius outside its calibrated window */
#define ${PFX}_REJ_STEP 16u      /* step from the last accepted angle above the limit */
#define ${PFX}_NO_SAMPLE 32u     /* no sample accepted since init or set_angle: the reading is
                                  * theirs, not a measurement */

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
"""
    + c_common.variant(c_common.STATE_COUNTERS, fixed=False)
    + r"""        float turns; /* y_star within the revolution [turns] */
        uint32_t flags;
        uint32_t rejected;
    } pub[2];
${state_members}} ${pfx}_state;

${init_decl}
/* One sample of the three Hall signals in the calibration's unit (see ${PFX}_UNIT_PER_COUNT).
 * Returns the flags of the reading it publishes (0: accepted). No library call; no
 * loop${update_loop}; cycles per sample: the firmware guide. */
uint32_t ${pfx}_update(${pfx}_state *s, float d1, float d2, float d3);

/* The last reading, consistent (revolutions and angle of the same sample) from any context:
 * the main loop while ${pfx}_update runs in an ISR, or an ISR that interrupts ${pfx}_update.
 * Single core only (one writer). */
"""
    + c_common.variant(c_common.HEADER_CLOSE, fixed=False)
)

_FLOAT_C = string.Template(
    r"""$banner
#include <stdint.h>

#include "${header}"

/* Bit-exact with hallcal reconstruct only without contraction of a * b + c into one fused
 * multiply-add (GCC's default for GNU dialects, e.g. -std=gnu11, and -Ofast): switched off
 * here for the compilers that take a pragma; otherwise compile with -ffp-contract=off. */
#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

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

"""
    + c_common.variant(c_common.HC_S32, fixed=False)
    + r"""
${atan2_fn}
"""
    + c_common.variant(c_common.HC_PUBLISH, fixed=False, type="float", angle="turns")
    + r"""
${init_def}
${set_angle_def}
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
        r->rejected = s->pub[before & 1u].rejected;
${read_copy}        after = s->seq;
    } while ((after - before) > 1u);${read_after}
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
 * -45 degrees above 22.5 degrees, 1/x from ${seed_text}
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
${seed_line}
${newton_steps}
    t = y * rc;
    t2 = t * t;
    th = (uint32_t)(int32_t)(t * ${poly}); /* atan(t) 2^32 / (2 pi), |.| <= 2^29 */
    return hc_base[k] + ((((0x96u >> o) & 1u) != 0u) ? (0u - th) : th);
}
"""
)

_FLOAT_INIT = string.Template(
    r"""void ${pfx}_init(${pfx}_state *s)
{
"""
    + c_common.variant(c_common.STATE_RESET, fixed=False)
    + r"""    hc_publish(s, 0, 0.0f, ${PFX}_NO_SAMPLE);
    hc_publish(s, 0, 0.0f, ${PFX}_NO_SAMPLE);
}
"""
)

#: ``set_angle`` (homed use) and the angle reduction it shares with the anticogging section.
_FLOAT_SET_ANGLE = string.Template(
    r"""/* angle [rad] as whole revolutions *r and turns in [0, 1), for |angle| < 1e5 rad: with
 * 2 pi = 6.28125 + 1.93530717e-3 (the first part has 8 significant bits, so r times it is
 * exact), then the rounding at either end of the revolution moved into r */
static float hc_turns(float angle, int32_t *r)
{
    const float q = angle * 0.159154937f;
    int32_t k = (int32_t)q;
    float a;
    if (q < (float)k) {
        k = k - 1; /* floor */
    }
    a = ((angle - ((float)k * 6.28125f)) - ((float)k * 1.93530717e-3f)) * 0.159154943f;
    if (a < 0.0f) {
        a = a + 1.0f;
        k = k - 1;
    }
    if (!(a < 1.0f)) {
        a = 0.0f;
        k = k + 1;
    }
    *r = k;
    return a;
}

uint32_t ${pfx}_set_angle(${pfx}_state *s, int32_t revolutions, float angle)
{
    uint32_t flags = ${PFX}_REJ_RANGE;
    if ((angle > -1.0e5f) && (angle < 1.0e5f)) { /* not NaN, infinite or beyond */
        int32_t k;
        const float a = hc_turns(angle, &k);
        const float e = a * ${n}.0f; /* electrical turns within the revolution */
        int32_t t = (int32_t)e;
        const int32_t rev = hc_s32((uint32_t)revolutions + (uint32_t)k);
        if (t > ${n_minus_1}) {
            t = ${n_minus_1};
        }
        s->rev = rev;
        s->turn = t;
        s->phase = (uint32_t)((e - (float)t) * 4294967296.0f);
        s->limit = ${step_limit}u; /* the step rule from the first sample on */
        s->held = 0u;
${set_angle_extra}        hc_publish(s, rev, a, ${PFX}_NO_SAMPLE | s->fault);
        hc_publish(s, rev, a, ${PFX}_NO_SAMPLE | s->fault);
        flags = 0u;
    }
    return flags;
}
"""
)

_INIT_DECL = """\
/* Start after power-up: the electrical angle is acquired from the first plausible sample, the
 * revolutions from y = 0 (the calibration run's start)${init_note}. The reading
 * is flagged ${PFX}_NO_SAMPLE until a sample is accepted. */
void ${pfx}_init(${pfx}_state *s);

/* Homed use: the rotor is at y = 2 pi revolutions + angle [rad] (any angle within 1e5 rad is
 * reduced to [0, 2 pi) and the revolutions adjusted); the step rule applies from the next
 * sample on. Returns 0, or ${PFX}_REJ_RANGE (state unchanged) for NaN, infinite or larger
 * angles. Call it from the context that calls update, after init.${set_angle_note} */
uint32_t ${pfx}_set_angle(${pfx}_state *s, int32_t revolutions, float angle);
"""

#: The lean sample path (with the power-up decoder, it runs once the pole pair is identified).
_FLOAT_UPDATE = string.Template(
    r"""uint32_t ${pfx}_update(${pfx}_state *s, float d1, float d2, float d3)
{
    uint32_t flags;
    /* f_init: alpha, beta = P (d - o) */
${projection}
    const float r2 = (a * a) + (b * b);
    /* plausibility: each channel in its calibrated range (NaN is not; the three tests without
     * short-circuit, one branch), the three consistent along P's null vector, then the
     * radius */
    if (${range_check}) {
        flags = ${PFX}_REJ_RANGE;
    } else if ${common_check} {
        flags = ${PFX}_REJ_RANGE;
    } else if ((hc_bits(r2) - ${r2_lo_bits}u) <= ${r2_span_bits}u) {
        /* r2 in [${r2_lo}, ${r2_hi}] */
        const uint32_t p = hc_angle(a, b); /* electrical angle, Q0.32 turns */
        const int32_t step = hc_s32(p - s->phase);         /* wrapped into [-1/2, 1/2) turn */
        const uint32_t mag = (step < 0) ? (0u - (uint32_t)step) : (uint32_t)step;
        int32_t turn = s->turn;
        int32_t rev = s->rev;
        if ((uint32_t)turn > ${n_minus_1}u) { /* a corrupt state: never an index out of the table */
            turn = 0;
            s->fault = ${PFX}_FAULT;
        }
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
        /* step rule: within (h + 1) w + m of the last accepted sample, h held since */
        if (mag <= s->limit) {
            /* eta from the table at f_init's angle within the revolution: interval i of
             * ${per_turn} per electrical turn, position i + f in Q16.16 */
${index}
            const uint32_t fx = ${fraction}; /* f 2^${fb}, 0 <= f < 1 */
            const int32_t t0 = (int32_t)hc_t[i];
            /* eta 2^${fb} = T[i] 2^${fb} + dT fx${curv_word} in integers: modular (unsigned)
             * arithmetic, exact since the true value fits in int32 */
            const uint32_t e = ((uint32_t)t0 << ${fb})
                               + ((uint32_t)((int32_t)hc_t[i + 1u] - t0) * fx)${curv};
            /* y_star within the revolution [turns], in (-1/2, 3/2): _read brings it to [0, 1) */
            const float y = ((float)x * ${inv_m16}) + ((float)hc_s32(e) * ${lsb});
            if (s->held != 0u) { /* held samples not yet forgiven */
                if (s->limit != ${step_limit}u) {
                    s->held = s->held + 1u; /* right after held samples: unconfirmed */
                } else {
                    s->held = s->held - 1u; /* confirmed by the sample before: one forgiven */
                }
            }
            s->phase = p;
            s->turn = turn;
            s->rev = rev;
            s->limit = ${step_limit}u;
            flags = s->fault; /* 0 or ${PFX}_FAULT (latched) */
            hc_publish(s, rev, y, flags);
        } else {
            flags = ${PFX}_REJ_STEP;
        }
    } else {
        flags = ${PFX}_REJ_AMPLITUDE;
    }
"""
    + c_common.variant(c_common.HOLD_RULE, fixed=False, angle="turns")
    + r"""    return flags;
}
"""
)


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
    return "(" + "\n        | ".join(f"(uint32_t){p}" for p in parts) + ") != 0u"


def _common_mode_check(d: FirmwareDesign) -> str:
    """C expression, true when the component along P's null vector is outside its window (or
    not a number): the sum d1 + d2 + d3 when P's rows sum to zero (the null vector is then
    (1, 1, 1) / sqrt(3)), else the null vector's products; compared as the magnitude's bit
    pattern about the window's centre."""
    pl = d.plausibility
    if d.rejects_common_mode:
        k = math.sqrt(3.0)
        expr = "((d1 + d2) + d3)"
        lo = k * pl.null_lo + float(np.sum(d.offset))
        hi = k * pl.null_hi + float(np.sum(d.offset))
    else:
        nv = pl.null
        expr = (
            f"((({_cf(nv[0], 'null vector')} * d1) + ({_cf(nv[1], 'null vector')} * d2)) + "
            f"({_cf(nv[2], 'null vector')} * d3))"
        )
        lo = pl.null_lo + float(nv @ d.offset)
        hi = pl.null_hi + float(nv @ d.offset)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return (
        f"((hc_bits({expr} - {_cf(mid, 'common-mode window')}) & 0x7FFFFFFFu) > "
        f"{_bits(_f32_up(half))}u)"
    )


def _atan2_c(
    name: str, purpose: str, x_lo: float, x_hi: float, seed: tuple[float, float], newton: int,
    poly_turns: NDArray[np.float64], atan_bound: float, magic: bool = False,
) -> str:  # fmt: skip
    """A float atan2 (Q0.32 turns out) with its own reciprocal seed, Newton steps and polynomial
    (coefficients of atan in turns, odd powers ascending)."""
    if magic:
        seed_text = f"the bit pattern (any normal x; [{x_lo:.6g}, {x_hi:.6g}] here)"
        seed_line = (
            f"    rc = hc_float(0x{RECIPROCAL_MAGIC:08X}u - hc_bits(x)); /* 1/x within 5.08 % */"
        )
        steps = "\n".join(["    rc = rc * (2.0f - (x * rc));"] * newton)
    else:
        seed_text = f"a linear seed valid for x in [{x_lo:.6g}, {x_hi:.6g}]"
        seed_line = (
            f"    rc = {_cf(seed[0], 'reciprocal seed')} - ({_cf(seed[1], 'reciprocal seed')} * x);"
        )
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
        seed_text=seed_text,
        seed_line=seed_line,
        newton=newton,
        atan_bound=f"{atan_bound:.2e}",
        tan8=_cf(_TAN_PI_8),
        rsqrt2=_cf(math.sqrt(0.5)),
        newton_steps=steps,
        poly=poly,
    )


#: Insertion points of the float variant's templates an optional Section may fill (``hooks``;
#: ``state_members`` go after the lean members, whose offsets stay those of the lean build).
#: ``init_decl`` adds declarations before ``init``'s, ``init_note``, ``set_angle_note`` and
#: ``update_loop`` add to their comments, ``init_def`` replaces the default ``init``,
#: ``set_angle_extra`` adds statements to ``set_angle`` (before it publishes);
#: ``update_dispatch`` is ``(condition, function)``-like text "cond|name": while the condition
#: holds, ``update`` hands the sample to that function instead of running the lean path.
FLOAT_HOOKS = (
    "api_macros", "reading_members", "state_members", "init_decl", "init_def",
    "read_locals", "read_copy", "read_after", "before_update", "update_dispatch",
    "init_note", "set_angle_note", "set_angle_extra", "update_loop",
)  # fmt: skip


def _float_projection(d: FirmwareDesign) -> str:
    """alpha/beta = P (d - o) in C: from d2 - d1 and d3 - d1 when P's rows sum to zero."""
    P, o = d.projection, d.offset
    ab0 = P @ o
    if d.rejects_common_mode:
        return "\n".join(
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
    return "\n".join(
        [
            f"    const float a = ((({_cf(P[0, 0])} * d1) + ({_cf(P[0, 1])} * d2)) + "
            f"({_cf(P[0, 2])} * d3)) - {_cf(ab0[0], 'P o')};",
            f"    const float b = ((({_cf(P[1, 0])} * d1) + ({_cf(P[1, 1])} * d2)) + "
            f"({_cf(P[1, 2])} * d3)) - {_cf(ab0[1], 'P o')};",
        ]
    )


def _float_table(d: FirmwareDesign, fb: int) -> tuple[str, str, str]:
    """The table's declaration, the curvature term of eta 2^fb (empty for a linear table) and
    its description."""
    t = d.table
    m = t.points
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
        shift = f" << {t.curvature_shift}" if t.curvature_shift else ""
        curv = (
            "\n                               + (((uint32_t)(int32_t)hc_c[i] * "
            f"((fx * ({2**fb}u - fx)) >> {fb})){shift})"
        )
        word = f" + 2^{t.curvature_shift} C[i] (fx (2^{fb} - fx) >> {fb})"
    else:
        table_decl = (
            f"/* eta table of f_star: value T[i] (int16) at mechanical angle i / {m} turn, "
            f"linear in\n * between: eta = (T[i] (1 - f) + T[i+1] f) 2^-{t.shift} turn "
            "(T[M] = T[0]). */\n"
            f"static const int16_t hc_t[{m + 1}] = {{\n"
            + _c_list([str(int(v)) for v in values], 12)
            + "\n};"
        )
        curv = word = ""
    return table_decl, curv, word


def _float_subs(ctx: _Context, fn: _FloatNumbers) -> dict[str, Any]:
    """The substitutions of the lean float templates (shared with the optional sections)."""
    d = ctx.design
    n, m = d.pole_pairs, d.table.points
    pl = d.plausibility
    kbits = (m // n).bit_length() - 1  # M = n 2^k
    fb = _table_fraction_bits(d)
    table_decl, curv, curv_word = _float_table(d, fb)
    index = (
        f"            const uint32_t x = ((uint32_t)turn << {kbits + 16}) + (p >> {16 - kbits});\n"
        "            const uint32_t i = x >> 16;"
    )
    x_lo = math.cos(math.pi / 8.0) * pl.radius_lo
    return dict(
        header=f"{ctx.pfx}.h",
        pfx=ctx.pfx,
        PFX=ctx.PFX,
        table_decl=table_decl,
        atan2_fn=_atan2_c(
            "hc_angle",
            "",
            x_lo,
            pl.radius_hi,
            fn.seed,
            fn.newton,
            fn.poly,
            fn.atan_bound,
            fn.magic,
        ),  # fmt: skip
        n=n,
        n_minus_1=n - 1,
        projection=_float_projection(d),
        range_check=_range_check(fn.lo, fn.hi),
        common_check=_common_mode_check(d),
        r2_lo=_cf(float(_f32_down(fn.r2_lo)), "radius window"),
        r2_hi=_cf(float(_f32_up(fn.r2_hi)), "radius window"),
        r2_lo_bits=_bits(_f32_down(fn.r2_lo)),
        r2_span_bits=_bits(_f32_up(fn.r2_hi)) - _bits(_f32_down(fn.r2_lo)),
        step_limit=int(math.floor(pl.step_limit * 2.0**32)),
        step_growth=int(math.floor(pl.step_growth * 2.0**32)),
        step_first=int(math.floor(pl.step_first * 2.0**32)),
        per_turn=m // n,
        index=index,
        curv=curv,
        curv_word=curv_word,
        fb=fb,
        fraction="x & 0xFFFFu" if fb == 16 else f"(x & 0xFFFFu) >> {16 - fb}",
        lsb=_cf(2.0 ** -(d.table.shift + fb), "table unit"),
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
    init_decl = hooks["init_decl"] + string.Template(_INIT_DECL).substitute(
        pfx=ctx.pfx, PFX=ctx.PFX, init_note=hooks["init_note"],
        set_angle_note=hooks["set_angle_note"],
    )  # fmt: skip
    pl = d.plausibility
    speed = pl.speed * TWO_PI / d.pole_pairs  # rad per sample, mechanical
    return _FLOAT_H.substitute(
        banner=banner,
        pfx=ctx.pfx,
        PFX=ctx.PFX,
        speed_limit=f"{speed:.6e}",
        speed_text=_speed_text(speed, d.sample_time),
        adc_scale=f"{ctx.adc_scale:g}",
        unit_per_count=_cf(1.0 / ctx.adc_scale, "1 / adc_scale"),
        update_loop=hooks["update_loop"],
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
        set_angle_def=_FLOAT_SET_ANGLE.substitute(subs, set_angle_extra=hooks["set_angle_extra"]),
        before_update=hooks["before_update"],
        update_def=update,
        read_locals=hooks["read_locals"],
        read_copy=hooks["read_copy"],
        read_after=hooks["read_after"],
        section_defs="".join(s.source for s in secs),
    )
