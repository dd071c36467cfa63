"""Generated C (hallcal.output.codegen) compiled with the system C compiler, against Python f_star.

The driver below is compiled together with the generated sources (it includes the .c file, so the
static integer atan2 is reachable) in a temporary directory. It reads samples on stdin and writes
y_star on stdout (``run``), spins the motor 10^6 revolutions forward and back with exact synthetic
signals (``long``), feeds random and adversarial inputs (``fuzz``, also under ASan/UBSan) and
measures the integer atan2 (``atan``).
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from hallcal.errors import HallcalInputError
from hallcal.output.codegen import CORDIC_ITERATIONS, cordic_error_bound, export_c
from hallcal.sensor.flux import FluxModel, FourierBasis, sinusoidal_theta
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sensor.reconstruction import projection_matrix

TWO_PI = 2.0 * math.pi
CC = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc, gcc or clang) on PATH")

DRIVER = r"""/* Test driver for the generated sources: -DHC_Q=0 (float), -DHC_Q=1 (fixed). */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if HC_Q
#include "PFX_q.c"
typedef PFX_q_state st_t;
#else
#include "PFX.c"
typedef PFX_state st_t;
#endif

static uint64_t rng_state = 88172645463325252ull;
static uint64_t rnd(void) {
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return rng_state;
}
static double urand(void) { return (double)(rnd() >> 11) * (1.0 / 9007199254740992.0); }

static int fail(const char *what, long long k) {
    fprintf(stderr, "FAIL %s at %lld\n", what, k);
    return 1;
}

/* run: samples on stdin (float32 or int32 triples), outputs on stdout */
static int mode_run(const char *y0) {
    st_t s;
    long long k = 0;
#if HC_Q
    int32_t d[3];
    PFX_q_init(&s, strtoll(y0, NULL, 10));
    while (fread(d, sizeof d, 1, stdin) == 1) {
        uint32_t ret = PFX_q_update(&s, d[0], d[1], d[2]);
        int64_t full = PFX_q_angle_i64(&s);
        if (ret != (uint32_t)((uint64_t)full & 0xFFFFFFFFu) || ret != PFX_q_angle(&s))
            return fail("return != angle", k);
        fwrite(&full, sizeof full, 1, stdout);
        ++k;
    }
#else
    float d[3];
    PFX_init(&s, strtof(y0, NULL));
    while (fread(d, sizeof d, 1, stdin) == 1) {
        double out[2];
        out[0] = (double)PFX_update(&s, d[0], d[1], d[2]);
        out[1] = PFX_angle_f64(&s);
        if (!(PFX_angle_in_rev(&s) >= 0.0f && PFX_angle_in_rev(&s) < 6.2831855f))
            return fail("angle_in_rev out of range", k);
        fwrite(out, sizeof out, 1, stdout);
        ++k;
    }
#endif
    return 0;
}

/* long: fast spinning, exact positions pos_k = a k / b turns forward, then back */
static int mode_long(int argc, char **argv) {
    long long a, b, nfwd, ntot, every, k, an, rev, num, el;
    double amp, o[3], ph[3];
    int n, h;
    long long e;
    st_t s;
#if HC_Q
    int32_t *tab;
#else
    float *tab;
#endif
    if (argc < 15) return fail("usage", 0);
    a = atoll(argv[2]); b = atoll(argv[3]); nfwd = atoll(argv[4]); ntot = atoll(argv[5]);
    every = atoll(argv[6]); amp = atof(argv[7]); n = atoi(argv[8]);
    for (h = 0; h < 3; ++h) { o[h] = atof(argv[9 + h]); ph[h] = atof(argv[12 + h]); }
    tab = malloc(sizeof *tab * 3 * (size_t)b);
    if (!tab) return fail("malloc", 0);
    for (e = 0; e < b; ++e) {
        double th = 2.0 * 3.14159265358979323846 * (double)e / (double)b;
        for (h = 0; h < 3; ++h) {
            double v = o[h] + amp * cos(th - ph[h]);
#if HC_Q
            tab[3 * e + h] = (int32_t)llround(v);
#else
            tab[3 * e + h] = (float)v;
#endif
        }
    }
#if HC_Q
    PFX_q_init(&s, 0);
#else
    PFX_init(&s, 0.0f);
#endif
    an = (a * n) % b;
    rev = 0;
    num = 0;
    el = 0;
    for (k = 1; k <= ntot; ++k) {
        if (k <= nfwd) { /* forward: pos += a / b turn */
            num += a;
            if (num >= b) { num -= b; ++rev; }
            el += an;
            if (el >= b) el -= b;
        } else { /* backward */
            num -= a;
            if (num < 0) { num += b; --rev; }
            el -= an;
            if (el < 0) el += b;
        }
#if HC_Q
        PFX_q_update(&s, tab[3 * el], tab[3 * el + 1], tab[3 * el + 2]);
        if (k % every == 0 || k == ntot || k == nfwd)
            printf("%lld %lld %lld %ld %lu\n", k, rev, num, (long)PFX_q_revolutions(&s),
                   (unsigned long)PFX_q_angle(&s));
#else
        PFX_update(&s, tab[3 * el], tab[3 * el + 1], tab[3 * el + 2]);
        if (k % every == 0 || k == ntot || k == nfwd)
            printf("%lld %lld %lld %ld %.9g\n", k, rev, num, (long)PFX_revolutions(&s),
                   (double)PFX_angle_in_rev(&s));
#endif
    }
    free(tab);
    return 0;
}

