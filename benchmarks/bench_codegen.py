"""Benchmark of the generated firmware (hallcal.output.codegen) on ARM: size, instructions, cycles.

Run ``python benchmarks/bench_codegen.py [--out benchmarks/bench_codegen.txt]`` (needs Debian's
``gcc-arm-none-eabi``, ``libnewlib-arm-none-eabi`` and ``qemu-system-arm``). It calibrates the
demo (the paper's simulation study) and ring-jig recording 1, exports both, cross-compiles the
float variant for Cortex-M4F and the fixed-point variant for Cortex-M0+ (and, for comparison,
for the FPU-less Cortex-M4), and reports

* ``arm-none-eabi-size`` of each object, the table bytes and the bytes of code per function,
  and ``arm-none-eabi-nm -u`` (what the object needs from libraries: nothing);
* instructions per call of ``update``, counted from a QEMU single-step trace (``-d exec``) over
  the first 2000 samples of the demo's validation run plus a fast spin (0.055 electrical turn per
  sample, forward and back: every octant, the 45-degree rotation and the turn boundaries);
* the Cortex-M4 cycles of each traced call, from the instructions actually executed and the
  M4 timing table of ``tests/arm_harness.py`` (TRM r0p1: taken branch 3, VLDR 2, LDR 2 or 1
  when pipelined after a load, STR with immediate offset 1, VMUL/VADD 1, VCVT 1, ...), with
  zero-wait-state memory; and where the cycles go (per instruction class);
* the largest difference to ``hallcal reconstruct`` on the whole recording.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import arm_harness as ah  # noqa: E402

from hallcal.io import read_artifact, read_dataset  # noqa: E402
from hallcal.output.codegen import CORDIC_STEPS, export_c  # noqa: E402
from hallcal.pipeline.calibration import lut_from_artifact  # noqa: E402
from hallcal.sensor.flux import FluxModel, FourierBasis  # noqa: E402

TWO_PI = 2.0 * math.pi
DEMO_ADC_SCALE = 2.0**14
RINGJIG = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "ring-jig"
if not RINGJIG.exists():
    RINGJIG = Path("/work/shared/data/real/ring-jig")


def _fast_spin(art: dict) -> np.ndarray:
    flux = FluxModel(
        FourierBasis(tuple(art["model"]["harmonics"])), np.array(art["model"]["theta"])
    )
    n = art["pole_pairs"]
    k = np.arange(3000)
    y0 = 0.3 + np.cumsum(0.055 * TWO_PI / n * np.where(k < 1500, 1.0, -1.0))
    return flux(y0)


def _demo(folder: Path) -> tuple[dict, np.ndarray]:
    from hallcal.demo import run_demo

    run_demo(folder, report=False)
    return read_artifact(folder / "calibration.json"), read_dataset(folder / "validation.npz").d


def _ringjig(folder: Path) -> tuple[dict, np.ndarray] | None:
    import hallcal
    from hallcal.fit.constant_speed import find_constant_speed

    path = RINGJIG / "hall_calibration_one_rotation_1.txt"
    if not path.exists():
        return None
    d = np.loadtxt(path, dtype=np.int64).astype(np.float64)
    start, mid, _ = find_constant_speed(d, 25).split(2.0)
    setup = {"pole_pairs": 25, "sample_time": 1.0,
             "trajectory": {"kind": "constant-speed", "start": start, "stop": mid}}  # fmt: skip
    cal = hallcal.calibrate({f"d{h + 1}": d[:, h] for h in range(3)}, setup)
    cal.save(folder / "ringjig1.json")
    return read_artifact(folder / "ringjig1.json"), d


def _classes(tr: ah.Trace, calls: int) -> list[str]:
    """Cycles per call by instruction class."""
    groups = {
        "FP load (VLDR)": ("vldr",), "FP arithmetic": ("vadd", "vsub", "vmul", "vneg", "vabs"),
        "FP compare/status": ("vcmp", "vcmpe", "vmrs"), "FP convert/move": ("vcvt", "vmov"),
        "FP store": ("vstr",), "integer loads": ah._INT_LOADS + ("ldrd",),
        "integer stores": ah._INT_STORES + ("strd",), "branches": ah._BRANCHES,
        "push/pop": ("push", "pop"),
    }  # fmt: skip
    out: Counter = Counter()
    for _, (_execs, cyc, mn, _ops) in tr.per_pc.items():
        base = mn.lower().split(".")[0]
        base = ah._fp_base(base) if base.startswith("v") else ah._base(mn)
        name = next((g for g, ms in groups.items() if base in ms), "integer ALU/multiply/IT")
        out[name] += cyc
    return [f"      {c / calls:6.1f}  {g}" for g, c in out.most_common()]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="also write the report here")
    args = ap.parse_args(argv)
    missing = ah.toolchain()
    if missing is not None:
        print(f"{missing} not found: install gcc-arm-none-eabi, libnewlib-arm-none-eabi and "
              "qemu-system-arm", file=sys.stderr)  # fmt: skip
        return 2
    lines = [
        "hallcal.output.codegen benchmark (benchmarks/bench_codegen.py)",
        "=" * 64,
        f"host    : {platform.machine()}, {os.cpu_count()} cores, shared with other jobs",
        f"compiler: {subprocess.run(['arm-none-eabi-gcc', '--version'], capture_output=True, text=True).stdout.splitlines()[0]}",  # noqa: E501
        f"QEMU    : {subprocess.run(['qemu-system-arm', '--version'], capture_output=True, text=True).stdout.splitlines()[0]}",  # noqa: E501
        "flags   : -O2 -std=c99 (strict warnings, -Werror); M4F: -mcpu=cortex-m4 -mfpu=fpv4-sp-d16 "
        "-mfloat-abi=hard; M0+: -mcpu=cortex-m0plus",
        "",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        wd = Path(tmp)
        cases = [("demo (n_m = 11, normalized signals; fixed point at 2^14 counts per unit)",
                  *_demo(wd / "demo"), DEMO_ADC_SCALE)]  # fmt: skip
        rj = _ringjig(wd)
        if rj is not None:
            cases.append(("ring-jig 1 (n_m = 25, raw 16-bit counts)", *rj, 1.0))
        for title, art, d, scale in cases:
            gen = wd / f"gen{len(lines)}"
            res = export_c(art, gen, source="calibration.json", adc_scale=scale)
            lut = lut_from_artifact(art)
            t = res.design.table
            lines += [
                title,
                "-" * len(title),
                f"table   : {t.points} intervals ({res.table_points // res.pole_pairs} per "
                f"electrical turn), {'quadratic' if t.quadratic else 'linear'}, "
                f"{res.table_bytes} bytes; {res.table_error:.2e} rad from the calibration's "
                f"(budget {res.budget:.2e})",
                f"bounds  : float {res.float_bound:.2e} rad, fixed {res.fixed_bound:.2e} rad "
                f"(atan2 {res.atan2_bound:.1e} / {res.fixed_atan2_bound:.1e} rad electrical, "
                f"{CORDIC_STEPS} CORDIC steps)",
            ]
            spin = _fast_spin(art)
            for variant, target in (("float", "m4f"), ("fixed", "m0plus"), ("fixed", "m4f")):
                fixed = variant == "fixed"
                b = ah.build(gen, wd / f"b{len(lines)}", target=target, fixed=fixed)

                def conv(v, fixed=fixed, scale=scale):
                    return np.round(v * scale) if fixed else v.astype(np.float32)

                raw = ah.run(b, conv(d))
                y = ah.angles(b, raw)
                y_py = lut.f_star(conv(d) / scale if fixed else conv(d).astype(np.float64))
                err = float(np.max(np.abs(y - y_py)))
                x = np.concatenate([conv(d[:2000]), conv(spin)])
                tr = ah.trace(b, x)
                size = ah.sizes(b.obj)
                funcs = ah.function_sizes(b)
                code = {k: v for k, v in funcs.items() if not k.startswith("hc_t") and
                        k not in ("hc_c", "hc_turn", "hc_base")}  # fmt: skip
                lines += [
                    f"  {variant} on {b.target.name}: text {size['text']} bytes (data "
                    f"{size['data']}, bss {size['bss']}); nm -u: "
                    f"{' '.join(ah.undefined_symbols(b.obj)) or 'nothing'}",
                    "    code bytes: " + ", ".join(f"{k} {v}" for k, v in sorted(code.items())),
                    f"    max |C - python| over {len(d)} samples: {err:.2e} rad "
                    f"({int(np.sum(raw[:, 2] != 0))} samples rejected)",
                    f"    instructions per sample (traced, {len(tr.counts)} calls): min "
                    f"{tr.counts.min()}, median {int(np.median(tr.counts))}, max "
                    f"{tr.counts.max()}",
                ]
                if target == "m4f":
                    lines += [
                        f"    Cortex-M4 cycles per sample (estimate from the trace): min "
                        f"{tr.cycles.min()}, median {int(np.median(tr.cycles))}, max "
                        f"{tr.cycles.max()} -> {tr.cycles.max() / 168:.2f} us at 168 MHz",
                    ]
                    if not fixed:
                        lines += ["    where the cycles go (per sample):"]
                        lines += _classes(tr, len(tr.counts))
            lines.append("")
    load = os.getloadavg()
    lines.append(f"load average at the end: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    report = "\n".join(lines) + "\n"
    print(report, end="")
    if args.out is not None:
        args.out.write_text(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
