"""Worst-case cycles per sample of the generated firmware on adversarial inputs, stated models.

Run ``python benchmarks/bench_cycles.py [--out benchmarks/bench_cycles.txt]`` (needs Debian's
``gcc-arm-none-eabi``, ``libnewlib-arm-none-eabi`` and ``qemu-system-arm``). It calibrates the
demo (the paper's simulation study) and ring-jig recording 1, exports both (the lean code: the
artifacts without their identifiability analysis; the demo also with the power-up decoder),
cross-compiles (GCC, ``-O2 -std=c99``) the float variant for the Cortex-M4F and the fixed-point
variant for the Cortex-M0+, and traces every instruction executed per sample under QEMU
(``-singlestep -d exec``, ``tests/arm_harness.py``: ``update`` with the helpers and the decoder
it calls, and ``read`` after it, as a control loop calls them).

Inputs:

* typical: 2000 samples of the recording (the demo's validation run, the ring jig's capture) and
  a fast spin through every octant and turn boundary both ways;
* adversarial: the typical ones, plus 100 trials of each class of ``tests/slip_trials.py``
  (overspeed to twice the speed limit, a bad first sample, bursts of 2-5 bad samples, a stuck
  channel, a clipped channel: step rejections, holds, faults, re-acquisitions, revolution
  wraps), NaN and infinite inputs (float), rails and random counts; the state re-initialised
  every 64 samples (the acquisition after ``init``);
* the power-up decoder (demo): the first 6 samples after each of 40 power-ups on the demo's
  bench motor, i.e. the samples before the lock.

Models (cycles from the executed instruction stream):

* Cortex-M4 (TRM r0p1 tables 3-1 and 7-1): taken branch 1 + P with P = 1, 2, 3 (the TRM's
  range for the pipeline refill); loads 2 (1 when pipelined after a load), STR with an
  immediate offset 1, FPU arithmetic 1, VLDR 2; zero wait states; and P = 3 with one flash wait
  state charged, conservatively, to every taken branch and every load (a flash without an
  accelerator's cache hit; the state in RAM would pay nothing);
* Cortex-M0+ (TRM r0p1 table 3-1): loads and stores 2, taken branches 2 (BL 3), MULS 1 or 32
  (the implementer's choice: the fast or the small multiplier), zero wait states.
"""

from __future__ import annotations

import math
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import arm_harness as ah  # noqa: E402
import firmware_support as fs  # noqa: E402
import slip_trials as st  # noqa: E402
from bench_support import DEMO_ADC_SCALE, arm_args, demo_case, finish_report, ringjig_case  # noqa: E402

from hallcal._constants import TWO_PI  # noqa: E402
from hallcal.output.codegen import export_c  # noqa: E402
from hallcal.sensor.flux import FluxModel, FourierBasis  # noqa: E402

M4_MODELS = [ah.CycleModel("m4", p, 0) for p in (1, 2, 3)] + [ah.CycleModel("m4", 3, 1)]
M0_MODELS = [ah.CycleModel("m0plus", muls=1), ah.CycleModel("m0plus", muls=32)]


def _flux(art: dict) -> FluxModel:
    return FluxModel(
        FourierBasis(tuple(art["model"]["harmonics"])), np.array(art["model"]["theta"])
    )


def _spin(art: dict) -> np.ndarray:
    n = art["pole_pairs"]
    k = np.arange(3000)
    y0 = 0.3 + np.cumsum(0.055 * TWO_PI / n * np.where(k < 1500, 1.0, -1.0))
    return _flux(art)(y0)


