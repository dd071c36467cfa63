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

These lean figures come from the artifacts without their ``"identifiability"`` entry (the
homing API). Then the power-up identification in the float variant (the artifacts as they
are):

* flash of the decoder's tables and code, and the M4 cycles per sample before the lock (every
  sample evaluates all n_m hypotheses: traced over the first 6 samples of power-ups) and after
  it (the validation run and the fast spin, against the build without the decoder on the same
  samples);
* agreement with ``PowerUpIdentifier`` (host gcc -O2): on the demo's bench motor 200 power-ups
  at standstill and 200 moving (0.5 to 5 rad/s either way), simulated as
  ``benchmarks/bench_powerup.py`` does; the same lock sample and pole pair every time, the
  largest Lambda difference, the angle after the lock against the stated bound; 24 of them on
  the M4F under QEMU (the same bits as the host); on ring-jig 1, 50 random starts in the
  held-out revolutions (200 samples each, as bench_powerup: the gated lock comes after 96);
  and, as a stress, 1000 power-ups at standstill on a weak bench (7 pole pairs, magnet
  variation 0.01, the true flux as the model), where locks take up to thousands of samples.
"""

from __future__ import annotations

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
import firmware_support as fs  # noqa: E402
from bench_support import DEMO_ADC_SCALE, arm_args, demo_case, finish_report, ringjig_case  # noqa: E402

from hallcal._constants import TWO_PI  # noqa: E402
from hallcal.output.codegen import CORDIC_STEPS, export_c  # noqa: E402
from hallcal.sensor.flux import FluxModel, FourierBasis  # noqa: E402


def _fast_spin(art: dict) -> np.ndarray:
    flux = FluxModel(
        FourierBasis(tuple(art["model"]["harmonics"])), np.array(art["model"]["theta"])
    )
    n = art["pole_pairs"]
    k = np.arange(3000)
    y0 = 0.3 + np.cumsum(0.055 * TWO_PI / n * np.where(k < 1500, 1.0, -1.0))
    return flux(y0)


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


def _decisions(exe: Path, dec, x: np.ndarray) -> dict:
    """C (host driver, ``lam`` mode) against PowerUpIdentifier on power-ups x (K x N x 3)."""
    import subprocess

    K, N, _ = x.shape
    n = dec.pole_pairs
    out = subprocess.run([str(exe), "lam", str(N)], input=x.reshape(-1, 3).tobytes(),
                         capture_output=True, check=True).stdout  # fmt: skip
    rec = np.frombuffer(out, dtype=np.uint8).reshape(K, N, 12 + 4 * n)
    words = rec[:, :, :12].copy().view(np.uint32)
    lam_c = rec[:, :, 12:].copy().view(np.float32).astype(np.float64)
    same = locked = 0
    lock_at: list[int] = []
    worst_lam = 0.0
    for k in range(K):
        lock, j, _ = fs.identify_python(dec, x[k].astype(np.float64))
        ident = words[k, :, 2] >> 31
        lock_c = int(np.argmax(ident)) if ident.any() else None
        stop = N if lock is None else lock + 1
        same += int(lock_c == lock and ((words[k, stop - 1, 2] >> 16) & 0x7FFF) == j)
        if lock is not None:
            locked += 1
            lock_at.append(lock + 1)
        acc = np.zeros(n)
        for i, e in enumerate(dec.sample_costs(x[k].astype(np.float64))[:stop]):
            acc = acc + e
            acc = acc - acc.min()
            small = acc < 50.0
            if small.any():
                worst_lam = max(worst_lam, float(np.max(np.abs(lam_c[k, i] - acc)[small])))
    return {"starts": K, "same": same, "locked": locked, "lock_at": lock_at,
            "lam": worst_lam, "words": words}  # fmt: skip


def _powerup(wd: Path, title: str, art: dict, d: np.ndarray, scale: float, lean_gen: Path):
    """The power-up section of one case: size, cycles before and after the lock, agreement."""
    from hallcal.sensor.absolute import absolute_reconstruction
    from hallcal.sim.bench import BenchConfig

    gen = wd / f"pu_{lean_gen.name}"
    res = export_c(art, gen, source="calibration.json", adc_scale=scale, fixed_point=False)
    out = [f"  power-up identification ({title.split(' (')[0]}):"]
    if not res.identifies_pole_pair:
        return out + [f"    no decoder: {res.powerup_message}"]
    dec, lut = fs.python_decoder(art)
    out.append(
        f"    verdict: {art['identifiability']['status']}; tables R, Z: {dec.pole_pairs} x "
        f"{dec.grid} + 1 floats each = {res.powerup_table_bytes} bytes"
    )
    b = ah.build(gen, wd / f"{gen.name}_m4f", target="m4f", fixed=False)
    lean_b = ah.build(lean_gen, wd / f"{gen.name}_lean", target="m4f", fixed=False)
    size = ah.sizes(b.obj)
    funcs = ah.function_sizes(b)
    code = {k: v for k, v in funcs.items() if not k.startswith("hc_pu_") and
            k not in ("hc_t", "hc_c", "hc_base")}  # fmt: skip
    out += [
        f"    float on Cortex-M4F: text {size['text']} bytes (data {size['data']}, bss "
        f"{size['bss']}); nm -u: {' '.join(ah.undefined_symbols(b.obj)) or 'nothing'}",
        "    code bytes: " + ", ".join(f"{k} {v}" for k, v in sorted(code.items())),
    ]
    # starts: the demo's bench motor, or offsets into the held-out revolutions of a recording
    if scale != 1.0:
        pu = fs.PowerUps(BenchConfig(seed=1))
        rng = np.random.default_rng(77)
        angle = rng.uniform(0.0, TWO_PI, 400)
        speed = np.concatenate([np.zeros(200), rng.uniform(0.5, 5.0, 200)
                                * rng.choice([-1.0, 1.0], 200)])  # fmt: skip
        kinds = {"standstill": slice(0, 200), "moving 0.5-5 rad/s": slice(200, 400)}
        N = 400
        x = np.stack([pu.run(a, N, float(v), seed=60_000 + i)
                      for i, (a, v) in enumerate(zip(angle, speed, strict=True))])  # fmt: skip
    else:
        from hallcal.fit.constant_speed import find_constant_speed

        _, mid, stop = find_constant_speed(d, dec.pole_pairs).split(2.0)
        N = 200  # > K0 = 96: the goodness-of-fit gate decides within the window
        starts = np.random.default_rng(1001).integers(mid, stop - N, 50)
        x = np.stack([d[s : s + N] for s in starts])
        kinds = {"50 starts in the held-out revolutions": slice(0, 50)}
    x = x.astype(np.float32)
    host = fs.compile_driver(gen, fixed=False, flags=["-O2"], name="host_pu")
    for name, sl in kinds.items():
        r = _decisions(host, dec, x[sl])
        y_c = fs.angles(r["words"].reshape(-1, 3), fixed=False).reshape(r["starts"], -1)
        worst = 0.0
        for k, xk in enumerate(x[sl]):
            ident = r["words"][k, :, 2] >> 31
            if ident.any():
                at = int(np.argmax(ident))
                y_py = absolute_reconstruction(dec, lut, xk.astype(np.float64)).y_star
                worst = max(worst, float(np.max(np.abs(y_c[k, at:] - y_py[at:]))))
        la = np.array(r["lock_at"] or [0])
        out.append(
            f"    {name}: {r['same']}/{r['starts']} same lock sample and pole pair as "
            f"PowerUpIdentifier; locked {r['locked']} (samples median {np.median(la):.0f}, max "
            f"{la.max()}); max |Lambda_C - Lambda_py| {r['lam']:.1e}; after the lock max "
            f"|y_C - y_py| {worst:.2e} rad (bound {res.float_bound:.2e})"
        )
    # QEMU: a sample of starts on the M4F, bit for bit as the host
    sample = x[:12] if len(x) < 400 else np.concatenate([x[:12], x[200:212]])
    raw = ah.run(b, sample.reshape(-1, 3), block=N)
    same_bits = np.array_equal(raw, fs.run(host, sample.reshape(-1, 3), fixed=False, block=N))
    agree = 0
    for k, xk in enumerate(sample):
        lock, j, _ = fs.identify_python(dec, xk.astype(np.float64))
        ident = raw.reshape(len(sample), N, 3)[k, :, 2] >> 31
        lock_c = int(np.argmax(ident)) if ident.any() else None
        agree += int(lock_c == lock)
    out.append(
        f"    on the M4F under QEMU: {agree}/{len(sample)} same lock sample as Python, "
        f"{'the same bits as' if same_bits else 'DIFFERENT bits from'} the host build"
    )
    # cycles: before the lock (the first 6 samples of power-ups), after it
    first = x[:40, :6].reshape(-1, 3)
    raw6 = ah.run(b, first, block=6)
    tr = ah.trace(b, first, block=6)
    pre = np.ones(len(first), dtype=bool)
    pre.reshape(-1, 6)[:, 1:] = (raw6[:, 2] >> 31).reshape(-1, 6)[:, :-1] == 0
    spin = _fast_spin(art)
    post_x = np.concatenate([d[:2000], spin]).astype(np.float32)
    after = np.concatenate([[False], (ah.run(b, post_x)[:-1, 2] >> 31) == 1])
    tr_post = ah.trace(b, post_x)
    tr_lean = ah.trace(lean_b, post_x)
    cb, ca, cl = tr.cycles[pre], tr_post.cycles[after], tr_lean.cycles[after]
    out += [
        f"    Cortex-M4 cycles per sample before the lock ({int(pre.sum())} traced): min "
        f"{cb.min()}, median {int(np.median(cb))}, max {cb.max()} -> {cb.max() / 168:.1f} us "
        f"at 168 MHz ({(cb.max() - np.median(ca)) / dec.pole_pairs:.0f} per hypothesis)",
        f"    Cortex-M4 cycles per sample after the lock ({int(after.sum())} traced): min "
        f"{ca.min()}, median {int(np.median(ca))}, max {ca.max()}; the build without the "
        f"decoder on the same samples: min {cl.min()}, median {int(np.median(cl))}, max "
        f"{cl.max()} (difference per sample {int((ca - cl).min())} .. {int((ca - cl).max())})",
    ]
    return out


def _weak_bench(wd: Path) -> list[str]:
    """Stress of the decisions: a weak bench where the evidence accumulates slowly."""
    from hallcal.sim.bench import BenchConfig

    cfg = BenchConfig(pole_pairs=7, magnet_variation=0.01, seed=0)
    art = fs.bench_artifact(cfg)
    gen = wd / "weak"
    res = export_c(art, gen, adc_scale=2.0**14, fixed_point=False)
    dec, _ = fs.python_decoder(art)
    host = fs.compile_driver(gen, fixed=False, flags=["-O2"], name="host_weak")
    pu = fs.PowerUps(cfg)
    rng = np.random.default_rng(5)
    angles = rng.uniform(0.0, TWO_PI, 1000)
    x = np.stack([pu.run(a, 3000, 0.0, seed=900 + i) for i, a in enumerate(angles)])
    x = x.astype(np.float32)
    r = _decisions(host, dec, x)
    la = np.array(r["lock_at"])
    title = "weak bench (7 pole pairs, magnet variation 0.01, the true flux as the model)"
    return [
        title,
        "-" * len(title),
        f"  {art['identifiability']['message']}",
        f"  tables {res.powerup_table_bytes} bytes; 1000 power-ups at standstill, 3000 samples: "
        f"{r['same']}/1000 same lock sample and pole pair as PowerUpIdentifier (host gcc -O2); "
        f"locked {r['locked']} (samples median {np.median(la):.0f}, 99th percentile "
        f"{np.percentile(la, 99):.0f}, max {la.max()}); max |Lambda_C - Lambda_py| "
        f"{r['lam']:.1e}",
    ]


def main(argv: list[str] | None = None) -> int:
    args = arm_args(argv, __doc__)
    if args is None:
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
                  *demo_case(wd / "demo"), DEMO_ADC_SCALE)]  # fmt: skip
        rj = ringjig_case(wd)
        if rj is not None:
            cases.append(("ring-jig 1 (n_m = 25, raw 16-bit counts)", *rj, 1.0))
        for title, art, d, scale in cases:
            gen = wd / f"gen{len(lines)}"
            lean = {k: v for k, v in art.items() if k != "identifiability"}
            res = export_c(lean, gen, source="calibration.json", adc_scale=scale)
            lut = art.lut()
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
            lines += _powerup(wd, title, art, d, scale, gen)
            lines.append("")
        lines += _weak_bench(wd)
        lines.append("")
    return finish_report(lines, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
