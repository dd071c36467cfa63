"""No slip without the fault flag: 100 000 adversarial trials per class, float and fixed point.

Run ``python benchmarks/bench_slip.py [--trials 100000] [--out benchmarks/bench_slip.txt]``
(any host C compiler). It calibrates the demo (the paper's simulation study), exports it as the
README does for a drive (default options; the fixed-point variant at 2^14 counts per unit),
compiles the generated float and fixed-point sources with the host test driver
(``tests/firmware_support.py``, ``-O2``; the same C gives the same bits on the Cortex-M4F and
M0+, ``tests/test_codegen_arm.py``) and runs the trial classes of ``tests/slip_trials.py``:
overspeed up to twice the stated speed limit, a plausible bad first sample after ``set_angle``,
bursts of 2-5 plausible bad samples, a stuck channel (2-40 samples), a clipped channel (30-95 %
of its amplitude). Each trial is 64 samples from ``set_angle`` at the true position (homed use);
it slips when its last reading is more than half a pole pitch from the truth, and is flagged
when the fault flag is latched in that reading. The truth is the demo's identified flux model
(the signals), with the paper's noise (variance 7.5e-6).

Reported per class and variant: slips, slips without the fault flag (the figure that must be 0),
faults (the price: trials that end with the fault latched), and the largest error of a trial
without the fault; for the overspeed class also the split at the speed limit.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import firmware_support as fs  # noqa: E402
import slip_trials as st  # noqa: E402
from bench_support import DEMO_ADC_SCALE, demo_case, finish_report  # noqa: E402

from hallcal.output.codegen import export_c  # noqa: E402
from hallcal.sensor.flux import FluxModel, FourierBasis  # noqa: E402

NOISE = math.sqrt(7.5e-6)  # the paper's Hall noise (variance 7.5e-6 per channel)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100_000, help="trials per class")
    ap.add_argument("--out", type=Path, default=None, help="also write the report here")
    args = ap.parse_args(argv)
    if fs.CC is None:
        print("no C compiler (cc, gcc or clang) on PATH", file=sys.stderr)
        return 2

    lines = [
        "hallcal.output.codegen: no slip without the fault flag (benchmarks/bench_slip.py)",
        "=" * 78,
        f"host    : {platform.machine()}, {os.cpu_count()} cores, shared with other jobs",
        f"compiler: {fs.CC} -O2 (the host test driver of tests/firmware_support.py)",
        "",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        wd = Path(tmp)
        art, _ = demo_case(wd / "demo")
        gen = wd / "fw"
        res = export_c(art, gen, source="calibration.json", adc_scale=DEMO_ADC_SCALE,
                       powerup=False)  # fmt: skip
        pl = res.design.plausibility
        n = res.pole_pairs
        w = res.glitch_safe_speed
        ts = res.design.sample_time
        lines += [
            f"demo export (n_m = {n}): speed limit {w:.4g} rad per sample ({w / ts:.4g} rad/s), "
            f"f_init slope {pl.slope:.3f}, window {pl.step_limit:.4g} electrical turn, "
            f"fault after {res.fault_after} (alias-safe holds {pl.alias_holds})",
            f"{args.trials} trials per class and variant, 64 samples each, homed (set_angle)",
            "",
            f"{'class':<13s} {'variant':<7s} {'slips':>7s} {'silent':>7s} {'faults':>7s} "
            f"{'worst error without fault [rad]':>32s}",
        ]
        flux = FluxModel(FourierBasis(tuple(art["model"]["harmonics"])),
                         np.array(art["model"]["theta"]))  # fmt: skip
        exe = {f: fs.compile_driver(gen, fixed=f, flags=["-O2"], name=f"slip_{int(f)}")
               for f in (False, True)}  # fmt: skip
        notes = []
        for i, kind in enumerate(st.CLASSES):
            tr = st.make_trials(kind, flux, n=n, w=w, noise=NOISE, trials=args.trials,
                                length=64, seed=1000 + i)  # fmt: skip
            for fixed in (False, True):
                r = st.run_trials(exe[fixed], tr, fixed=fixed, scale=DEMO_ADC_SCALE)
                s = st.summarize(r, tr, n, w)
                lines.append(
                    f"{kind:<13s} {'fixed' if fixed else 'float':<7s} {s['slips']:7d} "
                    f"{s['silent']:7d} {s['faults']:7d} {s['worst_unflagged']:32.2e}"
                )
                if kind == "overspeed":
                    notes.append(
                        f"overspeed {'fixed' if fixed else 'float'}: {s['over']} trials above the "
                        f"speed limit, {s['trials'] - s['over']} within it: {s['slips_within']} "
                        f"slips and {s['faults_within']} faults within it"
                    )
        lines += ["", *notes, "",
                  f"half a pole pitch: {math.pi / n:.4f} rad; 'silent' = slips without the fault "
                  "flag (must be 0)"]  # fmt: skip
    return finish_report(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
