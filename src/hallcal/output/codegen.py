"""Firmware export: eq. (f_final) as C99 for microcontrollers, in float and in fixed point.

``export_c(artifact, out_dir)`` turns a calibration artifact (``"hallcal-calibration/1"``) into
``<prefix>.h`` / ``<prefix>.c`` (single-precision float, for MCUs with an FPU) and, optionally,
``<prefix>_q.h`` / ``<prefix>_q.c`` (int32 arithmetic with int64 intermediate products, no float,
no ``<math.h>``, for MCUs without an FPU). Both mirror :meth:`hallcal.sensor.lut.LUT.f_star`:

* f_init, eq. (fimp): ``alpha, beta = P (d - o)``, ``psi = atan2(beta, alpha)``, unwrapped against
  the previous electrical angle with the rule Gamma (``mod(dpsi + pi, 2 pi) - pi``, ties to
  ``-pi``) and divided by the pole pairs n_m; the unwrap runs on its own uncorrected state.
* the correction ``eta(mod(y, 2 pi))`` of eq. (f_final): the very same piecewise-linear interpolant
  with wrap-around as ``np.interp(..., period=2 pi)`` over the stored nodes (y_hat_i, eta_i). The
  nodes are kept as they are (no resampling, so no extra interpolation error); an O(1) search finds
  the interval: a bucket table over a uniform grid of the angle gives the last node at or below the
  bucket start and a short forward scan, whose worst-case length is computed at export, finishes.

The angle is never stored as one growing number: the state holds the revolution count (int32), the
electrical turn within the revolution (0 .. n_m - 1) and the wrapped electrical angle, so the
accuracy after 10^6 revolutions is the accuracy of the first one. The float variant's returned
``float`` is the full angle and therefore has the float's resolution (6e-8 |y|); the revolution
count and the angle within the revolution (or the double helper) keep the stated bound forever.

Error bounds against the Python f_star are derived here from the float and fixed-point formats and
stated in the generated files and in :class:`ExportResult`; ``tests/test_codegen.py`` measures
them with the compiled code.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import string
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from hallcal.errors import HallcalInputError
from hallcal.sensor.lut import LUT

__all__ = [
    "ARTIFACT_FORMAT",
    "CORDIC_ITERATIONS",
    "ExportResult",
    "cordic_error_bound",
    "export_c",
]

TWO_PI = 2.0 * math.pi
#: The artifact format this exporter reads.
ARTIFACT_FORMAT = "hallcal-calibration/1"
#: CORDIC iterations of the integer atan2 of the fixed-point variant.
CORDIC_ITERATIONS = 26
#: Vectors enter the CORDIC with max(|a|, |b|) in [2^(NORM_BITS-1), 2^NORM_BITS).
_NORM_BITS = 29
_U32 = 1 << 32
_LSB_RAD = TWO_PI / _U32  # one unit of a Q0.32 turn
_EPS_F32 = 2.0**-24  # unit roundoff of IEEE single precision


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_c` wrote and the accuracy it states.

    All bounds are mechanical rad of ``|y_C - y_python|``, y_python being
    :meth:`hallcal.sensor.lut.LUT.f_star` in double precision on the same input samples.

    Attributes
    ----------
    status : str
        ``"ok"``, or ``"warning"`` when ``messages`` says something needs the user's attention.
    paths : tuple of Path
        Files written (``.h`` then ``.c``, float variant first).
    pole_pairs : int
        n_m.
    points : int
        M, table nodes per revolution (as in the artifact, not resampled).
    buckets : int
        Entries of the bucket table of the O(1) node search (a power of two).
    max_search_steps : int
        Worst-case forward steps of the node search after the bucket lookup (both variants).
    table_bytes : int
        Bytes of ``static const`` data of the float variant.
    table_bytes_q : int or None
        Bytes of ``static const`` data of the fixed-point variant (None if not written).
    float_bound : float
        Bound for the float variant's revolution count + angle within the revolution (and its
        double helper). The returned ``float`` adds its own rounding, 0.5 ulp(|y|).
    fixed_bound : float or None
        Bound for the fixed-point variant's output (revolutions + Q0.32 angle).
    atan2_bound : float or None
        Bound on the error of the integer atan2 [rad, electrical].
    assumed_amplitude : float
        Smallest Hall amplitude (artifact signal unit) the offset-rounding terms assume.
    sha256 : str
        SHA-256 of the artifact's canonical JSON (also written into the files).
    messages : tuple of str
        Warnings and notes.
    """

    status: str
    paths: tuple[Path, ...]
    pole_pairs: int
    points: int
    buckets: int
    max_search_steps: int
    table_bytes: int
    table_bytes_q: int | None
    float_bound: float
    fixed_bound: float | None
    atan2_bound: float | None
    assumed_amplitude: float
    sha256: str
    messages: tuple[str, ...] = ()


def cordic_error_bound(iterations: int = CORDIC_ITERATIONS) -> float:
    """Worst-case error [rad] of the generated integer atan2 (CORDIC, vectoring mode).

    Terms: the convergence residual ``atan(2^-(N-1))``; the truncation of ``b >> i`` and ``a >> i``
    (at most sqrt(2) units per iteration on a vector of length >= 2^28: ``N sqrt(2) / 2^28``); the
    rounding of the N arctangent constants to Q0.32 turns (half a unit each); the truncation of the
    input to 29 bits (``sqrt(2) / 2^28``).
    """
    n = int(iterations)
    lo = 2.0 ** (_NORM_BITS - 1)
    return (
        math.atan(2.0 ** -(n - 1))
        + n * math.sqrt(2.0) / lo
        + 0.5 * n * _LSB_RAD
        + math.sqrt(2.0) / lo
    )


# --------------------------------------------------------------------------------------------
# Reading and checking the artifact
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Calibration:
    pole_pairs: int
    projection: NDArray[np.float64]
    offset: NDArray[np.float64]
    y_hat: NDArray[np.float64]
    eta: NDArray[np.float64]
    lut: LUT
    sha256: str
    fmt: str


def _bad(source: str, key: str, why: str) -> HallcalInputError:
    return HallcalInputError(f"{source}: key '{key}' {why}")


def _need(obj, key: str, path: str, source: str):
    if not isinstance(obj, Mapping) or key not in obj:
        raise _bad(source, path, "is missing")
    return obj[key]


