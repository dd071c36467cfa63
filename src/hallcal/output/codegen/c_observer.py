"""The model-based observer (:mod:`hallcal.sensor.observer`) as C99 in single precision.

``export_observer_c(artifact, out_dir)`` writes ``<prefix>.h`` / ``<prefix>.c``: the same
per-sample algorithm as :func:`hallcal.sensor.observer.run_observer` (tracking
maximum-likelihood angle by Gauss-Newton on the cubic Hermite interpolant of g, tabulated as
each interval's power-basis coefficients so that one Horner evaluation per channel gives g and
dg/dy; the misfit window, the gain/offset adaptation, the one-sensor fallback), in ``float``,
with the API style
of the lean export: ``_init``, ``_set_angle`` (revolutions and angle before the next
sample), ``_update`` (one sample), ``_read`` (one consistent snapshot: revolutions, angle,
misfit, state, excluded channel). It includes only ``<stdint.h>``, uses no library function
(the chi-square thresholds and the reciprocals of the window's degrees of freedom are
tabulated; the adaptation's 6x6 system is solved by an L D L^T factorization, which needs no
square root; exp(-x) of the forgetting is its cubic Taylor polynomial), no dynamic memory.

The angle is kept as a revolution count and a float angle within the revolution, so that its
resolution does not degrade over a long run. Work per sample is bounded (no loop depends on
the data): one table look-up and one Gauss-Newton step; on an outlier sample the common-gain
test and the three fits without one channel (closed form on the linearized model); one part
of the adaptation's 16-sample cycle (a row or a column of the 6x6, a triangular solve); an
8-node search on the first sample after init/set_angle; an exclusion's resets on the sample after
the one that decides it. Cycles: benchmarks/bench_observer_c.txt.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.io import ArtifactData, validate_artifact
from hallcal.output.codegen.c_text import comment_text
from hallcal.output.codegen.export import _write_files
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.observer import (
    ADAPT_CYCLE,
    ObserverModel,
    ObserverSettings,
    acquire_offsets,
    chi_square_quantile,
    observer_model,
)

__all__ = ["ObserverExport", "export_observer_c"]


@dataclass(frozen=True)
class ObserverExport:
    """What :func:`export_observer_c` wrote.

    Attributes
    ----------
    paths : tuple of Path
        The header and the source.
    table_points : int
        M, table points per revolution.
    table_bytes : int
        Bytes of the table of cubics (4 floats per channel and node) plus the threshold and
        reciprocal tables and the start's search offsets.
    """

    paths: tuple[Path, ...]
    table_points: int
    table_bytes: int


def _f(x: float) -> str:
    """A float literal that reads back to the same single-precision value."""
    v = float(np.float32(x))
    if not math.isfinite(v):
        raise HallcalInputError(f"the observer's constant {x!r} cannot be a float")
    return f"{v:.9g}f" if ("." in f"{v:.9g}" or "e" in f"{v:.9g}") else f"{v:.9g}.0f"


def _bits(x: float) -> int:
    """The IEEE 754 single-precision bits of x."""
    return int(np.array(x, dtype=np.float32).view(np.uint32))


def _rows(a: np.ndarray) -> str:
    return ",\n".join("    {" + ", ".join(_f(x) for x in row) + "}" for row in a)


def _noise(art: Mapping[str, Any], flux: FluxModel, n: int) -> np.ndarray:
    entry = art.get("observer")
    if isinstance(entry, Mapping) and "noise_variance" in entry:
        return np.asarray(entry["noise_variance"], dtype=np.float64)
    nv = art.get("diagnostics", {}).get("noise_variance")
    if isinstance(nv, int | float) and nv > 0:
        return np.full(3, float(nv))
    raise HallcalInputError("artifact: no noise level for the observer (key 'observer')")


def export_observer_c(
    artifact: Mapping[str, Any] | ArtifactData,
    out_dir: str | os.PathLike[str],
    *,
    prefix: str = "hallcal_obs",
    source: str = "artifact",
) -> ObserverExport:
    """Write the observer as C99 (float) for firmware.

    Parameters
    ----------
    artifact : mapping
        A calibration artifact (checked by :func:`~hallcal.io.validate_artifact`).
    out_dir : path-like
        Folder for ``<prefix>.h`` and ``<prefix>.c`` (created if needed).
    prefix : str, keyword-only
        C name prefix (a C identifier).
    source : str, keyword-only
        The artifact's name for messages and the file banner.

    Returns
    -------
    ObserverExport

    Raises
    ------
    HallcalInputError
        A malformed artifact, a prefix that is not a C identifier, no noise level.
    """
    if not prefix.isidentifier() or not prefix.isascii():
        raise HallcalInputError(f"--prefix '{prefix}' is not a C identifier")
    art = validate_artifact(artifact, source)
    flux = art.flux()
    n = art.pole_pairs
    model = observer_model(flux, n, _noise(art.data, flux, n))
    texts = _texts(model, ObserverSettings(), prefix, comment_text(Path(source).name))
    paths = _write_files(out_dir, texts)  # one set, write errors as one line (hallcal.io)
    s = ObserverSettings()
    # every table: the cubics (4 floats per channel and node), the thresholds and the
    # reciprocals (float), the search offsets (int16), the blame counts' units ONE (5 uint32),
    # the prior Q (6 floats) and the per-channel BLO, BHI, C0, W0, GROSS (5 x 3 floats)
    nbytes = (model.points * 3 * 4 * 4 + 2 * (2 * s.window + 1) * 4 + s.acquire_points * 2
              + 5 * 4 + 6 * 4 + 5 * 3 * 4)  # fmt: skip
    return ObserverExport(paths, model.points, nbytes)


def _texts(
    model: ObserverModel, s: ObserverSettings, prefix: str, source: str
) -> list[tuple[str, str]]:
    """The header and the source, filled from the model and the settings."""
    P = prefix.upper()
    W = s.window
    if s.fault_window > 255:  # the blame counts are packed one byte per channel
        raise ValueError("the C observer needs fault_window <= 255")
    z = -_normal_quantile(s.false_alarm)
    thr = [0.0] + [chi_square_quantile(float(k), z) for k in range(1, 2 * W + 1)]
    inv = [0.0] + [1.0 / k for k in range(1, 2 * W + 1)]
    w0 = 1.0 / model.sigma**2
    gross = [max(s.gross * math.sqrt(2.0) * model.amplitude[i], 8.0 * model.sigma[i])
             for i in range(3)]  # fmt: skip
    subst = {
        "@P@": P,
        "@p@": prefix,
        "@SOURCE@": source,
        "@M@": str(model.points),
        "@W@": str(W),
        "@FW@": str(s.fault_window),
        # 2^-124 <= x < 2^124 as one unsigned compare of the float's bits (positive floats
        # order as their bits; negative ones and NaN fall above the range)
        "@XLO@": hex(_bits(2.0**-124)),  # bounds whose bits are Thumb-2 immediates
        "@XRANGE@": hex(_bits(2.0**124) - _bits(2.0**-124)),
        "@FWPAD@": str(4 * -(-s.fault_window // 4)),
        "@FWW@": str(-(-s.fault_window // 4)),
        "@RINGRESET@": "".join(
            f"    s->ring_blame.w[{i}] = 0xffffffffu;\n" for i in range(-(-s.fault_window // 4))
        ),
        "@FC@": str(s.fault_count),
        "@NA@": str(s.acquire_points),
        "@CYCLE@": str(ADAPT_CYCLE),
        # a power of two above VMAX / h: the table's argument u positive (see table)
        "@BIAS@": str(1 << math.ceil(math.log2(0.4 * model.points / model.pole_pairs + 1.0))),
        "@OFF@": ", ".join(
            str(int(o)) for o in acquire_offsets(model.points, model.pole_pairs, s.acquire_points)
        ),
        "@NM@": _f(model.pole_pairs),
        "@H@": _f(TWO_PI / model.points),
        "@INVH@": _f(model.points / TWO_PI),
        "@TWO_PI@": _f(TWO_PI),
        "@VMAX@": _f(0.4 * TWO_PI / model.pole_pairs),
        "@MAXSTEP@": _f(TWO_PI / model.pole_pairs / 8.0),
        "@KV@": _f(s.speed_gain),
        "@KA@": _f(s.accel_gain),
        "@CAP@": _f(s.sample_cap),
        "@OUTLIER@": _f(s.outlier),
        "@EXPLAINED@": _f(s.explained),
        "@INVMEM@": _f(1.0 / s.adapt_memory),
        "@XMAX@": _f(ADAPT_CYCLE / s.adapt_min_samples),
        "@Q@": ", ".join(
            _f(s.prior_samples * w0[p >> 1] * (1.0 if p & 1 else model.amplitude[p >> 1] ** 2))
            for p in range(6)
        ),
        "@ALO@": _f(s.gain_bounds[0]),
        "@AHI@": _f(s.gain_bounds[1]),
        "@BLO@": ", ".join(
            _f(model.center[i] - s.offset_bound * model.amplitude[i]) for i in range(3)
        ),
        "@BHI@": ", ".join(
            _f(model.center[i] + s.offset_bound * model.amplitude[i]) for i in range(3)
        ),
        "@STALE@": _f(s.stale_travel),
        "@READMIT@": _f(s.readmit_travel),
        "@C@": ", ".join(_f(x) for x in model.center),
        "@W0@": ", ".join(_f(x) for x in w0),
        "@GROSS@": ", ".join(_f(x) for x in gross),
        "@T@": _rows(_cubics(model)),
        "@THRINV@": ",\n    ".join(
            ", ".join(
                "{" + _f(a) + ", " + _f(b) + "}"
                for a, b in zip(thr[i : i + 3], inv[i : i + 3], strict=True)
            )
            for i in range(0, len(inv), 3)
        ),
    }
    parts, dispatch = _adapt_parts()
    h, c = _HEADER, _SOURCE.replace("@PARTS@", parts).replace("@DISPATCH@", dispatch)
    for key, value in subst.items():
        h = h.replace(key, value)
        c = c.replace(key, value)
    return [(f"{prefix}.h", h), (f"{prefix}.c", c)]


def _cubics(model: ObserverModel) -> np.ndarray:
    """Per node j and channel i the power-basis coefficients (c0, c1, c2, c3) of the cubic
    Hermite interpolant of g_i - c_i on [y_j, y_j+1] in t = y / h - j (values p0, p1 and
    scaled slopes m0 = h g'_j, m1 = h g'_j+1): c0 = p0, c1 = m0, c2 = 3 (p1 - p0) - 2 m0 - m1,
    c3 = 2 (p0 - p1) + m0 + m1; shape (M, 12), computed in float64."""
    h = TWO_PI / model.points
    p0 = model.value - model.center
    p1 = np.roll(p0, -1, axis=0)
    m0 = h * model.slope
    m1 = np.roll(m0, -1, axis=0)
    c = np.stack([p0, m0, 3.0 * (p1 - p0) - 2.0 * m0 - m1, 2.0 * (p0 - p1) + m0 + m1], axis=2)
    return c.reshape(model.points, 12)


def _adapt_parts() -> tuple[str, str]:
    """The adaptation's parts 1..14 as straight-line C (one function each: rows 0, 1, 2 and
    rows 3-5 together of the information H, row 0's last three entries with rows 1 and 2, row
    0 first turning the measure's forgetting argument into exp(-x) and its den into CYCLE / den;
    columns 0..5 of its L D L^T,
    the two triangular solves, the second in two parts (x5..x2, x1..x0); the bounded update of
    channels 0 and 1), the switch cases that call them and the cases of a waiting phase (after
    an exclusion: no part); no loop, so that each part's cycles are its own few dozen
    operations."""
    fns: list[str] = []
    calls: list[str] = []

    def fn(name: str, body: list[str]) -> None:
        fns.append(f"NOINLINE static void {name}(@p@_state *s)\n{{\n" + "\n".join(body) + "\n}\n")
        calls.append(f"                case {len(calls) + 1}u:\n                    {name}(s);"
                     "\n                    break;")  # fmt: skip

    merged: list[str] = ["    const float lam = s->lam;"]
    for p in range(6):
        i = p >> 1
        prior = f"(1.0f - lam) * Q[{p}]"
        extra = f"s->u[{i}]" if p & 1 else f"s->u[{i}] * s->fy[{i}] * s->fy[{i}]"
        body = [f"    const float v{p} = s->t * s->qv[{p}];"]
        if p == 0:  # the measure's forgetting exp(-x) (cubic Taylor) and CYCLE / den
            body = ["    const float x = s->lam, t = (float)CYCLE / s->t, v0 = t * s->qv[0];",
                    "    const float lam = 1.0f - x * (1.0f - x * (0.5f - x * (1.0f / 6.0f)));",
                    "    s->lam = lam;", "    s->t = t;"]  # fmt: skip
        diag = f"s->H[{p}][{p}]"
        body.append(f"    {diag} = (({diag} * lam + {prior}) + {extra}) - v{p} * s->qv[{p}];")
        for q in range(p + 1, 6 if p else 3):  # row 0's last three entries: in rows 1 and 2
            add = f" + s->u[{i}] * s->fy[{i}]" if (q == p + 1 and not p & 1) else ""
            body.append(f"    s->H[{p}][{q}] = (s->H[{p}][{q}] * lam{add}) - v{p} * s->qv[{q}];")
        if p == 0:
            fn("row0", body)
        elif p < 3:
            # H[0][4] with row 1, H[0][3] and H[0][5] with row 2 (row 0 has the forgetting and
            # CYCLE / den)
            fn(f"row{p}", ["    const float lam = s->lam;", *body] + [
                f"    s->H[0][{q}] = s->H[0][{q}] * lam - (s->t * s->qv[0]) * s->qv[{q}];"
                for q in ((4,) if p == 1 else (3, 5))])  # fmt: skip
        else:  # rows 3, 4 and 5 (3, 2 and 1 entries) in one part
            merged += body
    fn("rows345", merged)
    for j in range(6):
        body = [f"    float t = s->H[{j}][{j}], rj;"]
        body += [f"    const float m{k} = s->L[{j}][{k}] * s->P[{k}];" for k in range(j)]
        body += [f"    t -= s->L[{j}][{k}] * m{k};" for k in range(j)]
        body += ["    if (!(t > 0.0f)) {", "        s->pending = 0u;", "        return;", "    }",
                 f"    s->P[{j}] = t;", "    rj = 1.0f / t;", f"    s->R[{j}] = rj;"]  # fmt: skip
        for i in range(j + 1, 6):
            terms = "".join(f" - s->L[{i}][{k}] * m{k}" for k in range(j))
            body.append(f"    s->L[{i}][{j}] = (s->H[{j}][{i}]{terms}) * rj;")
        fn(f"column{j}", body)
    body = ["    const float z0 = s->gr[0];"]
    for i in range(1, 6):
        terms = "".join(f" - s->L[{i}][{k}] * z{k}" for k in range(i))
        body.append(f"    const float z{i} = s->gr[{i}]{terms};")
    body += [f"    s->z[{i}] = z{i};" for i in range(6)]
    fn("forward", body)
    for half, rows in (("backward5", range(5, 1, -1)), ("backward1", range(1, -1, -1))):
        body = [f"    const float z{k} = s->z[{k}];" for k in range(rows[0] + 1, 6)]
        for i in rows:
            terms = "".join(f" - s->L[{k}][{i}] * z{k}" for k in range(i + 1, 6))
            body.append(f"    const float z{i} = s->z[{i}] * s->R[{i}]{terms};")
        body += [f"    s->z[{i}] = z{i};" for i in rows]
        fn(half, body)  # D L^T x = z in two parts: x5..x2, then x1..x0
    # the bounded update of channels 0 and 1 (of 2 and the commit: the cycle's last part)
    calls.append(f"                case {len(calls) + 1}u:\n                    bound01(s);"
                 "\n                    break;")  # fmt: skip
    # the sample after an exclusion waits (phase + 2 CYCLE - 1: no part; see exclude)
    held = range(2 * ADAPT_CYCLE - 1, 3 * ADAPT_CYCLE - 1)
    calls.append(
        "".join(f"                case {ph}u:\n" for ph in held) + "                    break;"
    )
    return "\n".join(fns), "\n".join(calls)


def _normal_quantile(p: float) -> float:
    """The standard normal quantile at p (the observer's, see :func:`run_observer`)."""
    import statistics

    return statistics.NormalDist().inv_cdf(p)


_HEADER = """\
/* @p@.h: the model-based angle observer of hallcal (tracking maximum-likelihood angle, misfit
 * monitor, gain/offset adaptation, one-sensor fallback), single precision. Generated from
 * @SOURCE@ by hallcal export-c --observer; see docs/firmware.md. */
#ifndef @P@_H
#define @P@_H
#include <stdint.h>

#define @P@_M @M@u
#define @P@_WINDOW @W@u
#define @P@_FAULT_WINDOW @FW@u

/* state of a reading (the observer's ObserverState, in that order) */
#define @P@_OK 0u
#define @P@_ADAPTING 1u
#define @P@_STALE 2u
#define @P@_DEGRADED 3u
#define @P@_FAULT 4u

typedef struct {
    int32_t revolutions; /* whole revolutions */
    float angle;         /* [rad] within the revolution, 0 <= angle < 2 pi */
    float misfit;        /* windowed chi-square per degree of freedom, about 1 when it fits */
    uint8_t state;       /* @P@_OK .. @P@_FAULT */
    int8_t excluded;     /* channel 0..2 excluded, -1 none */
    uint32_t flags;      /* state | (excluded + 1) << 8, in one word */
    uint32_t sample;     /* samples processed */
} @p@_reading;

typedef struct { /* the fields of every sample first (short offsets) */
    int32_t rev;
    float ang, v, acc, clean, bad, sum_chi; /* angle, speed, acceleration of the tracker */
    float a[3], b[3];
    float w[3];                     /* the weights 1 / sigma_i^2, 0 for the channel excluded */
    uint32_t k;
    volatile uint32_t seq;
    volatile @p@_reading buf[2]; /* volatile: the copies stay between the reads of seq */
    float H[6][6];                  /* the adaptation's information (upper triangle) */
    float L[6][6], P[6], R[6];      /* its L D L^T (R = 1 / P), built over a cycle */
    float gr[6], z[6], wm[3];       /* the cycle's gradient, solution, channels measured */
    float qv[6], fy[3], u[3], lam, t; /* the cycle's sample: projection, regressors, weights;
                                       * forgetting, CYCLE / den (den until row 0) */
    uint8_t pending, phase;         /* a cycle's update is under way; its part next */
    float ring_chi[@P@_WINDOW];
    uint8_t ring_dof[@P@_WINDOW];
    union {
        int8_t b[@FWPAD@];
        uint32_t w[@FWW@]; /* the ring's reset in words */
    } ring_blame;   /* -1: no blame */
    uint32_t blames; /* the ring's marks per channel (byte q: channel q, byte 3: none explains) */
    int32_t sum_dof;
    uint32_t window_from; /* window entries written before this sample count as empty */
    int8_t excluded, next;          /* the channel excluded; the one excluded at the next sample */
    uint8_t blamed_out, suppress, acquire;
} @p@_state;

void @p@_init(@p@_state *s); /* angle 0 of revolution 0 */
/* the angle before the next sample (0 <= angle < 2 pi); 1: refused (out of range) */
uint8_t @p@_set_angle(@p@_state *s, int32_t revolutions, float angle);
uint8_t @p@_update(@p@_state *s, float d1, float d2, float d3);
void @p@_read(const @p@_state *s, @p@_reading *r);

#endif
"""

_SOURCE = """\
/* @p@.c: generated from @SOURCE@ by hallcal export-c --observer. */
#include "@p@.h"

#define M @M@
#define W @W@
#define FW @FW@
#define FC @FC@
#define NA @NA@
#define CYCLE @CYCLE@
#define BIAS @BIAS@

static const float NM = @NM@;
static const float HSTEP = @H@;
static const float INVH = @INVH@;
static const float TWOPI = @TWO_PI@;
static const float MAXSTEP = @MAXSTEP@;
static const float VMAX = @VMAX@;
static const float KV = @KV@;
static const float KA = @KA@;
static const float CAP = @CAP@;
static const float OUTLIER = @OUTLIER@;
static const float EXPLAINED = @EXPLAINED@;
static const float INVMEM = @INVMEM@;
static const float XMAX = @XMAX@; /* the forgetting per cycle at most: CYCLE / adapt_min_samples */
/* the prior's information: prior_samples w0_i (amplitude_i^2, 1) */
static const float Q[6] = {@Q@};
static const float ALO = @ALO@;
static const float AHI = @AHI@;
static const float BLO[3] = {@BLO@}; /* the levels' bounds: c_i -+ offset_bound amplitude_i */
static const float BHI[3] = {@BHI@};
static const float STALE = @STALE@;
static const float READMIT = @READMIT@;
static const float C0[3] = {@C@};
static const float W0[3] = {@W0@};
static const float GROSS[3] = {@GROSS@};
static const int16_t OFF[NA] = {@OFF@};
/* a mark's count in the packed blame counts (index mark + 1: none, channel 0, 1, 2, 3) */
static const uint32_t ONE[5] = {0u, 1u, 0x100u, 0x10000u, 0x1000000u};
/* per k degrees of freedom of the window: the alarm threshold and 1 / k (one address) */
static const float THRINV[2 * W + 1][2] = {
    @THRINV@
};
static const float T[M][12] = { /* per channel i: the cubic of g_i - c_i on [y_j, y_j+1] in
                                  * t = y / h - j (y_j = j 2 pi / M, h = 2 pi / M): constant,
                                  * t, t^2, t^3 coefficients */
@T@
};

#if defined(__GNUC__)
#define NOINLINE __attribute__((noinline)) /* the rare parts out of the common path */
#else
#define NOINLINE
#endif

#if defined(__GNUC__)
#define RARE(x) __builtin_expect(!!(x), 0) /* block layout: the worst-case path falls through */
#define LIKELY(x) __builtin_expect(!!(x), 1)
#else
#define RARE(x) (x)
#define LIKELY(x) (x)
#endif

#if defined(__GNUC__)
#define fabs_(x) __builtin_fabsf(x) /* VABS.F32: no library call */
#else
static float fabs_(float x) { return x < 0.0f ? -x : x; }
#endif
/* finite: the exponent bits not all ones (IEEE 754 single) */
static uint32_t bits_(float x)
{
    union {
        float f;
        uint32_t u;
    } v;
    v.f = x;
    return v.u;
}
#define FIN(x) ((bits_(x) & 0x7f800000u) != 0x7f800000u)
#if defined(__FINITE_MATH_ONLY__) && __FINITE_MATH_ONLY__
/* (-ffast-math: x - x would be folded to 0) an exponent of all ones carries into bit 31 */
#define FINITE3(x, y, z)                                                                       \
    (((((bits_(x) & 0x7f800000u) + 0x00800000u) | ((bits_(y) & 0x7f800000u) + 0x00800000u) |   \
       ((bits_(z) & 0x7f800000u) + 0x00800000u)) & 0x80000000u) == 0u)
#else
/* x - x is +0 for a finite x and NaN otherwise, and NaN fails every comparison: the readings
 * stay in the FPU's registers */
#define FINITE3(x, y, z) (((x) - (x)) + ((y) - (y)) + ((z) - (z)) <= 0.0f)
#endif

/* cubic Hermite interpolation of g - c and dg/dy at y (any real y: wrap-around); the table
 * holds, per node and channel, the interval's cubic in t = y / h - j (its power-basis
 * coefficients: the same polynomial as the Hermite form of values and slopes) */
static void table(float y, float f[3], float dg[3])
{
    /* u > 0 for y > -VMAX (y = angle + speed: -VMAX < y < 2 pi + VMAX; BIAS, a power of two
     * above VMAX / h, keeps u's binade), so that the conversion's truncation is the floor */
    float u = y * INVH + (float)BIAS, t, c, a, b;
    uint32_t j = (uint32_t)u;
    const float *p;
    t = u - (float)j;
    p = T[(j - (uint32_t)BIAS) & (uint32_t)(M - 1)];
    /* Horner: a = c3 t + c2, b = a t + c1, g = b t + c0; its derivative in t,
     * 3 c3 t^2 + 2 c2 t + c1 = b + (a + c3 t) t, from the same partial sums */
#define CUBIC(i, k)                                                                            \
    c = p[(k) + 3] * t;                                                                        \
    a = c + p[(k) + 2];                                                                        \
    b = a * t + p[(k) + 1];                                                                    \
    f[i] = b * t + p[k];                                                                       \
    dg[i] = (b + (a + c) * t) * INVH;
    CUBIC(0, 0)
    CUBIC(1, 4)
    CUBIC(2, 8)
#undef CUBIC
}

/* one Gauss-Newton step on the linearized model, bounded; the chi2 after it in *chi */
static float gn(float srr, float num, float den, float *chi)
{
    float step, c;
    if (den <= 0.0f) {
        *chi = srr;
        return 0.0f;
    }
    if (RARE(fabs_(num) > MAXSTEP * den)) { /* bounded: no division (den > 0) */
        step = num > 0.0f ? MAXSTEP : -MAXSTEP;
    } else {
        step = num / den;
    }
    c = srr - step * (2.0f * num - step * den);
    *chi = c > 0.0f ? c : 0.0f;
    return step;
}

/* the start: the best of NA table nodes within half a pole pitch of y0 */
NOINLINE static float acquire(const @p@_state *s, float d0, float d1, float d2, float w0,
                              float w1, float w2, float y0)
{
    const float a0 = s->a[0], a1 = s->a[1], a2 = s->a[2];
    const float e0 = d0 - s->b[0], e1 = d1 - s->b[1], e2 = d2 - s->b[2];
    float best = 3.0e38f, c, r0, r1, r2, u = y0 * INVH + 0.5f;
    const float *p;
    int32_t j0 = (int32_t)u, j, bj;
    int q;
    if ((float)j0 > u) {
        j0 -= 1;
    }
    bj = j0;
#if defined(__GNUC__) && (__GNUC__ >= 8)
#pragma GCC unroll 8
#endif
    for (q = 0; q < NA; q++) {
        j = j0 + OFF[q];
        p = T[(uint32_t)j & (uint32_t)(M - 1)];
        r0 = e0 - a0 * p[0];
        r1 = e1 - a1 * p[4];
        r2 = e2 - a2 * p[8];
        c = w0 * r0 * r0 + w1 * r1 * r1 + w2 * r2 * r2;
        if (c < best) {
            best = c;
            bj = j;
        }
    }
    return (float)bj * HSTEP;
}

/* The adaptation, one small part per sample of its cycle of CYCLE samples (the cycle advances
 * on samples without the fits of the outlier test, but for the first after an exclusion): 0 the
 * sample's regressors, 1..4 rows 0 (H00..H02), 1 (and H04), 2 (and H03, H05) and 3-5 of the
 * information H (upper triangle), 5..10 one column of its L D L^T, 11 L z = gr,
 * 12 and 13 D L^T x = z (x5..x2, x1..x0), 14 the bounded update of channels 0 and 1, 15 of
 * channel 2 and the commit of all three. */
/* the cycle's sample, channel i (in update: f, dg, r, J, w, step of the sample) */
#define MEASURE(i, fi, gi, ri, Ji, wi)                                                         \
    do {                                                                                   \
        const float fy_ = (fi) + (gi) * step, ry_ = (ri) - (Ji) * step;                    \
        const float u_ = (float)CYCLE * (wi);                                              \
        s->fy[i] = fy_;                                                                    \
        s->u[i] = u_;                                                                      \
        s->qv[2 * (i)] = (wi) * fy_ * (Ji);                                                \
        s->qv[2 * (i) + 1] = (wi) * (Ji);                                                  \
        s->gr[2 * (i)] = u_ * fy_ * ry_;                                                   \
        s->gr[2 * (i) + 1] = u_ * ry_;                                                     \
        s->wm[i] = (wi);                                                                   \
    } while (0)

@PARTS@
/* the bounded update of the channels measured, one channel per part (into z: the new a_i, b_i;
 * unchanged for a channel not measured), committed with the last channel's (so that the gains
 * and levels change at one sample, as in Python) */
#define BOUND(i)                                                                             \
    if (s->wm[i] > 0.0f) {                                                                   \
        float t_ = s->a[i] + s->z[2 * (i)];                                                  \
        t_ = t_ < ALO ? ALO : t_;                                                            \
        s->z[2 * (i)] = t_ > AHI ? AHI : t_;                                                 \
        t_ = s->b[i] + s->z[2 * (i) + 1];                                                    \
        t_ = t_ < BLO[i] ? BLO[i] : t_;                                                      \
        s->z[2 * (i) + 1] = t_ > BHI[i] ? BHI[i] : t_;                                       \
    } else {                                                                                 \
        s->z[2 * (i)] = s->a[i];                                                             \
        s->z[2 * (i) + 1] = s->b[i];                                                         \
    }

NOINLINE static void bound01(@p@_state *s)
{
    BOUND(0)
    BOUND(1)
}

NOINLINE static void apply(@p@_state *s)
{
    BOUND(2)
    s->a[0] = s->z[0];
    s->b[0] = s->z[1];
    s->a[1] = s->z[2];
    s->b[1] = s->z[3];
    s->a[2] = s->z[4];
    s->b[2] = s->z[5];
}

/* the weights of the channels in use (after a change of the excluded channel) */
static void weights(@p@_state *s)
{
    s->w[0] = s->excluded != 0 ? W0[0] : 0.0f;
    s->w[1] = s->excluded != 1 ? W0[1] : 0.0f;
    s->w[2] = s->excluded != 2 ? W0[2] : 0.0f;
}

/* the exclusion of channel s->next (decided on the previous sample) */
NOINLINE static void exclude(@p@_state *s)
{
    s->excluded = s->next;
    weights(s);
    s->next = -1;
    s->blamed_out = 1u;
    s->clean = 0.0f;
    s->blames = 0u; /* the blame ring and */
@RINGRESET@    s->window_from = s->k; /* the window start again */
    s->sum_chi = 0.0f;
    s->sum_dof = 0;
    if (s->phase < CYCLE) { /* the adaptation's next sample waits (not on this one's time): a
                             * phase ph + 2 CYCLE - 1, which runs no part and returns to ph */
        s->phase = (uint8_t)(s->phase + 2u * CYCLE - 1u);
    }
}

void @p@_init(@p@_state *s)
{
    int i, j;
    s->rev = 0;
    s->ang = 0.0f;
    s->v = s->acc = s->clean = s->bad = s->sum_chi = 0.0f;
    s->sum_dof = 0;
    for (i = 0; i < 3; i++) {
        s->a[i] = 1.0f;
        s->b[i] = C0[i];
    }
    for (i = 0; i < 6; i++) { /* L is written column by column before it is read */
        for (j = 0; j < 6; j++) {
            s->H[i][j] = (i != j) ? 0.0f : Q[i];
        }
    }
    s->pending = 0u;
    s->phase = 0u;
    s->blames = 0u;
    s->window_from = 0u;
@RINGRESET@    s->excluded = -1;
    weights(s);
    s->next = -1;
    s->blamed_out = 0u;
    s->suppress = 0u;
    s->acquire = 1u;
    s->k = 0u;
    s->seq = 0u;
    s->buf[0].revolutions = 0;
    s->buf[0].angle = 0.0f;
    s->buf[0].misfit = 0.0f;
    s->buf[0].state = @P@_OK;
    s->buf[0].excluded = -1;
    s->buf[0].flags = 0u;
    s->buf[0].sample = 0u;
    s->buf[1] = s->buf[0];
}

uint8_t @p@_set_angle(@p@_state *s, int32_t revolutions, float angle)
{
    if (!(angle >= 0.0f && angle < TWOPI)) { /* NaN, infinite or outside the revolution */
        return 1u;
    }
    s->rev = revolutions;
    s->ang = angle;
    s->v = 0.0f;
    s->acc = 0.0f;
    s->acquire = 1u; /* the next sample searches within half a pole pitch of it */
    return 0u;
}

/* one of three values by a channel index (no local array is indexed: they stay in registers) */
#define SEL(i, x0, x1, x2) ((i) == 0 ? (x0) : ((i) == 1 ? (x1) : (x2)))

uint8_t @p@_update(@p@_state *s, float d1, float d2, float d3)
{
    float w0, w1, w2, f0 = 0.0f, f1 = 0.0f, f2 = 0.0f, g0 = 0.0f, g1 = 0.0f, g2 = 0.0f;
    float r0 = 0.0f, r1 = 0.0f, r2 = 0.0f, J0 = 0.0f, J1 = 0.0f, J2 = 0.0f, tr0, tr1, tr2;
    float tn0, tn1, tn2, td0, td1, td2, f[3], dg[3], yp, y, step = 0.0f, chi = 0.0f;
    float srr = 0.0f, num = 0.0f, den = 0.0f, best, best_step, e, travel, mf = 0.0f;
    float n0, n1, n2, s0, s1, s2, c0, c1, c2, Jb;
    float cc, cmax = CAP, A01, A11, rs, Js0, Js1, Js2, det, x, e0, e1, e2, i0, i1, i2;
    int active, blamed = -1, mark = -1, above = 0, stale, fitted, loo = 0;
    int fin0, fin1, fin2, i, dof;
    uint32_t fin = 7u; /* bit i: reading i finite */
    uint32_t slot, jw, ph, bw, nb, others;
    int8_t old;
    if (RARE(s->next >= 0)) { /* the exclusion decided on the previous sample */
        exclude(s);
    }
    if (LIKELY(FINITE3(d1, d2, d3))) { /* all finite: the weights of the channels in use */
        w0 = s->w[0];
        w1 = s->w[1];
        w2 = s->w[2];
        active = s->excluded < 0 ? 3 : 2;
    } else {
        fin0 = FIN(d1);
        fin1 = FIN(d2);
        fin2 = FIN(d3);
        d1 = fin0 ? d1 : 0.0f;
        d2 = fin1 ? d2 : 0.0f;
        d3 = fin2 ? d3 : 0.0f;
        fin = (uint32_t)fin0 | (uint32_t)fin1 << 1 | (uint32_t)fin2 << 2;
        if (s->excluded < 0) { /* a disconnected channel */
            s->excluded = (int8_t)(!fin0 ? 0 : (!fin1 ? 1 : 2));
            s->blamed_out = 0u;
            s->clean = 0.0f;
            weights(s);
        }
        w0 = fin0 ? s->w[0] : 0.0f; /* 0 for a channel not in use */
        w1 = fin1 ? s->w[1] : 0.0f;
        w2 = fin2 ? s->w[2] : 0.0f;
        /* the channels in use: finite and not excluded (here one is: it was, or is now) */
        i = (int)(fin & ~(1u << s->excluded));
        active = (i & 1) + (i >> 1 & 1) + (i >> 2);
    }
    yp = s->ang + s->v;
    y = yp;
    fitted = 0;
    if (RARE(active < 2)) {
        /* no fit: fault */
    } else if (RARE(s->acquire)) {
        y = acquire(s, d1, d2, d3, w0, w1, w2, yp);
        s->acquire = 0u;
    } else {
        fitted = 1;
        table(yp, f, dg);
        f0 = f[0];
        f1 = f[1];
        f2 = f[2];
        g0 = dg[0];
        g1 = dg[1];
        g2 = dg[2];
        J0 = s->a[0] * g0;
        J1 = s->a[1] * g1;
        J2 = s->a[2] * g2;
        r0 = d1 - s->a[0] * f0 - s->b[0];
        r1 = d2 - s->a[1] * f1 - s->b[1];
        r2 = d3 - s->a[2] * f2 - s->b[2];
        /* an unused channel has w = 0 and a finite r: it adds exact zeros */
        tr0 = w0 * r0 * r0;
        tr1 = w1 * r1 * r1;
        tr2 = w2 * r2 * r2;
        tn0 = w0 * J0 * r0;
        tn1 = w1 * J1 * r1;
        tn2 = w2 * J2 * r2;
        td0 = w0 * J0 * J0;
        td1 = w1 * J1 * J1;
        td2 = w2 * J2 * J2;
        srr = tr0 + tr1 + tr2;
        num = tn0 + tn1 + tn2;
        den = td0 + td1 + td2;
        step = gn(srr, num, den, &chi);
        cmax = active == 3 ? 2.0f * CAP : CAP; /* CAP per degree of freedom */
        if (active == 3 && chi > OUTLIER) {
            /* explained by a common gain of the field parts? else the fits without a channel */
            Js0 = s->a[0] * f0;
            Js1 = s->a[1] * f1;
            Js2 = s->a[2] * f2;
            A01 = w0 * J0 * Js0 + w1 * J1 * Js1 + w2 * J2 * Js2;
            A11 = w0 * Js0 * Js0 + w1 * Js1 * Js1 + w2 * Js2 * Js2;
            rs = w0 * Js0 * r0 + w1 * Js1 * r1 + w2 * Js2 * r2;
            det = den * A11 - A01 * A01;
            if (!(det > 0.0f && (srr - EXPLAINED) * det <= num * (A11 * num - 2.0f * A01 * rs)
                                                            + den * rs * rs)) {
                loo = 1;
                /* the three fits without one channel; their 1 / den from one division */
                e0 = den - (J0 * J0) * w0; /* (recomputed: not kept live) */
                e1 = den - (J1 * J1) * w1;
                e2 = den - (J2 * J2) * w2;
                x = e0 * e1 * e2;
                if (LIKELY(bits_(x) - @XLO@u < @XRANGE@u)) { /* 2^-124 <= x < 2^124 */
                    x = 1.0f / x;
                    i0 = e1 * e2 * x;
                    i1 = e0 * e2 * x;
                    i2 = e0 * e1 * x;
                } else { /* a den not positive (gnr: no step) or out of range */
                    i0 = e0 > 0.0f ? 1.0f / e0 : 0.0f;
                    i1 = e1 > 0.0f ? 1.0f / e1 : 0.0f;
                    i2 = e2 > 0.0f ? 1.0f / e2 : 0.0f;
                }
                /* chi2 of the fit without q, unbounded: (srr - tr_q) - n_q^2 / e_q */
                n0 = num - (r0 * J0) * w0;
                n1 = num - (r1 * J1) * w1;
                n2 = num - (r2 * J2) * w2;
                s0 = n0 * i0;
                s1 = n1 * i1;
                s2 = n2 * i2;
                c0 = (srr - (r0 * r0) * w0) - s0 * n0;
                c1 = (srr - (r1 * r1) * w1) - s1 * n1;
                c2 = (srr - (r2 * r2) * w2) - s2 * n2;
                /* the smallest (the first of equals), by conditional moves; the chosen
                 * channel's residual off the fit without it */
                best = c0;
                best_step = s0;
                blamed = 0;
                Jb = J0;
                e = r0 - J0 * s0;
                if (c1 < best) {
                    best = c1;
                    best_step = s1;
                    blamed = 1;
                    Jb = J1;
                    e = r1 - J1 * s1;
                }
                if (c2 < best) {
                    best = c2;
                    best_step = s2;
                    blamed = 2;
                    Jb = J2;
                    e = r2 - J2 * s2;
                }
                if (!(best < EXPLAINED && best < 0.1f * chi)) {
                    blamed = -1;
                    mark = 3;
                } else {
                    if (fabs_(best_step) > MAXSTEP) { /* the chosen fit's step, bounded */
                        x = best_step > 0.0f ? MAXSTEP : -MAXSTEP;
                        e += Jb * (best_step - x); /* the residual at the bounded step */
                        best_step = x;
                    }
                    if (fabs_(e) < GROSS[blamed]) {
                        blamed = -1;
                    } else {
                        step = best_step;
                        mark = blamed;
                        cmax = CAP; /* CAP when a channel is blamed */
                    }
                }
            }
        }
        y = yp + step;
    }
    /* fault isolation (the ring all -1 when no mark is in it: nothing to do without one) */
    if ((mark >= 0) | (s->blames != 0u)) {
        slot = s->k % (uint32_t)FW;
        old = s->ring_blame.b[slot];
        s->ring_blame.b[slot] = (int8_t)mark;
        bw = s->blames + ONE[mark + 1] - ONE[old + 1];
        s->blames = bw;
        if (blamed >= 0 && s->excluded < 0 && !s->suppress) {
            nb = (bw >> (8 * blamed)) & 0xffu;
            others = ((bw * 0x01010101u) >> 24) - nb; /* the bytes' sum, less channel blamed's */
            if (nb >= FC && 4u * others <= nb) {
                s->next = (int8_t)blamed; /* excluded from the next sample on */
            }
        }
    }
    if (blamed < 0 && fitted) { /* the tracker: acceleration, then speed (bounded: then no
                                 * acceleration, so that it does not wind up) */
        e = s->acc + KA * step;
        x = s->v + e + KV * step;
        if (RARE(fabs_(x) > VMAX)) {
            x = x > 0.0f ? VMAX : -VMAX;
            e = 0.0f;
        }
        s->acc = e;
        s->v = x;
    }
    /* the angle within the revolution (|y - angle| < 2 pi: one wrap at most) */
    if (RARE(y >= TWOPI)) {
        y -= TWOPI;
        s->rev++;
    } else if (RARE(y < 0.0f)) {
        y += TWOPI;
        s->rev--;
    }
    s->ang = y;
    travel = NM * fabs_(s->v);
    /* misfit window */
    /* a sample's cap: CAP per degree of freedom, CAP when a channel is blamed */
    cc = chi < cmax ? chi : cmax;
    dof = fitted ? active - 1 : 0;
    jw = s->k % (uint32_t)W;
    if (LIKELY(s->k >= s->window_from + (uint32_t)W)) {
        s->sum_chi -= s->ring_chi[jw];
        s->sum_dof -= (int32_t)s->ring_dof[jw];
    }
    s->sum_chi += cc;
    s->sum_dof += dof;
    s->ring_chi[jw] = cc;
    s->ring_dof[jw] = (uint8_t)dof;
    if (s->sum_dof > 0) {
        mf = s->sum_chi * THRINV[s->sum_dof][1];
        above = s->sum_chi > THRINV[s->sum_dof][0];
    }
    stale = 0;
    if (!above) {
        s->bad = 0.0f;
        s->suppress = 0u;
    } else {
        x = s->bad + travel;
        s->bad = x;
        stale = x >= STALE;
        if (RARE(s->excluded >= 0 && s->blamed_out && (fin >> s->excluded & 1u))) {
            s->excluded = -1;
            s->suppress = 1u;
            weights(s);
        }
    }
    /* adaptation: one part per sample of its cycle */
    if (!loo) {
        /* readmission (not on an outlier's fits: three channels in use; before the
         * adaptation, which reads neither the excluded channel nor its gain) */
        if (RARE(fitted && s->excluded >= 0)) {
            i = s->excluded;
            if (!(fin >> i & 1u)) {
                s->clean = 0.0f;
            } else {
                e = SEL(i, r0, r1, r2) - SEL(i, J0, J1, J2) * step;
                s->clean = (W0[i] * e * e < 16.0f) ? s->clean + travel : 0.0f;
            }
            if (s->clean >= READMIT) {
                s->excluded = -1;
                s->clean = 0.0f;
                weights(s);
            }
        }
        ph = s->phase;
        if (ph == 0u) {
            /* settled: the step within 5 sigma of the angle's own noise (1 / den) */
            if (fitted && !stale && blamed < 0 && step * step * den < 25.0f) {
                x = (float)CYCLE * travel * INVMEM;
                s->lam = x < XMAX ? x : XMAX; /* row0 makes it exp(-x) */
                s->t = den; /* row0 makes it CYCLE / den (no division on this sample) */
                MEASURE(0, f0, g0, r0, J0, w0);
                MEASURE(1, f1, g1, r1, J1, w1);
                MEASURE(2, f2, g2, r2, J2, w2);
                s->pending = (uint8_t)(den > 0.0f);
                s->phase = 1u;
            }
        } else {
            if (s->pending) {
                switch (ph) {
@DISPATCH@
                default:
                    if (!stale) {
                        apply(s);
                    }
                    s->pending = 0u;
                    break;
                }
            }
            s->phase = (uint8_t)((ph + 1u) % (uint32_t)CYCLE);
        }
    }
    /* publish */
    {
        uint32_t next = s->seq + 1u;
        volatile @p@_reading *rd = &s->buf[next & 1u];
        /* by priority, each a conditional move: a model that no longer fits outranks a
         * channel out */
        uint8_t st = above ? @P@_ADAPTING : @P@_OK;
        st = s->excluded >= 0 ? @P@_DEGRADED : st;
        st = stale ? @P@_STALE : st;
        st = active < 2 ? @P@_FAULT : st;
        rd->revolutions = s->rev;
        rd->angle = s->ang;
        rd->misfit = mf;
        rd->flags = (uint32_t)st | ((uint32_t)(s->excluded + 1) << 8);
        rd->sample = s->k + 1u;
        s->seq = next;
        s->k++;
        return st;
    }
}

void @p@_read(const @p@_state *s, @p@_reading *r)
{
    uint32_t a, b, f;
    do {
        const volatile @p@_reading *q;
        a = s->seq;
        q = &s->buf[a & 1u];
        r->revolutions = q->revolutions;
        r->angle = q->angle;
        r->misfit = q->misfit;
        f = q->flags; /* state and excluded channel published in it, one word */
        r->sample = q->sample;
        b = s->seq;
    } while (a != b);
    r->flags = f;
    r->state = (uint8_t)(f & 0xffu);
    r->excluded = (int8_t)((int32_t)(f >> 8) - 1);
}
"""
