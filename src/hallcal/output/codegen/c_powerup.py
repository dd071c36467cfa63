"""Optional section: identification of the pole pair at power-up (float variant).

When the artifact's ``"identifiability"`` verdict allows it, the float variant carries the
decoder of :mod:`hallcal.sensor.absolute` (``PowerUpIdentifier``): ``init`` takes no angle, each
sample until the lock adds the evidence of every pole-pair hypothesis, and the reading says when
the angle is in the calibration's frame. The section fills the float variant's insertion points
(:data:`~hallcal.output.codegen.c_float.FLOAT_HOOKS`) and keeps the lean path's code; without it
the generated code keeps the homing API and its banner says why (:func:`_homing_note`).
"""

from __future__ import annotations

import string
import textwrap
from collections.abc import Sequence

import numpy as np

from hallcal._constants import TWO_PI
from hallcal.output.codegen.c_float import _FLOAT_UPDATE, _atan2_c
from hallcal.output.codegen.c_text import _U32, _c_list, _cf, comment_text
from hallcal.output.codegen.numbers import _EPS_F32, _TAN_PI_8, _float_atan2_design
from hallcal.output.codegen.sections import Section, _Context
from hallcal.output.firmware import EXP2_CUT, PowerUpCode, PowerUpFirmware

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
    s->pub[q & 1u].rejected = s->rejected;
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
    s->mismatch = 0u;
    s->fit = 0.0f;
${gate_init}    s->best = 0u;
    s->samples = 0u; /* lam is set by the first sample of evidence (no loop: no memset) */
    s->seq = 0u;
    hc_publish_id(s, 0, 0.0f, ${PFX}_NO_SAMPLE, 0u);
    hc_publish_id(s, 0, 0.0f, ${PFX}_NO_SAMPLE, 0u);
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
${travel_update}${rsqrt_steps}
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
${gain_scale}        const float ea = ${ea};         /* residual r = ea u + eb n */
        const float eb = ${eb};
        /* tangent t = dR u + R v + dZ n: <t, u>, <t, v>, <t, n> in the metric S */
${tangent_calc}
        float q = ${tt_c0} - (${tt_c1} * tt); /* 1/tt: seed on [${tt_lo}, ${tt_hi}], Newton */
        float cost;
${tt_steps}
        cost = rr - ((rt * rt) * q);
${gain_update}${bias_update}        if (cost > ${cap}) {
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
    /* misfit test (hallcal.sensor.misfit): lmin is what the best hypothesis's whole cost grew
     * by; D >= ln(1 / beta) = ${fit_hi_text}: no pole pair fits (mismatch, for good); the lock
     * needs D <= -ln(1 / gamma) = -${fit_lo_text} (the best fits) besides the posterior */
    s->fit = s->fit + ((lmin * ${fit_weight}) - ${fit_drift});
${gate_sum}    if (s->fit >= ${fit_hi}) {
        s->mismatch = 1u;
        s->locked = 0u;
    } else if ((s->fit <= ${fit_lo})${travel_cond}${gate_cond}) {
        s->locked = hc_lock_rule(s->lam, best);
${gate_check}${bias_check}    } else {
        s->locked = 0u;
    }
}

