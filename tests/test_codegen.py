"""Generated firmware (hallcal.output.codegen) compiled with the host C compiler.

What is checked, and against what:

* the files: names, permissions, comments (sanitized, no absolute path), C99 hygiene (strict
  warnings as errors, MISRA-minded patterns: no function-like macro, no builtin, no float
  equality, no increment inside a condition, unsigned right shifts only, no library symbol);
* agreement with ``hallcal reconstruct`` (``LUT.f_star`` in double precision) on recorded-like
  data, within the stated bounds and within 1e-5 rad;
* the atan2 of each variant against ``numpy.arctan2`` over a million vectors in the radius window;
* 10^6 revolutions forward and back (exact bookkeeping);
* plausibility: NaN/inf/rails rejected, counted and held; fault after N in a row; a glitch
  sample at a random angle and speed never makes the angle slip (10 000 of them); disconnected
  and saturated channels flagged within 10 samples; common mode rejected exactly (fixed point);
* the snapshot under interruption (a POSIX timer signal as the interrupt);
* sanitizers over a million random and adversarial inputs;
* refusals: malformed artifacts (the key named), implausible numbers, hostile adc_scale, hostile
  file names (no code reaches the C).
"""

from __future__ import annotations

import copy
import math
import os
import re
import subprocess

import numpy as np
import pytest
from firmware_support import (
    CC,
    STRICT,
    Calibration,
    angles,
    c_code,
    compile_driver,
    misra_check,
    run,
    sanitizer_flags,
)

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.output.codegen import comment_text, export_c
from hallcal.output.codegen.numbers import MAGIC_SEED_ERROR, RECIPROCAL_MAGIC, _fixed_numbers

pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc, gcc or clang) on PATH")


@pytest.fixture(scope="module")
def cal() -> Calibration:
    return Calibration()


@pytest.fixture(scope="module")
def work(tmp_path_factory, cal):
    d = tmp_path_factory.mktemp("codegen")
    res = export_c(cal.artifact, d, source="/home/someone/cal.json")
    return d, res


@pytest.fixture(scope="module")
def exe_f(work):
    return compile_driver(work[0], fixed=False, flags=["-O2"])


@pytest.fixture(scope="module")
def exe_q(work):
    return compile_driver(work[0], fixed=True, flags=["-O2"])


_code = c_code


# ------------------------------------------------------------------------------------------
# Files and hygiene
# ------------------------------------------------------------------------------------------


def test_files_modes_comments_and_result(work, cal):
    d, res = work
    assert [p.name for p in res.paths] == ["hallcal.h", "hallcal.c", "hallcal_q.h", "hallcal_q.c"]
    # no warnings; the synthetic artifact has no identifiability analysis: the homing API
    assert not res.identifies_pole_pair and res.powerup_table_bytes == 0
    assert [m for m in res.messages if not m.startswith("no power-up identification")] == []
    assert not [p for p in d.iterdir() if p.name.startswith(".")]  # no temporary files left
    umask = os.umask(0)
    os.umask(umask)
    for p in res.paths:
        assert (p.stat().st_mode & 0o777) == (0o666 & ~umask)  # as any file the user writes
        text = p.read_text(encoding="ascii")
        assert "Source artifact : cal.json" in text and "/home/someone" not in text
        assert res.sha256 in text and "Pole pairs n_m  : 11" in text
    # the budget: a tenth of the noise floor; the table within it and within 4 kB
    assert res.budget == pytest.approx(min(0.1 * cal.noise_floor, 1e-5))
    assert res.table_error <= res.budget and res.table_bytes <= 4096
    assert res.table_points % cal.n == 0  # n_m 2^k intervals
    assert res.float_bound < 1e-5 and res.fixed_bound < 1e-5
    assert res.atan2_bound < 1e-4 and res.fixed_atan2_bound < 1e-4


def test_strict_c99_and_no_library_symbols(work):
    d, _ = work
    nm = "nm"
    for name in ("hallcal.c", "hallcal_q.c"):
        obj = d / (name[:-2] + ".o")
        r = subprocess.run([CC, *STRICT, "-O2", "-c", str(d / name), "-o", str(obj)],
                           capture_output=True, text=True)  # fmt: skip
        assert r.returncode == 0, r.stderr
        und = subprocess.run([nm, "-u", str(obj)], capture_output=True, text=True).stdout
        assert und.split() == [], und  # no libm, no libc, no helper
    # the fixed-point variant needs no FPU register at all (GCC on x86 and ARM know the flag)
    cmd = [CC, "-std=c99", "-O2", "-mgeneral-regs-only", "-c", str(d / "hallcal_q.c")]
    r = subprocess.run([*cmd, "-o", os.devnull], capture_output=True, text=True)
    if "unrecognized" not in r.stderr and "unknown argument" not in r.stderr:
        assert r.returncode == 0, r.stderr


def test_misra_minded_patterns(work):
    d, _ = work
    misra_check(d)


def test_comment_text_cannot_end_a_comment():
    for hostile in ["x*/y", "a\\\nb", "??/", "??=x", "\u00e4\u00fc", "a/*b", "x\ny", "t\x00"]:
        out = comment_text(hostile)
        assert "*/" not in out and "/*" not in out and "\\" not in out and "??" not in out
        assert "\n" not in out and out.isascii()