#if HC_Q
static int32_t adversarial_i(void) {
    static const int32_t special[] = {0, 1, -1, 2147483647, -2147483647 - 1, 4095, 2048, 65535,
                                      -65536, 1 << 30, -(1 << 30)};
    uint64_t r = rnd();
    switch (r % 4) {
    case 0: return special[(r >> 8) % (sizeof special / sizeof special[0])];
    case 1: return (int32_t)(uint32_t)(rnd() >> 32);
    case 2: return (int32_t)((rnd() >> 40) % 4096);
    default: return (int32_t)((rnd() >> 40) % 1048576) - 524288;
    }
}
#else
static float adversarial_f(void) {
    static const float special[] = {0.0f, -0.0f, 1.0f, -1.0f, 3.4028235e38f, -3.4028235e38f,
                                    1e-45f, 1e30f, -1e30f, 2000.0f, 4095.0f};
    uint64_t r = rnd();
    uint32_t bits;
    float f;
    switch (r % 6) {
    case 0: return special[(r >> 8) % (sizeof special / sizeof special[0])];
    case 1: return INFINITY;
    case 2: return -INFINITY;
    case 3: return NAN;
    case 4:
        bits = (uint32_t)(rnd() >> 32);
        memcpy(&f, &bits, sizeof f);
        return f;
    default: return (float)(urand() * 4096.0);
    }
}
#endif

/* fuzz: random valid, adversarial and all-equal inputs; invariants checked on every sample */
static int mode_fuzz(long long count) {
    st_t s;
    long long k;
    for (k = 0; k < count; ++k) {
        uint64_t kind = rnd() % 8;
#if HC_Q
        int32_t d[3];
        uint32_t ret;
        if (k % 100000 == 0) PFX_q_init(&s, (int64_t)rnd());
        if (kind < 3) {
            double th = urand() * 6.283185307179586;
            d[0] = (int32_t)(2000 + 1500 * cos(th));
            d[1] = (int32_t)(2000 + 1500 * cos(th - 2.0943951));
            d[2] = (int32_t)(2000 + 1500 * cos(th - 4.1887902));
        } else if (kind == 3) {
            d[0] = d[1] = d[2] = adversarial_i();
        } else {
            d[0] = adversarial_i(); d[1] = adversarial_i(); d[2] = adversarial_i();
        }
        ret = PFX_q_update(&s, d[0], d[1], d[2]);
        if (ret != PFX_q_angle(&s)) return fail("q return", k);
        if (s.turn < 0 || s.turn >= HC_N) return fail("q turn", k);
#else
        float d[3];
        float ret;
        if (k % 100000 == 0) PFX_init(&s, (float)((urand() - 0.5) * 2e4));
        if (kind < 3) {
            double th = urand() * 6.283185307179586;
            d[0] = (float)(2000 + 1500 * cos(th));
            d[1] = (float)(2000 + 1500 * cos(th - 2.0943951));
            d[2] = (float)(2000 + 1500 * cos(th - 4.1887902));
        } else if (kind == 3) {
            d[0] = d[1] = d[2] = adversarial_f();
        } else {
            d[0] = adversarial_f(); d[1] = adversarial_f(); d[2] = adversarial_f();
        }
        ret = PFX_update(&s, d[0], d[1], d[2]);
        if (!isfinite(ret)) return fail("non-finite output", k);
        if (!(PFX_angle_in_rev(&s) >= 0.0f && PFX_angle_in_rev(&s) < 6.2831855f))
            return fail("angle_in_rev range", k);
        if (!isfinite(s.psi) || s.turn < 0 || s.turn >= HC_N) return fail("state", k);
#endif
    }
#if HC_Q
    printf("ok %lu\n", (unsigned long)PFX_q_rejected(&s));
#else
    printf("ok %lu\n", (unsigned long)PFX_rejected(&s));
#endif
    return 0;
}

