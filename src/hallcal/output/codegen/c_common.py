"""C text that the float and the fixed-point variants share, written once.

Each fragment names the variant's identifiers with ``@{p}`` (the function and type prefix,
``${pfx}`` or ``${pfx}_q``) and ``@{F}`` (the macro prefix, ``${PFX}`` or ``${PFX}_Q``);
:func:`variant` fills them in, and the ``${...}`` placeholders are left to the variant's
:class:`string.Template`. The rules are those of docs/firmware.md (the hold and fault rule of
rejected samples, the state after ``init``).
"""

from __future__ import annotations

import string


class _Fragment(string.Template):
    delimiter = "@"


def variant(fragment: str, *, fixed: bool, **names: str) -> str:
    """`fragment` for the fixed-point (``fixed``) or the float variant; `names` fill the rest."""
    tag = "_q" if fixed else ""
    return _Fragment(fragment).substitute(p="${pfx}" + tag, F="${PFX}" + tag.upper(), **names)


#: The header up to the table size (no newline after it): guard, includes, C++ linkage, pole
#: pairs, table points.
HEADER_OPEN = r"""$banner
#ifndef @{F}_H
#define @{F}_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define @{F}_POLE_PAIRS ${n}
#define @{F}_TABLE_POINTS ${m}"""

#: The header from ``read`` to its end.
HEADER_CLOSE = r"""void @{p}_read(const @{p}_state *s, @{p}_reading *r);

/* Clear the latched fault flag (after the cause is removed and the angle re-referenced). */
void @{p}_clear_fault(@{p}_state *s);
$section_decls
#ifdef __cplusplus
}
#endif

#endif /* @{F}_H */
"""

#: Two's complement of a uint32 without an implementation-defined cast.
HC_S32 = """\
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
"""

#: The state after ``init``: f_init from y = 0, angle acquired from the first sample.
STATE_RESET = """\
    s->rev = 0; /* f_init from y = 0 before the first sample, as the calibration run */
    s->turn = 0;
    s->phase = 0u;
    s->limit = 0xFFFFFFFFu; /* the electrical angle is acquired from the first sample */
    s->held = 0u;
    s->rejected = 0u;
    s->fault = 0u;
    s->seq = 0u;
"""

#: The hold and fault rule of a rejected sample: count it, hold the last reading, latch the
#: fault after FAULT_AFTER in a row, widen the step limit meanwhile (``@{angle}``: the member
#: of the published reading within the revolution).
HOLD_RULE = r"""    if (flags > @{F}_FAULT) { /* rejected: count it and hold the last reading */
        const uint32_t last = s->seq & 1u;
        if (s->rejected < 0xFFFFFFFFu) {
            s->rejected = s->rejected + 1u;
        }
        if (s->held < @{F}_FAULT_AFTER) {
            s->held = s->held + 1u;
        }
        if (s->held >= @{F}_FAULT_AFTER) {
            /* longer could alias at up to twice the speed limit: fault, then re-acquire */
            s->fault = @{F}_FAULT;
            s->limit = 0xFFFFFFFFu;
        } else if (s->limit == ${step_limit}u) {
            s->limit = ${step_first}u; /* room for a glitch accepted last, and w */
        } else if (s->limit < 0x80000000u) {
            s->limit = s->limit + ${step_growth}u;
        } else {
            /* not yet acquired after init */
        }
        flags = flags | @{F}_HELD | s->fault | (s->pub[last].flags & @{F}_NO_SAMPLE);
        hc_publish(s, s->pub[last].revolutions, s->pub[last].@{angle}, flags);
    }
"""

#: The state's members from ``held`` to the published reading's revolutions (the step rule's
#: counters, the fault latch and the double-buffered reading of ``read``).
STATE_COUNTERS = """\
    uint32_t held;     /* rejected (or accepted after rejected) samples, less those accepted
                        * right after an accepted one */
    uint32_t rejected; /* rejected samples since init */
    uint32_t fault;    /* @{F}_FAULT once @{F}_FAULT_AFTER samples in a row were rejected */
    volatile uint32_t seq; /* readings published; the last one is pub[seq & 1] */
    volatile struct {
        int32_t revolutions;
"""

#: Publish a reading into the double buffer that ``read`` copies (``@{angle}``: the member within
#: the revolution, of C type ``@{type}``).
HC_PUBLISH = """\
static void hc_publish(@{p}_state *s, int32_t rev, @{type} @{angle}, uint32_t flags)
{
    const uint32_t q = s->seq + 1u;
    s->pub[q & 1u].revolutions = rev;
    s->pub[q & 1u].@{angle} = @{angle};
    s->pub[q & 1u].flags = flags;
    s->pub[q & 1u].rejected = s->rejected;
    s->seq = q;
}
"""