def test_the_magic_seeds_stated_error_is_its_largest_over_every_mantissa():
    """MAGIC_SEED_ERROR is max |1 - x seed(x)| over every x in [1, 2) (every mantissa; the
    relative error repeats with the exponent), exactly: x and the seed have 24-bit mantissas, so
    x seed(x) and 1 minus it are exact in double."""
    m = np.arange(2**23, dtype=np.uint32) | np.uint32(127 << 23)  # x in [1, 2)
    x = m.view(np.float32).astype(np.float64)
    seed = (np.uint32(RECIPROCAL_MAGIC) - m).view(np.float32).astype(np.float64)
    assert float(np.max(np.abs(1.0 - x * seed))) == MAGIC_SEED_ERROR


def test_hostile_artifact_path_reaches_no_code(tmp_path, cal):
    """An artifact path with a line splice out of the comment, one with a trigraph: the generated
    files define only the API, checked by compiling a probe with the injected name."""
    names = [
        "x*\\\n/\n#define HALLCAL_INJECTED 1\nint hallcal_injected_symbol = 42;\n/*.json",
        "??/\nint hallcal_injected_symbol = 42;\n.json",
        "/tmp/\u00e4\u00f6\u00fc/k\u00e4l.json",
    ]
    for i, name in enumerate(names):
        out = tmp_path / f"o{i}"
        export_c(cal.artifact, out, source=name)
        for p in out.iterdir():
            text = p.read_text(encoding="ascii")
            assert "hallcal_injected_symbol = 42" not in _code(text)
            assert "HALLCAL_INJECTED" not in _code(text)
        probe = out / "probe.c"
        probe.write_text('#include "hallcal.c"\n#include "hallcal_q.c"\n'
                         "#ifdef HALLCAL_INJECTED\n#error injected\n#endif\n"
                         "int probe(void) { return hallcal_injected_symbol; }\n")  # fmt: skip
        r = subprocess.run([CC, "-std=c99", "-trigraphs", "-c", str(probe), "-o", os.devnull],
                           capture_output=True, text=True)  # fmt: skip
        assert r.returncode != 0 and "hallcal_injected_symbol" in r.stderr


# ------------------------------------------------------------------------------------------
# Agreement with hallcal reconstruct
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fixed", [False, True])
def test_matches_python(work, cal, exe_f, exe_q, fixed):
    _, res = work
    d = cal.recording(120_000, seed=1)
    raw = run(exe_q if fixed else exe_f, d, fixed=fixed)
    assert not np.any(raw[:, 2])  # recorded-like data: nothing rejected
    y = angles(raw, fixed=fixed)
    ys = cal.lut.f_star(d)
    err = float(np.max(np.abs(y - ys)))
    bound = res.fixed_bound if fixed else res.float_bound
    print(f"{'fixed' if fixed else 'float'}: max |C - python| {err:.2e} rad, bound {bound:.2e}")
    assert err <= bound <= 1e-5
    assert np.ptp(ys) > 4 * TWO_PI and np.any(np.diff(ys) < 0)  # revolutions both ways


@pytest.mark.parametrize(("n", "fixed"), [(1, False), (1, True), (2, False), (2, True), (4, True)])
def test_other_pole_pairs(tmp_path, n, fixed):
    """n_m = 1 (the electrical turn is the revolution: 2^32 period) and 2 (2^31 period)."""
    c = Calibration(n=n, points=1024, trapezoid=0.5, seed=n)
    res = export_c(c.artifact, tmp_path)
    exe = compile_driver(tmp_path, fixed=fixed, flags=["-O2"], pole_pairs=n)
    d = c.recording(20_000, seed=5)
    y = angles(run(exe, d, fixed=fixed), fixed=fixed)
    err = float(np.max(np.abs(y - c.lut.f_star(d))))
    assert err <= (res.fixed_bound if fixed else res.float_bound)


def test_volts_with_adc_scale_and_prefix(tmp_path):
    """Signals in volts (the float variant takes volts, the fixed one counts) and a prefix."""
    adc = 4096 / 3.3
    c = Calibration(amplitude=1.2, offset=(1.65, 1.62, 1.67), noise=2.5e-3, seed=5)
    res = export_c(c.artifact, tmp_path, prefix="motor2", adc_scale=adc)
    assert [p.name for p in res.paths] == ["motor2.h", "motor2.c", "motor2_q.h", "motor2_q.c"]
    y0 = 9.0 * np.sin(np.linspace(0, 6, 20_000))
    v = c.truth(y0) + np.random.default_rng(2).normal(0, 2.5e-3, (y0.size, 3))
    yf = angles(run(compile_driver(tmp_path, "motor2", fixed=False, flags=["-O2"]), v,
                    fixed=False), fixed=False)  # fmt: skip
    assert np.max(np.abs(yf - c.lut.f_star(v.astype(np.float32)))) <= res.float_bound
    counts = np.round(v * adc)
    yq = angles(run(compile_driver(tmp_path, "motor2", fixed=True, flags=["-O2"]), counts,
                    fixed=True), fixed=True)  # fmt: skip
    assert np.max(np.abs(yq - c.lut.f_star(counts / adc))) <= res.fixed_bound
    # rounding to counts: what ExportResult says it adds, against f_star on the volts
    q_err = yq - c.lut.f_star(v)
    assert float(np.sqrt(np.mean(q_err**2))) <= res.quantization_rms * 1.5 + res.fixed_bound


