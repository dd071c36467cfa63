"""Benchmark of the generated firmware code (hallcal.output.codegen): speed, size, MCU cycles.

Run ``python benchmarks/bench_codegen.py [--out benchmarks/bench_codegen.txt]``. It builds a
raw-ADC-like calibration (n_m = 11, M = 4096 nodes, trapezoidal flux, unequal projection), exports
it, compiles the float and the fixed-point variant at -O2 with the system C compiler (as separate
objects linked to a timing loop, as in firmware: no inlining across the call), and reports

* ns per sample on this machine (best of several passes over 65536 recorded-like samples),
* the agreement with the Python f_star on those samples,
* ``size`` of each object file and the bytes of its ``static const`` tables,
* an estimate of Cortex-M4 cycles per sample from an operation count, with its assumptions.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from hallcal.output.codegen import CORDIC_ITERATIONS, export_c
from hallcal.sensor.flux import FluxModel, FourierBasis, sinusoidal_theta
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sensor.reconstruction import projection_matrix

TWO_PI = 2.0 * math.pi
N_SAMPLES = 65536

BENCH_C = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "hallcal.h"
#include "hallcal_q.h"

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

int main(int argc, char **argv) {
    long n, reps, passes, i, r, p;
    float *df;
    int32_t *dq;
    double best_f = 1e30, best_q = 1e30;
    volatile float sink_f = 0.0f;
    volatile uint32_t sink_q = 0u;
    FILE *fin, *fout;
    if (argc < 6) return 2;
    n = atol(argv[1]);
    reps = atol(argv[2]);
    passes = atol(argv[3]);
    df = malloc(sizeof(float) * 3 * (size_t)n);
    dq = malloc(sizeof(int32_t) * 3 * (size_t)n);
    fin = fopen(argv[4], "rb");
    fout = fopen(argv[5], "wb");
    if (!df || !dq || !fin || !fout) return 1;
    if (fread(df, sizeof(float), 3 * (size_t)n, fin) != 3 * (size_t)n) return 1;
    if (fread(dq, sizeof(int32_t), 3 * (size_t)n, fin) != 3 * (size_t)n) return 1;
    { /* outputs for the agreement check */
        hallcal_state s;
        hallcal_q_state q;
        hallcal_init(&s, 0.0f);
        hallcal_q_init(&q, 0);
        for (i = 0; i < n; ++i) {
            double out[2];
            hallcal_update(&s, df[3 * i], df[3 * i + 1], df[3 * i + 2]);
            hallcal_q_update(&q, dq[3 * i], dq[3 * i + 1], dq[3 * i + 2]);
            out[0] = hallcal_angle_f64(&s);
            out[1] = (double)hallcal_q_angle_i64(&q);
            fwrite(out, sizeof out, 1, fout);
        }
        fclose(fout);
    }
    for (p = 0; p < passes; ++p) {
        hallcal_state s;
        hallcal_q_state q;
        double t0;
        hallcal_init(&s, 0.0f);
        t0 = now();
        for (r = 0; r < reps; ++r)
            for (i = 0; i < n; ++i)
                sink_f = hallcal_update(&s, df[3 * i], df[3 * i + 1], df[3 * i + 2]);
        t0 = now() - t0;
        if (t0 < best_f) best_f = t0;
        hallcal_q_init(&q, 0);
        t0 = now();
        for (r = 0; r < reps; ++r)
            for (i = 0; i < n; ++i)
                sink_q = hallcal_q_update(&q, dq[3 * i], dq[3 * i + 1], dq[3 * i + 2]);
        t0 = now() - t0;
        if (t0 < best_q) best_q = t0;
    }
    printf("%.3f %.3f\n", 1e9 * best_f / (double)(n * reps), 1e9 * best_q / (double)(n * reps));
    (void)sink_f;
    (void)sink_q;
    return 0;
}
"""