#if HC_Q
/* atan: worst-case error of the integer atan2 against double atan2 */
static int mode_atan(long long count) {
    double worst = 0.0, worst_a = 0, worst_b = 0;
    long long k;
    for (k = 0; k < count; ++k) {
        int64_t A, B;
        uint32_t z;
        double ref, got, err;
        int scale = (int)(rnd() % 62);
        if (k < 4096) { /* a sweep of directions at full scale */
            double th = 6.283185307179586 * (double)k / 4096.0;
            A = (int64_t)llround(cos(th) * 4.0e18);
            B = (int64_t)llround(sin(th) * 4.0e18);
        } else if (k % 3 == 0) { /* small integers: exact inputs */
            A = (int64_t)(rnd() % 2001) - 1000;
            B = (int64_t)(rnd() % 2001) - 1000;
        } else {
            A = (int64_t)(rnd() >> 2) >> scale;
            B = (int64_t)(rnd() >> 2) >> scale;
            if (rnd() & 1) A = -A;
            if (rnd() & 1) B = -B;
        }
        if (!hc_atan2_q(A, B, &z)) {
            if (A != 0 || B != 0) return fail("atan zero", k);
            continue;
        }
        ref = atan2((double)B, (double)A);
        got = (double)z * (6.283185307179586 / 4294967296.0);
        err = remainder(got - ref, 6.283185307179586);
        if (fabs(err) > worst) { worst = fabs(err); worst_a = (double)A; worst_b = (double)B; }
    }
    printf("%.6e %.17g %.17g\n", worst, worst_a, worst_b);
    return 0;
}
#endif

