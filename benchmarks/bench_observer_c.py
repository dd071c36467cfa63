"""The observer's C export (``hallcal export-c --observer``) on a Cortex-M4F under QEMU.

Paper bench (11 pole pairs), calibrated as in bench_observer.py; the C of
:mod:`hallcal.output.codegen.c_observer` cross-compiled for the Cortex-M4F
(``tests/arm_harness.py``:
strict flags, ``-O2``, bare metal on ``mps2-an386``) and run on

* 3000 samples of a validation run with a channel stuck at its zero-field level from sample
  1500 and 10 glitch samples (3.0 on channel 0) from sample 2500: the largest difference from
  Python's y_obs on the same float32 inputs;
* an adversarial set (``firmware_support.observer_adversarial``): the start (the node search),
  glitches of every size on every channel at every phase of the adaptation's cycle, a channel
  stuck, at a rail, clipped and disconnected (the exclusion samples), non-finite readings,
  random readings (every sample an outlier), swapped wires (stale) and a return to healthy
  signals (readmission);

the Cortex-M4 cycles of ``update`` + ``read`` per sample (QEMU single-step trace, the harness's M4
timing table, a taken branch 1 + 2 cycles: :func:`arm_harness.model_cycles`), per kind of sample
and per function. Code and table sizes.

Run: ``python benchmarks/bench_observer_c.py`` (needs gcc-arm-none-eabi and qemu-system-arm);
output committed beside it (bench_observer_c.txt).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import arm_harness as ah  # noqa: E402
from bench_observer import ramp, setup_for  # noqa: E402
from firmware_support import observer_adversarial as adversarial  # noqa: E402

import hallcal  # noqa: E402
from hallcal.output.codegen.c_observer import export_observer_c  # noqa: E402
from hallcal.pipeline.observe import run_on  # noqa: E402
from hallcal.sim.bench import BenchConfig  # noqa: E402


def main() -> None:
    missing = ah.toolchain()
    if missing:
        print(f"missing tool: {missing}")
        return
    cfg = BenchConfig(seed=0)
    cal = hallcal.calibrate(ramp(cfg, 13.0, 26.0, 1).columns(), setup_for(cfg, range(1, 12)))
    with tempfile.TemporaryDirectory() as tmp:
        gen = Path(tmp) / "gen"
        res = export_observer_c(cal.to_artifact(), gen)
        b = ah.build(gen, Path(tmp) / "work", target="m4f", fixed=False, prefix="hallcal_obs")
        val = ramp(cfg, 10.0, 20.0, 21)
        d = val.d[:3000].astype(np.float32).copy()
        d[1500:, 1] = np.float32(cal.flux.theta[1, 0])
        d[2500:2510, 0] = np.float32(3.0)
        y = ah.angles(b, ah.run(b, d))
        py = run_on(cal, d.astype(np.float64))
        print(f"Cortex-M4F (QEMU) against Python on the same float32 inputs: max |y_C - y_obs| "
              f"= {np.max(np.abs(y - py.y_obs)):.2g} rad over 3000 samples (stuck channel from "
              "1500, glitches at 2500); states equal: "
              f"{bool(np.array_equal(ah.run(b, d)[:, 2] & 0xFF, py.state_code))}")  # fmt: skip
        adv = adversarial(val.d[:6000], cal.flux.theta[:, 0])
        ya = ah.angles(b, ah.run(b, adv))
        pa = run_on(cal, adv.astype(np.float64))
        print(f"adversarial set ({len(adv)} samples): max |y_C - y_obs| = "
              f"{np.max(np.abs(ya - pa.y_obs)):.2g} rad; Python states "
              + ", ".join(f"{s} {np.mean(pa.state == s):.0%}" for s in
                          ("ok", "adapting", "stale", "degraded", "fault")))  # fmt: skip
        ct = ah.trace_calls(b, adv, read=True)
        cyc = ah.model_cycles(ct, ah.CycleModel())
        print(
            f"cycles per sample, update + read ({ah.CycleModel().label()}): median "
            f"{int(np.median(cyc))}, max {int(cyc.max())} (sample {int(np.argmax(cyc))}); "
            f"the start (node search) {int(cyc[0])}; healthy first 1000 samples: median "
            f"{int(np.median(cyc[1:1000]))}, max {int(cyc[1:1000].max())}"
        )
        ct1 = ah.trace_calls(b, adv, read=False)
        cyc1 = ah.model_cycles(ct1, ah.CycleModel())
        print(
            f"update alone: median {int(np.median(cyc1))}, max {int(cyc1.max())}; read alone "
            f"(the difference): max {int((cyc - cyc1).max())}"
        )
        tr = ah.trace(b, adv)
        by: dict[str, float] = {}
        for pc, (_, c, _, _) in tr.per_pc.items():
            for name, (addr, size) in b.functions.items():
                if addr <= pc < addr + size:
                    by[name] = by.get(name, 0.0) + c
        split = ", ".join(f"{k} {v / len(tr.cycles):.0f}" for k, v in
                          sorted(by.items(), key=lambda kv: -kv[1]))  # fmt: skip
        print(f"mean per sample by function over the adversarial set: {split}")
        sz = ah.sizes(b.obj)
        print(
            f"object: text {sz['text']} bytes (tables {res.table_bytes} bytes: "
            f"{res.table_points} intervals x 3 channels x 4 cubic coefficients, floats; the "
            f"thresholds, the search offsets and the constant arrays), data {sz['data']}, "
            f"bss {sz['bss']}; "
            f"nm -u: {ah.undefined_symbols(b.obj)}"
        )
        print(f"(run at load average {os.getloadavg()[0]:.1f} on 2 shared cores; the cycles are "
              "counted from the instruction trace under the M4 timing model, not timed, so the "
              "load does not change them)")  # fmt: skip


if __name__ == "__main__":
    main()