# Cortex-M4 operation counts per sample (instructions a compiler emits for the generated code)
# with cycle costs from the Cortex-M4 Technical Reference Manual: integer ALU, MUL/SMULL/SMLAL,
# CLZ 1 cycle; LDR/VLDR 2 (no pipelining of consecutive loads assumed); taken branch 3;
# VADD/VSUB/VMUL/VCVT/VCMP/VMRS 1, VFMA 3, VDIV 14. Flash wait states are not counted (code and
# tables in zero-wait memory or behind a flash accelerator/cache).
M4_FLOAT = [
    ("offsets: 3 VLDR + 3 VSUB", 3 * 2 + 3),
    ("projection: 6 VLDR + 2 VMUL + 4 VFMA", 6 * 2 + 2 + 4 * 3),
    ("NaN/inf/zero checks: 4 VCMP + 2 VMRS + 3 branches", 4 + 2 + 3 * 1),
    ("unwrap: 3 LDR state + VSUB + 2 VCMP/VMRS + 2 branches + 3 STR", 3 * 2 + 1 + 4 + 2 + 3),
    ("within the revolution: 2 VLDR (1/n, turn base) + VFMA", 2 * 2 + 3),
    ("wrap for the look-up: VCMP/VMRS + branch (+ 2 VADD)", 2 + 1 + 2),
    ("bucket: VLDR + VMUL + VCVT + VMOV + clamp + LDRH", 2 + 1 + 1 + 1 + 2 + 2),
    ("node search: 2 tests x (VLDR + VCMP + VMRS + branch)", 2 * (2 + 1 + 1 + 3)),
    ("interpolation: 4 VLDR + 3 VSUB + VDIV + VFMA", 4 * 2 + 3 + 14 + 3),
    ("normalize to [0, 2 pi): 2 x (VCMP/VMRS + branch) + VADD", 2 * (2 + 1) + 1),
    ("output: 2 STR + VCVT + VMUL + VFMA + VADD", 2 + 1 + 1 + 3 + 1),
    ("call, prologue/epilogue (push/pop, return)", 12),
]
M4_ATAN2F = 150  # assumed: newlib atan2f (fdlibm, single precision); CMSIS-DSP is about 50
M4_FIXED = [
    ("offsets: 3 x (64-bit shift + 64-bit SUB + constant)", 3 * 4),
    ("input range check: 3 abs64 + 2 OR64 + CLZ64 + branch", 3 * 4 + 2 * 2 + 4 + 1),
    ("projection: 6 LDR + 6 SMULL/SMLAL", 6 * 2 + 6),
    ("atan2 scaling: 2 abs64, OR64, CLZ64, 2 variable 64->32 shifts, half plane", 8 + 2 + 4 + 14),
    (
        f"CORDIC, unrolled: {CORDIC_ITERATIONS} x (mask SUB+ASR 2; a: EOR with shifted "
        "operand, SUB, ADD 3; b: 3; z: MOVW/MOVT, EOR, SUB, ADD 5)",
        CORDIC_ITERATIONS * (2 + 3 + 3 + 5),
    ),
    ("unwrap: 3 LDR state + SUB/CMP + 2 branches + 3 STR", 3 * 2 + 2 + 2 * 2 + 3),
    ("within the revolution: p / n_m as UMULL + LSR, LDR turn base, ADD", 2 + 2 + 1),
    ("bucket: LSR + LDRH", 1 + 2),
    ("node search: 2 tests x (LDR + SUB + CMP + branch)", 2 * (2 + 1 + 1 + 3)),
    ("interpolation: 3 LDR + SUB + SMULL + 64-bit round/shift + ADD", 3 * 2 + 1 + 1 + 4 + 1),
    ("output: ADD + carry tests + 2 STR", 1 + 3 + 2),
    ("call, prologue/epilogue (push/pop of 8 registers, return)", 16),
]