def test_float_only_export(tmp_path, cal):
    res = export_c(cal.artifact, tmp_path, fixed_point=False)
    assert [p.name for p in res.paths] == ["hallcal.h", "hallcal.c"]
    assert res.fixed_bound is None and res.quantization_rms is None


# ------------------------------------------------------------------------------------------
# atan2, long runs
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fixed", [False, True])
def test_atan2_within_its_bound(work, cal, exe_f, exe_q, fixed):
    """A million vectors over all angles with radii across the window (both ends)."""
    _, res = work
    design = res.design
    rng = np.random.default_rng(11)
    m = 1_000_000
    phi = rng.uniform(0.0, TWO_PI, m)
    phi[:4096] = TWO_PI * np.arange(4096) / 4096  # octant and rotation boundaries included
    if fixed:
        q = _fixed_numbers(design, 1.0)
        r_lo, r_hi = math.sqrt(q.r2_lo) * 2**15, math.sqrt(q.r2_hi) * 2**15
        r = rng.uniform(r_lo * 1.001, r_hi * 0.999, m)
        ab = np.round(np.column_stack([r * np.cos(phi), r * np.sin(phi)])).astype(np.int32)
        exe = exe_q
        period = 2.0**32 / cal.n  # mechanical units per electrical turn
    else:
        r = rng.uniform(design.plausibility.radius_lo, design.plausibility.radius_hi, m)
        ab = np.column_stack([r * np.cos(phi), r * np.sin(phi)]).astype(np.float32)
        exe = exe_f
        period = 2.0**32
    out = subprocess.run([str(exe), "angle"], input=ab.tobytes(), capture_output=True,
                         check=True).stdout  # fmt: skip
    got = np.frombuffer(out, dtype=np.uint32).astype(np.float64) / period * TWO_PI
    ref = np.arctan2(ab[:, 1].astype(np.float64), ab[:, 0].astype(np.float64))
    err = np.abs(np.mod(got - ref + math.pi, TWO_PI) - math.pi)
    bound = res.fixed_atan2_bound if fixed else res.atan2_bound
    print(f"atan2 {'fixed' if fixed else 'float'}: max {err.max():.2e}, bound {bound:.2e}")
    assert err.max() <= bound


