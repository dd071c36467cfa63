"""The generated firmware on ARM: Cortex-M4F and Cortex-M0+ code under QEMU, against Python.

Skipped only when the toolchain is absent (Debian: ``gcc-arm-none-eabi``,
``libnewlib-arm-none-eabi``, ``qemu-system-arm``; ``.ci/run`` installs them). The float variant
runs on ``mps2-an386`` (Cortex-M4 with FPU), the fixed-point variant on ``microbit`` (the M0
core; the code is compiled for the M0+, whose instruction set is the same), both bare metal
with semihosting (``tests/arm_harness.py``). Checked:

* the objects of the generated code need nothing from any library (``arm-none-eabi-nm -u``
  is empty: no libm, no libgcc helper, no double), and the demo's table fits in 4 kB;
* on the demo's validation run (96 000 samples) and on the three ring-jig recordings, both
  variants are within their stated bounds and 1e-5 rad of ``hallcal reconstruct``, give the
  same validation figures as Python, and the same bits as the host build;
* the float variant's worst traced path is at most 200 Cortex-M4 cycles (estimated from the
  QEMU instruction trace with the M4 timing table) and the fixed-point one at most 400
  Cortex-M0+ instructions, on the validation run and on a fast spin through every octant;
* 10 000 single glitches at random angles and speeds make no slip on either core;
* the power-up decoder (the demo's artifact with its identifiability analysis) on the M4F: on
  power-ups simulated on the demo's bench motor, the same lock sample and pole pair as
  ``PowerUpIdentifier``, the same bits as the host build, the angle after the lock within the
  stated bound; its cycles before the lock bounded, and after the lock those of the lean path
  plus the dispatch.

The lean tests export the artifacts without their ``"identifiability"`` entry (the homing API
they were written for; the lean code is the same either way).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import arm_harness as ah
import firmware_support as fs
import numpy as np
import pytest

from hallcal._constants import TWO_PI
from hallcal.io import read_artifact, read_dataset
from hallcal.output.codegen import export_c
from hallcal.sensor.metrics import angle_error

MISSING = ah.toolchain()
pytestmark = pytest.mark.skipif(
    MISSING is not None, reason=f"ARM toolchain incomplete ({MISSING} not found)"
)
DEMO_ADC_SCALE = 2.0**14  # the demo's signals are normalized: 16384 counts per unit


def _ringjig_dir() -> Path:
    env = os.environ.get("HALLCAL_REAL_DATA")
    if env:
        return Path(env)
    return Path(__file__).parent / "data" / "ring-jig"  # shipped with the tests


RINGJIG = [_ringjig_dir() / f"hall_calibration_one_rotation_{i}.txt" for i in (1, 2, 3)]


@pytest.fixture(scope="module")
def demo(demo_run, tmp_path_factory):
    """The demo's calibration and validation run (conftest: one run_demo per session),
    exported (float and fixed point) into this module's own folder."""
    out, _ = demo_run
    art = read_artifact(out / "calibration.json")
    work = tmp_path_factory.mktemp("demo_arm")
    gen = work / "fw"
    res = export_c(_lean(art), gen, source="calibration.json", adc_scale=DEMO_ADC_SCALE)
    val = read_dataset(out / "validation.npz")
    return {"art": art, "gen": gen, "res": res, "d": val.d, "y_ref": val["y_ref"], "dir": work}


def _lean(art: dict) -> dict:
    """The artifact without its identifiability analysis: the export keeps the homing API."""
    return {k: v for k, v in art.items() if k != "identifiability"}


def _builds(gen: Path, workdir: Path, n: int) -> dict[str, ah.Build]:
    return {
        "float": ah.build(gen, workdir / "m4f", target="m4f", fixed=False),
        "fixed": ah.build(gen, workdir / "m0plus", target="m0plus", fixed=True),
    }


