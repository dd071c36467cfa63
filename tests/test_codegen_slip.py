"""The generated firmware's guarantees at the edges: no slip without the fault flag, one API.

Host C compiler only (the ARM builds of the same C give the same bits:
``tests/test_codegen_arm.py``). Checked:

* the adversarial trial classes of ``tests/slip_trials.py`` (overspeed up to twice the stated
  speed limit, a bad first sample after ``set_angle``, bursts of 2-5 bad samples, stuck and
  clipped channels), 3000 trials each, float and fixed point: no slip without the fault flag,
  and up to the speed limit no fault from speed alone (``benchmarks/bench_slip.py`` runs
  100 000 per class on the demo);
* ``set_angle`` reduces any angle within 1e5 rad to [0, 2 pi) with the revolutions adjusted
  and refuses NaN, infinities and larger angles; ``init`` and ``set_angle`` publish a reading
  flagged NO_SAMPLE; a corrupt ``turn`` in the state never indexes out of the table (UBSan and
  ASan) and latches the fault;
* with the decoder, ``set_angle`` ends the identification (identified, pole pair 0);
* the README's firmware snippet compiles (strict C99) and runs unchanged against the default
  export (with the power-up decoder) and against ``powerup=False``;
* contraction into fused multiply-adds is switched off in the source: with ``-std=gnu11 -Os``
  (an IDE's default) the bits are those of ``-std=c99``; ``-Ofast`` (fast-math) stays within
  the stated bound of Python;
* the generated comments keep the punctuation of hallcal's own text.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import slip_trials as st
from firmware_support import (
    CC,
    STRICT,
    Calibration,
    angles,
    bench_artifact,
    compile_driver,
    run,
    sanitizer_flags,
)

from hallcal._constants import TWO_PI
from hallcal.output.codegen import export_c
from hallcal.sim.bench import BenchConfig

pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc, gcc or clang) on PATH")
README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.fixture(scope="module")
def cal() -> Calibration:
    return Calibration()


@pytest.fixture(scope="module")
def work(tmp_path_factory, cal):
    d = tmp_path_factory.mktemp("slip")
    res = export_c(cal.artifact, d, source="cal.json")
    exe = {f: compile_driver(d, fixed=f, flags=["-O2"]) for f in (False, True)}
    return d, res, exe


@pytest.mark.parametrize("fixed", [False, True])
@pytest.mark.parametrize("kind", st.CLASSES)
def test_no_slip_without_the_fault_flag(work, cal, kind, fixed):
    _, res, exe = work
    tr = st.make_trials(kind, cal.truth, n=cal.n, w=res.glitch_safe_speed, noise=cal.noise,
                        trials=3000, length=64, seed=77)  # fmt: skip
    s = st.summarize(st.run_trials(exe[fixed], tr, fixed=fixed), tr, cal.n,
                     res.glitch_safe_speed)  # fmt: skip
    print(f"{kind} {'fixed' if fixed else 'float'}: {s}")
    assert s["silent"] == 0
    if kind == "overspeed":  # up to the speed limit: no slip and no fault from speed alone
        assert s["slips_within"] == 0 and s["faults_within"] == 0
    if kind == "clipped":  # clipping moves the angle, but never by half a pole pitch
        assert s["slips"] == 0


def _c_program(tmp_path: Path, gen: Path, body: str, *, flags=(), name="prog") -> Path:
    src = tmp_path / f"{name}.c"
    src.write_text('#include <math.h>\n#include <stdio.h>\n#include "hallcal.c"\n' + body)
    exe = tmp_path / name
    subprocess.run([CC, "-std=c99", *flags, f"-I{gen}", str(src), "-o", str(exe), "-lm"],
                   check=True, capture_output=True, text=True)  # fmt: skip
    return exe


def test_set_angle_wraps_refuses_and_flags(work, tmp_path):
    gen, res, _ = work
    body = r"""
