"""The fixed-point variant (``<prefix>_q.h``, ``<prefix>_q.c``): 32-bit integers only.

No float, no 64-bit arithmetic, no division: for Cortex-M0+/M3 and FPU-less M4. Templates of the
header and the source, and the code that fills them from a :class:`_Context` and the
:class:`_FixedNumbers`.
"""

from __future__ import annotations

import string
from collections.abc import Sequence

from hallcal._constants import TWO_PI
from hallcal.output.codegen import c_common
from hallcal.output.codegen.c_text import _U32, _c_list, _cu, _int_add, _int_sub, _speed_text
from hallcal.output.codegen.numbers import CORDIC_STEPS, _FixedNumbers
from hallcal.output.codegen.sections import Section, _Context
from hallcal.sensor.firmware_tables import CorrectionTable

_FIXED_H = string.Template(
    c_common.variant(c_common.HEADER_OPEN, fixed=True)
    + r"""
#define ${PFX}_Q_FAULT_AFTER ${fault_after} /* rejected samples: fault latched, re-acquired */
/* Speed limit [rad per sample, mechanical]${speed_text}: up to it nothing slips (one glitch
 * sample included); from it to twice it a slip cannot happen without ${PFX}_Q_FAULT. */
#define ${PFX}_Q_SPEED_LIMIT ${speed_limit}
/* Angles are Q0.32 turns: 2^32 = one revolution = 2 pi rad; one unit is this many rad: */
#define ${PFX}_Q_RAD_PER_LSB 1.4629180792671596e-9

/* Flags of a reading (bit mask). */
#define ${PFX}_Q_HELD 1u           /* this sample was rejected: the reading is the last accepted */
#define ${PFX}_Q_FAULT 2u          /* ${PFX}_Q_FAULT_AFTER rejected (or unconfirmed) samples, or
                                    * a corrupt state; latched until cleared */
#define ${PFX}_Q_REJ_RANGE 4u      /* a channel outside its calibrated range, or the three
                                    * inconsistent (along P's null vector) */
#define ${PFX}_Q_REJ_AMPLITUDE 8u  /* alpha/beta radius outside its calibrated window */
#define ${PFX}_Q_REJ_STEP 16u      /* step from the last accepted angle above the limit */
#define ${PFX}_Q_NO_SAMPLE 32u     /* no sample accepted since init or set_angle: the reading
                                    * is theirs, not a measurement */

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
"""
    + c_common.variant(c_common.STATE_COUNTERS, fixed=True)
    + r"""        uint32_t angle; /* Q0.32 turns */
        uint32_t flags;
        uint32_t rejected;
    } pub[2];
} ${pfx}_q_state;

/* Start after power-up: the electrical angle is acquired from the first plausible sample, the
 * revolutions from y = 0 (the calibration run's start). The reading is flagged
 * ${PFX}_Q_NO_SAMPLE until a sample is accepted. */
void ${pfx}_q_init(${pfx}_q_state *s);

/* Homed use: the rotor is at y = revolutions + angle / 2^32 turns (every angle is in range);
 * the step rule applies from the next sample on. Returns 0. Call it from the context that
 * calls update, after init. */
uint32_t ${pfx}_q_set_angle(${pfx}_q_state *s, int32_t revolutions, uint32_t angle);

/* One sample of the three Hall signals as raw ADC counts (any int32 is safe). Returns the flags
 * of the reading it publishes (0: accepted). No loop, 32-bit integers only; cycles per sample:
 * see the banner and the firmware guide. */
uint32_t ${pfx}_q_update(${pfx}_q_state *s, int32_t d1, int32_t d2, int32_t d3);

/* The last reading, consistent (revolutions and angle of the same sample) from any context:
 * the main loop while ${pfx}_q_update runs in an ISR, or an ISR that interrupts it.
 * Single core only (one writer). */
"""
    + c_common.variant(c_common.HEADER_CLOSE, fixed=True)
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

"""
    + c_common.variant(c_common.HC_S32, fixed=True)
    + r"""
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

"""
    + c_common.variant(c_common.HC_PUBLISH, fixed=True, type="uint32_t", angle="angle")
    + r"""
void ${pfx}_q_init(${pfx}_q_state *s)
{
"""
    + c_common.variant(c_common.STATE_RESET, fixed=True)
    + r"""    hc_publish(s, 0, 0u, ${PFX}_Q_NO_SAMPLE);
    hc_publish(s, 0, 0u, ${PFX}_Q_NO_SAMPLE);
}

uint32_t ${pfx}_q_set_angle(${pfx}_q_state *s, int32_t revolutions, uint32_t angle)
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
    s->limit = ${step_limit}u; /* the step rule from the first sample on */
    s->held = 0u;
    hc_publish(s, revolutions, angle, ${PFX}_Q_NO_SAMPLE | s->fault);
    hc_publish(s, revolutions, angle, ${PFX}_Q_NO_SAMPLE | s->fault);
    return 0u;
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
        /* the three consistent: the component along P's null vector in its window */
        const uint32_t cm = ${common_mode};
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
        if ((cm - ${cm_lo}u) > ${cm_span}u) {
            flags = ${PFX}_Q_REJ_RANGE;
        } else if ((r2 < ${r2_lo}u) || (r2 > ${r2_hi}u)) {
            flags = ${PFX}_Q_REJ_AMPLITUDE;
        } else {
            const uint32_t p = hc_angle(a, b);
            int32_t turn = s->turn;
            int32_t rev = s->rev;
            uint32_t mag;
            if ((uint32_t)turn > ${n_minus_1}u) { /* a corrupt state: never an index out of range */
                turn = 0;
                s->fault = ${PFX}_Q_FAULT;
            }
${unwrap}
            /* step rule: within (h + 1) w + m of the last accepted sample, h held since */
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
                if (s->held != 0u) { /* held samples not yet forgiven */
                    if (s->limit != ${step_limit}u) {
                        s->held = s->held + 1u; /* right after held samples: unconfirmed */
                    } else {
                        s->held = s->held - 1u; /* confirmed by the sample before */
                    }
                }
                s->phase = p;
                s->turn = turn;
                s->rev = rev;
                s->limit = ${step_limit}u;
                flags = s->fault; /* 0 or ${PFX}_Q_FAULT (latched) */
                hc_publish(s, out_rev, out, flags);
            } else {
                flags = ${PFX}_Q_REJ_STEP;
            }
        }
    }