@pytest.fixture(scope="module")
def demo_builds(demo):
    return _builds(demo["gen"], demo["dir"] / "arm", demo["art"]["pole_pairs"])


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def test_objects_need_no_library(demo, demo_builds):
    res = demo["res"]
    assert res.table_bytes <= 4096
    for variant, b in demo_builds.items():
        assert ah.undefined_symbols(b.obj) == [], variant
        size = ah.sizes(b.obj)
        print(f"{variant} on {b.target.name}: {size} (table {res.table_bytes} bytes)")
        assert size["data"] == 0 and size["bss"] == 0  # tables in flash, no static state
    # the fixed variant built for the M4 (no FPU use) needs nothing either
    b = ah.build(demo["gen"], demo["dir"] / "arm" / "m4q", target="m4f", fixed=True)
    assert ah.undefined_symbols(b.obj) == []


@pytest.mark.parametrize("variant", ["float", "fixed"])
def test_demo_on_arm_matches_python(demo, demo_builds, variant, tmp_path):
    fixed = variant == "fixed"
    b = demo_builds[variant]
    res = demo["res"]
    d = demo["d"]
    x = np.round(d * DEMO_ADC_SCALE) if fixed else d.astype(np.float32)
    raw = ah.run(b, x)
    assert not np.any(raw[:, 2])  # nothing rejected on the validation run
    y = ah.angles(b, raw)
    lut = demo["art"].lut()
    y_py = lut.f_star(x / DEMO_ADC_SCALE if fixed else x.astype(np.float64))
    err = float(np.max(np.abs(y - y_py)))
    bound = res.fixed_bound if fixed else res.float_bound
    # the validation figure (hallcal.pipeline's: RMS about the mean error against the encoder),
    # C and Python (Python on the unrounded signals, as hallcal reconstruct computes it)
    rms_c = angle_error(y, demo["y_ref"]).rms
    rms_py = angle_error(lut.f_star(d), demo["y_ref"]).rms
    print(f"demo {variant} on {b.target.name}: max |C - python| {err:.2e} rad (bound "
          f"{bound:.2e}); validation RMS {1e3 * rms_c:.4f} mrad vs {1e3 * rms_py:.4f}")  # fmt: skip
    assert err <= bound <= 1e-5
    assert abs(rms_c - rms_py) <= 1e-3 * rms_py  # the same figure to 3 digits
    # the same bits as the host build (IEEE single precision without contraction; integers)
    host = fs.compile_driver(res.paths[0].parent, fixed=fixed, flags=["-O2"],
                             name=f"host_{variant}", pole_pairs=res.pole_pairs)  # fmt: skip
    np.testing.assert_array_equal(fs.run(host, x, fixed=fixed), raw)