static void show(hallcal_state *s, uint32_t ret)
{
    hallcal_reading r;
    hallcal_read(s, &r);
    printf("%u %ld %.9g %u\n", (unsigned)ret, (long)r.revolutions, (double)r.angle,
           (unsigned)r.flags);
}
int main(void)
{
    hallcal_state s;
    hallcal_init(&s);
    show(&s, 0u);
    show(&s, hallcal_set_angle(&s, 0, -0.5f));
    show(&s, hallcal_set_angle(&s, 3, 7.0f));
    show(&s, hallcal_set_angle(&s, 0, 6.2831855f));
    show(&s, hallcal_set_angle(&s, 0, NAN));
    show(&s, hallcal_set_angle(&s, 0, INFINITY));
    show(&s, hallcal_set_angle(&s, 0, 2.0e5f));
    show(&s, hallcal_set_angle(&s, -2, -12.0f));
    return 0;
}
"""
    out = subprocess.run([str(_c_program(tmp_path, gen, body))], capture_output=True, text=True,
                         check=True).stdout.split("\n")  # fmt: skip
    rows = [line.split() for line in out if line]
    ret = [int(r[0]) for r in rows]
    rev = [int(r[1]) for r in rows]
    ang = [float(r[2]) for r in rows]
    flags = [int(r[3]) for r in rows]
    assert flags[0] == 32 and rev[0] == 0 and ang[0] == 0.0  # init: NO_SAMPLE
    # -0.5 rad is the previous revolution's 2 pi - 0.5 (not 0, one pole pitch off)
    assert ret[1] == 0 and rev[1] == -1 and ang[1] == pytest.approx(TWO_PI - 0.5, abs=1e-6)
    assert rev[2] == 4 and ang[2] == pytest.approx(7.0 - TWO_PI, abs=1e-6)
    # 6.2831855f is 1.7e-7 above 2 pi: the next revolution (and within [0, 2 pi) anyway)
    assert rev[3] * TWO_PI + ang[3] == pytest.approx(6.2831855, abs=1e-6) and ang[3] < TWO_PI
    for k in (4, 5, 6):  # NaN, infinity, beyond 1e5 rad: refused, the state kept
        assert ret[k] == 4 and (rev[k], ang[k]) == (rev[3], ang[3])
    assert rev[7] * TWO_PI + ang[7] == pytest.approx(-2 * TWO_PI - 12.0, abs=1e-5)
    assert 0.0 <= ang[7] < TWO_PI
    assert all(f & 32 for f in flags)  # nothing measured yet: every reading says so


def test_corrupt_turn_never_indexes_out_of_the_table(work, cal, tmp_path):
    gen, _, _ = work
    san = sanitizer_flags()
    if san is None:
        pytest.skip("the compiler has no ASan/UBSan")
    d = cal.signals(0.3 + 0.01 * np.arange(4), seed=1)
    vals = ", ".join(f"{v:.1f}f" for v in d.ravel())
    body = f"""