def calibration() -> tuple[dict, LUT, np.ndarray]:
    """A raw-ADC-like calibration and a recorded-like data set in ADC counts."""
    n, amp = 11, 1500.0
    rng = np.random.default_rng(3)
    harmonics = sorted(set(range(1, n + 2)) | {2 * n, 3 * n, 5 * n})
    basis = FourierBasis(tuple(harmonics))
    phases = np.array([0.0, TWO_PI / 3 + 0.03, 2 * TWO_PI / 3 - 0.02])
    offset = np.array([2000.3, 1990.1, 2010.7])
    theta = sinusoidal_theta(
        basis, n, amplitude=amp * np.array([1.0, 0.99, 1.02]), offset=offset, phases=phases
    )
    for h in harmonics:
        if h not in (n, 3 * n, 5 * n):
            js, jc = basis.index(h)
            theta[:, [js, jc]] += rng.normal(0, 0.02 * amp / 4, (3, 2))
    for k, c in ((3, 0.05), (5, 0.02)):
        js, jc = basis.index(k * n)
        theta[:, jc] += c * amp * np.cos(k * phases)
        theta[:, js] += c * amp * np.sin(k * phases)
    truth = FluxModel(basis, theta)
    P = projection_matrix(phases + np.array([0.0, 0.01, -0.005]))
    o_est = offset + amp * np.array([3e-4, -2e-4, 1e-4])
    lut = build_lut(truth, n, points=4096, projection=P, offset=o_est)
    artifact = {
        "format": "hallcal-calibration/1",
        "pole_pairs": n,
        "reconstruction": {"projection": P.tolist(), "offset": o_est.tolist()},
        "lut": {"y_hat": lut.y_hat.tolist(), "eta": lut.eta.tolist(), "points": 4096},
    }
    k = np.arange(N_SAMPLES)
    y0 = 14.0 * np.sin(TWO_PI * 1.5 * k / N_SAMPLES) + 0.3 * np.sin(TWO_PI * k / 700.0)
    d = np.round(truth(y0) + np.random.default_rng(1).normal(0.0, 3.0, (N_SAMPLES, 3)))
    return artifact, lut, d