def _array(value, shape: tuple[int, ...] | None, key: str, source: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _bad(source, key, "must be numbers") from None
    if shape is not None and arr.shape != shape:
        raise _bad(source, key, f"must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise _bad(source, key, "must be finite numbers")
    return arr


def _read_artifact(artifact: Mapping, source: str) -> _Calibration:
    if not isinstance(artifact, Mapping):
        raise HallcalInputError(f"{source}: the calibration artifact must be a JSON object")
    fmt = _need(artifact, "format", "format", source)
    if fmt != ARTIFACT_FORMAT:
        raise _bad(source, "format", f"is {fmt!r}, expected {ARTIFACT_FORMAT!r}")
    n = _need(artifact, "pole_pairs", "pole_pairs", source)
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or not 1 <= int(n) <= 10000:
        raise _bad(source, "pole_pairs", "must be an integer in 1..10000")
    rec = _need(artifact, "reconstruction", "reconstruction", source)
    P = _need(rec, "projection", "reconstruction.projection", source)
    P = _array(P, (2, 3), "reconstruction.projection", source)
    if np.linalg.matrix_rank(P) < 2:
        raise _bad(source, "reconstruction.projection", "must have rank 2")
    o = _need(rec, "offset", "reconstruction.offset", source)
    o = _array(o, (3,), "reconstruction.offset", source)
    lut_d = _need(artifact, "lut", "lut", source)
    y_hat = _need(lut_d, "y_hat", "lut.y_hat", source)
    eta = _need(lut_d, "eta", "lut.eta", source)
    y_hat = _array(y_hat, None, "lut.y_hat", source)
    eta = _array(eta, None, "lut.eta", source)
    if y_hat.ndim != 1 or y_hat.shape != eta.shape:
        raise _bad(source, "lut.eta", "must be a list as long as lut.y_hat")
    m = y_hat.size
    if not 4 <= m <= 65000:
        raise _bad(source, "lut.y_hat", f"must have 4..65000 nodes, got {m}")
    if "points" in lut_d:
        points = lut_d["points"]
        if isinstance(points, bool) or not isinstance(points, int | np.integer) or points != m:
            raise _bad(source, "lut.points", f"is {points!r} but lut.y_hat has {m} nodes")
    if np.max(np.abs(eta)) >= math.pi:
        raise _bad(source, "lut.eta", "has corrections of pi rad or more")
    lut = LUT.from_arrays(int(n), P, o, y_hat, eta)
    # eq. (recon_biject): y_hat strictly increasing over one revolution (checked on the nodes
    # themselves too, so that a table with reordered nodes is refused as well)
    monotone = bool(np.all(np.diff(y_hat) > 0) and y_hat[-1] < y_hat[0] + TWO_PI)
    if not (lut.bijective and monotone):
        raise _bad(
            source,
            "lut",
            f"is not bijective (min slope {lut.min_slope:.3g}): the table would give wrong angles",
        )
    canon = json.dumps(artifact, sort_keys=True, separators=(",", ":"), default=_json_default)
    sha = hashlib.sha256(canon.encode()).hexdigest()
    return _Calibration(int(n), P, o, y_hat, eta, lut, sha, str(fmt))


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return str(obj)


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


def _periodic_nodes(y_hat: NDArray, eta: NDArray) -> tuple[NDArray, NDArray]:
    """The nodes ``np.interp(x, y_hat, eta, period=2 pi)`` uses: sorted mod 2 pi, with the last
    node before 0 and the first node after 2 pi appended (M + 2 nodes)."""
    x = np.mod(y_hat, TWO_PI)
    order = np.argsort(x, kind="stable")
    xs, es = x[order], eta[order]
    return (
        np.concatenate([[xs[-1] - TWO_PI], xs, [xs[0] + TWO_PI]]),
        np.concatenate([[es[-1]], es, [es[0]]]),
    )


def _bucket_table(nodes: NDArray, starts: NDArray, margin: float) -> tuple[NDArray, int]:
    """For each bucket the last interval j with nodes[j] <= start - margin, and the worst-case
    forward scan to any point below the next bucket's start + margin."""
    m = nodes.size - 2
    first = np.clip(np.searchsorted(nodes, starts - margin, side="right") - 1, 0, m)
    ends = np.append(starts[1:], starts[-1] + (starts[-1] - starts[-2]))
    last = np.clip(np.searchsorted(nodes, ends + margin, side="right") - 1, 0, m)
    return first.astype(np.int64), int(np.max(last - first))


@dataclass(frozen=True)
class _FloatTables:
    x: NDArray[np.float32]
    eta: NDArray[np.float32]
    bucket: NDArray[np.int64]
    max_scan: int
    bytes: int


@dataclass(frozen=True)
class _FixedTables:
    x: NDArray[np.int64]  # linear Q0.32-turn positions (may be < 0 or >= 2^32 at the sentinels)
    eta: NDArray[np.int64]
    slope: NDArray[np.int64]
    slope_bits: int
    bucket: NDArray[np.int64]
    max_scan: int
    max_width: int
    max_slope: float
    offset: NDArray[np.int64]
    offset_bits: int
    projection: NDArray[np.int64]
    projection_exp: int
    turn_base: NDArray[np.int64]
    atan: NDArray[np.int64]
    bytes: int


def _float_tables(cal: _Calibration, buckets: int) -> _FloatTables:
    xl, el = _periodic_nodes(cal.y_hat, cal.eta)
    xf = xl.astype(np.float32)
    ef = el.astype(np.float32)
    if not np.all(np.diff(xf.astype(np.float64)) > 0):
        raise HallcalInputError(
            "lut: two nodes y_hat coincide in single precision; use fewer points"
        )
    starts = TWO_PI * np.arange(buckets) / buckets
    # The C code finds the bucket of x by a float product; 1e-5 rad of margin covers its rounding.
    bucket, scan = _bucket_table(xf.astype(np.float64), starts, 1e-5)
    m, n = cal.y_hat.size, cal.pole_pairs
    nbytes = 4 * 2 * (m + 2) + 2 * buckets + 4 * n + 4 * 9
    return _FloatTables(xf, ef, bucket, scan, nbytes)


def _fixed_tables(cal: _Calibration, buckets: int, adc_scale: float) -> _FixedTables:
    xl, el = _periodic_nodes(cal.y_hat, cal.eta)
    xq = np.array([round(v / TWO_PI * _U32) for v in xl], dtype=np.int64)
    eq = np.array([round(v / TWO_PI * _U32) for v in el], dtype=np.int64)
    widths = np.diff(xq)
    if not np.all(widths > 0):
        raise HallcalInputError("lut: two nodes y_hat coincide in Q0.32 turns; use fewer points")
    if np.max(np.abs(eq)) >= 2**31:
        raise HallcalInputError("lut: eta does not fit in a signed Q0.32 turn")
    slopes = np.diff(eq) / widths
    max_slope = float(np.max(np.abs(slopes)))
    max_width = int(np.max(widths))
    # Slope in Q(31-F).F with |slope| * 2^F < 2^30 and |slope_q| * width < 2^62.
    sbits = 30
    while sbits > 0 and (max_slope * 2.0**sbits >= 2.0**30):
        sbits -= 1
    while sbits > 0 and max_slope * 2.0**sbits * max_width >= 2.0**62:
        sbits -= 1
    if sbits < 1:
        raise HallcalInputError("lut: the table is too steep for the fixed-point variant")
    slope_q = np.array([round(float(s) * 2.0**sbits) for s in slopes], dtype=np.int64)
    bucket_shift = 32 - int(round(math.log2(buckets)))
    starts = np.arange(buckets, dtype=np.int64) << bucket_shift
    bucket, scan = _bucket_table(xq, starts, 0)
    # Offsets in counts, Q(31-F).F with F <= 16 fractional bits.
    oc = cal.offset * float(adc_scale)
    obits = 16
    while obits > 0 and np.max(np.abs(oc)) * 2.0**obits >= 2.0**30:
        obits -= 1
    if np.max(np.abs(oc)) >= 2.0**30:
        raise HallcalInputError("reconstruction.offset: offsets of 2^30 ADC counts or more")
    off_q = np.array([round(float(v) * 2.0**obits) for v in oc], dtype=np.int64)
    # Projection scaled by a power of two (atan2 does not see a common scale) to 30 bits.
    pmax = float(np.max(np.abs(cal.projection)))
    pexp = 29 - math.floor(math.log2(pmax))
    proj_q = np.array(
        [[round(float(v) * 2.0**pexp) for v in row] for row in cal.projection], dtype=np.int64
    )
    if np.max(np.abs(proj_q)) >= 2**30:  # log2 rounding at an exact power of two
        pexp -= 1
        proj_q = np.array(
            [[round(float(v) * 2.0**pexp) for v in row] for row in cal.projection],
            dtype=np.int64,
        )
    n = cal.pole_pairs
    turn_base = np.array([(t * _U32) // n for t in range(n)], dtype=np.int64)
    atan = np.array(
        [round(math.atan(2.0**-i) / TWO_PI * _U32) for i in range(CORDIC_ITERATIONS)],
        dtype=np.int64,
    )
    m = cal.y_hat.size
    nbytes = 4 * (m + 2) * 2 + 4 * (m + 1) + 2 * buckets + 4 * n + 4 * 9
    return _FixedTables(
        xq, eq, slope_q, sbits, bucket, scan, max_width, max_slope, off_q, obits, proj_q, pexp,
        turn_base, atan, nbytes,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Error bounds
# --------------------------------------------------------------------------------------------


def _condition(P: NDArray) -> float:
    s = np.linalg.svd(P, compute_uv=False)
    return float(s[0] / s[-1])


def _float_bound(cal: _Calibration, ft: _FloatTables, amplitude: float) -> float:
    """Single-precision rounding, propagated to the output (mechanical rad).

    Electrical angle: atan2f within 2 ulp of pi; the projection, about 8 roundings relative to
    the alpha/beta vector amplified by the condition number of P; the offsets' rounding relative
    to the amplitude. Within the revolution: 6 roundings of numbers below 8 (the scale by 1/n_m,
    the turn base, their sum, the wrap by 2 pi for the look-up, y + eta and its normalization).
    An error in the looked-up angle moves eta by the table's largest slope.
    """
    n = cal.pole_pairs
    kappa = _condition(cal.projection)
    slope = float(np.max(np.abs(np.diff(ft.eta.astype(float)) / np.diff(ft.x.astype(float)))))
    e_el = (
        4 * 2.0**-22  # atan2f: 4 ulp at pi (glibc and newlib are within 2)
        + 8 * _EPS_F32 * kappa
        + math.sqrt(2.0) * kappa * _EPS_F32 * float(np.max(np.abs(cal.offset))) / amplitude
    )
    e_y = e_el / n + 6 * _EPS_F32 * 8.0
    e_tab = 4 * _EPS_F32 * float(np.max(np.abs(cal.eta)))
    return e_y * (1.0 + slope) + e_tab


def _fixed_bound(
    cal: _Calibration, qt: _FixedTables, amplitude: float, adc_scale: float
) -> tuple[float, float]:
    """Fixed-point error bound (mechanical rad) and the integer atan2's bound (electrical rad).

    Electrical angle: the CORDIC (:func:`cordic_error_bound`); the projection's rounding to 30
    bits and the truncation of very large inputs to 31 bits (2^-28 relative, times the condition
    number of P); the offsets' rounding to 2^-(F+1) counts relative to the amplitude. Within the
    revolution: the turn base and p / n_m round down (2 units of 2^-32 turn); table nodes, values
    and slopes round to half a unit each; an error of the looked-up angle moves eta by the
    table's largest slope.
    """
    n = cal.pole_pairs
    kappa = _condition(cal.projection)
    e_atan = cordic_error_bound(CORDIC_ITERATIONS)
    d_off = 2.0 ** -(qt.offset_bits + 1) / float(adc_scale)  # artifact units
    e_el = e_atan + kappa * 2.0**-28 + math.sqrt(2.0) * kappa * d_off / amplitude
    e_u = e_el / n + 2 * _LSB_RAD
    s = qt.max_slope
    e_tab = _LSB_RAD * (0.5 + 0.5 * s + 0.5 + 2.0 ** -(qt.slope_bits + 1) * qt.max_width)
    return e_u * (1.0 + s) + e_tab, e_atan


# --------------------------------------------------------------------------------------------
# C formatting
# --------------------------------------------------------------------------------------------


def _c_float(v: float) -> str:
    s = f"{float(np.float32(v)):.9g}"
    if not any(c in s for c in ".eEn"):
        s += ".0"
    return s + "f"


def _c_list(values: Sequence[str], per_line: int, indent: str = "    ") -> str:
    lines = []
    for i in range(0, len(values), per_line):
        lines.append(indent + ", ".join(values[i : i + per_line]) + ",")
    return "\n".join(lines)


def _c_u32(v: int) -> str:
    return f"{int(v) % _U32}u"


def _c_i32(v: int) -> str:
    v = int(v)
    if not -(2**31) <= v < 2**31:
        raise ValueError(v)
    if v == -(2**31):
        return "(-2147483647 - 1)"
    return str(v)


def _banner(
    fname: str,
    cal: _Calibration,
    source: str,
    version: str,
    lines: Sequence[str],
) -> str:
    body = [
        f"{fname} -- generated by hallcal {version} (hallcal.output.codegen). Do not edit.",
        "",
        f"Source artifact : {source}",
        f"  format        : {cal.fmt}",
        f"  sha256        : {cal.sha256}",
        f"Pole pairs n_m  : {cal.pole_pairs}",
        f"Table           : M = {cal.y_hat.size} nodes (y_hat_i, eta_i) per revolution, as stored",
        "",
        'Method: van Meer et al., "Self-Calibrating Position Measurements: Applied to Imperfect',
        'Hall Sensors": f_init of eq. (fimp) and y_star = y + eta(mod(y, 2 pi)) of eq. (f_final).',
        *lines,
    ]
    for text in body:
        if "*/" in text:
            raise HallcalInputError("the source name must not contain '*/'")
    return "/*\n" + "\n".join((" * " + t).rstrip() for t in body) + "\n */\n"


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("hallcal")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        return "(unknown version)"


# --------------------------------------------------------------------------------------------
# C templates
# --------------------------------------------------------------------------------------------

_FLOAT_H = string.Template(
    r"""$banner
#ifndef ${PFX}_H
#define ${PFX}_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define ${PFX}_POLE_PAIRS $n
#define ${PFX}_POINTS $m

/* State of one sensor set. Treat as opaque: use the functions below. No dynamic memory. */
typedef struct {
    int32_t rev;       /* whole revolutions of f_init (uncorrected unwrap state) */
    int32_t turn;      /* electrical turn within the revolution, 0 .. n_m - 1 */
    float psi;         /* last electrical angle atan2(beta, alpha) [rad], [-pi, pi] */
    int32_t out_rev;   /* whole revolutions of the last y_star */
    float out_angle;   /* last y_star within its revolution [rad], [0, 2 pi) */
    uint32_t rejected; /* samples without angle information (NaN/inf/zero alpha-beta), held */
} ${pfx}_state;

/* Start at y_initial [rad] (the estimate before the first sample; 0 by convention).
 * A NaN, infinite or |y_initial| >= 1e9 value starts at 0. */
void ${pfx}_init(${pfx}_state *s, float y_initial);

/* One sample of the three Hall signals (raw, in the artifact's unit: ADC counts or volts).
 * Returns y_star [rad], the full corrected mechanical angle, rounded to float (resolution
 * 6e-8 |y|: use ${pfx}_revolutions + ${pfx}_angle_in_rev for long runs). A sample whose
 * alpha/beta is NaN, infinite or exactly zero carries no angle: the state is held, the last
 * y_star is returned and ${pfx}_rejected counts it. Do not compile with -ffast-math. */
float ${pfx}_update(${pfx}_state *s, float d1, float d2, float d3);

/* y_star = 2 pi * revolutions + angle_in_rev, angle_in_rev in [0, 2 pi). Exact bookkeeping:
 * the accuracy does not decay with the number of revolutions (the count wraps at 2^31). */
int32_t ${pfx}_revolutions(const ${pfx}_state *s);
float ${pfx}_angle_in_rev(const ${pfx}_state *s);
/* The full angle in double precision [rad] (software double on MCUs without a double FPU). */
double ${pfx}_angle_f64(const ${pfx}_state *s);
uint32_t ${pfx}_rejected(const ${pfx}_state *s);

#ifdef __cplusplus
}
#endif

#endif /* ${PFX}_H */
"""
)

_FLOAT_C = string.Template(
    r"""$banner
#include <math.h>
#include <stdint.h>

#include "$header"

/* atan2f may be replaced (e.g. by a faster vendor routine with the same contract). */
#ifndef ${PFX}_ATAN2F
#define ${PFX}_ATAN2F atan2f
#endif

#define HC_N $n                /* pole pairs n_m */
#define HC_M $m              /* table nodes per revolution */
#define HC_B $b              /* buckets of the node search */
#define HC_MAX_SCAN $scan         /* worst-case forward steps after the bucket look-up */
#define HC_PI_F 3.14159274f    /* float(pi) */
#define HC_2PI_F 6.28318548f   /* float(2 pi) */
/* 2 pi = HC_2PI_HI + HC_2PI_LO; HC_2PI_HI has 8 significant bits, so (x + HC_2PI_HI) + HC_2PI_LO
 * and r * HC_2PI_HI for |r| < 2^16 add only the rounding of a float, not the error of 2 pi's. */
#define HC_2PI_HI 6.28125f
#define HC_2PI_LO 1.93530717958647692528676655901e-3f
#define HC_2PI_D 6.283185307179586476925286766559
#define HC_PI_D 3.141592653589793238462643383280

static const float hc_inv_n = $inv_n;           /* 1 / n_m */
static const float hc_bucket_scale = $bucket_scale;   /* HC_B / (2 pi) */

/* f_init, eq. (fimp): alpha, beta = P (d - offset). */
static const float hc_proj[2][3] = {
    {$p0},
    {$p1},
};
static const float hc_offset[3] = {$offset};

/* 2 pi t / n_m [rad], t = 0 .. n_m - 1: the start of each electrical turn. */
static const float hc_turn_base[HC_N] = {
$turn_base
};

/* eq. (f_final): nodes y_hat_i mod 2 pi, sorted, with the last node - 2 pi prepended and the
 * first node + 2 pi appended (the wrap-around of np.interp(..., period=2 pi)) [rad]. */
static const float hc_x[HC_M + 2] = {
$x
};
/* eta_i = y0_i - y_hat_i at those nodes [rad]. */
static const float hc_eta[HC_M + 2] = {
$eta
};
/* Bucket k = [2 pi k / HC_B, 2 pi (k + 1) / HC_B): last interval j with hc_x[j] <= its start. */
static const uint16_t hc_bucket[HC_B] = {
$bucket
};

static int32_t hc_s32(uint32_t u) /* two's complement, without implementation-defined casts */
{
    return u <= 0x7FFFFFFFu ? (int32_t)u : (int32_t)(u - 0x80000000u) - 0x7FFFFFFF - 1;
}

static float hc_output(const ${pfx}_state *s)
{
    const float r = (float)s->out_rev;
    return r * HC_2PI_HI + (r * HC_2PI_LO + s->out_angle);
}

void ${pfx}_init(${pfx}_state *s, float y_initial)
{
    double y = (double)y_initial, rev, rem, e, t;
    if (!(y > -1e9 && y < 1e9)) {
        y = 0.0; /* NaN, inf or out of range */
    }
    rev = floor(y / HC_2PI_D);
    rem = y - rev * HC_2PI_D;
    if (rem < 0.0) {
        rem += HC_2PI_D;
        rev -= 1.0;
    }
    if (rem >= HC_2PI_D) {
        rem -= HC_2PI_D;
        rev += 1.0;
    }
    s->out_rev = (int32_t)rev;
    s->out_angle = (float)rem;
    if (s->out_angle >= HC_2PI_F) {
        s->out_angle = 0.0f;
        s->out_rev += 1;
    }
    /* electrical angle n_m y = 2 pi (n_m rev + t) + psi with psi in [-pi, pi) */
    e = rem * HC_N;
    t = floor((e + HC_PI_D) / HC_2PI_D);
    s->psi = (float)(e - t * HC_2PI_D);
    if (t >= HC_N) {
        t -= HC_N;
        rev += 1.0;
    }
    s->rev = (int32_t)rev;
    s->turn = (int32_t)t;
    s->rejected = 0u;
}

float ${pfx}_update(${pfx}_state *s, float d1, float d2, float d3)
{
    const float x1 = d1 - hc_offset[0], x2 = d2 - hc_offset[1], x3 = d3 - hc_offset[2];
    const float a = hc_proj[0][0] * x1 + hc_proj[0][1] * x2 + hc_proj[0][2] * x3;
    const float b = hc_proj[1][0] * x1 + hc_proj[1][1] * x2 + hc_proj[1][2] * x3;
    float psi, dpsi, r, x, eta, y;
    int32_t turn, rev, k, j;

    if (!(isfinite(a) && isfinite(b)) || (a == 0.0f && b == 0.0f)) {
        s->rejected += 1u; /* no angle information: hold the last estimate */
        return hc_output(s);
    }
    psi = ${PFX}_ATAN2F(b, a);
    /* Gamma of eq. (fimp): the step mod(dpsi + pi, 2 pi) - pi moves the turn count by -1, 0, 1 */
    dpsi = psi - s->psi;
    turn = s->turn;
    rev = s->rev;
    if (dpsi < -HC_PI_F) {
        if (++turn == HC_N) {
            turn = 0;
            rev = hc_s32((uint32_t)rev + 1u);
        }
    } else if (dpsi >= HC_PI_F) {
        if (--turn < 0) {
            turn = HC_N - 1;
            rev = hc_s32((uint32_t)rev - 1u);
        }
    }
    s->psi = psi;
    s->turn = turn;
    s->rev = rev;

    /* f_init within the revolution, in [-pi/n_m, 2 pi - pi/n_m) */
    r = psi * hc_inv_n + hc_turn_base[turn];
    /* eta(mod(y, 2 pi)): piecewise-linear with wrap-around, O(1) node search */
    x = r < 0.0f ? (r + HC_2PI_HI) + HC_2PI_LO : r;
    k = (int32_t)(x * hc_bucket_scale);
    if (k > HC_B - 1) {
        k = HC_B - 1;
    }
    j = hc_bucket[k];
    while (j < HC_M && x >= hc_x[j + 1]) {
        ++j;
    }
    eta = (hc_eta[j + 1] - hc_eta[j]) / (hc_x[j + 1] - hc_x[j]) * (x - hc_x[j]) + hc_eta[j];

    /* y_star = 2 pi rev + r + eta, kept as revolutions + [0, 2 pi) */
    y = r + eta;
    if (y < 0.0f) {
        y = (y + HC_2PI_HI) + HC_2PI_LO;
        rev = hc_s32((uint32_t)rev - 1u);
    }
    if (y >= HC_2PI_F) {
        y = (y - HC_2PI_HI) - HC_2PI_LO;
        rev = hc_s32((uint32_t)rev + 1u);
    }
    s->out_rev = rev;
    s->out_angle = y;
    return hc_output(s);
}

int32_t ${pfx}_revolutions(const ${pfx}_state *s) { return s->out_rev; }

float ${pfx}_angle_in_rev(const ${pfx}_state *s) { return s->out_angle; }

double ${pfx}_angle_f64(const ${pfx}_state *s)
{
    return (double)s->out_rev * HC_2PI_D + (double)s->out_angle;
}

uint32_t ${pfx}_rejected(const ${pfx}_state *s) { return s->rejected; }
"""
)

_FIXED_H = string.Template(
    r"""$banner
#ifndef ${PFX}_Q_H
#define ${PFX}_Q_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define ${PFX}_Q_POLE_PAIRS $n
#define ${PFX}_Q_POINTS $m
/* Angles are Q0.32 turns: 2^32 = one revolution = 2 pi rad, i.e. this many rad per unit: */
#define ${PFX}_Q_RAD_PER_LSB 1.4629180792671596e-9

/* State of one sensor set. Treat as opaque: use the functions below. No dynamic memory. */
typedef struct {
    int32_t rev;        /* whole revolutions of f_init (uncorrected unwrap state) */
    int32_t turn;       /* electrical turn within the revolution, 0 .. n_m - 1 */
    uint32_t phase;     /* last electrical angle, Q0.32 turns */
    int32_t out_rev;    /* whole revolutions of the last y_star */
    uint32_t out_angle; /* last y_star within its revolution, Q0.32 turns */
    uint32_t rejected;  /* samples without angle information (alpha = beta = 0), held */
} ${pfx}_q_state;

/* Start at y_initial = revolutions * 2^32 + angle, Q32.32 turns (0 by convention). */
void ${pfx}_q_init(${pfx}_q_state *s, int64_t y_initial);

/* One sample of the three Hall signals as raw ADC integers (any int32 is safe). Returns y_star
 * within the revolution, Q0.32 turns (unsigned; wraps naturally); the revolution count is
 * ${pfx}_q_revolutions. A sample with alpha = beta = 0 carries no angle: the state is held. */
uint32_t ${pfx}_q_update(${pfx}_q_state *s, int32_t d1, int32_t d2, int32_t d3);

int32_t ${pfx}_q_revolutions(const ${pfx}_q_state *s);
uint32_t ${pfx}_q_angle(const ${pfx}_q_state *s);
/* The full angle, revolutions * 2^32 + angle (Q32.32 turns). */
int64_t ${pfx}_q_angle_i64(const ${pfx}_q_state *s);
uint32_t ${pfx}_q_rejected(const ${pfx}_q_state *s);

#ifdef __cplusplus
}
#endif

#endif /* ${PFX}_Q_H */
"""
)

_FIXED_C = string.Template(
    r"""$banner
#include <stdint.h>

#include "$header"

/* Integer arithmetic only: int32, with int64 for the products P (d - o), the slope times the
 * offset in a table interval and a few 64-bit sums. No float, no <math.h>, no division except
 * by the constant n_m. Right shifts of negative integers must be arithmetic (checked below);
 * that holds for GCC, Clang, IAR, ARM Compiler and every common MCU compiler. */
typedef char hc_requires_arithmetic_shift[
    (((int32_t)-1 >> 1) == -1 && ((int64_t)-1 >> 1) == -1) ? 1 : -1];

#define HC_N $n                  /* pole pairs n_m */
#define HC_M $m                /* table nodes per revolution */
#define HC_BUCKET_SHIFT $bshift       /* bucket = angle >> HC_BUCKET_SHIFT ($b buckets) */
#define HC_MAX_SCAN $scan           /* worst-case forward steps after the bucket look-up */
#define HC_OFFSET_BITS $obits        /* offsets are Q(31-F).F ADC counts, F = HC_OFFSET_BITS */
#define HC_SLOPE_BITS $sbits         /* table slopes are Q(31-F).F, F = HC_SLOPE_BITS */
#define HC_CORDIC_ITERATIONS $iters
#define HC_NORM_BITS $normbits          /* CORDIC input: max(|a|, |b|) in [2^(B-1), 2^B) */

/* f_init, eq. (fimp). Offsets [counts * 2^HC_OFFSET_BITS]; projection P * 2^$pexp (any common
 * scale of alpha and beta leaves atan2 unchanged). */
static const int32_t hc_offset[3] = {$offset};
static const int32_t hc_proj[2][3] = {
    {$p0},
    {$p1},
};

/* floor(t * 2^32 / n_m), t = 0 .. n_m - 1: the start of each electrical turn, Q0.32 turns. */
static const uint32_t hc_turn_base[HC_N] = {
$turn_base
};

/* eq. (f_final): nodes y_hat_i mod 2 pi, sorted, with the last node - 1 turn prepended and the
 * first node + 1 turn appended (the wrap-around of np.interp(..., period=2 pi)), Q0.32 turns
 * modulo 2^32. */
static const uint32_t hc_x[HC_M + 2] = {
$x
};
/* eta_i at those nodes, signed Q0.32 turns. */
static const int32_t hc_eta[HC_M + 2] = {
$eta
};
/* (eta_{j+1} - eta_j) / (x_{j+1} - x_j), Q(31-F).F with F = HC_SLOPE_BITS. */
static const int32_t hc_slope[HC_M + 1] = {
$slope
};
/* Bucket k = [k, k + 1) << HC_BUCKET_SHIFT: last interval j with hc_x[j] <= its start. */
static const uint16_t hc_bucket[$b] = {
$bucket
};

static int32_t hc_s32(uint32_t u) /* two's complement, without implementation-defined casts */
{
    return u <= 0x7FFFFFFFu ? (int32_t)u : (int32_t)(u - 0x80000000u) - 0x7FFFFFFF - 1;
}

static uint64_t hc_abs64(int64_t v) { return v < 0 ? 0u - (uint64_t)v : (uint64_t)v; }

static int hc_bitlen64(uint64_t v) /* number of significant bits, 0 for 0 */
{
#if defined(__GNUC__) && !defined(${PFX}_PORTABLE)
    return v ? 64 - __builtin_clzll(v) : 0;
#else
    int n = 0;
    if (v >= ((uint64_t)1 << 32)) { v >>= 32; n += 32; }
    if (v >= ((uint64_t)1 << 16)) { v >>= 16; n += 16; }
    if (v >= ((uint64_t)1 << 8)) { v >>= 8; n += 8; }
    if (v >= ((uint64_t)1 << 4)) { v >>= 4; n += 4; }
    if (v >= ((uint64_t)1 << 2)) { v >>= 2; n += 2; }
    if (v >= 2u) { v >>= 1; n += 1; }
    return n + (int)v;
#endif
}

/* Integer atan2(B, A) as a Q0.32 turn (2^32 = 2 pi): the vector is scaled by a power of two to
 * HC_NORM_BITS bits, rotated into the right half plane and rotated to the x axis by CORDIC
 * (vectoring mode). Worst-case error $atan_bound rad. Returns 0 for the zero vector. */
static int hc_atan2_q(int64_t A, int64_t B, uint32_t *turns)
{
    const int len = hc_bitlen64(hc_abs64(A) | hc_abs64(B));
    int32_t a, b;
    uint32_t z = 0u;
    if (len == 0) {
        return 0;
    }
    if (len > HC_NORM_BITS) {
        a = (int32_t)(A >> (len - HC_NORM_BITS));
        b = (int32_t)(B >> (len - HC_NORM_BITS));
    } else {
        a = (int32_t)A * ((int32_t)1 << (HC_NORM_BITS - len));
        b = (int32_t)B * ((int32_t)1 << (HC_NORM_BITS - len));
    }
    if (a < 0) { /* rotate by pi */
        a = -a;
        b = -b;
        z = 0x80000000u;
    }
    /* CORDIC step i: rotate by -+atan(2^-i) towards the x axis, z accumulates the angle.
     * Branch-free: m = 0 if b > 0 (clockwise), m = -1 otherwise; (v ^ m) - m = +-v.
     * Unrolled so that shifts and constants are immediates. */
#define HC_STEP(i, atan_i)                                                                    \
    do {                                                                                      \
        const int32_t m = (b - 1) >> 31;                                                      \
        const int32_t na = a + (((b >> (i)) ^ m) - m);                                        \
        b -= ((a >> (i)) ^ m) - m;                                                            \
        z += ((uint32_t)(atan_i) ^ (uint32_t)m) - (uint32_t)m;                                \
        a = na;                                                                               \
    } while (0)
$cordic_steps
#undef HC_STEP
    *turns = z;
    return 1;
}

void ${pfx}_q_init(${pfx}_q_state *s, int64_t y_initial)
{
    const uint32_t frac = (uint32_t)((uint64_t)y_initial & 0xFFFFFFFFu);
    const int32_t rev = (int32_t)((y_initial - (int64_t)frac) / 4294967296LL);
    const uint64_t e = (uint64_t)frac * HC_N; /* electrical angle within the revolution */
    s->rev = rev;
    s->turn = (int32_t)(e >> 32);
    s->phase = (uint32_t)(e & 0xFFFFFFFFu);
    s->out_rev = rev;
    s->out_angle = frac;
    s->rejected = 0u;
}

uint32_t ${pfx}_q_update(${pfx}_q_state *s, int32_t d1, int32_t d2, int32_t d3)
{
    int64_t x1 = (int64_t)d1 * ((int64_t)1 << HC_OFFSET_BITS) - hc_offset[0];
    int64_t x2 = (int64_t)d2 * ((int64_t)1 << HC_OFFSET_BITS) - hc_offset[1];
    int64_t x3 = (int64_t)d3 * ((int64_t)1 << HC_OFFSET_BITS) - hc_offset[2];
    int64_t A, B;
    int32_t v1, v2, v3, turn, rev, j, eta;
    uint32_t p, u, f;
    const int len = hc_bitlen64(hc_abs64(x1) | hc_abs64(x2) | hc_abs64(x3));

    if (len > 30) { /* only for inputs 2^(30 - HC_OFFSET_BITS) counts or more from the offset */
        x1 >>= len - 30;
        x2 >>= len - 30;
        x3 >>= len - 30;
    }
    v1 = (int32_t)x1;
    v2 = (int32_t)x2;
    v3 = (int32_t)x3;
    A = (int64_t)hc_proj[0][0] * v1 + (int64_t)hc_proj[0][1] * v2 + (int64_t)hc_proj[0][2] * v3;
    B = (int64_t)hc_proj[1][0] * v1 + (int64_t)hc_proj[1][1] * v2 + (int64_t)hc_proj[1][2] * v3;
    if (!hc_atan2_q(A, B, &p)) {
        s->rejected += 1u; /* no angle information: hold the last estimate */
        return s->out_angle;
    }
    /* Gamma of eq. (fimp): the wrapped step hc_s32(p - phase) in [-pi, pi) (ties to -pi);
     * crossing the zero of the unsigned phase moves the electrical turn count */
    turn = s->turn;
    rev = s->rev;
    if (hc_s32(p - s->phase) >= 0) {
        if (p < s->phase && ++turn == HC_N) {
            turn = 0;
            rev = hc_s32((uint32_t)rev + 1u);
        }
    } else if (p > s->phase && --turn < 0) {
        turn = HC_N - 1;
        rev = hc_s32((uint32_t)rev - 1u);
    }
    s->phase = p;
    s->turn = turn;
    s->rev = rev;

    /* f_init within the revolution, Q0.32 turns */
    u = hc_turn_base[turn] + p / HC_N;
    /* eta(u): piecewise-linear with wrap-around, O(1) node search */
    j = hc_bucket[u >> HC_BUCKET_SHIFT];
    while (j < HC_M && hc_s32(u - hc_x[j + 1]) >= 0) {
        ++j;
    }
    eta = hc_eta[j] + (int32_t)(((int64_t)hc_slope[j] * (int64_t)(u - hc_x[j])
                                 + ((int64_t)1 << (HC_SLOPE_BITS - 1))) >> HC_SLOPE_BITS);
    /* y_star = rev + u + eta, kept as revolutions + Q0.32 turn */
    f = u + (uint32_t)eta;
    if (eta >= 0) {
        if (f < u) {
            rev = hc_s32((uint32_t)rev + 1u);
        }
    } else if (f > u) {
        rev = hc_s32((uint32_t)rev - 1u);
    }
    s->out_rev = rev;
    s->out_angle = f;
    return f;
}

int32_t ${pfx}_q_revolutions(const ${pfx}_q_state *s) { return s->out_rev; }

uint32_t ${pfx}_q_angle(const ${pfx}_q_state *s) { return s->out_angle; }

int64_t ${pfx}_q_angle_i64(const ${pfx}_q_state *s)
{
    return (int64_t)s->out_rev * 4294967296LL + (int64_t)s->out_angle;
}

uint32_t ${pfx}_q_rejected(const ${pfx}_q_state *s) { return s->rejected; }
"""
)


# --------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix="." + path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="ascii", newline="\n") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def export_c(
    artifact: Mapping,
    out_dir: str | os.PathLike,
    *,
    prefix: str = "hallcal",
    fixed_point: bool = True,
    source: str | None = None,
    buckets: int | None = None,
    adc_scale: float = 1.0,
    min_amplitude: float | None = None,
) -> ExportResult:
    """Generate C99 sources of f_star (eq. (f_final)) from a calibration artifact.

    Writes ``<prefix>.h`` and ``<prefix>.c`` (float) and, with ``fixed_point``,
    ``<prefix>_q.h`` and ``<prefix>_q.c`` (integer only), each atomically (temporary file and
    ``os.replace``). The C API (names with the default prefix)::

        void  hallcal_init(hallcal_state *s, float y_initial);
        float hallcal_update(hallcal_state *s, float d1, float d2, float d3);
        int32_t hallcal_revolutions(const hallcal_state *s);   /* + angle_in_rev, angle_f64 */
        void  hallcal_q_init(hallcal_q_state *s, int64_t y_initial);         /* Q32.32 turns */
        uint32_t hallcal_q_update(hallcal_q_state *s, int32_t d1, int32_t d2, int32_t d3);

    Parameters
    ----------
    artifact : mapping
        The calibration artifact as read from JSON (``"format": "hallcal-calibration/1"``,
        ``pole_pairs``, ``reconstruction.projection`` / ``offset``, ``lut.y_hat`` / ``eta``).
    out_dir : path
        Directory for the files (created if missing).
    prefix : str, keyword-only
        C identifier prefix of files, types, functions and macros.
    fixed_point : bool, keyword-only
        Also write the fixed-point variant.
    source : str, keyword-only
        Name of the artifact (e.g. its path) for the generated comments and error messages.
    buckets : int, keyword-only
        Size of the bucket table of the node search, a power of two; default the smallest
        power of two >= M (at most 2 search steps for tables with slope >= 0.5).
    adc_scale : float, keyword-only
        ADC counts per unit of the artifact's Hall signals (fixed point only: its inputs are
        integer counts ``round(adc_scale * d)``). 1 when the artifact is in counts.
    min_amplitude : float, keyword-only
        Smallest Hall amplitude (artifact unit) for which the stated bounds hold (the offsets'
        rounding is relative to it). Default: a quarter of the largest offset, or 1 if the offsets
        are below 1 (signals centred on zero).

    Returns
    -------
    ExportResult

    Raises
    ------
    HallcalInputError
        The artifact is malformed (the message names the key) or its table is not bijective.
    """
    src = source if source is not None else "<calibration artifact>"
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", prefix):
        raise HallcalInputError(f"prefix {prefix!r} is not a C identifier")
    if not (math.isfinite(adc_scale) and adc_scale > 0):
        raise HallcalInputError("adc_scale must be a positive number")
    cal = _read_artifact(artifact, src)
    m, n = cal.y_hat.size, cal.pole_pairs
    if buckets is None:
        buckets = 1 << max(2, math.ceil(math.log2(m)))
    if buckets < 4 or buckets > 65536 or buckets & (buckets - 1):
        raise HallcalInputError("buckets must be a power of two in 4..65536")
    omax = float(np.max(np.abs(cal.offset)))
    amplitude = float(min_amplitude) if min_amplitude is not None else max(omax / 4.0, 1.0)
    if not (math.isfinite(amplitude) and amplitude > 0):
        raise HallcalInputError("min_amplitude must be a positive number")

    messages: list[str] = []
    ft = _float_tables(cal, buckets)
    float_bound = _float_bound(cal, ft, amplitude)
    qt = _fixed_tables(cal, buckets, adc_scale) if fixed_point else None
    fixed_bound = atan_bound = None
    if qt is not None:
        fixed_bound, atan_bound = _fixed_bound(cal, qt, amplitude, adc_scale)
        if amplitude * adc_scale < 64:
            messages.append(
                f"the Hall amplitude is about {amplitude * adc_scale:.3g} ADC counts: the "
                "fixed-point variant takes integer counts (set adc_scale if the artifact is in "
                "volts or normalized units)"
            )
    scan = max(ft.max_scan, qt.max_scan if qt is not None else 0)
    if scan > 8:
        messages.append(
            f"the node search may take {scan} steps (steep table); more buckets make it shorter"
        )

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    version = _version()
    pfx, PFX = prefix, prefix.upper()
    paths: list[Path] = []

    bounds_f = [
        "",
        "Stated error bounds vs the Python f_star (hallcal.sensor.lut.LUT, double precision):",
        f"  revolutions + angle_in_rev, angle_f64 : <= {float_bound:.2e} rad (mechanical)",
        "  returned float y_star                 : the above + 0.5 ulp(|y|) = 6e-8 |y| rad",
        f"  assumed Hall amplitude >= {amplitude:.6g} (artifact unit)",
        f"Node search: {buckets} buckets, <= {ft.max_scan} forward steps.",
        f"Tables: {ft.bytes} bytes (static const).",
        "NaN/inf/zero alpha-beta samples are rejected and the last estimate is held.",
    ]
    header = _banner(f"{pfx}.h", cal, src, version, bounds_f)
    h_text = _FLOAT_H.substitute(banner=header, pfx=pfx, PFX=PFX, n=n, m=m)
    c_text = _FLOAT_C.substitute(
        banner=_banner(f"{pfx}.c", cal, src, version, bounds_f),
        header=f"{pfx}.h",
        pfx=pfx,
        PFX=PFX,
        n=n,
        m=m,
        b=buckets,
        scan=ft.max_scan,
        inv_n=_c_float(1.0 / n),
        bucket_scale=_c_float(buckets / TWO_PI),
        p0=", ".join(_c_float(v) for v in cal.projection[0]),
        p1=", ".join(_c_float(v) for v in cal.projection[1]),
        offset=", ".join(_c_float(v) for v in cal.offset),
        turn_base=_c_list([_c_float(TWO_PI * t / n) for t in range(n)], 6),
        x=_c_list([_c_float(v) for v in ft.x], 6),
        eta=_c_list([_c_float(v) for v in ft.eta], 6),
        bucket=_c_list([str(int(v)) for v in ft.bucket], 12),
    )
    for name, text in ((f"{pfx}.h", h_text), (f"{pfx}.c", c_text)):
        _write_atomic(out / name, text)
        paths.append(out / name)

    if qt is not None:
        assert fixed_bound is not None and atan_bound is not None
        bounds_q = [
            "",
            "Fixed point: int32 arithmetic, int64 intermediate products and sums; no float.",
            "  inputs  : raw ADC counts, int32 (any value is safe)",
            f"  offsets : Q{31 - qt.offset_bits}.{qt.offset_bits} counts"
            f" (adc_scale {adc_scale:g} counts per artifact unit)",
            "  angles  : Q0.32 turns (2^32 = 2 pi rad), revolutions in a separate int32",
            f"Integer atan2 (CORDIC, {CORDIC_ITERATIONS} iterations): |error| <= "
            f"{atan_bound:.2e} rad (electrical)",
            "Stated error bound vs the Python f_star (hallcal.sensor.lut.LUT, double precision):",
            f"  revolutions + angle : <= {fixed_bound:.2e} rad (mechanical)",
            f"  assumed Hall amplitude >= {amplitude * adc_scale:.6g} counts",
            f"Node search: {buckets} buckets, <= {qt.max_scan} forward steps.",
            f"Tables: {qt.bytes} bytes (static const).",
        ]
        hq = _FIXED_H.substitute(
            banner=_banner(f"{pfx}_q.h", cal, src, version, bounds_q), pfx=pfx, PFX=PFX, n=n, m=m
        )
        cq = _FIXED_C.substitute(
            banner=_banner(f"{pfx}_q.c", cal, src, version, bounds_q),
            header=f"{pfx}_q.h",
            pfx=pfx,
            PFX=PFX,
            n=n,
            m=m,
            b=buckets,
            bshift=32 - int(round(math.log2(buckets))),
            scan=qt.max_scan,
            obits=qt.offset_bits,
            sbits=qt.slope_bits,
            iters=CORDIC_ITERATIONS,
            normbits=_NORM_BITS,
            pexp=qt.projection_exp,
            atan_bound=f"{atan_bound:.2e}",
            offset=", ".join(_c_i32(v) for v in qt.offset),
            p0=", ".join(_c_i32(v) for v in qt.projection[0]),
            p1=", ".join(_c_i32(v) for v in qt.projection[1]),
            turn_base=_c_list([_c_u32(v) for v in qt.turn_base], 6),
            cordic_steps="\n".join(
                f"    HC_STEP({i}, {_c_u32(v)}); /* atan(2^-{i}) in Q0.32 turns */"
                for i, v in enumerate(qt.atan)
            ),
            x=_c_list([_c_u32(v) for v in qt.x], 8),
            eta=_c_list([_c_i32(v) for v in qt.eta], 8),
            slope=_c_list([_c_i32(v) for v in qt.slope], 8),
            bucket=_c_list([str(int(v)) for v in qt.bucket], 12),
        )
        for name, text in ((f"{pfx}_q.h", hq), (f"{pfx}_q.c", cq)):
            _write_atomic(out / name, text)
            paths.append(out / name)

    return ExportResult(
        status="warning" if messages else "ok",
        paths=tuple(paths),
        pole_pairs=n,
        points=m,
        buckets=buckets,
        max_search_steps=scan,
        table_bytes=ft.bytes,
        table_bytes_q=qt.bytes if qt is not None else None,
        float_bound=float_bound,
        fixed_bound=fixed_bound,
        atan2_bound=atan_bound,
        assumed_amplitude=amplitude,
        sha256=cal.sha256,
        messages=tuple(messages),
    )