int main(void)
{{
    static const float d[12] = {{{vals}}};
    hallcal_state s;
    hallcal_reading r;
    int k;
    uint32_t fl = 0u;
    hallcal_init(&s);
    (void)hallcal_update(&s, d[0], d[1], d[2]);
    s.turn = 5000; /* a corrupted state */
    for (k = 1; k < 4; ++k) {{
        fl |= hallcal_update(&s, d[3 * k], d[3 * k + 1], d[3 * k + 2]);
    }}
    hallcal_read(&s, &r);
    printf("%u %ld %u\\n", (unsigned)fl, (long)s.turn, (unsigned)r.flags);
    return 0;
}}
"""
    exe = _c_program(tmp_path, gen, body, flags=san)
    out = subprocess.run([str(exe)], capture_output=True, text=True, check=True)
    fl, turn, flags = (int(v) for v in out.stdout.split())
    assert (fl & 2) and (flags & 2)  # the fault latched
    assert 0 <= turn < cal.n  # repaired
    assert "runtime error" not in out.stderr


def _readme_snippet() -> str:
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Firmware") :]
    return re.search(r"```c\n(.*?)```", section, re.S).group(1)


HARNESS = r"""
#include <stdio.h>
#include <stdint.h>
static int32_t adc[3]; /* the ADC's counts (the bench's signals are centred on 0) */
static long accepted;
static long samples;
static int32_t last_rev;
static float last_angle;
static void controller_step(int32_t revolutions, float angle, uint32_t flags)
{
    samples += 1;
    accepted += (flags == 0u) ? 1 : 0;
    last_rev = revolutions;
    last_angle = angle;
}
"""

MAIN = r"""
int main(void)
{
    long v[3];
    position_init();
    while (scanf("%ld %ld %ld", &v[0], &v[1], &v[2]) == 3) {
        adc[0] = (int32_t)v[0];
        adc[1] = (int32_t)v[1];
        adc[2] = (int32_t)v[2];
        adc_isr();
    }
    printf("%ld %ld %ld %.9g\n", samples, accepted, (long)last_rev, (double)last_angle);
    return 0;
}
"""


@pytest.mark.parametrize("powerup", [True, False])
def test_readme_snippet_compiles_and_runs_unchanged(tmp_path, powerup):
    """The README's export (``--adc-scale 2048``) of a bench motor with its identifiability
    analysis, with the decoder (the default) and without; the snippet with a stub ADC and
    controller, strict C99; 12-bit counts of a slow turn: every sample accepted, the angle at
    the end within 2 mrad of the truth (the decoder's frame or y = 0's)."""
    cfg = BenchConfig()
    art = bench_artifact(cfg)
    res = export_c(art, tmp_path, adc_scale=2048.0, powerup=powerup)
    assert res.identifies_pole_pair == powerup
    src = tmp_path / "app.c"
    src.write_text(HARNESS + _readme_snippet() + MAIN)
    exe = tmp_path / "app"
    subprocess.run([CC, *STRICT, "-Wno-unused-function", "-O2", f"-I{tmp_path}", str(src),
                    str(tmp_path / "hallcal.c"), "-o", str(exe)], check=True,
                   capture_output=True, text=True)  # fmt: skip
    truth = cfg.truth()
    y0 = 0.02 + 0.002 * np.arange(600)  # from near the calibration's start, 0.5 rad/s at 4 kHz
    rng = np.random.default_rng(3)
    d = truth(y0) + rng.normal(0.0, math.sqrt(cfg.noise_variance), (len(y0), 3))
    counts = np.round(2048.0 * d).astype(int)  # the export's scale: 2048 counts per unit
    x = "\n".join(" ".join(str(v) for v in row) for row in counts) + "\n"
    out = subprocess.run([str(exe)], input=x, capture_output=True, text=True,
                         check=True).stdout.split()  # fmt: skip
    n, ok = int(out[0]), int(out[1])
    assert n == len(y0)
    y_end = TWO_PI * int(out[2]) + float(out[3])
    print(f"powerup={powerup}: {ok}/{n} accepted, end {y_end:.5f} rad, truth {y0[-1]:.5f}")
    assert ok >= n - 1
    assert abs(y_end - y0[-1]) < 2e-3


def _has_fma() -> bool:
    try:
        return " fma " in Path("/proc/cpuinfo").read_text() + " "
    except OSError:
        return False


@pytest.mark.skipif(not _has_fma() or shutil.which("gcc") is None,
                    reason="needs GCC and an x86 CPU with FMA to run contracted code")  # fmt: skip
def test_contraction_is_off_in_the_source(work, cal, tmp_path):
    """GCC contracts a * b + c into an FMA by default in the GNU dialects (-std=gnu11 -Os, an
    IDE's default); the generated source switches that off with a pragma, so the bits are those
    of -std=c99. Without the pragma the same build differs (the test can see it). -Ofast
    (fast-math: reassociation, reciprocals) is outside IEEE arithmetic: its result is held to
    the stated bound of Python instead, and the count of samples whose bits differ printed."""
    gen, res, exe = work
    d = cal.recording(20000, seed=5)
    ref = run(exe[False], d, fixed=False)
    x = d.astype(np.float32)
    fma = ["-march=haswell"]
    gnu = compile_driver(gen, fixed=False, flags=["-std=gnu11", "-Os", *fma], name="gnu11")
    np.testing.assert_array_equal(run(gnu, d, fixed=False), ref)
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(gen / "hallcal.h", bare)
    text = (gen / "hallcal.c").read_text()
    (bare / "hallcal.c").write_text(re.sub(r"#pragma[^\n]*\n", "\n", text))
    contracted = run(compile_driver(bare, fixed=False, flags=["-std=gnu11", "-Os", *fma]), d,
                     fixed=False)  # fmt: skip
    differ = int(np.sum(np.any(contracted != ref, axis=1)))
    assert differ > 0  # FMA changes bits: the pragma is what keeps them
    fast = run(compile_driver(gen, fixed=False, flags=["-Ofast", *fma], name="ofast"), d,
               fixed=False)  # fmt: skip
    err = np.abs(angles(fast, fixed=False) - cal.lut.f_star(x.astype(np.float64)))
    print(f"gnu11 -Os with FMA: bit-exact; without the pragma {differ} of {len(d)} samples "
          f"differ; -Ofast: {int(np.sum(np.any(fast != ref, axis=1)))} differ, max |C - python| "
          f"{err.max():.2e} rad (bound {res.float_bound:.2e})")  # fmt: skip
    assert err.max() <= res.float_bound


def test_generated_comments_read_as_written(work):
    """hallcal's own text keeps its punctuation; only what comes from outside (the file name,
    the prefix) is reduced to safe characters."""
    gen, _, _ = work
    h = (gen / "hallcal.h").read_text()
    assert "the calibration's table" in h and "rad/s" in h and "|error| <=" in h
    assert "calibration_s" not in h and "rad_s" not in h and "_error_" not in h
    for text in (h, (gen / "hallcal.c").read_text(), (gen / "hallcal_q.h").read_text()):
        comments = re.findall(r"/\*.*?\*/", text, re.S)
        assert all("/*" not in c[2:] for c in comments)  # nothing opens a comment inside one
        assert "??" not in text and "\\\n" not in text


def test_set_angle_ends_the_power_up_identification(tmp_path):
    """With the decoder, a homed axis needs no identification: after set_angle the reading
    says identified, pole pair 0, and the lean path tracks the angle from the given position
    (within 2 mrad of the truth; the step rule applies from the first sample)."""
    cfg = BenchConfig()
    art = bench_artifact(cfg)
    res = export_c(art, tmp_path, adc_scale=2048.0, fixed_point=False)
    assert res.identifies_pole_pair
    y0 = 2.5 + 0.002 * np.arange(1, 201)
    rng = np.random.default_rng(4)
    d = cfg.truth()(y0) + rng.normal(0.0, math.sqrt(cfg.noise_variance), (len(y0), 3))
    vals = ", ".join(f"{v:.9g}f" for v in d.ravel())
    body = f"""