"""
    + c_common.variant(c_common.HOLD_RULE, fixed=True, angle="angle")
    + r"""    return flags;
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
        r->rejected = s->pub[before & 1u].rejected;
        after = s->seq;
    } while ((after - before) > 1u);
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


def _fixed_header(ctx: _Context, banner: str, secs: Sequence[Section]) -> str:
    d = ctx.design
    speed = d.plausibility.speed * TWO_PI / d.pole_pairs  # rad per sample, mechanical
    return _FIXED_H.substitute(
        speed_limit=f"{speed:.6e}",
        speed_text=_speed_text(speed, d.sample_time),
        banner=banner,
        pfx=ctx.pfx,
        PFX=ctx.PFX,
        n=d.pole_pairs,
        m=d.table.points,
        fault_after=d.plausibility.fault_after,
        section_decls="".join(s.header for s in secs),
    )


def _fixed_unwrap(q: _FixedNumbers, n: int) -> dict[str, str]:
    """The unwrap of f_init and the wrap into one electrical period (one pole pair: 2^32)."""
    if n == 1:
        return dict(
            unwrap=_UNWRAP_1,
            wrap_period="    /* one pole pair: the electrical turn is the whole 2^32 */",
            init_wrap="    /* one pole pair: the phase is the angle */",
            period_text="2^32",
        )
    period = q.turns.period
    return dict(
        unwrap=_UNWRAP_N.format(half=q.turns.half, period=period, n_minus_1=n - 1)
        .replace(f"step - {period};", _int_sub("step", period) + ";")
        .replace(f"step + {period};", _int_add("step", period) + ";"),
        wrap_period=f"    if (p >= {period}u) {{\n        p = p - {period}u;\n    }}",
        init_wrap=(f"    if (s->phase >= {period}u) {{\n        s->phase = {period - 1}u;\n    }}"),
        period_text=str(period),
    )