@pytest.mark.parametrize("fixed", [False, True])
def test_million_revolutions(work, cal, exe_f, exe_q, fixed):
    """10^6 revolutions forward at 0.058 electrical turn per sample (below the default speed
    limit, 1/16), then 5e4 back, on exact synthetic signals; every 10^5 samples the reading is
    compared with f_star of that very sample (unwrapped at the true position)."""
    _, res = work
    a, b = 53, 10007  # mechanical position k a / b turn, exact in integers in the driver
    nfwd = 10**6 * b // a
    ntot = nfwd + 50_000 * b // a
    amp = cal.amplitude
    offs = [float(v) for v in cal.lut.offset]
    args = [str(exe_q if fixed else exe_f), "long", str(a), str(b), str(nfwd), str(ntot)]
    args += [str(100_000), repr(amp), str(cal.n)]
    args += [repr(v) for v in offs] + [repr(float(v)) for v in cal.proj_phases]
    out = subprocess.run(args, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    tab = np.array([[float(v) for v in line.split()] for line in out.stdout.splitlines()])
    _, rev, num, rev_c, ang_c = tab.T
    assert rev.max() >= 10**6 - 1 and rev[-1] < rev.max()
    frac = TWO_PI * num / b
    el = np.mod(num * cal.n, b)
    ph = np.asarray(cal.proj_phases)
    d = np.asarray(offs) + amp * np.cos(TWO_PI * el[:, None] / b - ph[None, :])
    d = np.round(d) if fixed else d.astype(np.float32).astype(np.float64)
    expected = np.array(
        [cal.lut.f_star(row[None, :], y_initial=f)[0] for row, f in zip(d, frac, strict=True)]
    )
    if fixed:
        got = ang_c * (TWO_PI / 2**32)
    else:
        got = ang_c.astype(np.uint32).view(np.float32).astype(np.float64)
    err = np.abs((rev_c - rev) * TWO_PI + got - expected)
    print(f"{'fixed' if fixed else 'float'} after 1e6 revolutions: max error {err.max():.2e}")
    assert err.max() <= (res.fixed_bound if fixed else res.float_bound)


# ------------------------------------------------------------------------------------------
# Plausibility: bad samples, glitches, disconnected and saturated sensors
# ------------------------------------------------------------------------------------------


def _constant_speed(cal, steps, w, *, start=0.3, seed=0):
    """Signals at constant mechanical speed w [rad/sample] from start, with noise."""
    y0 = start + w * np.arange(steps)
    return y0, cal.signals(y0, seed=seed)


@pytest.mark.parametrize("fixed", [False, True])
def test_bad_samples_rejected_counted_held_and_fault(work, cal, exe_f, exe_q, fixed):
    """NaN/inf (float), rails and a common mode are rejected; the reading is held, each
    rejection counted; the fault flag after FAULT_AFTER in a row, latched, cleared by
    nothing but clear_fault (so it stays set in the readings after the bad run)."""
    _, res = work
    y0, d = _constant_speed(cal, 400, 0.002)
    bad = d.copy()
    if not fixed:
        bad[50, 0] = np.nan
        bad[60, 1] = np.inf
        bad[70, 2] = -np.inf
    bad[80] = 4095  # all channels at the rail (a common mode)
    bad[90, 1] = 0  # one channel disconnected
    bad[200:212, 0] = 4095  # a saturated channel for 12 samples
    raw = run(exe_q if fixed else exe_f, bad, fixed=fixed)
    flags = raw[:, 2]
    rows = ([] if fixed else [50, 60, 70]) + [80, 90] + list(range(200, 212))
    assert np.all(flags[rows] & 1)  # HELD
    assert np.all(raw[rows, :2] == raw[np.array(rows) - 1, :2]) or True
    for r in rows:  # the reading is the last accepted one
        prev = max(k for k in range(r) if k not in rows)
        assert np.all(raw[r, :2] == raw[prev, :2])
    ok = np.setdiff1d(np.arange(200), rows)
    assert not np.any(flags[ok])
    fault_at = 200 + res.fault_after - 1
    assert np.all(flags[fault_at:] & 2) and not np.any(flags[:fault_at] & 2)  # latched
    # the accepted samples give what they give without the bad ones (before the fault run)
    clean = run(exe_q if fixed else exe_f, d[ok], fixed=fixed)
    np.testing.assert_array_equal(raw[ok, :2], clean[:, :2])


@pytest.mark.parametrize("fixed", [False, True])
def test_common_mode_is_rejected_exactly(work, cal, exe_q, exe_f, fixed):
    """Adding the same count to all three channels changes nothing (bit for bit) in the fixed
    variant, whose integer projection rows sum to zero; in float, integer counts below 2^24
    enter as exact differences, so there too."""
    y0, d = _constant_speed(cal, 2000, 0.004)
    k = np.random.default_rng(5).integers(-60, 60, size=(len(d), 1))
    exe = exe_q if fixed else exe_f
    a = run(exe, d, fixed=fixed)
    b = run(exe, d + k, fixed=fixed)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("fixed", [False, True])
def test_single_glitches_never_slip(work, cal, exe_f, exe_q, fixed):
    """10 000 trials: constant speed (uniform up to the stated speed limit, either way), one
    sample replaced at a random time by a glitch; half are the signals of a random angle
    (plausible amplitude: only the step rule can catch them), half random counts. After the
    glitch the output must come back to the clean run's output exactly: no slip; a fault only
    where the glitch was accepted at the edge of the window near the speed limit."""
    _, res = work
    rng = np.random.default_rng(2024)
    trials, length = 10_000, 40
    safe = res.glitch_safe_speed  # rad per sample, mechanical
    w = rng.uniform(-safe, safe, trials) * 0.98
    start = rng.uniform(0, TWO_PI, trials)
    k = np.arange(length)
    y0 = start[:, None] + w[:, None] * k[None, :]
    d = cal.signals(y0.ravel(), seed=7).reshape(trials, length, 3)
    dirty = d.copy()
    at = rng.integers(5, 20, trials)
    plausible = rng.random(trials) < 0.5
    glitch_angle = rng.uniform(0, TWO_PI, trials)
    g_plaus = cal.signals(glitch_angle, seed=8)
    g_rand = rng.integers(0, 4096, (trials, 3)).astype(float)
    dirty[np.arange(trials), at] = np.where(plausible[:, None], g_plaus, g_rand)
    exe = exe_q if fixed else exe_f
    clean = run(exe, d.reshape(-1, 3), fixed=fixed, block=length).reshape(trials, length, 3)
    raw = run(exe, dirty.reshape(-1, 3), fixed=fixed, block=length).reshape(trials, length, 3)
    # each trial starts from (0, 0): the first sample is acquired wherever it is; compare the
    # last sample (13 or more after the glitch) bit for bit
    same = np.all(raw[:, -1, :2] == clean[:, -1, :2], axis=1)
    y_clean = angles(clean[:, -1], fixed=fixed)
    y_dirty = angles(raw[:, -1], fixed=fixed)
    slips = np.abs(y_dirty - y_clean) > math.pi / cal.n
    accepted = np.sum((raw[np.arange(trials), at, 2] & 1) == 0)
    print(
        f"{'fixed' if fixed else 'float'}: {trials} glitches, {accepted} accepted by the checks, "
        f"{int(np.sum(~same))} outputs different at the end, {int(slips.sum())} slips"
    )
    faults = int(np.sum(np.any(raw[:, :, 2] & 2, axis=1)))
    print(
        f"  {faults} faults (a glitch accepted at the edge of the window while the rotor runs "
        "near the speed limit the other way: the angle cannot be trusted to come back)"
    )
    assert not slips.any()
    assert same.all()
    # measured 0.7 % at speeds uniform up to the limit: a fault, never a slip; the rest absorbed
    assert faults <= trials // 40
    assert accepted < trials // 4  # most glitches are caught (the rest are near the angle)


@pytest.mark.parametrize("fixed", [False, True])
@pytest.mark.parametrize("what", ["disconnected", "saturated", "connector"])
def test_disconnect_and_saturation_flagged_within_10_samples(work, cal, exe_f, exe_q, fixed,
                                                             what):  # fmt: skip
    """At random angles and speeds (standstill included), from a random sample on, a channel
    reads 0 (disconnected, pulled down), the ADC's full scale 4095 (saturated), or all three
    read 0 (connector off): the fault flag within 10 samples, every time."""
    rng = np.random.default_rng({"disconnected": 1, "saturated": 2, "connector": 3}[what])
    trials, length = 500, 60
    w = rng.uniform(-0.01, 0.01, trials) * (rng.random(trials) > 0.2)
    start = rng.uniform(0, TWO_PI, trials)
    y0 = start[:, None] + w[:, None] * np.arange(length)[None, :]
    d = cal.signals(y0.ravel(), seed=4).reshape(trials, length, 3)
    at = rng.integers(10, 30, trials)
    ch = rng.integers(0, 3, trials)
    for t in range(trials):
        if what == "connector":
            d[t, at[t] :, :] = 0
        else:
            d[t, at[t] :, ch[t]] = 0 if what == "disconnected" else 4095
    raw = run(exe_q if fixed else exe_f, d.reshape(-1, 3), fixed=fixed, block=length)
    flags = raw[:, 2].reshape(trials, length)
    first_fault = np.argmax((flags & 2) != 0, axis=1)
    assert np.all(flags[np.arange(trials), -1] & 2)
    delay = first_fault - at + 1  # samples from the first bad one, inclusive
    print(f"{what}: fault after {delay.min()}..{delay.max()} samples")
    assert np.all(delay <= 10)
    assert not np.any(flags[:, :10])  # nothing before the fault


def test_clear_fault_and_recovery(tmp_path, cal, work):
    """After a fault and the cause removed, the samples are accepted again (the step limit
    has grown past half a turn); the flag stays until clear_fault."""
    d_dir, _ = work
    y0, d = _constant_speed(cal, 200, 0.003)
    d[50:70, 1] = 0
    drv = tmp_path / "clear.c"
    drv.write_text(
        '#include <stdio.h>\n#include "hallcal.c"\n'
        "int main(void) { hallcal_state s; hallcal_reading r; float v[3]; int k = 0;\n"
        "  hallcal_init(&s);\n"
        "  while (fread(v, sizeof v, 1, stdin) == 1) {\n"
        "    if (k == 120) hallcal_clear_fault(&s);\n"
        "    (void)hallcal_update(&s, v[0], v[1], v[2]); hallcal_read(&s, &r);\n"
        '    printf("%u %lu\\n", (unsigned)r.flags, (unsigned long)r.rejected); ++k; }\n'
        "  return 0; }\n"
    )  # fmt: skip
    exe = tmp_path / "clear"
    subprocess.run([CC, "-std=c99", f"-I{d_dir}", str(drv), "-o", str(exe)], check=True)
    out = subprocess.run([str(exe)], input=d.astype(np.float32).tobytes(), capture_output=True,
                         check=True).stdout.decode().split("\n")  # fmt: skip
    flags = np.array([int(line.split()[0]) for line in out if line])
    rejected = np.array([int(line.split()[1]) for line in out if line])
    assert np.all(flags[50:70] & 1) and rejected[69] == 20
    assert np.all(flags[70:120] == 2)  # accepted again, fault still latched
    assert np.all(flags[120:] == 0)


# ------------------------------------------------------------------------------------------
# The snapshot under interruption
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fixed", [False, True])
def test_snapshot_is_consistent_under_interrupts(work, cal, exe_f, exe_q, fixed):
    """A POSIX interval timer interrupts the main loop every 10 us. Mode 0: update in the
    interrupt, read in the main loop; mode 1: the other way round. Every pair read must be a
    pair that was published (revolutions and angle of the same sample). Mode 2 pairs the
    revolutions and the angle of two reads, and must be caught tearing: the check can fail."""
    exe = exe_q if fixed else exe_f
    # fast spin: a revolution boundary every 40 samples
    y0, d = _constant_speed(cal, 20_000, TWO_PI / 40.0 * 0.999, start=0.01)
    published = run(exe, d, fixed=fixed)
    pairs = {(int(a), int(b)) for a, b in published[:, :2]}
    pairs.add((0, 0))  # the initial reading
    result = {}
    for mode in (0, 1, 2):
        out = subprocess.run([str(exe), "isr", str(mode), "200000"], input=np.ascontiguousarray(
            d, dtype=np.int32 if fixed else np.float32).tobytes(), capture_output=True,
            timeout=120)  # fmt: skip
        assert out.returncode == 0, out.stderr
        got = np.frombuffer(out.stdout, dtype=np.uint32).reshape(-1, 2)
        torn = sum((int(a), int(b)) not in pairs for a, b in got)
        result[mode] = (len(got), torn)
    print(f"{'fixed' if fixed else 'float'} (reads, torn): {result}")
    assert result[0][0] > 1000 and result[0][1] == 0
    assert result[1][0] > 100 and result[1][1] == 0
    assert result[2][1] > 0


# ------------------------------------------------------------------------------------------
# Sanitizers
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fixed", [False, True])
def test_sanitizers_random_and_adversarial(work, cal, fixed):
    wd, _ = work
    flags = sanitizer_flags()
    if flags is None:
        pytest.skip(f"{CC} cannot build with -fsanitize=address,undefined")
    exe = compile_driver(wd, fixed=fixed, flags=flags, name=f"san_{int(fixed)}")
    env = dict(os.environ, UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1")
    out = subprocess.run([str(exe), "fuzz", "1000000"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.startswith("ok")
    d = cal.recording(20_000, seed=3)
    a = run(exe, d, fixed=fixed)
    b = run(compile_driver(wd, fixed=fixed, flags=["-O2"], name=f"o2_{int(fixed)}"), d,
            fixed=fixed)  # fmt: skip
    np.testing.assert_array_equal(a, b)  # -O1 with sanitizers and -O2: the same bits


# ------------------------------------------------------------------------------------------
# Refusals
# ------------------------------------------------------------------------------------------


def _broken(artifact, path, value):
    art = copy.deepcopy(artifact)
    keys = path.split(".")
    target = art
    for key in keys[:-1]:
        target = target[key]
    if value is KeyError:
        del target[keys[-1]]
    else:
        target[keys[-1]] = value
    return art


@pytest.mark.parametrize(
    ("path", "value", "named"),
    [
        ("format", "hallcal-calibration/0", 'unsupported format "hallcal-calibration/0"'),
        ("pole_pairs", KeyError, "'pole_pairs'"),
        ("pole_pairs", 0, "'pole_pairs'"),
        ("pole_pairs", 10**400, "'pole_pairs'"),
        ("reconstruction.offset", [1.0, 2.0], "'reconstruction.offset'"),
        ("reconstruction.offset", [1e300, 0.0, 0.0], "'reconstruction.offset'"),
        ("reconstruction.projection", [[1, 0, 0], [2, 0, 0]], "'reconstruction.projection'"),
        (
            "reconstruction.projection",
            [[1e-40, 0, 0], [0, 1e-40, 0]],
            "'reconstruction.projection'",
        ),
        ("lut.eta", KeyError, "'lut.eta'"),
        ("lut.points", 17, "'lut.points'"),
        ("lut.y_hat", [0.0, 1.0, float("nan"), 3.0], "'lut.y_hat[2]'"),
        ("model", KeyError, "'model'"),
        ("model.theta", [[1.0]], "'model.theta'"),
    ],
)
def test_bad_artifact_names_the_key(tmp_path, cal, path, value, named):
    """The one validator (hallcal.io.validate_artifact) names the key, or the format."""
    with pytest.raises(HallcalInputError, match=re.escape(named)):
        export_c(_broken(cal.artifact, path, value), tmp_path, source="bad.json")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("how", ["fold", "swap"])
def test_non_bijective_table_is_refused(tmp_path, cal, how):
    y_hat = np.array(cal.artifact["lut"]["y_hat"])
    eta = np.array(cal.artifact["lut"]["eta"])
    if how == "fold":  # the model's y_hat goes back: eq. (recon_biject) fails
        y0 = y_hat + eta
        y_hat[100] = y_hat[99] - 1e-3
        eta[100] = y0[100] - y_hat[100]
    else:  # nodes out of order
        y_hat[[100, 101]] = y_hat[[101, 100]]
    art = _broken(cal.artifact, "lut.y_hat", y_hat.tolist())
    art["lut"]["eta"] = eta.tolist()
    with pytest.raises(HallcalInputError, match="not bijective"):
        export_c(art, tmp_path)


@pytest.mark.parametrize(
    ("scale", "why"),
    [
        (1e30, "2\\^30 counts"),  # signals beyond the int32 arithmetic
        (1e-3, "noise floor"),  # rounding to counts noisier than the Hall sensors
        (float("nan"), "positive"),
        (-1.0, "positive"),
    ],
)
def test_hostile_adc_scale_is_refused(tmp_path, cal, scale, why):
    with pytest.raises(HallcalInputError, match=why):
        export_c(cal.artifact, tmp_path, adc_scale=scale)
    assert not list(tmp_path.iterdir())


def test_normalized_artifact_needs_an_adc_scale(tmp_path):
    """An artifact in normalized units (amplitude 1) exported with adc_scale 1 would make the
    fixed variant take counts of -1, 0, 1: refused, not a silently wrong angle."""
    c = Calibration(amplitude=1.0, offset=(0.0, 0.0, 0.0), noise=2.7e-3)
    with pytest.raises(HallcalInputError, match="adc_scale 1"):
        export_c(c.artifact, tmp_path)
    res = export_c(c.artifact, tmp_path, adc_scale=2**14)
    assert res.quantization_rms < 0.1 * res.noise_floor


@pytest.mark.parametrize(
    ("kwargs", "why"),
    [
        ({"prefix": "my-motor"}, "C identifier"),
        ({"prefix": "int"}, "C keyword"),
        ({"prefix": "x" * 40}, "C identifier"),
        ({"table_points": 1000}, "table_points"),
        ({"tolerance": 2.0}, "tolerance"),
        ({"fault_after": 2}, "fault_after"),
        ({"max_speed": -1.0}, "max_speed"),
        ({"max_speed": 1e6}, "cannot follow"),
    ],
)
def test_bad_options(tmp_path, cal, kwargs, why):
    with pytest.raises(HallcalInputError, match=why):
        export_c(cal.artifact, tmp_path, **kwargs)


def test_max_speed_sets_the_step_limit(tmp_path, cal):
    slow = export_c(cal.artifact, tmp_path / "a", max_speed=20.0)
    fast = export_c(cal.artifact, tmp_path / "b", max_speed=150.0, fault_after=10)
    assert slow.step_limit < fast.step_limit < 0.5
    # 20 rad/s at 4 kHz, n = 11: 0.0088 electrical turn per sample; the window is f_init's
    # largest step there (slope s w, s from the sensors' distortion) plus the noise margin
    pl = slow.design.plausibility
    w = 20.0 * 2.5e-4 * cal.n / TWO_PI
    assert pl.speed == pytest.approx(w, rel=1e-12)
    assert slow.step_limit == pytest.approx(pl.slope * w + pl.step_noise, rel=1e-12)
    assert 1.0 <= pl.slope < 1.5  # the test sensors' distortion
    assert slow.glitch_safe_speed == pytest.approx(20.0 * 2.5e-4, rel=1e-12)
    # slow: many holds are alias-free, so the requested fault count stands; fast: fewer
    assert slow.fault_after == 8 and slow.design.plausibility.alias_holds >= 7
    assert fast.fault_after < 10 and any("fault flag latches after" in m for m in fast.messages)


# ------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cli_artifact(tmp_path_factory, cal):
    """The test calibration as a complete artifact file (hallcal's setup for 11 pole pairs)."""
    from hallcal.io import default_setup, write_artifact

    folder = tmp_path_factory.mktemp("cli")
    art = copy.deepcopy(cal.artifact)
    art["setup"] = default_setup()
    path = folder / "cal.json"
    write_artifact(path, art)
    return folder, path


def _hallcal(*args, cwd, env=None):
    import sys

    return subprocess.run([sys.executable, "-m", "hallcal.cli", *args], cwd=cwd,
                          capture_output=True, text=True, env=env, timeout=300)  # fmt: skip


def test_cli_export_options_and_refusals(cli_artifact):
    folder, path = cli_artifact
    r = _hallcal("export-c", str(path), "--out", "fw1", "--no-fixed-point", "--no-powerup",
                 cwd=folder)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "left out on request" in r.stderr  # the note says why init needs the position
    assert sorted(p.name for p in (folder / "fw1").iterdir()) == ["hallcal.c", "hallcal.h"]
    r = _hallcal("export-c", str(path), "--out", "fw2", "--max-speed", "50", "--prefix", "m2",
                 "--fault-after", "6", "--tolerance", "0.2", cwd=folder)  # fmt: skip
    assert r.returncode == 0, r.stderr
    h = (folder / "fw2" / "m2.h").read_text()
    assert "#define M2_FAULT_AFTER 6" in h and "m2_update" in h
    for args, why in [
        (["--adc-scale", "1e30"], "2^30 counts"),
        (["--adc-scale", "0.001"], "noise floor"),
        (["--table-points", "1000"], "table_points"),
        (["--max-speed", "1e7"], "cannot follow"),
        (["--prefix", "a b"], "C identifier"),
    ]:
        r = _hallcal("export-c", str(path), "--out", "bad", *args, cwd=folder)
        assert r.returncode == 2, (args, r.stderr)
        assert r.stderr.count("\n") == 1 and why in r.stderr and "Traceback" not in r.stderr
        assert not (folder / "bad").exists()


def test_cli_non_ascii_paths_in_an_ascii_locale(cli_artifact):
    folder, path = cli_artifact
    hostile = folder / "k\u00e4l*\\\n#define X 1\n.json"
    hostile.write_bytes(path.read_bytes())
    env = dict(os.environ, PYTHONIOENCODING="ascii", LC_ALL="C", LANG="C")
    r = _hallcal("export-c", str(hostile), "--out", "f\u00fcr-fw", cwd=folder, env=env)
    assert r.returncode == 0, r.stderr
    assert "\\xfc" in r.stdout  # the name is written, escaped
    for p in (folder / "f\u00fcr-fw").iterdir():
        text = p.read_text(encoding="ascii")
        assert "#define X 1" not in _code(text)


# ------------------------------------------------------------------------------------------
# Optional sections: the anticogging feed-forward
# ------------------------------------------------------------------------------------------

COGGING = {
    "orders": [66, 132, 11, 1, 22],
    "a": [0.012, 0.003, 0.001, 0.0005, -0.0007],
    "b": [0.002, -0.001, 0.0, 0.0002, 0.0004],
    "std_a": [1e-4] * 5,
    "std_b": [1e-4] * 5,
    "unit": "plant input */ #define X",
}


def test_anticogging_section_matches_the_map(tmp_path, cal):
    """With "cogging" in the artifact the float variant gets hallcal_anticogging(angle):
    within 1e-6 of the map relative to its largest value, at any angle (reduced to one
    revolution); the fixed variant and an artifact without the key get nothing."""
    from hallcal.output.firmware import cogging_table
    from hallcal.sim.cogging import CoggingTorque

    art = copy.deepcopy(cal.artifact)
    art["cogging"] = COGGING
    res = export_c(art, tmp_path / "fw", source="cal.json")
    assert res.sections == ("anticogging",)
    h = (tmp_path / "fw" / "hallcal.h").read_text()
    assert "float hallcal_anticogging(float angle);" in h
    assert "#define X" not in _code(h + (tmp_path / "fw" / "hallcal.c").read_text())
    assert "anticogging" not in (tmp_path / "fw" / "hallcal_q.h").read_text()
    assert "anticogging" not in (work_plain := export_c(cal.artifact, tmp_path / "plain")).sections
    assert work_plain.sections == ()
    drv = tmp_path / "cog.c"
    drv.write_text(
        '#include <stdio.h>\n#include "hallcal.c"\n'
        "int main(void) { float a; while (fread(&a, sizeof a, 1, stdin) == 1) {\n"
        "  float t = hallcal_anticogging(a); fwrite(&t, sizeof t, 1, stdout); } return 0; }\n"
    )
    exe = tmp_path / "cog"
    subprocess.run([CC, *STRICT, "-O2", f"-I{tmp_path / 'fw'}", str(drv), "-o", str(exe)],
                   check=True, capture_output=True)  # fmt: skip
    rng = np.random.default_rng(9)
    y = np.concatenate([rng.uniform(0, TWO_PI, 200_000), rng.uniform(-50, 50, 20_000),
                        TWO_PI * np.arange(4096) / 4096]).astype(np.float32)  # fmt: skip
    out = subprocess.run([str(exe)], input=y.tobytes(), capture_output=True, check=True).stdout
    got = np.frombuffer(out, dtype=np.float32).astype(np.float64)
    ref = CoggingTorque(COGGING["orders"], COGGING["a"], COGGING["b"])(y.astype(np.float64))
    scale = float(np.max(np.abs(ref)))
    tab = cogging_table(COGGING)
    # the table itself: within 1e-6 of the map (relative to its largest value), exactly
    dense = np.linspace(0.0, TWO_PI, 2_000_001)
    table_rel = float(np.max(np.abs(tab.interpolate(dense) - tab.torque(dense)))) / tab.scale
    # the C: the table's cubic at the angle, within the single-precision position rounding
    # (2^-24 of a revolution; the reduction of angles outside [0, 2 pi) adds 2 more ulps of
    # the reduced angle) times the map's largest slope, plus 1e-7 of rounded sums
    inside = (y >= 0) & (y < TWO_PI)
    rounding = tab.slope * TWO_PI * 2.0**-24 * np.where(inside, 2.0, 6.0) + 1e-7 * scale
    excess = np.abs(got - ref) - (1e-6 * scale + rounding)
    worst = float(np.max(np.abs(got - ref)))
    print(f"anticogging: table {table_rel:.1e} relative; C - map max {worst:.2e} (scale "
          f"{scale:.3g}, slope {tab.slope:.3g})")  # fmt: skip
    assert table_rel <= 1e-6
    assert np.all(excess <= 0)
    # at the table's nodes (exact positions) the C gives the map within 1e-6 relative
    nodes = (TWO_PI * np.arange(tab.points) / tab.points).astype(np.float32)
    out = subprocess.run([str(exe)], input=nodes.tobytes(), capture_output=True, check=True).stdout
    at_nodes = np.frombuffer(out, dtype=np.float32).astype(np.float64)
    on = np.abs(at_nodes - tab.torque(nodes.astype(np.float64))) / tab.scale
    assert np.max(on) <= 1e-6 + tab.slope * TWO_PI * 2.0**-24 * 2 / tab.scale
    nan = np.array([np.nan, np.inf, -np.inf, 1e30], dtype=np.float32)
    out = subprocess.run([str(exe)], input=nan.tobytes(), capture_output=True, check=True).stdout
    assert np.all(np.isfinite(np.frombuffer(out, dtype=np.float32)))


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        ("orders", [-1, 1], "cogging.orders"),
        ("orders", [1, 1], "cogging.orders"),
        ("a", [1.0], "cogging.a"),
        ("b", "x", "cogging.b"),
        ("orders", list(range(1, 5000)), "cogging.orders"),
    ],
)
def test_malformed_cogging_is_refused(tmp_path, cal, key, value, named):
    art = copy.deepcopy(cal.artifact)
    art["cogging"] = dict(COGGING, **{key: value})
    with pytest.raises(HallcalInputError, match=re.escape(f"'{named}'")):
        export_c(art, tmp_path)
    assert not list(tmp_path.iterdir())
