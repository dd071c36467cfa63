"""The observer's C export (``hallcal export-c --observer``) on a Cortex-M4F under QEMU.

Paper bench (11 pole pairs), calibrated as in bench_observer.py; the C of
:mod:`hallcal.output.codegen.observer` cross-compiled for the Cortex-M4F (``tests/arm_harness.py``:
strict flags, ``-O2``, bare metal on ``mps2-an386``) and run on 3000 samples of a validation run
with a channel stuck at its zero-field level from sample 1500 and 10 glitch samples (3.0 on
channel 1) from sample 2500: the largest difference from Python's y_obs on the same float32
inputs, and the Cortex-M4 cycles per ``update`` (QEMU single-step trace, the harness's M4 timing
table) on normal samples, outlier samples and the acquisition samples (start, exclusion), with
the time split per function on 1200 normal samples. Code and table sizes.

Run: ``python benchmarks/bench_observer_c.py`` (needs gcc-arm-none-eabi and qemu-system-arm);
output committed beside it (bench_observer_c.txt).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import arm_harness as ah  # noqa: E402
from bench_observer import ramp, setup_for  # noqa: E402

import hallcal  # noqa: E402
from hallcal.output.codegen.observer import export_observer_c  # noqa: E402
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
              "1500, glitches at 2500)")  # fmt: skip
        tr = ah.trace(b, d[:2600])
        cyc = tr.cycles
        acq = [0, int(py.first_exclusion)]
        normal = np.delete(cyc, acq + list(range(1500, 1510)))
        print(
            f"cycles per update: median {np.median(normal):.0f}, max on normal samples "
            f"{np.max(normal[:1400]):.0f}; outlier samples (fits without each channel) up to "
            f"{np.max(np.delete(cyc, acq)):.0f}; acquisition (64-point search: start, "
            f"exclusion at sample {acq[1]}) {cyc[acq[0]]:.0f} and {cyc[acq[1]]:.0f}"
        )
        tr2 = ah.trace(b, d[200:1400])
        by: dict[str, float] = {}
        for pc, (_, c, _, _) in tr2.per_pc.items():
            for name, (addr, size) in b.functions.items():
                if addr <= pc < addr + size:
                    by[name] = by.get(name, 0.0) + c
        split = ", ".join(f"{k} {v / len(tr2.cycles):.0f}" for k, v in
                          sorted(by.items(), key=lambda kv: -kv[1]))  # fmt: skip
        print(f"per normal sample by function (update includes the inlined adaptation): {split}")
        sz = ah.sizes(b.obj)
        print(
            f"object: text {sz['text']} bytes (tables {res.table_bytes} bytes: "
            f"{res.table_points} points x 3 x (g, dg/dy) floats and the thresholds), "
            f"data {sz['data']}, bss {sz['bss']}; nm -u: {ah.undefined_symbols(b.obj)}"
        )


if __name__ == "__main__":
    main()
