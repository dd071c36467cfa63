"""Optional section: the anticogging feed-forward ``<prefix>_anticogging(angle)`` (float variant).

Written when the artifact has ``"cogging"``: the calibration's cogging map T_c(y0) as a table
over one revolution with cubic interpolation (:func:`hallcal.output.firmware.cogging_table`).
"""

from __future__ import annotations

import string

from hallcal._constants import TWO_PI
from hallcal.output.codegen.c_text import _c_list, _cf, comment_text
from hallcal.output.codegen.sections import Section, _Context
from hallcal.output.firmware import cogging_table

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
    float u;
    int32_t r;
    uint32_t i;
    float t;
    if (!((a > -1.0e5f) && (a < 1.0e5f))) { /* NaN, infinite or far beyond one revolution */
        a = 0.0f;
    }
    u = hc_turns(a, &r) * ${points}.0f; /* table position, ${points} per revolution */
    if (!(u < ${points}.0f)) {
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
    tab = cogging_table(ctx.artifact["cogging"], source="calibration artifact")
    m = tab.points
    vals = list(tab.values)
    ext = [vals[-1], *vals, vals[0], vals[1]]
    k = tab.torque.orders
    orders = ", ".join(str(v) for v in k[:12]) + (", ..." if len(k) > 12 else "")
    unit = ctx.artifact["cogging"].get("unit", "")
    unit = comment_text((unit if isinstance(unit, str) else "") or "artifact unit", limit=40)
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
