"""The model-based observer (:mod:`hallcal.sensor.observer`) as C99 in single precision.

``export_observer_c(artifact, out_dir)`` writes ``<prefix>.h`` / ``<prefix>.c``: the same
per-sample algorithm as :func:`hallcal.sensor.observer.run_observer` (tracking
maximum-likelihood angle by Gauss-Newton on cubic Hermite tables of g and dg/dy, the misfit
window, the gain/offset adaptation, the one-sensor fallback), in ``float``, with the API style
of the lean export: ``_init`` (revolutions and angle before the first sample), ``_update`` (one
sample), ``_read`` (one consistent snapshot: revolutions, angle, misfit, state, excluded
channel). It includes only ``<stdint.h>``, uses no library function (the square roots and the
chi-square thresholds are tabulated here; the adaptation's 6x6 system is solved by an LDL^T
factorization, which needs no square root; exp(-x) of the forgetting is 1 - x + x^2/2 - x^3/6,
within 5e-6 for the x below 0.06 it takes up to a quarter electrical turn per sample), no
dynamic memory, and divisions only in the Gauss-Newton steps and the 6x6 solve.

The angle is kept as a revolution count and a float angle within the revolution, so that its
resolution does not degrade over a long run. Worst-case work per sample is bounded (no loop
depends on the data): 2 Gauss-Newton steps, on an outlier sample 1 scaled fit and 3 fits
without one channel, the adaptation; a 64-point search at start and after an exclusion.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.io import ArtifactData, validate_artifact
from hallcal.output.codegen.export import _write_files
from hallcal.output.codegen.text import comment_text
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.observer import (
    ObserverModel,
    ObserverSettings,
    chi_square_quantile,
    observer_model,
)

__all__ = ["ObserverExport", "export_observer_c"]

TWO_PI = 2.0 * math.pi


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
        Bytes of the g and dg/dy tables (float) plus the threshold table.
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
    art = artifact if isinstance(artifact, ArtifactData) else validate_artifact(artifact, source)
    flux = art.flux()
    n = art.pole_pairs
    model = observer_model(flux, n, _noise(art.data, flux, n))
    texts = _texts(model, ObserverSettings(), prefix, comment_text(Path(source).name))
    paths = _write_files(out_dir, texts)  # one set, write errors as one line (hallcal.io)
    W = ObserverSettings().window
    nbytes = model.points * 3 * 2 * 4 + (2 * W + 1) * 4
    return ObserverExport(paths, model.points, nbytes)


def _texts(
    model: ObserverModel, s: ObserverSettings, prefix: str, source: str
) -> list[tuple[str, str]]:
    """The header and the source, filled from the model and the settings."""
    P = prefix.upper()
    W = s.window
    z = -_normal_quantile(s.false_alarm)
    thr = [0.0] + [chi_square_quantile(float(k), z) for k in range(1, 2 * W + 1)]
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
        "@FC@": str(s.fault_count),
        "@ITER@": str(s.iterations),
        "@NM@": _f(model.pole_pairs),
        "@H@": _f(TWO_PI / model.points),
        "@INVH@": _f(model.points / TWO_PI),
        "@TWO_PI@": _f(TWO_PI),
        "@PITCH@": _f(TWO_PI / model.pole_pairs),
        "@MAXSTEP@": _f(TWO_PI / model.pole_pairs / 8.0),
        "@KV@": _f(s.speed_gain),
        "@CAP@": _f(s.sample_cap),
        "@OUTLIER@": _f(s.outlier),
        "@EXPLAINED@": _f(s.explained),
        "@INVMEM@": _f(1.0 / s.adapt_memory),
        "@PRIOR@": _f(s.prior_samples),
        "@ALO@": _f(s.gain_bounds[0]),
        "@AHI@": _f(s.gain_bounds[1]),
        "@BBOUND@": _f(s.offset_bound),
        "@STALE@": _f(s.stale_travel),
        "@READMIT@": _f(s.readmit_travel),
        "@C@": ", ".join(_f(x) for x in model.center),
        "@AMP@": ", ".join(_f(x) for x in model.amplitude),
        "@W0@": ", ".join(_f(x) for x in w0),
        "@GROSS@": ", ".join(_f(x) for x in gross),
        "@G@": _rows(model.value),
        "@DG@": _rows(model.slope),
        "@THR@": ",\n    ".join(
            ", ".join(_f(x) for x in thr[i : i + 6]) for i in range(0, len(thr), 6)
        ),  # fmt: skip
    }
    h, c = _HEADER, _SOURCE
    for key, value in subst.items():
        h = h.replace(key, value)
        c = c.replace(key, value)
    return [(f"{prefix}.h", h), (f"{prefix}.c", c)]


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

typedef struct {
    int32_t rev;
    float ang, v, clean, bad, sum_chi;
    float a[3], b[3], b0[3];
    float H[6][6];
    float ring_chi[@P@_WINDOW];
    uint8_t ring_dof[@P@_WINDOW];
    int8_t ring_blame[@P@_FAULT_WINDOW];
    int16_t blame[4];
    int32_t sum_dof;
    uint32_t window_from, blame_from; /* ring entries written before these samples count as empty */
    int8_t excluded;
    uint8_t blamed_out, suppress, acquire;
    uint32_t k;
    volatile uint32_t seq;
    @p@_reading buf[2];
} @p@_state;

void @p@_init(@p@_state *s, int32_t revolutions, float angle);
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
#define ITER @ITER@

static const float NM = @NM@;
static const float HSTEP = @H@;
static const float INVH = @INVH@;
static const float TWOPI = @TWO_PI@;
static const float PITCH = @PITCH@;
static const float MAXSTEP = @MAXSTEP@;
static const float KV = @KV@;
static const float CAP = @CAP@;
static const float OUTLIER = @OUTLIER@;
static const float EXPLAINED = @EXPLAINED@;
static const float INVMEM = @INVMEM@;
static const float PRIOR = @PRIOR@;
static const float ALO = @ALO@;
static const float AHI = @AHI@;
static const float BBOUND = @BBOUND@;
static const float STALE = @STALE@;
static const float READMIT = @READMIT@;
static const float C0[3] = {@C@};
static const float AMP[3] = {@AMP@};
static const float W0[3] = {@W0@};
static const float GROSS[3] = {@GROSS@};
static const float THR[2 * W + 1] = {
    @THR@
};
static const float G[M][3] = {
@G@
};
static const float DG[M][3] = {
@DG@
};

static float fabs_(float x) { return x < 0.0f ? -x : x; }
static int finite_(float x) { return x >= -3.4e38f && x <= 3.4e38f; }

/* cubic Hermite interpolation of g and dg/dy at y (any real y: wrap-around) */
static void table(float y, float g[3], float dg[3])
{
    float u = y * INVH;
    int32_t j = (int32_t)u;
    float t, t2, t3, h00, h10, h01, h11, d00, d10, d11;
    uint32_t i0, i1;
    int i;
    if ((float)j > u) {
        j -= 1;
    }
    t = u - (float)j;
    i0 = (uint32_t)j & (uint32_t)(M - 1);
    i1 = (i0 + 1u) & (uint32_t)(M - 1);
    t2 = t * t;
    t3 = t2 * t;
    h00 = 2.0f * t3 - 3.0f * t2 + 1.0f;
    h10 = (t3 - 2.0f * t2 + t) * HSTEP;
    h01 = -2.0f * t3 + 3.0f * t2;
    h11 = (t3 - t2) * HSTEP;
    d00 = (6.0f * t2 - 6.0f * t) * INVH;
    d10 = 3.0f * t2 - 4.0f * t + 1.0f;
    d11 = 3.0f * t2 - 2.0f * t;
    for (i = 0; i < 3; i++) {
        g[i] = h00 * G[i0][i] + h10 * DG[i0][i] + h01 * G[i1][i] + h11 * DG[i1][i];
        dg[i] = d00 * (G[i0][i] - G[i1][i]) + d10 * DG[i0][i] + d11 * DG[i1][i];
    }
}

static float chi2(const @p@_state *s, const float d[3], const float w[3], float y)
{
    float g[3], dg[3], chi = 0.0f, r;
    int i;
    table(y, g, dg);
    for (i = 0; i < 3; i++) {
        if (w[i] > 0.0f) {
            r = d[i] - s->a[i] * (g[i] - C0[i]) - s->b[i];
            chi += w[i] * r * r;
        }
    }
    return chi;
}

/* Gauss-Newton from y; returns y, chi2 in *chi */
static float fit(const @p@_state *s, const float d[3], const float w[3], float y, int iters,
                 float max_step, float *chi)
{
    float g[3], dg[3], num, den, r, J, step;
    int it, i;
    for (it = 0; it < iters; it++) {
        table(y, g, dg);
        num = 0.0f;
        den = 0.0f;
        for (i = 0; i < 3; i++) {
            if (w[i] > 0.0f) {
                r = d[i] - s->a[i] * (g[i] - C0[i]) - s->b[i];
                J = s->a[i] * dg[i];
                num += w[i] * J * r;
                den += w[i] * J * J;
            }
        }
        if (den <= 0.0f) {
            break;
        }
        step = num / den;
        if (step > max_step) {
            step = max_step;
        } else if (step < -max_step) {
            step = -max_step;
        }
        y += step;
    }
    *chi = chi2(s, d, w, y);
    return y;
}

/* chi2 of the best angle and common gain of the field parts */
static float fit_scaled(const @p@_state *s, const float d[3], const float w[3], float y)
{
    float g[3], dg[3], sc = 1.0f, A00, A01, A11, r0, r1, f, r, Jy, det, step, chi = 0.0f;
    int it, i;
    for (it = 0; it < ITER + 1; it++) {
        table(y, g, dg);
        A00 = A01 = A11 = r0 = r1 = 0.0f;
        for (i = 0; i < 3; i++) {
            if (w[i] > 0.0f) {
                f = s->a[i] * (g[i] - C0[i]);
                r = d[i] - sc * f - s->b[i];
                Jy = sc * s->a[i] * dg[i];
                A00 += w[i] * Jy * Jy;
                A01 += w[i] * Jy * f;
                A11 += w[i] * f * f;
                r0 += w[i] * Jy * r;
                r1 += w[i] * f * r;
            }
        }
        det = A00 * A11 - A01 * A01;
        if (det <= 0.0f) {
            break;
        }
        step = (A11 * r0 - A01 * r1) / det;
        step = step > MAXSTEP ? MAXSTEP : (step < -MAXSTEP ? -MAXSTEP : step);
        y += step;
        sc += (A00 * r1 - A01 * r0) / det;
    }
    table(y, g, dg);
    for (i = 0; i < 3; i++) {
        if (w[i] > 0.0f) {
            r = d[i] - sc * s->a[i] * (g[i] - C0[i]) - s->b[i];
            chi += w[i] * r * r;
        }
    }
    return chi;
}

static float acquire(const @p@_state *s, const float d[3], const float w[3], float y0,
                     float *chi)
{
    float best = 3.0e38f, best_y = y0, y, c;
    int q;
    for (q = 0; q < 64; q++) {
        y = y0 + PITCH * ((float)q * (1.0f / 64.0f) - 0.5f);
        c = chi2(s, d, w, y);
        if (c < best) {
            best = c;
            best_y = y;
        }
    }
    return fit(s, d, w, best_y, ITER + 2, PITCH * (1.0f / 64.0f), chi);
}

/* recursive least squares of the gains and levels, regressors projected off the angle */
static void adapt(@p@_state *s, const float d[3], const float w[3], float y, float x)
{
    float g[3], dg[3], q[6], gr[6], L[6][6], P[6], R[6], z[6], lam, sJ = 0.0f, f, Jy, r, t, lim;
    int i, j, k;
    table(y, g, dg);
    lam = 1.0f - x + 0.5f * x * x - x * x * x * (1.0f / 6.0f);
    for (i = 0; i < 3; i++) {
        if (w[i] > 0.0f) {
            sJ += w[i] * (s->a[i] * dg[i]) * (s->a[i] * dg[i]);
        }
    }
    if (sJ <= 0.0f) {
        return;
    }
    for (i = 0; i < 6; i++) {
        for (j = 0; j < 6; j++) {
            s->H[i][j] *= lam;
        }
        q[i] = 0.0f;
        gr[i] = 0.0f;
    }
    for (i = 0; i < 3; i++) {
        s->H[2 * i][2 * i] += (1.0f - lam) * PRIOR * W0[i] * AMP[i] * AMP[i];
        s->H[2 * i + 1][2 * i + 1] += (1.0f - lam) * PRIOR * W0[i];
        if (w[i] > 0.0f) {
            f = g[i] - C0[i];
            Jy = s->a[i] * dg[i];
            r = d[i] - s->a[i] * f - s->b[i];
            s->H[2 * i][2 * i] += w[i] * f * f;
            s->H[2 * i][2 * i + 1] += w[i] * f;
            s->H[2 * i + 1][2 * i] += w[i] * f;
            s->H[2 * i + 1][2 * i + 1] += w[i];
            q[2 * i] = w[i] * f * Jy;
            q[2 * i + 1] = w[i] * Jy;
            gr[2 * i] = w[i] * f * r;
            gr[2 * i + 1] = w[i] * r;
        }
    }
    sJ = 1.0f / sJ;
    for (i = 0; i < 6; i++) {
        t = q[i] * sJ;
        for (j = 0; j < 6; j++) {
            s->H[i][j] -= t * q[j];
        }
    }
    /* L D L^T of H (pivots P, their reciprocals R), then H z = gr */
    for (j = 0; j < 6; j++) {
        t = s->H[j][j];
        for (k = 0; k < j; k++) {
            t -= L[j][k] * L[j][k] * P[k];
        }
        if (!(t > 0.0f)) {
            return;
        }
        P[j] = t;
        R[j] = 1.0f / t;
        for (i = j + 1; i < 6; i++) {
            t = s->H[i][j];
            for (k = 0; k < j; k++) {
                t -= L[i][k] * L[j][k] * P[k];
            }
            L[i][j] = t * R[j];
        }
    }
    for (i = 0; i < 6; i++) {
        t = gr[i];
        for (k = 0; k < i; k++) {
            t -= L[i][k] * z[k];
        }
        z[i] = t;
    }
    for (i = 5; i >= 0; i--) {
        t = z[i] * R[i];
        for (k = i + 1; k < 6; k++) {
            t -= L[k][i] * z[k];
        }
        z[i] = t;
    }
    for (i = 0; i < 3; i++) {
        if (w[i] > 0.0f) {
            t = s->a[i] + z[2 * i];
            s->a[i] = t < ALO ? ALO : (t > AHI ? AHI : t);
            lim = BBOUND * AMP[i];
            t = s->b[i] + z[2 * i + 1];
            t = t < s->b0[i] - lim ? s->b0[i] - lim : t;
            s->b[i] = t > s->b0[i] + lim ? s->b0[i] + lim : t;
        }
    }
}

void @p@_init(@p@_state *s, int32_t revolutions, float angle)
{
    int i, j;
    float t;
    s->rev = revolutions;
    s->ang = angle;
    s->v = s->clean = s->bad = s->sum_chi = 0.0f;
    s->sum_dof = 0;
    for (i = 0; i < 3; i++) {
        s->a[i] = 1.0f;
        s->b[i] = C0[i];
        s->b0[i] = C0[i];
    }
    for (i = 0; i < 6; i++) {
        for (j = 0; j < 6; j++) {
            t = PRIOR * W0[i >> 1] * ((i & 1) ? 1.0f : AMP[i >> 1] * AMP[i >> 1]);
            s->H[i][j] = (i != j) ? 0.0f : t;
        }
    }
    s->blame[0] = s->blame[1] = s->blame[2] = s->blame[3] = 0;
    s->window_from = 0u;
    s->blame_from = 0u;
    s->excluded = -1;
    s->blamed_out = 0u;
    s->suppress = 0u;
    s->acquire = 1u;
    s->k = 0u;
    s->seq = 0u;
    s->buf[0].revolutions = revolutions;
    s->buf[0].angle = angle;
    s->buf[0].misfit = 0.0f;
    s->buf[0].state = @P@_OK;
    s->buf[0].excluded = -1;
    s->buf[0].flags = 0u;
    s->buf[0].sample = 0u;
    s->buf[1] = s->buf[0];
}

uint8_t @p@_update(@p@_state *s, float d1, float d2, float d3)
{
    float d[3], w[3], wk[3], g[3], dg[3], yp, y, chi = 0.0f, best, best_y, cq, yq, e, travel;
    float mf = 0.0f, cc, cmax;
    int i, q, active = 0, blamed = -1, mark = -1, others, above = 0, stale, fin[3];
    uint32_t slot, jw;
    int8_t old;
    d[0] = d1;
    d[1] = d2;
    d[2] = d3;
    for (i = 0; i < 3; i++) {
        fin[i] = finite_(d[i]);
        if (!fin[i]) {
            d[i] = 0.0f;
            if (s->excluded < 0) {
                s->excluded = (int8_t)i;
                s->blamed_out = 0u;
                s->clean = 0.0f;
                s->acquire = 1u;
            }
        }
    }
    for (i = 0; i < 3; i++) {
        w[i] = (i == s->excluded || !fin[i]) ? 0.0f : W0[i];
        if (w[i] > 0.0f) {
            active++;
        }
    }
    yp = s->ang + s->v;
    y = yp;
    if (active >= 2 && s->acquire) {
        y = acquire(s, d, w, yp, &chi);
        s->acquire = 0u;
    } else if (active == 3) {
        y = fit(s, d, w, yp, ITER, MAXSTEP, &chi);
        if (chi > OUTLIER && fit_scaled(s, d, w, y) > EXPLAINED) {
            best = 3.0e38f;
            best_y = y;
            for (q = 0; q < 3; q++) {
                for (i = 0; i < 3; i++) {
                    wk[i] = w[i];
                }
                wk[q] = 0.0f;
                yq = fit(s, d, wk, yp, ITER, MAXSTEP, &cq);
                if (cq < best) {
                    best = cq;
                    best_y = yq;
                    blamed = q;
                }
            }
            if (!(best < EXPLAINED && best < 0.1f * chi)) {
                blamed = -1;
                mark = 3;
            } else {
                table(best_y, g, dg);
                e = d[blamed] - s->a[blamed] * (g[blamed] - C0[blamed]) - s->b[blamed];
                if (fabs_(e) < GROSS[blamed]) {
                    blamed = -1;
                } else {
                    y = best_y;
                    mark = blamed;
                }
            }
        }
    } else if (active == 2) {
        y = fit(s, d, w, yp, ITER, MAXSTEP, &chi);
    }
    /* fault isolation */
    slot = s->k % (uint32_t)FW;
    old = (s->k >= s->blame_from + (uint32_t)FW) ? s->ring_blame[slot] : (int8_t)-1;
    if (old >= 0) {
        s->blame[old]--;
    }
    s->ring_blame[slot] = (int8_t)mark;
    if (mark >= 0) {
        s->blame[mark]++;
    }
    if (blamed >= 0 && s->excluded < 0 && !s->suppress) {
        others = 0;
        for (q = 0; q < 4; q++) {
            if (q != blamed) {
                others += s->blame[q];
            }
        }
        if (s->blame[blamed] >= FC && 4 * others <= s->blame[blamed]) {
            s->excluded = (int8_t)blamed;
            s->blamed_out = 1u;
            s->clean = 0.0f;
            w[blamed] = 0.0f;
            y = acquire(s, d, w, yp, &chi);
            s->blame_from = s->k + 1u; /* the blame ring and the window start again */
            s->blame[0] = s->blame[1] = s->blame[2] = s->blame[3] = 0;
            s->window_from = s->k;
            s->sum_chi = 0.0f;
            s->sum_dof = 0;
            blamed = -1;
            active = 2;
        }
    }
    if (blamed < 0 && active >= 2) {
        s->v += KV * (y - yp);
    }
    /* the angle within the revolution */
    while (y >= TWOPI) {
        y -= TWOPI;
        s->rev++;
    }
    while (y < 0.0f) {
        y += TWOPI;
        s->rev--;
    }
    s->ang = y;
    travel = NM * fabs_(s->v);
    /* misfit window */
    cmax = CAP * (active >= 3 ? 2.0f : 1.0f);
    cc = chi < cmax ? chi : cmax;
    if (blamed >= 0 && cc > CAP) {
        cc = CAP;
    }
    jw = s->k % (uint32_t)W;
    if (s->k >= s->window_from + (uint32_t)W) {
        s->sum_chi -= s->ring_chi[jw];
        s->sum_dof -= (int32_t)s->ring_dof[jw];
    }
    s->sum_chi += cc;
    s->sum_dof += active >= 2 ? active - 1 : 0;
    s->ring_chi[jw] = cc;
    s->ring_dof[jw] = (uint8_t)(active >= 2 ? active - 1 : 0);
    if (s->sum_dof > 0) {
        mf = s->sum_chi / (float)s->sum_dof;
        above = s->sum_chi > THR[s->sum_dof];
    }
    s->bad = above ? s->bad + travel : 0.0f;
    stale = above && s->bad >= STALE;
    if (!above) {
        s->suppress = 0u;
    } else if (s->excluded >= 0 && s->blamed_out && fin[(int)s->excluded]) {
        s->excluded = -1;
        s->suppress = 1u;
    }
    if (!stale && blamed < 0 && active >= 2) {
        adapt(s, d, w, y, travel * INVMEM);
    }
    /* readmission */
    if (s->excluded >= 0) {
        i = s->excluded;
        if (!fin[i]) {
            s->clean = 0.0f;
        } else {
            table(y, g, dg);
            e = d[i] - s->a[i] * (g[i] - C0[i]) - s->b[i];
            s->clean = (W0[i] * e * e < 16.0f) ? s->clean + travel : 0.0f;
        }
        if (s->clean >= READMIT) {
            s->excluded = -1;
            s->clean = 0.0f;
        }
    }
    /* publish */
    {
        uint32_t next = s->seq + 1u;
        @p@_reading *r = &s->buf[next & 1u];
        r->revolutions = s->rev;
        r->angle = s->ang;
        r->misfit = mf;
        r->state = active < 2 ? @P@_FAULT
                   : (s->excluded >= 0 ? @P@_DEGRADED
                   : (stale ? @P@_STALE : (above ? @P@_ADAPTING : @P@_OK)));
        r->excluded = s->excluded;
        r->flags = (uint32_t)r->state | ((uint32_t)(s->excluded + 1) << 8);
        r->sample = s->k + 1u;
        s->seq = next;
        s->k++;
        return r->state;
    }
}

void @p@_read(const @p@_state *s, @p@_reading *r)
{
    uint32_t a, b;
    do {
        a = s->seq;
        *r = s->buf[a & 1u];
        b = s->seq;
    } while (a != b);
}
"""