"""
)


def _pu_newton(var: str, expr: str, steps: int, indent: str) -> str:
    return "\n".join(f"{indent}{var} = {expr};" for _ in range(steps))


#: How ``<prefix>_identify_sample`` differs from the lean update template: (text, replacement),
#: each text found exactly once.
_IDENTIFY_EDITS: tuple[tuple[str, str], ...] = (
    (
        "uint32_t ${pfx}_update(${pfx}_state *s, float d1, float d2, float d3)\n{",
        "/* The sample path until the pole pair is identified: the lean path's checks and f_init,\n"
        " * the evidence of every hypothesis, and the output in the frame of the current\n"
        " * maximum-likelihood pole pair; once identified, the state moves to that frame for good\n"
        " * and the lean path takes over. */\n"
        "uint32_t ${pfx}_identify_sample(${pfx}_state *s, float d1, float d2, float d3)\n{",
    ),
    (
        "        if (mag <= s->limit) {\n",
        "        if (mag <= s->limit) {\n"
        "            /* zeta: along the projection's null vector, in sigmas */\n"
        "            const float zeta = ${zeta};\n"
        "            int32_t oturn;\n"
        "            int32_t orev = rev;\n"
        "            uint32_t ident;\n"
        "            if (s->mismatch == 0u) { /* no evidence once no pole pair fits */\n"
        "                hc_evidence(s, a, b, r2, zeta, (uint32_t)turn, p);\n"
        "            }\n"
        "            ident = s->best;\n"
        "            oturn = turn + (int32_t)ident; /* the output in the frame of the best */\n"
        "            if (oturn > ${n_minus_1}) {\n"
        "                oturn = oturn - ${n};\n"
        "                orev = hc_s32((uint32_t)rev + 1u);\n"
        "            }\n",
    ),
    ("${index}\n", "${index_o}\n"),
    # the decoder's finer atan2 for f_init too (the table positions need it; hc_angle stays
    # called once, so compilers keep it inlined in the lean path, whose cycles must not change)
    (
        "const uint32_t p = hc_angle(a, b); /* electrical angle, Q0.32 turns */",
        "const uint32_t p = hc_angle_fine(a, b); /* electrical angle, Q0.32 turns */",
    ),
    (
        "            s->phase = p;\n"
        "            s->turn = turn;\n"
        "            s->rev = rev;\n"
        "            s->limit = ${step_limit}u;\n"
        "            flags = s->fault; /* 0 or ${PFX}_FAULT (latched) */\n"
        "            hc_publish(s, rev, y, flags);\n",
        "            s->phase = p;\n"
        "            s->limit = ${step_limit}u;\n"
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
        "                ident = ident | (s->mismatch << 17);\n"
        "            }\n"
        "            hc_publish_id(s, orev, y, flags, ident);\n",
    ),
    (
        "        hc_publish(s, s->pub[last].revolutions, s->pub[last].turns, flags);\n",
        "        hc_publish_id(s, s->pub[last].revolutions, s->pub[last].turns, flags,\n"
        "                      s->pub_ident[last]);\n",
    ),
    (
        "    if (flags > ${PFX}_FAULT) { /* rejected: count it and hold the last reading */",
        "    if (flags > ${PFX}_FAULT) { /* rejected: counted, last reading held, no evidence */",
    ),
)


def _powerup_identify(ctx: _Context) -> str:
    """``<prefix>_identify_sample``: the lean sample path with the evidence and the output in
    the frame of the current maximum-likelihood pole pair, derived from the lean template's
    text (so the checks, the unwrap and the table are literally the lean path's)."""
    n = ctx.design.pole_pairs
    text = _FLOAT_UPDATE.template
    for old, new in _IDENTIFY_EDITS:
        if text.count(old) != 1:  # pragma: no cover - guards the template's shape
            raise AssertionError(f"the lean update template changed: {old[:60]!r}")
        text = text.replace(old, new)
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


#: The common-gain profile's update in the per-hypothesis loop (module doc of
#: :mod:`hallcal.sensor.absolute`, step 5 "with it"): inc is what the profiled cost grows by,
#: a censored sample moves the gain with Huber's weight cap / inc.
_GAIN_UPDATE = string.Template(
    r"""        {
            const float tp = (rj * tu) + (zj * tn); /* <t, p>, p = R_j u + Z_j n */
            const float pr = ${pr} - ((tp * rt) * q);
            const float pp = ${pp} - ((tp * tp) * q);
            const float info = i0 + pp;
            const float inc = cost - ((pr * pr) / info);
            float u = 1.0f;
            if (inc > ${cap}) {
                u = ${cap} / inc;
            }
            s->info[j] = i0 + (u * pp);
            s->gain[j] = sj + ((u * pr) / s->info[j]);
            cost = inc;
        }
"""
)


def _gain_terms(pu: PowerUpFirmware) -> dict[str, str]:
    """The substitutions of the per-hypothesis loop for the common-gain profile (none without
    it: the residual at the calibrated gain, the decoder of artifacts made before it)."""
    dec = pu.decoder
    if dec is None or not dec.gain_sd > 0.0:
        return {"gain_scale": "", "ea": "rho - rj", "eb": "zeta - zj", "gain_update": ""}
    A, B, C = pu.gram_a, pu.gram_b, pu.gram_c
    big = max(float(np.max(np.abs(A))), float(np.max(np.abs(B))), abs(C))
    has_n = abs(B[0]) > 1e-12 * big or abs(B[1]) > 1e-12 * big
    w = "Gram"
    cnn = _cf(C, w)
    if has_n:
        pr = f"((rj * ((ea * guu) + (eb * gun))) + (zj * ((ea * gun) + (eb * {cnn}))))"
        pp = f"((((rj * rj) * guu) + (((2.0f * rj) * zj) * gun)) + ((zj * zj) * {cnn}))"
    else:
        pr = f"((rj * (ea * guu)) + (zj * (eb * {cnn})))"
        pp = f"(((rj * rj) * guu) + ((zj * zj) * {cnn}))"
    first = "(s->samples != 0u)"
    scale = (
        f"        const float sj = {first} ? s->gain[j] : 1.0f; /* s_j, I_j (set at the first\n"
        "                                                  * sample: no loop in init) */\n"
        f"        const float i0 = {first} ? s->info[j] : {_cf(dec.gain_weight, 'gain prior')};\n"
    )
    return {
        "gain_scale": scale,
        "ea": "rho - (sj * rj)",
        "eb": "zeta - (sj * zj)",
        "gain_update": _GAIN_UPDATE.substitute(pr=pr, pp=pp, cap=_cf(pu.cost_cap, "cost cap")),
    }


def _fine_atan2(ctx: _Context) -> str:
    """``hc_angle_fine``: the lean atan2's octant reduction with more Newton steps and polynomial
    terms, for the decoder's table positions (within :data:`POWERUP_ATAN2_POLY`)."""
    at = _float_atan2_design(
        ctx.design.plausibility,
        reciprocal_target=POWERUP_ATAN2_POLY,
        poly_target=POWERUP_ATAN2_POLY,
        max_newton=6,
        max_terms=8,
    )
    # float rounding: 12 roundings relative to tan(pi/8), and t * poly to Q0.32 (2^29: 64 units)
    fine_bound = (
        at.poly_error
        + 0.354 * at.reciprocal_error
        + 12.0 * _EPS_F32 * _TAN_PI_8
        + 64.0 * TWO_PI / _U32
    )
    return _atan2_c("hc_angle_fine", " (the decoder's, finer than the lean path's)",
                    at.x_lo, at.x_hi, at.seed, at.newton, at.poly / TWO_PI,
                    fine_bound)  # fmt: skip


def _powerup_source(ctx: _Context, pu: PowerUpFirmware) -> str:
    """The decoder's tables and functions (:data:`_PU_C`) and ``<prefix>_identify_sample``."""
    n, L = ctx.design.pole_pairs, pu.grid
    g = L.bit_length() - 1
    exp2 = pu.exp2
    poly = f"{_cf(exp2[-1], 'exp2')}"
    for cf in exp2[-2::-1]:
        poly = f"({_cf(cf, 'exp2')} + (f * {poly}))"
    gram_decls, gram_calc, tangent_calc, gram_note = _powerup_metric(pu)
    assert pu.decoder is not None and pu.report is not None  # an emitted decoder has both
    mis = pu.decoder.misfit
    source = _PU_C.substitute(
        pfx=ctx.pfx,
        PFX=ctx.PFX,
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
        atan2_fine=_fine_atan2(ctx),
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
        fit_weight=_cf(mis.weight, "misfit weight"),
        fit_drift=_cf(mis.drift, "misfit drift"),
        fit_hi=_cf(mis.bound, "misfit bound"),
        fit_lo=_cf(-mis.fit_bound, "fit bound"),
        fit_hi_text=f"{mis.bound:.4g}",
        fit_lo_text=f"{mis.fit_bound:.4g}",
        **_gain_terms(pu),
        **_travel_terms(pu),
        **_gate_terms(pu),
        **_bias_terms(pu),
    )
    return source + _powerup_identify(ctx) + "\n"


def _powerup_hooks(ctx: _Context, pu: PowerUpFirmware) -> dict[str, str]:
    """What the decoder puts into the float variant's insertion points (:data:`FLOAT_HOOKS`)."""
    pfx, PFX, n = ctx.pfx, ctx.PFX, ctx.design.pole_pairs
    assert pu.report is not None  # an emitted decoder has its analysis
    return {
        "api_macros": (
            f"/* This code identifies the pole pair at power-up by itself after {pfx}_init:\n"
            " * reading.identified says when the angle is in the calibration's frame. */\n"
            f"#define {PFX}_POWERUP 1\n"
            f"#define {PFX}_POWERUP_GRID {pu.grid}\n"
        ),
        "reading_members": (
            "    uint32_t identified; /* 1 once the pole pair is identified (the test locked) */\n"
            "    uint32_t mismatch;   /* 1: no pole pair fits, the signals do not match this\n"
            "                          * calibration (ring remounted, wiring changed or sensors\n"
            "                          * drifted): recalibrate; never identified then */\n"
            "    uint32_t pole_pair;  /* j: the calibration frame is f_init's + j pole pitches;\n"
            "                          * the current maximum-likelihood j until identified */\n"
        ),
        "state_members": (
            "    /* power-up identification (after the lean path's members: their offsets, and so\n"
            "     * the lean path's code, are those of the build without it) */\n"
            "    volatile uint32_t pub_ident[2]; /* of pub[i]: pole pair j, + 0x10000 once\n"
            "                                     * identified, + 0x20000 on a mismatch */\n"
            "    uint32_t locked;   /* pole pair identified: the lean path runs */\n"
            "    uint32_t mismatch; /* no pole pair fits (misfit test): no more evidence */\n"
            "    float fit;         /* misfit statistic D (log-likelihood ratio) */\n"
            "    uint32_t best;     /* maximum-likelihood pole-pair offset j */\n"
            "    uint32_t samples;  /* samples of evidence so far (until identified) */\n"
            f"    float lam[{n}];    /* Lambda_j - min Lambda [noise sigma^2] */\n"
            + _gain_members(pu, n)
        ),
        "init_decl": (
            f"/* Until the pole pair is identified, {pfx}_update hands each sample to this\n"
            " * function; it has external linkage only so that compilers keep it out of the lean\n"
            f" * path (whose cycles it would lengthen). Call {pfx}_update, not this. */\n"
            f"uint32_t {pfx}_identify_sample({pfx}_state *s, float d1, float d2, float d3);\n\n"
        ),
        "init_note": (
            ";\n * then the pole pair is identified from the magnets' signatures (no homing): the\n"
            " * readings are in the frame of the current maximum-likelihood pole pair (angle\n"
            " * right within the electrical period from the first sample) and\n"
            " * reading.identified becomes 1 when the probability of a wrong pole pair is below "
            f"{pu.report.error_target:g}\n"
            " * and the signals fit the model; reading.mismatch becomes 1 instead when no pole\n"
            " * pair fits (ring remounted, wiring changed: recalibrate)"
        ),
        "set_angle_note": (
            "\n * It also ends the power-up identification: the reading says identified, pole\n"
            " * pair 0."
        ),
        "set_angle_extra": (
            "        s->locked = 1u; /* homed: the frame is known, no identification */\n"
            "        s->best = 0u;\n"
            "        s->pub_ident[0] = 0x10000u;\n"
            "        s->pub_ident[1] = 0x10000u;\n"
        ),
        "update_loop": (
            " once the pole pair is identified (before: the n_m hypotheses in a\n * loop, about"
            " ten times the cycles)"
        ),
        "init_def": _PU_INIT.substitute(pfx=pfx, PFX=PFX, n=n, gate_init=_gate_init(pu)),
        "read_locals": "    uint32_t ident;\n",
        "read_copy": "        ident = s->pub_ident[before & 1u];\n",
        "read_after": (
            "\n    r->pole_pair = ident & 0xFFFFu;\n    r->identified = (ident >> 16) & 1u;"
            "\n    r->mismatch = ident >> 17;"
        ),
        "before_update": _powerup_source(ctx, pu),
        "update_dispatch": f"s->locked == 0u|{pfx}_identify_sample",
    }


def _gain_members(pu: PowerUpFirmware, n: int) -> str:
    """State members of the common-gain profile and of the travel before the lock (none
    without them)."""
    dec = pu.decoder
    out = ""
    if dec is not None and dec.gain_sd > 0.0:
        out += (
            f"    float gain[{n}];   /* s_j: common gain of the signals under hypothesis j */\n"
            f"    float info[{n}];   /* I_j: its information [1 / gain^2] */\n"
        )
    if dec is not None and dec.gate_rate > 0.0:
        out += "    float cost;        /* Q: the best hypothesis's whole cost [noise sigma^2] */\n"
    if dec is not None and dec.gate_bias_dispersion > 0.0:
        out += (
            f"    float bias[{5 * n}]; /* per hypothesis j at 5 j: the gate's bias sums h (2) and\n"
            "                        * H (Haa, Hab, Hbb), Huber-weighted [noise sigma^2] */\n"
        )
    if dec is not None and dec.lock_travel > 0.0:
        out += (
            "    float pos;         /* f_init's electrical angle since power-up [turns] */\n"
            "    float pmin;        /* its range so far: the lock waits for the travel */\n"
            "    float pmax;\n"
            "    uint32_t pprev;    /* the last sample's angle, Q0.32 turns */\n"
        )
    return out


#: The travel of f_init's electrical angle since power-up (step 7: the lock waits for it).
_TRAVEL_UPDATE = r"""    if (s->samples != 0u) { /* unwrapped from the steps, as f_init */
        s->pos = s->pos + ((float)hc_s32(p - s->pprev) * 2.32830644e-10f);
        if (s->pos > s->pmax) {
            s->pmax = s->pos;
        }
        if (s->pos < s->pmin) {
            s->pmin = s->pos;
        }
    } else {
        s->pos = 0.0f;
        s->pmin = 0.0f;
        s->pmax = 0.0f;
    }
    s->pprev = p;
"""


def _travel_terms(pu: PowerUpFirmware) -> dict[str, str]:
    """The travel's update and its part of the lock condition (none without it)."""
    dec = pu.decoder
    if dec is None or not dec.lock_travel > 0.0:
        return {"travel_update": "", "travel_cond": ""}
    return {
        "travel_update": _TRAVEL_UPDATE,
        "travel_cond": f" && ((s->pmax - s->pmin) >= {_cf(dec.lock_travel, 'lock travel')})",
    }


#: The goodness-of-fit gate at the first lock (step 7 of the specification): the best
#: hypothesis's whole cost Q within the chi-square(2 k) quantile of 1 - alpha_g, written without a
#: root: x = Q - 2 k - gz, fits when x <= 0 or x^2 <= g4 k.
_GATE_CHECK = string.Template(
    r"""        if (s->locked != 0u) { /* the gate: Q within the chi-square(2 k) quantile */
            const float k = (float)s->samples;
            const float x = (s->cost - (2.0f * k)) - ${gz};
            if ((x > 0.0f) && ((x * x) > (${g4} * k))) {
                s->locked = 0u; /* no pole pair fits as the noise allows: mismatch */
                s->mismatch = 1u;
            }
        }
"""
)


def _gate_terms(pu: PowerUpFirmware) -> dict[str, str]:
    """The gate's sum, its sample condition and its check (none without it)."""
    dec = pu.decoder
    if dec is None or not dec.gate_rate > 0.0:
        return {"gate_sum": "", "gate_cond": "", "gate_check": ""}
    gz, g4 = dec.gate_terms
    return {
        "gate_sum": "    s->cost = s->cost + lmin; /* Q, the best's whole cost */\n",
        "gate_cond": f" && (s->samples >= {int(dec.gate_samples)}u)",
        "gate_check": _GATE_CHECK.substitute(gz=_cf(gz, "gate"), g4=_cf(g4, "gate")),
    }


#: The gate's bias half, its sums in the per-hypothesis loop (step 5 of the specification, "with
#: the bias half"): Huber's weight u = cap / max(e, cap) on the uncensored cost, then u G r and
#: u G with G the metric across the curve (the tangent projected out).
_BIAS_UPDATE = string.Template(
    r"""        {
            float *const hs = &s->bias[5u * j];
            const float tuq = tu * q;
            const float tnq = tn * q;
            float bu = 1.0f;
            float b0;
            float b1;
            float b2;
            float b3;
            float b4;
            if (cost > ${cap}) {
                bu = ${cap} / cost;
            }
            b0 = bu * (${ga} - (tuq * rt)); /* u G r */
            b1 = bu * (${gb} - (tnq * rt));
            b2 = bu * (guu - (tuq * tu)); /* u G */
            b3 = bu * (${gun} - (tuq * tn));
            b4 = bu * (${cnn} - (tnq * tn));
            if (s->samples != 0u) {
                b0 = hs[0] + b0;
                b1 = hs[1] + b1;
                b2 = hs[2] + b2;
                b3 = hs[3] + b3;
                b4 = hs[4] + b4;
            }
            hs[0] = b0; /* set by the first sample: no loop in init */
            hs[1] = b1;
            hs[2] = b2;
            hs[3] = b3;
            hs[4] = b4;
        }
"""
)

#: The bias half's check at the first lock (step 7): the best's residual mean within the
#: chi-square(2) quantile, S = h' H^-1 h <= cb written without a division.
_BIAS_CHECK = string.Template(
    r"""        if (s->locked != 0u) { /* the gate's bias half: the best's residual mean */
            const float *const hs = &s->bias[5u * best];
            const float det = (hs[2] * hs[4]) - (hs[3] * hs[3]);
            const float num = (((hs[4] * hs[0]) * hs[0]) - (((2.0f * hs[3]) * hs[0]) * hs[1]))
                              + ((hs[2] * hs[1]) * hs[1]);
            if (num > (${cb} * det)) {
                s->locked = 0u; /* the residual has a mean: the sensors changed, mismatch */
                s->mismatch = 1u;
            }
        }
"""
)


def _bias_terms(pu: PowerUpFirmware) -> dict[str, str]:
    """The bias half's sums and its check at the lock (none without it)."""
    dec = pu.decoder
    if dec is None or not dec.gate_bias_dispersion > 0.0:
        return {"bias_update": "", "bias_check": ""}
    A, B, C = pu.gram_a, pu.gram_b, pu.gram_c
    big = max(float(np.max(np.abs(A))), float(np.max(np.abs(B))), abs(C))
    has_n = abs(B[0]) > 1e-12 * big or abs(B[1]) > 1e-12 * big
    cnn = _cf(C, "Gram")
    if has_n:
        ga, gb, gun = "((ea * guu) + (eb * gun))", f"((ea * gun) + (eb * {cnn}))", "gun"
    else:
        ga, gb, gun = "(ea * guu)", f"(eb * {cnn})", "0.0f"
    cap = _cf(pu.cost_cap, "cost cap")
    return {
        "bias_update": _BIAS_UPDATE.substitute(cap=cap, ga=ga, gb=gb, gun=gun, cnn=cnn),
        "bias_check": _BIAS_CHECK.substitute(cb=_cf(dec.gate_bias_bound, "bias bound")),
    }


def _gate_init(pu: PowerUpFirmware) -> str:
    dec = pu.decoder
    return "    s->cost = 0.0f;\n" if dec is not None and dec.gate_rate > 0.0 else ""


def _powerup_section(ctx: _Context) -> Section | None:
    """Pole-pair identification at power-up in the float variant (see :data:`_PU_C`) when the
    artifact's identifiability verdict allows it; the fixed-point variant keeps the homing API."""
    pu = ctx.powerup
    if ctx.variant != "float" or pu is None or not pu.emitted:
        return None
    pfx, n, rep = ctx.pfx, ctx.design.pole_pairs, pu.report
    hooks = _powerup_hooks(ctx, pu)
    notes = (
        "",
        f"Power-up: the pole pair is identified after {pfx}_init (no angle, no homing): maximum",
        f"  likelihood over the {n} pole pairs from the magnets' signatures, sequential test to a",
        f"  wrong-pole-pair probability below {rep.error_target:g} (hallcal.sensor.absolute,",
        "  PowerUpIdentifier), and a misfit test that refuses when no pole pair fits",
        f"  (reading.mismatch). Until identified each sample evaluates all {n} hypotheses",
        "  (bounded loop), then the lean path runs alone. Verdict: "
        + comment_text(rep.status.value, limit=30)
        + f"; tables {pu.table_bytes} bytes.",
    )
    return Section("powerup", "", "", notes, hooks)


def _homing_note(pu: PowerUpFirmware, *, fixed: bool = False) -> list[str]:
    """Banner lines of a variant that does not identify the pole pair (homing API)."""
    if pu.status is PowerUpCode.SINGLE_POLE_PAIR:
        text = comment_text("Power-up: " + pu.message, limit=600)
        return ["", *textwrap.wrap(text, 90, subsequent_indent="  ")]
    if fixed and pu.emitted:
        why = (
            "the decoder needs single precision (24-bit mantissa arithmetic on every hypothesis, "
            "see the firmware guide), the float variant of this export identifies it"
        )
    else:
        why = pu.message
    why = comment_text(why, limit=600)
    return [
        "",
        "Power-up: this code does NOT identify the pole pair. After init, set_angle gives it the",
        "  rotor's position in the calibration's frame (0, 0 at the calibration run's start: the",
        "  same rotor position, or a homed axis). Why:",
        *("  " + line for line in textwrap.wrap(why, 88)),
    ]