def _line_residual(y: np.ndarray, k: np.ndarray) -> np.ndarray:
    A = np.column_stack([np.ones_like(k, dtype=float), k.astype(float)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return y - A @ coef


def _ringjig(i: int, folder: Path) -> dict:
    """Ring-jig recording i (raw 16-bit counts, 25 pole pairs) calibrated as
    tests/test_real_ringjig.py and ``benchmarks/bench_codegen.py`` do (constant speed over the
    first half of its constant-speed segment), its artifact exported into ``folder / "fw"``
    and both variants built for the ARM targets."""
    import hallcal
    from hallcal.fit.constant_speed import find_constant_speed

    raw = np.loadtxt(RINGJIG[i - 1], dtype=np.int64)
    d = raw.astype(np.float64)
    start, mid, stop = find_constant_speed(d, 25).split(2.0)
    setup = {"pole_pairs": 25, "sample_time": 1.0,
             "trajectory": {"kind": "constant-speed", "start": start, "stop": mid}}  # fmt: skip
    cal = hallcal.calibrate({f"d{h + 1}": d[:, h] for h in range(3)}, setup)
    cal.save(folder / "cal.json")
    art = read_artifact(folder / "cal.json")
    res = export_c(_lean(art), folder / "fw", source="cal.json")
    builds = _builds(folder / "fw", folder / "arm", 25)
    return {"raw": raw, "d": d, "mid": mid, "stop": stop, "art": art, "res": res, "builds": builds}


@pytest.fixture(scope="module")
def ringjig_1(tmp_path_factory) -> dict:
    """Ring jig 1 calibrated, exported and built once (:func:`_ringjig`) for its test on ARM and
    its cycle trace (``ringjig_trace``)."""
    if not RINGJIG[0].exists():
        pytest.skip("ring-jig data not available")
    return _ringjig(1, tmp_path_factory.mktemp("ringjig_1"))


@pytest.mark.skipif(not all(f.exists() for f in RINGJIG), reason="ring-jig data not available")
@pytest.mark.parametrize("i", [1, 2, 3])
def test_ringjig_on_arm_matches_python(request, tmp_path, i):
    """The real recordings (raw 16-bit counts), calibrated as tests/test_real_ringjig.py does;
    the whole file reconstructed from y = 0; held-out residual in electrical degrees."""
    jig = request.getfixturevalue("ringjig_1") if i == 1 else _ringjig(i, tmp_path)
    raw, d, mid, stop, res = jig["raw"], jig["d"], jig["mid"], jig["stop"], jig["res"]
    lut = jig["art"].lut()
    y_py = lut.f_star(d)
    k = np.arange(mid, stop)
    deg_py = math.degrees(_rms(_line_residual(y_py[mid:stop], k))) * 25
    for variant, b in jig["builds"].items():
        fixed = variant == "fixed"
        out = ah.run(b, raw.astype(np.int32) if fixed else raw.astype(np.float32))
        assert not np.any(out[:, 2])
        y = ah.angles(b, out)
        err = float(np.max(np.abs(y - y_py)))
        bound = res.fixed_bound if fixed else res.float_bound
        deg = math.degrees(_rms(_line_residual(y[mid:stop], k))) * 25
        print(f"ring-jig {i} {variant}: max |C - python| {err:.2e} rad (bound {bound:.2e}); "
              f"held-out {deg:.3f} vs {deg_py:.3f} electrical degrees RMS")  # fmt: skip
        assert err <= bound <= 1e-5
        assert abs(deg - deg_py) < 0.005


def _fast_spin(art: dict, adc_scale: float, fixed: bool) -> np.ndarray:
    """A spin at 0.055 electrical turn per sample forward then back: every octant, the
    45-degree rotation and the turn boundaries both ways."""
    c = art
    from hallcal.sensor.flux import FluxModel, FourierBasis

    flux = FluxModel(FourierBasis(tuple(c["model"]["harmonics"])), np.array(c["model"]["theta"]))
    n = c["pole_pairs"]
    k = np.arange(3000)
    y0 = 0.3 + np.cumsum(0.055 * TWO_PI / n * np.where(k < 1500, 1.0, -1.0))
    d = flux(y0)
    return np.round(d * adc_scale) if fixed else d.astype(np.float32)


def test_cycles_and_instructions_per_sample(demo, demo_builds):
    """The worst traced path (validation run and fast spin; the taken branch at 1 + 2): the
    float variant within 235 Cortex-M4 cycles (measured 218; 188 before the checks of issue
    28: the consistency check along P's null vector about 10, the step rule's bookkeeping, the
    turn's validation and the rejected count in the snapshot about 20 more), the fixed variant
    within 400 Cortex-M0+ instructions (measured 357). The adversarial worst case, with read and
    the other branch penalties and wait states: benchmarks/bench_cycles.txt."""
    d = demo["d"][:2000]
    worst = {}
    for variant, b in demo_builds.items():
        fixed = variant == "fixed"
        x = np.concatenate([
            np.round(d * DEMO_ADC_SCALE) if fixed else d.astype(np.float32),
            _fast_spin(demo["art"], DEMO_ADC_SCALE, fixed),
        ])  # fmt: skip
        tr = ah.trace(b, x)
        assert len(tr.counts) == len(x)  # every call traced
        assert not tr.unknown, tr.unknown
        worst[variant] = (int(np.median(tr.counts)), int(tr.counts.max()),
                          int(np.median(tr.cycles)), int(tr.cycles.max()))  # fmt: skip
        print(f"{variant} on {b.target.name}: instructions median/max {worst[variant][:2]}, "
              f"M4 cycle estimate median/max {worst[variant][2:]}")  # fmt: skip
    assert worst["float"][3] <= 235
    assert worst["fixed"][1] <= 400


@pytest.fixture(scope="module")
def ringjig_trace(ringjig_1):
    """Ring-jig 1 (25 pole pairs, raw 16-bit counts, a quadratic table) calibrated as
    ``benchmarks/bench_codegen.py`` does (``ringjig_1``); the float variant's trace on the M4F
    and the fixed variant's on the M0+, over 2000 samples of the recording and the fast spin."""
    d, art, res = ringjig_1["d"], ringjig_1["art"], ringjig_1["res"]
    assert res.table_bytes <= 4096
    traces = {}
    for variant, b in ringjig_1["builds"].items():
        fixed = variant == "fixed"
        x = np.concatenate([d[:2000] if fixed else d[:2000].astype(np.float32),
                            _fast_spin(art, 1.0, fixed)])  # fmt: skip
        tr = ah.trace(b, x)
        assert len(tr.counts) == len(x) and not tr.unknown
        print(f"ring-jig 1 {variant} on {b.target.name}: instructions median/max "
              f"{int(np.median(tr.counts))}/{tr.counts.max()}, M4 cycle estimate median/max "
              f"{int(np.median(tr.cycles))}/{tr.cycles.max()}")  # fmt: skip
        traces[variant] = tr
    return traces


def test_ringjig_cycles_no_worse(ringjig_trace):
    """Ring jig 1: float at most 270 M4 cycles (measured 255; 218 before the checks of issue
    28, see the demo's test: here the consistency check needs the null vector's three products,
    the projection does not reject common mode), fixed at most 440 M0+ instructions (measured
    422, 391 before). The issue's budget of 220 is not met: the checks cost about 40 cycles."""
    assert ringjig_trace["float"].cycles.max() <= 270
    assert ringjig_trace["fixed"].counts.max() <= 440


@pytest.mark.parametrize("variant", ["float", "fixed"])
def test_glitches_on_arm(demo, demo_builds, variant):
    """10 000 single glitches at random angles and speeds up to the glitch-safe speed: the
    reading after the glitch is the clean run's, bit for bit, on the target itself."""
    fixed = variant == "fixed"
    b = demo_builds[variant]
    res = demo["res"]
    art = demo["art"]
    from hallcal.sensor.flux import FluxModel, FourierBasis

    flux = FluxModel(
        FourierBasis(tuple(art["model"]["harmonics"])), np.array(art["model"]["theta"])
    )
    rng = np.random.default_rng(7)
    trials, length = 10_000, 32
    w = rng.uniform(-0.98, 0.98, trials) * res.glitch_safe_speed
    y0 = rng.uniform(0, TWO_PI, trials)[:, None] + w[:, None] * np.arange(length)[None, :]
    noise = rng.normal(0.0, 2.7e-3, (trials, length, 3))
    d = flux(y0.ravel()).reshape(trials, length, 3) + noise
    dirty = d.copy()
    at = rng.integers(5, 16, trials)
    dirty[np.arange(trials), at] = flux(rng.uniform(0, TWO_PI, trials))
    scale = DEMO_ADC_SCALE if fixed else 1.0
    conv = (lambda v: np.round(v * scale)) if fixed else (lambda v: v.astype(np.float32))
    clean = ah.run(b, conv(d.reshape(-1, 3)), block=length).reshape(trials, length, 3)
    raw = ah.run(b, conv(dirty.reshape(-1, 3)), block=length).reshape(trials, length, 3)
    y_c = ah.angles(b, clean[:, -1])
    y_d = ah.angles(b, raw[:, -1])
    slips = int(np.sum(np.abs(y_d - y_c) > math.pi / art["pole_pairs"]))
    faults = int(np.sum(raw[:, -1, 2] & 2 != 0))
    print(f"{variant} on {b.target.name}: {trials} glitches, {slips} slips, {faults} faults")
    assert slips == 0
    np.testing.assert_array_equal(raw[:, -1, :2], clean[:, -1, :2])
    # a fault where the glitch was accepted at the window's edge near the speed limit (1.8 %
    # measured on the demo, 0.7 % on the host test's motor); never a slip
    assert faults <= trials // 40


# ------------------------------------------------------------------------------------------
# Power-up identification on the Cortex-M4F
# ------------------------------------------------------------------------------------------

PU_STARTS = 12  # per kind (standstill, moving): QEMU runs them in one program
PU_SAMPLES = 250


@pytest.fixture(scope="module")
def demo_pu(demo):
    """The demo's artifact with its identifiability analysis: the float variant with the
    decoder, built for the M4F, and power-ups on the demo's bench motor (seed 1)."""
    from hallcal.sim.bench import BenchConfig

    assert demo["art"]["identifiability"]["status"] != "not_identifiable"
    gen = demo["dir"] / "fw_pu"
    res = export_c(demo["art"], gen, source="calibration.json", adc_scale=DEMO_ADC_SCALE,
                   fixed_point=False)  # fmt: skip
    b = ah.build(gen, demo["dir"] / "arm_pu", target="m4f", fixed=False)
    pu = fs.PowerUps(BenchConfig(seed=1))
    rng = np.random.default_rng(404)
    angle = rng.uniform(0.0, TWO_PI, 2 * PU_STARTS)
    speed = np.concatenate([np.zeros(PU_STARTS), rng.uniform(-5.0, 5.0, PU_STARTS)])
    x = np.stack([pu.run(a, PU_SAMPLES, float(v), seed=7000 + i)
                  for i, (a, v) in enumerate(zip(angle, speed, strict=True))])  # fmt: skip
    return {"res": res, "gen": gen, "b": b, "x": x.astype(np.float32)}


def test_powerup_on_m4f_locks_like_python(demo, demo_pu):
    """12 power-ups at standstill and 12 moving (up to 5 rad/s either way) on the M4F: the
    same lock sample and pole pair as PowerUpIdentifier (Python on the same float32 samples),
    the same bits as the host build, and after the lock the angle within the stated bound of
    the Python absolute reconstruction."""
    from hallcal.sensor.absolute import absolute_reconstruction

    res, b, x = demo_pu["res"], demo_pu["b"], demo_pu["x"]
    assert res.identifies_pole_pair
    assert ah.undefined_symbols(b.obj) == []
    size = ah.sizes(b.obj)
    assert size["data"] == 0 and size["bss"] == 0
    raw = ah.run(b, x.reshape(-1, 3), block=PU_SAMPLES)
    host = fs.compile_driver(demo_pu["gen"], fixed=False, flags=["-O2"], name="host_pu")
    np.testing.assert_array_equal(fs.run(host, x.reshape(-1, 3), fixed=False,
                                         block=PU_SAMPLES), raw)  # fmt: skip
    dec, lut = fs.python_decoder(demo["art"])
    raw = raw.reshape(len(x), PU_SAMPLES, 3)
    y_c = ah.angles(b, raw.reshape(-1, 3)).reshape(len(x), PU_SAMPLES)
    worst = 0.0
    for k in range(len(x)):
        lock, j, _ = fs.identify_python(dec, x[k].astype(np.float64))
        ident = raw[k, :, 2] >> 31
        assert lock is not None and int(np.argmax(ident)) == lock and ident.any()
        assert np.all(((raw[k, lock:, 2] >> 16) & 0x7FFF) == j)
        y_py = absolute_reconstruction(dec, lut, x[k].astype(np.float64)).y_star
        worst = max(worst, float(np.max(np.abs(y_c[k, lock:] - y_py[lock:]))))
    print(f"M4F power-ups: {len(x)} locked as Python; max |y_C - y_py| after the lock "
          f"{worst:.2e} rad (bound {res.float_bound:.2e})")  # fmt: skip
    assert worst <= res.float_bound


def test_powerup_cycles_before_and_after_the_lock(demo, demo_builds, demo_pu):
    """Before the lock every sample evaluates all n_m hypotheses: bounded (a fixed loop), at
    most 2500 M4 cycles for 11 pole pairs (measured about 1770: about 140 per hypothesis and
    the rest once). After the lock the lean path: at most 240 cycles (the lean bound, 235),
    and its worst path at most 8 more than that of the build without the decoder (the dispatch
    is a load, a compare and a branch, 4 cycles; GCC's block layout adds or saves taken branches
    here and there: measured worst paths 226 against 218, single samples 0 .. +13)."""
    b = demo_pu["b"]
    x = demo_pu["x"][:, :6].reshape(-1, 3)  # the first 6 samples of each power-up: the lock
    raw = ah.run(b, x, block=6)
    tr = ah.trace(b, x, block=6)
    pre = np.ones(len(x), dtype=bool)
    ident = (raw[:, 2] >> 31).reshape(-1, 6)
    pre.reshape(-1, 6)[:, 1:] = ident[:, :-1] == 0  # after init, or the reading before unlocked
    # after the lock: the demo's validation run and the fast spin, once locked
    post_x = np.concatenate([demo["d"][:2000], _fast_spin(demo["art"], DEMO_ADC_SCALE, False)])
    post_x = post_x.astype(np.float32)
    tr_post = ah.trace(b, post_x)
    post_raw = ah.run(b, post_x)
    after = np.concatenate([[False], (post_raw[:-1, 2] >> 31) == 1])
    tr_lean = ah.trace(demo_builds["float"], post_x)
    assert len(tr.counts) == len(x) and len(tr_post.counts) == len(post_x)
    before = tr.cycles[pre]
    print(f"M4 cycles per sample: before the lock min/median/max {before.min()}/"
          f"{int(np.median(before))}/{before.max()} ({int(pre.sum())} samples); after "
          f"{tr_post.cycles[after].min()}/{int(np.median(tr_post.cycles[after]))}/"
          f"{tr_post.cycles[after].max()}; lean build {tr_lean.cycles[after].min()}/"
          f"{int(np.median(tr_lean.cycles[after]))}/{tr_lean.cycles[after].max()}")  # fmt: skip
    assert pre.sum() >= 30 and after.sum() > 4000
    assert before.max() <= 2500
    assert tr_post.cycles[after].max() <= 240
    diff = tr_post.cycles[after] - tr_lean.cycles[after]
    print(f"difference per sample {diff.min()} .. {diff.max()}")
    assert tr_post.cycles[after].max() <= tr_lean.cycles[after].max() + 8


def test_no_fused_multiply_add_with_ide_flags(demo):
    """The source's pragma keeps GCC from contracting a * b + c into VFMA on the Cortex-M4F
    with the flags of an IDE (-std=gnu11 -Os) and with -Ofast; without it GCC emits them."""
    import re
    import subprocess

    t = ah.TARGETS["m4f"]
    src = demo["gen"] / "hallcal.c"
    bare = demo["dir"] / "bare_hallcal.c"
    bare.write_text(re.sub(r"#pragma[^\n]*\n", "\n", src.read_text()))
    counts = {}
    for name, path, flags in (
        ("gnu11 -Os", src, ["-std=gnu11", "-Os"]),
        ("-Ofast", src, ["-Ofast"]),
        ("gnu11 -Os without the pragma", bare, ["-std=gnu11", "-Os"]),
    ):
        obj = demo["dir"] / f"fma_{len(counts)}.o"
        subprocess.run(["arm-none-eabi-gcc", *t.cflags, *flags, f"-I{demo['gen']}", "-c",
                        str(path), "-o", str(obj)], check=True)  # fmt: skip
        dis = subprocess.run(["arm-none-eabi-objdump", "-d", str(obj)], capture_output=True,
                             text=True, check=True).stdout  # fmt: skip
        counts[name] = len(re.findall(r"\bvf(?:n?m[as])", dis))
    print(f"VFMA/VFMS on the Cortex-M4F: {counts}")
    assert counts["gnu11 -Os"] == 0 and counts["-Ofast"] == 0
    assert counts["gnu11 -Os without the pragma"] > 0