int main(void)
{{
    static const float d[{d.size}] = {{{vals}}};
    hallcal_state s;
    hallcal_reading r;
    uint32_t fl = 0u;
    int k;
    hallcal_init(&s);
    fl = hallcal_set_angle(&s, 0, 2.5f);
    hallcal_read(&s, &r);
    printf("%u %u %u\\n", (unsigned)fl, (unsigned)r.identified, (unsigned)r.flags);
    for (k = 0; k < {len(y0)}; ++k) {{
        fl |= hallcal_update(&s, d[3 * k], d[3 * k + 1], d[3 * k + 2]);
    }}
    hallcal_read(&s, &r);
    printf("%u %u %u %ld %.9g\\n", (unsigned)fl, (unsigned)r.identified, (unsigned)r.pole_pair,
           (long)r.revolutions, (double)r.angle);
    return 0;
}}
"""
    out = subprocess.run([str(_c_program(tmp_path, tmp_path, body))], capture_output=True,
                         text=True, check=True).stdout.split("\n")  # fmt: skip
    ret, ident0, flags0 = (int(v) for v in out[0].split())
    assert ret == 0 and ident0 == 1 and flags0 == 32  # identified at once, nothing measured yet
    fl, ident, j, rev, ang = out[1].split()
    assert int(fl) == 0 and int(ident) == 1 and int(j) == 0  # every sample accepted
    assert abs(TWO_PI * int(rev) + float(ang) - y0[-1]) < 2e-3