def _adversarial(art: dict, res, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Blocks of 64 samples (re-initialised): the trial classes, then hostile values."""
    blocks = []
    for i, kind in enumerate(st.CLASSES):
        tr = st.make_trials(kind, _flux(art), n=art["pole_pairs"], w=res.glitch_safe_speed,
                            noise=noise, trials=100, length=64, seed=100 + i)  # fmt: skip
        blocks.append(tr.d.reshape(-1, 3))
    lo, hi = res.design.plausibility.channel_lo, res.design.plausibility.channel_hi
    hostile = rng.uniform(lo - (hi - lo), hi + (hi - lo), (64 * 20, 3))
    blocks.append(hostile)
    return np.concatenate(blocks)


def _row(name: str, cycles: np.ndarray) -> str:
    return f"{name:<44s} {cycles.min():5d} {int(np.median(cycles)):6d} {cycles.max():5d}"


def _table(title: str, traces: dict, models: list, extra: dict | None = None) -> list[str]:
    """Cycles per sample: min / median / max of each input set, with and without read."""
    out = [f"  {title}", f"  {'model, inputs, calls':<44s} {'min':>5s} {'median':>6s} {'max':>5s}"]
    for model in models:
        out.append(f"  {model.label()}")
        for (inputs, read), ct in traces.items():
            cyc = ah.model_cycles(ct, model)
            out.append("    " + _row(f"{inputs}, update{' + read' if read else ''} "
                                      f"({len(cyc)})", cyc))  # fmt: skip
        for name, ct in (extra or {}).items():
            cyc = ah.model_cycles(ct, model)
            out.append("    " + _row(f"{name} ({len(cyc)})", cyc))
    return out


def _case(wd: Path, title: str, art: dict, d: np.ndarray, scale: float, noise: float,
          powerup: bool) -> list[str]:  # fmt: skip
    lean = {k: v for k, v in art.items() if k != "identifiability"}
    gen = wd / f"gen_{len(title)}"
    res = export_c(lean, gen, source="calibration.json", adc_scale=scale)
    rng = np.random.default_rng(11)
    typical = np.concatenate([d[:2000], _spin(art)])
    adv = np.concatenate([typical, _adversarial(art, res, noise, rng)])
    pl = res.design.plausibility
    lines = [title, "-" * len(title),
             f"step rule: speed limit {res.glitch_safe_speed:.4g} rad per sample, window "
             f"{pl.step_limit:.4g} electrical turn, fault after {res.fault_after}"]  # fmt: skip
    for variant, target, models in (("float", "m4f", M4_MODELS), ("fixed", "m0plus", M0_MODELS)):
        fixed = variant == "fixed"
        b = ah.build(gen, wd / f"{gen.name}_{target}", target=target, fixed=fixed)

        def conv(v, fixed=fixed):
            if not fixed:
                return v.astype(np.float32)
            return np.clip(np.round(np.nan_to_num(v * scale, nan=0.0)), -(2**31), 2**31 - 1)

        xa = conv(adv)
        if not fixed:  # NaN and infinities in the hostile block
            xa[-64 * 20 :: 7, 1] = np.nan
            xa[-64 * 20 + 3 :: 11, 2] = np.inf
        traces = {}
        start = len(typical)
        for read in (False, True):
            ct_t = ah.trace_calls(b, conv(typical), read=read)
            ct_a = ah.trace_calls(b, np.concatenate([conv(typical), xa[start:]]), read=read,
                                  block=64)  # fmt: skip
            traces[("typical", read)] = ct_t
            traces[("adversarial", read)] = ct_a
        lines += _table(f"{variant} on {b.target.name} ({sum(ah.function_sizes(b).values())} "
                        "bytes of code)", traces, models)  # fmt: skip
    if powerup:
        gen_pu = wd / f"pu_{len(title)}"
        export_c(art, gen_pu, source="calibration.json", adc_scale=scale, fixed_point=False)
        b = ah.build(gen_pu, wd / "pu_m4f", target="m4f", fixed=False)
        from hallcal.sim.bench import BenchConfig

        pu = fs.PowerUps(BenchConfig(seed=1))
        angles = np.random.default_rng(404).uniform(0.0, TWO_PI, 40)
        x = np.concatenate([pu.run(a, 6, 0.0, seed=9000 + i) for i, a in enumerate(angles)])
        x6 = x.astype(np.float32)
        raw6 = ah.run(b, x6, block=6)
        ct_pre = ah.trace_calls(b, x6, read=True, block=6)
        pre = np.ones(len(x6), dtype=bool)  # the samples while not identified
        pre.reshape(-1, 6)[:, 1:] = (raw6[:, 2] >> 31).reshape(-1, 6)[:, :-1] == 0
        ct_pre = ah.CallTrace([c for c, p in zip(ct_pre.calls, pre, strict=True) if p],
                              ct_pre.dis)  # fmt: skip
        px = np.concatenate([d[:2000], _spin(art)]).astype(np.float32)
        after = np.concatenate([[False], (ah.run(b, px)[:-1, 2] >> 31) == 1])
        post = ah.trace_calls(b, px, read=True)
        post = ah.CallTrace([c for c, a in zip(post.calls, after, strict=True) if a], post.dis)
        lines += _table("float with the power-up decoder on Cortex-M4F",
                        {}, M4_MODELS, {"before the lock (power-ups), update + read": ct_pre,
                                        "typical after the lock, update + read": post})  # fmt: skip
    return lines + [""]


def main(argv: list[str] | None = None) -> int:
    args = arm_args(argv, __doc__)
    if args is None:
        return 2
    gcc = subprocess.run(["arm-none-eabi-gcc", "--version"], capture_output=True, text=True)
    qemu = subprocess.run(["qemu-system-arm", "--version"], capture_output=True, text=True)
    lines = [
        "hallcal.output.codegen worst-case cycles (benchmarks/bench_cycles.py)",
        "=" * 70,
        f"host    : {platform.machine()}, {os.cpu_count()} cores, shared with other jobs",
        f"compiler: {gcc.stdout.splitlines()[0]}, -O2 -std=c99",
        f"QEMU    : {qemu.stdout.splitlines()[0]}",
        "cycles per sample from the traced instructions (see the docstring for the models);",
        "'update + read': what a control loop pays per sample",
        "",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        wd = Path(tmp)
        art, d = demo_case(wd / "demo")
        lines += _case(wd, "demo (n_m = 11, normalized signals; fixed point at 2^14 counts per "
                       "unit)", art, d, DEMO_ADC_SCALE, math.sqrt(7.5e-6), True)  # fmt: skip
        rj = ringjig_case(wd)
        if rj is not None:
            art, d = rj
            floor = art["diagnostics"]["noise_floor"]
            sigma = floor * 25 * 1000.0 / math.sqrt(2.0 / 3.0)  # counts: amplitude about 1000
            lines += _case(wd, "ring-jig 1 (n_m = 25, raw 16-bit counts)", art, d, 1.0, sigma,
                           False)  # fmt: skip
    return finish_report(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