int main(int argc, char **argv) {
    if (argc < 2) return fail("usage", 0);
    if (!strcmp(argv[1], "run")) return mode_run(argc > 2 ? argv[2] : "0");
    if (!strcmp(argv[1], "long")) return mode_long(argc, argv);
    if (!strcmp(argv[1], "fuzz")) return mode_fuzz(atoll(argv[2]));
#if HC_Q
    if (!strcmp(argv[1], "atan")) return mode_atan(atoll(argv[2]));
#endif
    return fail("unknown mode", 0);
}
"""

STRICT = ["-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Wconversion", "-Wshadow", "-Werror"]
SANITIZE = ["-O1", "-g", "-fsanitize=address,undefined", "-fno-sanitize-recover=all"]


# ------------------------------------------------------------------------------------------
# Calibrations and data
# ------------------------------------------------------------------------------------------


class Calibration:
    """A calibration as the pipeline would produce it, with the truth it came from."""

    def __init__(self, *, n, points, amplitude, offset, seed, trapezoid, adc_scale=1.0):
        rng = np.random.default_rng(seed)
        harmonics = sorted(set(range(1, n + 2)) | {2 * n, 3 * n, 5 * n})
        basis = FourierBasis(tuple(harmonics))
        phases = np.array([0.0, TWO_PI / 3 + 0.03, 2 * TWO_PI / 3 - 0.02])
        offset = np.asarray(offset, float)
        gains = amplitude * np.array([1.0, 0.99, 1.02])
        theta = sinusoidal_theta(basis, n, amplitude=gains, offset=offset, phases=phases)
        for h in harmonics:
            if h in (n, 3 * n, 5 * n):
                continue
            js, jc = basis.index(h)
            theta[:, [js, jc]] += rng.normal(0, 0.02 * amplitude / 4, (3, 2))
        for k, c in ((3, 0.05 * trapezoid), (5, 0.02 * trapezoid)):
            js, jc = basis.index(k * n)
            theta[:, jc] += c * amplitude * np.cos(k * phases)
            theta[:, js] += c * amplitude * np.sin(k * phases)
        self.truth = FluxModel(basis, theta)
        self.n = n
        # f_init of the calibration: unequal projection and slightly wrong offsets
        self.proj_phases = phases + np.array([0.0, 0.01, -0.005])
        P = projection_matrix(self.proj_phases)
        o_est = offset + amplitude * np.array([3e-4, -2e-4, 1e-4])
        lut = build_lut(self.truth, n, points=points, projection=P, offset=o_est)
        assert lut.bijective
        self.lut = LUT.from_arrays(n, P, o_est, lut.y_hat, lut.eta)
        self.adc_scale = adc_scale
        self.artifact = {
            "format": "hallcal-calibration/1",
            "pole_pairs": n,
            "reconstruction": {"projection": P.tolist(), "offset": o_est.tolist()},
            "lut": {"y_hat": lut.y_hat.tolist(), "eta": lut.eta.tolist(), "points": points},
            "model": {"basis": "fourier", "harmonics": harmonics, "theta": theta.tolist()},
            "setup": {"pole_pairs": n},
            "diagnostics": {"bijective": True},
        }

    def recording(self, n_samples, *, noise, seed, y_start=0.0):
        """Recorded-like data: several revolutions both ways, wobble, noise, ADC rounding.

        Returns the samples in ADC counts (integers, as float64).
        """
        k = np.arange(n_samples)
        y0 = (
            y_start
            + 14.0 * np.sin(TWO_PI * 1.5 * k / n_samples)
            + 0.3 * np.sin(TWO_PI * k / 700.0)
            + 0.02 * np.sin(TWO_PI * k / 37.0)
        )
        rng = np.random.default_rng(seed)
        d = self.truth(y0) + rng.normal(0.0, noise, (n_samples, 3))
        return np.round(d * self.adc_scale)


def compile_driver(workdir: Path, prefix: str, *, fixed: bool, flags=(), name=None) -> Path:
    src = workdir / f"drv_{prefix}.c"
    if not src.exists():
        src.write_text(DRIVER.replace("PFX", prefix))
    exe = workdir / (name or f"drv_{prefix}_{'q' if fixed else 'f'}")
    cmd = [CC, "-std=c99", *flags, f"-DHC_Q={int(fixed)}", f"-I{workdir}", str(src), "-o"]
    subprocess.run([*cmd, str(exe), "-lm"], check=True, capture_output=True, text=True)
    return exe


def run_float(exe: Path, d: np.ndarray, y_initial: float = 0.0) -> np.ndarray:
    out = subprocess.run(
        [str(exe), "run", repr(float(y_initial))],
        input=np.ascontiguousarray(d, dtype=np.float32).tobytes(),
        capture_output=True,
        check=True,
    ).stdout
    return np.frombuffer(out, dtype=np.float64).reshape(-1, 2)


def run_fixed(exe: Path, d: np.ndarray, y_initial_q: int = 0) -> np.ndarray:
    out = subprocess.run(
        [str(exe), "run", str(int(y_initial_q))],
        input=np.ascontiguousarray(d, dtype=np.int32).tobytes(),
        capture_output=True,
        check=True,
    ).stdout
    q = np.frombuffer(out, dtype=np.int64)
    return TWO_PI * (q // 2**32) + TWO_PI * ((q % 2**32) / 2**32)


def sanitizer_flags() -> list[str]:
    """ASan + UBSan (+ float-cast-overflow where the compiler has it), or skip."""
    probe = Path(os.environ.get("TMPDIR", "/tmp"))
    for extra in (["-fsanitize=float-cast-overflow"], []):
        flags = [*SANITIZE, *extra]
        r = subprocess.run(
            [CC, *flags, "-x", "c", "-", "-o", os.devnull],
            input="int main(void){return 0;}",
            capture_output=True,
            text=True,
            cwd=probe,
        )
        if r.returncode == 0:
            return flags
    pytest.skip(f"{CC} cannot build with -fsanitize=address,undefined")


@pytest.fixture(scope="module")
def cal() -> Calibration:
    # raw-ADC-like: offsets ~2000 counts, amplitude ~1500, trapezoidal flux, n_m = 11, M = 4096
    return Calibration(
        n=11, points=4096, amplitude=1500.0, offset=[2000.3, 1990.1, 2010.7], seed=3, trapezoid=1
    )


@pytest.fixture(scope="module")
def work(tmp_path_factory, cal):
    d = tmp_path_factory.mktemp("codegen")
    res = export_c(cal.artifact, d, source="cal.json")
    return d, res


@pytest.fixture(scope="module")
def exe_f(work):
    return compile_driver(work[0], "hallcal", fixed=False, flags=["-O2"])


@pytest.fixture(scope="module")
def exe_q(work):
    return compile_driver(work[0], "hallcal", fixed=True, flags=["-O2"])


@pytest.fixture(scope="module")
def data(cal):
    d = cal.recording(120_000, noise=3.0, seed=1)
    return d, cal.lut.f_star(d)


# ------------------------------------------------------------------------------------------
# Files, API, C99 hygiene
# ------------------------------------------------------------------------------------------


def test_files_comments_and_result(work, cal):
    d, res = work
    names = [p.name for p in res.paths]
    assert names == ["hallcal.h", "hallcal.c", "hallcal_q.h", "hallcal_q.c"]
    assert res.status == "ok" and res.messages == ()
    assert sorted(p.name for p in d.iterdir() if p.name.startswith(".")) == []  # no temp files
    assert res.points == 4096 and res.pole_pairs == 11 and res.max_search_steps <= 3
    assert res.float_bound < 1e-5 and res.fixed_bound < res.float_bound
    assert res.atan2_bound == pytest.approx(cordic_error_bound(CORDIC_ITERATIONS))
    for p in res.paths:
        text = p.read_text()
        assert "Source artifact : cal.json" in text and res.sha256 in text
        assert "Pole pairs n_m  : 11" in text and "M = 4096" in text
        assert "error bound" in text.lower()
    h = (d / "hallcal.h").read_text()
    assert "void hallcal_init(hallcal_state *s, float y_initial);" in h
    assert "float hallcal_update(hallcal_state *s, float d1, float d2, float d3);" in h
    hq = (d / "hallcal_q.h").read_text()
    assert "void hallcal_q_init(hallcal_q_state *s, int64_t y_initial);" in hq
    assert (
        "uint32_t hallcal_q_update(hallcal_q_state *s, int32_t d1, int32_t d2, int32_t d3);" in hq
    )
    for p in res.paths:  # only <stdint.h> and <math.h>, no dynamic memory
        includes = set(re.findall(r'#include [<"]([^>"]+)[>"]', p.read_text()))
        assert includes <= {"stdint.h", "math.h", "hallcal.h", "hallcal_q.h"}
        code = re.sub(r"/\*.*?\*/", "", p.read_text(), flags=re.S)
        assert not re.search(r"\b(malloc|calloc|free|realloc)\b", code)
    code_q = re.sub(r"/\*.*?\*/", "", (d / "hallcal_q.c").read_text(), flags=re.S)
    assert not re.search(r"\b(float|double)\b|math\.h", code_q)
    assert res.table_bytes > 8 * 4096 and res.table_bytes_q > res.table_bytes


def test_strict_c99_and_symbols(work):
    d, _ = work
    for name in ("hallcal.c", "hallcal_q.c"):
        obj = d / (name[:-2] + ".o")
        subprocess.run(
            [CC, *STRICT, "-Wdouble-promotion", "-O2", "-c", str(d / name), "-o", str(obj)],
            check=True,
            capture_output=True,
            text=True,
        )
        nm = shutil.which("nm")
        if nm:
            und = subprocess.run([nm, "-u", str(obj)], capture_output=True, text=True).stdout
            syms = {line.split()[-1] for line in und.splitlines() if line.strip()}
            allowed = {"atan2f", "floor"} if name == "hallcal.c" else set()
            assert syms <= allowed, syms
    # the fixed-point variant must not need an FPU at all (x86 and ARM GCC know this flag)
    r = subprocess.run(
        [CC, "-std=c99", "-O2", "-mgeneral-regs-only", "-c", str(d / "hallcal_q.c"), "-o",
         os.devnull],
        capture_output=True,
        text=True,
    )  # fmt: skip
    if "unrecognized" not in r.stderr and "unknown argument" not in r.stderr:
        assert r.returncode == 0, r.stderr


# ------------------------------------------------------------------------------------------
# Agreement with the Python f_star
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("y_start", [0.0, -7.9])
def test_float_matches_python(work, cal, exe_f, y_start):
    _, res = work
    if y_start == 0.0:
        d = cal.recording(120_000, noise=3.0, seed=1)
    else:
        d = cal.recording(30_000, noise=3.0, seed=2, y_start=y_start)
    y_init = float(np.float32(y_start))
    ys = cal.lut.f_star(d, y_initial=y_init)
    out = run_float(exe_f, d, y_init)
    assert out.shape == (len(d), 2)
    err_ret = np.max(np.abs(out[:, 0] - ys))
    err_rev = np.max(np.abs(out[:, 1] - ys))
    print(f"float: max |returned - python| {err_ret:.2e}, |rev+angle - python| {err_rev:.2e}")
    assert err_ret <= 1e-5
    assert err_rev <= res.float_bound
    assert np.ptp(ys) > 4 * TWO_PI  # several revolutions, both directions
    assert np.any(np.diff(ys) > 0) and np.any(np.diff(ys) < 0)


@pytest.mark.parametrize("y_start", [0.0, -7.9])
def test_fixed_matches_python(work, cal, exe_q, y_start):
    _, res = work
    if y_start == 0.0:
        d = cal.recording(120_000, noise=3.0, seed=1)
    else:
        d = cal.recording(30_000, noise=3.0, seed=2, y_start=y_start)
    y_init_q = round(y_start / TWO_PI * 2**32)
    ys = cal.lut.f_star(d, y_initial=y_init_q * TWO_PI / 2**32)
    yq = run_fixed(exe_q, d, y_init_q)
    err = np.max(np.abs(yq - ys))
    print(f"fixed: max |y_q - python| {err:.2e} rad (stated bound {res.fixed_bound:.2e})")
    assert err <= res.fixed_bound


def test_other_calibration_volts_prefix_and_slow_search(tmp_path):
    """n_m = 4, M = 300 (not a power of two), signals in volts with an ADC scale, a custom
    prefix, and a small bucket table so that the node search takes many steps."""
    adc = 4096 / 3.3
    c = Calibration(
        n=4, points=300, amplitude=1.0, offset=[1.65, 1.62, 1.67], seed=5, trapezoid=0.5,
        adc_scale=adc,
    )  # fmt: skip
    res = export_c(c.artifact, tmp_path, prefix="motor2", buckets=16, adc_scale=adc)
    assert [p.name for p in res.paths] == ["motor2.h", "motor2.c", "motor2_q.h", "motor2_q.c"]
    assert res.max_search_steps > 8 and res.status == "warning"
    counts = c.recording(40_000, noise=2e-3, seed=7)
    volts = counts / adc
    ys = c.lut.f_star(volts)
    out = run_float(compile_driver(tmp_path, "motor2", fixed=False, flags=["-O2"]), volts)
    assert np.max(np.abs(out[:, 0] - ys)) <= 1e-5
    assert np.max(np.abs(out[:, 1] - ys)) <= res.float_bound
    yq = run_fixed(compile_driver(tmp_path, "motor2", fixed=True, flags=["-O2"]), counts)
    assert np.max(np.abs(yq - ys)) <= res.fixed_bound


def test_float_only_export(tmp_path, cal):
    res = export_c(cal.artifact, tmp_path, fixed_point=False)
    assert [p.name for p in res.paths] == ["hallcal.h", "hallcal.c"]
    assert res.fixed_bound is None and res.table_bytes_q is None


# ------------------------------------------------------------------------------------------
# Long run: 10^6 revolutions
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fixed", [False, True])
def test_million_revolutions(work, cal, exe_f, exe_q, fixed):
    """Spin 10^6 revolutions forward (0.47 electrical turn per sample), then 5e4 back, with
    exact synthetic signals; checkpoints compare with the exact expected y_star."""
    _, res = work
    a, b = 428, 10007  # position k a / b turn: exact rational bookkeeping in the driver
    nfwd = 10**6 * b // a
    ntot = nfwd + 50_000 * b // a
    # integers for the fixed variant: a large amplitude keeps the ADC rounding at 1e-8 rad
    amp = 2.0**22 if fixed else 1500.0
    args = [str(exe_q if fixed else exe_f), "long", str(a), str(b), str(nfwd), str(ntot)]
    args += [str(100_000), repr(amp), str(cal.n)]
    args += [repr(float(v)) for v in cal.lut.offset] + [repr(float(v)) for v in cal.proj_phases]
    lines = subprocess.run(args, capture_output=True, text=True, check=True).stdout.split("\n")
    tab = np.array([[float(v) for v in line.split()] for line in lines if line])
    k, rev, num, rev_c, frac_c = tab.T
    assert rev.max() >= 10**6 - 1 and rev[-1] < 10**6 - 40_000
    frac = TWO_PI * num / b
    expected = frac + cal.lut.correction(frac)  # f_init is exact on these signals
    got = frac_c * (TWO_PI / 2**32) if fixed else frac_c
    err = np.abs((rev_c - rev) * TWO_PI + (got - expected))
    bound = res.fixed_bound if fixed else res.float_bound
    quantization = 1e-7  # ADC rounding of the synthetic signals
    print(f"{'fixed' if fixed else 'float'} after 1e6 revolutions: max error {err.max():.2e} rad")
    assert err.max() <= bound + quantization


# ------------------------------------------------------------------------------------------
# Integer atan2, sanitizers, NaN handling
# ------------------------------------------------------------------------------------------


def test_integer_atan2_bound(exe_q, work):
    _, res = work
    out = subprocess.run([str(exe_q), "atan", "2000000"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    worst = float(out.stdout.split()[0])
    print(f"integer atan2: measured max error {worst:.2e} rad, stated {res.atan2_bound:.2e}")
    assert worst <= res.atan2_bound < 1e-6


@pytest.mark.parametrize("fixed", [False, True])
def test_sanitizers_random_and_adversarial(work, cal, data, fixed):
    wd, _ = work
    flags = sanitizer_flags()
    if fixed:
        flags = [*flags, "-DHALLCAL_PORTABLE"]  # also the portable bit-length fallback
    exe = compile_driver(wd, "hallcal", fixed=fixed, flags=flags, name=f"san_{int(fixed)}")
    env = dict(os.environ, UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1")
    out = subprocess.run([str(exe), "fuzz", "1000000"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.startswith("ok")
    # the sanitized (and, fixed, portable) build gives the same output as the -O2 build
    d, ys = data
    seg = d[:20_000]
    if fixed:
        assert np.max(np.abs(run_fixed(exe, seg) - ys[:20_000])) <= work[1].fixed_bound
    else:
        assert np.max(np.abs(run_float(exe, seg)[:, 1] - ys[:20_000])) <= work[1].float_bound


def test_nan_and_inf_samples_hold_the_estimate(exe_f, data):
    """A sample without angle information is skipped: the output holds the last estimate and
    the samples after it give exactly what they give without the bad sample."""
    d, _ = data
    clean = d[:5000].astype(np.float32)
    bad_at = np.arange(100, 5000, 97)
    bad_values = [np.nan, np.inf, -np.inf]
    dirty = clean.copy()
    for i, j in enumerate(bad_at):
        dirty[j, i % 3] = bad_values[i % 3]
    dirty[2000:2050] = np.nan  # a burst on all channels
    bad_at = np.union1d(bad_at, np.arange(2000, 2050))
    keep = np.setdiff1d(np.arange(len(dirty)), bad_at)
    out_dirty = run_float(exe_f, dirty)
    out_clean = run_float(exe_f, dirty[keep])
    assert np.all(np.isfinite(out_dirty))
    np.testing.assert_array_equal(out_dirty[keep], out_clean)
    assert np.all(out_dirty[bad_at, 1] == out_dirty[bad_at - 1, 1])


# ------------------------------------------------------------------------------------------
# Bad artifacts
# ------------------------------------------------------------------------------------------


def _broken(artifact, path, value):
    art = {k: (dict(v) if isinstance(v, dict) else v) for k, v in artifact.items()}
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
        ("format", "hallcal-calibration/0", "format"),
        ("pole_pairs", KeyError, "pole_pairs"),
        ("pole_pairs", 0, "pole_pairs"),
        ("reconstruction.offset", [1.0, 2.0], "reconstruction.offset"),
        ("reconstruction.projection", [[1, 0, 0], [2, 0, 0]], "reconstruction.projection"),
        ("lut.eta", KeyError, "lut.eta"),
        ("lut.points", 17, "lut.points"),
        ("lut.y_hat", [0.0, 1.0, float("nan"), 3.0], "lut.y_hat"),
    ],
)
def test_bad_artifact_names_the_key(tmp_path, cal, path, value, named):
    with pytest.raises(HallcalInputError, match=re.escape(f"'{named}'")):
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


def test_bad_prefix(tmp_path, cal):
    with pytest.raises(HallcalInputError, match="C identifier"):
        export_c(cal.artifact, tmp_path, prefix="my-motor")