def _fixed_table(t: CorrectionTable, n: int) -> dict[str, str]:
    """The table (offset binary), eta from it and the interval index from f_init's angle."""
    m = t.points
    kbits = (m // n).bit_length() - 1  # M = n 2^k
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
    eshift = t.shift - 16
    return dict(
        fixed_table=fixed_table,
        fixed_eta=fixed_eta,
        fixed_index=fixed_index,
        eshift=str(eshift),
        ebias=str((1 << 31) >> eshift),
    )


def _fixed_atan2_subs(q: _FixedNumbers, n: int) -> dict[str, object]:
    """The constants of ``hc_angle``: CORDIC steps, reciprocal, cube and octant assembly."""
    at = q.atan
    steps = "\n".join(_CORDIC_STEP.format(i=i, atan=at.cordic[i]) for i in range(CORDIC_STEPS))
    return dict(
        steps=CORDIC_STEPS,
        last=CORDIC_STEPS - 1,
        atan_bound=f"{at.atan_bound:.2e}",
        cordic_steps=steps,
        sx=at.sx,
        xh_lo="computed",
        xh_hi="2^16",
        kr=at.kr,
        seed_a=at.seed_a,
        seed_b=at.seed_b,
        seed_shift=at.seed_shift,
        two_kr1=1 << (at.kr + 1),
        kr_15=at.kr - 15,
        sy=at.sy,
        e_tau=at.kr + at.sx - at.sy,
        cube_shift=at.cube_shift,
        cube_mul=at.cube_mul,
        cube_post=at.cube_post,
        d_shift=at.d_shift,
        s_mul=at.s_mul,
        s_post=at.s_post,
        eighth=q.turns.eighth,
        quarter=q.turns.quarter,
        half_turn=q.turns.half if n > 1 else 1 << 31,
        period=q.turns.period,
    )


def _fixed_input_subs(q: _FixedNumbers) -> dict[str, int | str]:
    """The channel ranges, the centres, the common-mode window and the integer projection (all
    modulo 2^32)."""
    mul, cm_lo, cm_span = q.common_mode
    common = (
        "(x1 + x2) + x3"
        if mul is None
        else f"(({mul[0] % _U32}u * x1) + ({mul[1] % _U32}u * x2)) + ({mul[2] % _U32}u * x3)"
    )
    subs: dict[str, int | str] = dict(
        common_mode=common,
        cm_lo=cm_lo % _U32,
        cm_span=cm_span,
        kl=q.lo_shift,
        xb=q.bias,
        pshift=q.proj_shift,
        r2_lo=q.r2_lo,
        r2_hi=q.r2_hi,
        a0=q.a0[0] % _U32,
        b0=q.a0[1] % _U32,
    )
    for h in range(3):
        subs[f"lo{h + 1}"] = q.lo[h] % _U32
        subs[f"span{h + 1}"] = q.hi[h] - q.lo[h]
        subs[f"c{h + 1}"] = q.centre[h] % _U32
        for r in range(2):
            subs[f"p{r}{h}"] = q.proj_hi[r][h] % _U32
            subs[f"l{r}{h}"] = q.proj_lo[r][h]
    return subs


def _fixed_source(ctx: _Context, q: _FixedNumbers, banner: str, defs: str) -> str:
    d = ctx.design
    n = d.pole_pairs
    return _FIXED_C.substitute(
        banner=banner,
        header=f"{ctx.pfx}_q.h",
        pfx=ctx.pfx,
        PFX=ctx.PFX,
        n=n,
        n_minus_1=n - 1,
        turn_base=_c_list([_cu(v) for v in q.turns.turn_base], 6),
        step_growth=q.step_growth,
        step_first=q.step_first,
        rowsum="zero" if d.rejects_common_mode else "the float rows' sums",
        step_limit=q.step_limit,
        section_defs=defs,
        **_fixed_unwrap(q, n),
        **_fixed_table(d.table, n),
        **_fixed_atan2_subs(q, n),
        **_fixed_input_subs(q),
    )