def _run(cmd: list[str]) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True).stdout


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="also write the report here")
    ap.add_argument("--reps", type=int, default=8, help="passes over the samples per timing")
    args = ap.parse_args(argv)
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    size = shutil.which("size")
    if cc is None:
        print("no C compiler on PATH", file=sys.stderr)
        return 2
    artifact, lut, d = calibration()
    with tempfile.TemporaryDirectory() as tmp:
        wd = Path(tmp)
        res = export_c(artifact, wd, source="bench calibration (n_m = 11, M = 4096)")
        objs = []
        for name in ("hallcal", "hallcal_q"):
            obj = wd / f"{name}.o"
            _run([cc, "-std=c99", "-O2", "-c", str(wd / f"{name}.c"), "-o", str(obj)])
            objs.append(obj)
        (wd / "bench.c").write_text(BENCH_C)
        exe = wd / "bench"
        cmd = [cc, "-std=c99", "-O2", f"-I{wd}", str(wd / "bench.c"), *map(str, objs)]
        _run([*cmd, "-o", str(exe), "-lm"])
        data = wd / "data.bin"
        data.write_bytes(d.astype(np.float32).tobytes() + d.astype(np.int32).tobytes())
        out = wd / "out.bin"
        timing = _run([str(exe), str(N_SAMPLES), str(args.reps), "7", str(data), str(out)])
        ns_f, ns_q = (float(v) for v in timing.split())
        got = np.frombuffer(out.read_bytes(), dtype=np.float64).reshape(-1, 2)
        sizes = "(size not found)\n"
        if size:  # from the directory, so that the file names are short
            sizes = subprocess.run(
                [size, *(o.name for o in objs)], cwd=wd, check=True, capture_output=True, text=True
            ).stdout
        cc_version = _run([cc, "--version"]).splitlines()[0]

    ys = lut.f_star(d)
    err_f = float(np.max(np.abs(got[:, 0] - ys)))
    q = got[:, 1]
    yq = TWO_PI * np.floor(q / 2**32) + TWO_PI * (np.mod(q, 2**32) / 2**32)
    err_q = float(np.max(np.abs(yq - ys)))
    text = [int(row.split()[0]) for row in sizes.splitlines()[1:] if row.split()[:1] != []]
    tables = (res.table_bytes, res.table_bytes_q or 0)
    code = [str(t - b) for t, b in zip(text, tables, strict=False)] if size else ["?", "?"]
    m4_f = sum(c for _, c in M4_FLOAT) + M4_ATAN2F
    m4_q = sum(c for _, c in M4_FIXED)
    lines = [
        "hallcal.output.codegen benchmark (benchmarks/bench_codegen.py)",
        "=" * 56,
        f"machine : {_cpu()}, {platform.system()} {platform.machine()}, {os.cpu_count()} cores",
        f"          shared with other jobs (load average {os.getloadavg()[0]:.1f} at the end)",
        f"compiler: {cc_version}, -std=c99 -O2, objects linked to a timing loop",
        f"table   : n_m = {res.pole_pairs}, M = {res.points} nodes, {res.buckets} buckets, "
        f"<= {res.max_search_steps} search steps",
        "",
        f"Time per sample (best of 7 passes of {args.reps} x {N_SAMPLES} recorded-like samples):",
        f"  float (hallcal_update, glibc atan2f)      : {ns_f:7.1f} ns",
        f"  fixed (hallcal_q_update, CORDIC {CORDIC_ITERATIONS} steps) : {ns_q:7.1f} ns",
        "",
        f"Agreement with the Python f_star on the same {N_SAMPLES} samples (max abs, rad):",
        f"  float (revolutions + angle) : {err_f:.2e}   stated bound {res.float_bound:.2e}",
        f"  fixed (revolutions + angle) : {err_q:.2e}   stated bound {res.fixed_bound:.2e}",
        f"  integer atan2 stated bound  : {res.atan2_bound:.2e} rad electrical",
        "",
        "Code size (size of the -O2 x86-64 objects; text includes the static const tables):",
        *("  " + s for s in sizes.rstrip().splitlines()),
        f"  static const tables: float {res.table_bytes} bytes, fixed {res.table_bytes_q} bytes",
        f"  code without the tables (text - tables): float {code[0]} bytes, fixed {code[1]} bytes",
        "  (about 10 M bytes float and 14 M bytes fixed point: choose M for the flash you have)",
        "",
        "Cortex-M4 estimate from an operation count (cycles per sample). Assumptions: Cortex-M4",
        "TRM timings: ALU, MUL, SMULL/SMLAL, CLZ 1 cycle; LDR/VLDR 2; taken branch 3; VADD/VSUB/",
        "VMUL/VCVT/VCMP/VMRS 1; VFMA 3; VDIV 14; tables in zero-wait-state memory; 2 node-search",
        f"tests per sample (the worst case for this table is {res.max_search_steps} steps).",
        "",
        "  float variant (Cortex-M4F, single-precision FPU):",
        *(f"    {c:4d}  {name}" for name, c in M4_FLOAT),
        f"    {M4_ATAN2F:4d}  atan2f (assumed: newlib; CMSIS-DSP arm_atan2_f32 is about 50)",
        f"    {m4_f:4d}  total -> {m4_f / 168:.2f} us at 168 MHz",
        "",
        "  fixed-point variant (Cortex-M3/M4 without FPU):",
        *(f"    {c:4d}  {name}" for name, c in M4_FIXED),
        f"    {m4_q:4d}  total -> {m4_q / 168:.2f} us at 168 MHz, {m4_q / 80:.2f} us at 80 MHz",
        "",
        f"At the paper's 4 kHz sample rate either variant takes {100 * m4_q * 4e3 / 168e6:.1f}%"
        " or less of a 168 MHz Cortex-M4.",
    ]
    report = "\n".join(lines) + "\n"
    print(report, end="")
    if args.out is not None:
        args.out.write_text(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
