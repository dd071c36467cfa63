"""Test support for the generated firmware: calibrations, a host C driver, signal generators.

Used by ``tests/test_codegen.py``, ``tests/test_codegen_arm.py`` and
``benchmarks/bench_codegen.py``. The driver (``DRIVER``) is compiled together with the generated
source (it includes the ``.c`` file, so the static atan2 is reachable) and works on binary files
or pipes:

* ``run [block]``: samples (N x 3, float32 or int32) on stdin; for each, ``update`` and ``read``;
  the reading (revolutions, angle bits, flags) as 3 uint32 on stdout. With ``block`` > 0 the
  state is re-initialised to (0, 0) every ``block`` samples.
* ``angle``: vectors (a, b) (float32 or int32 pairs) on stdin; the atan2 (uint32) on stdout.
* ``long a b nfwd ntot every amp n o1 o2 o3 ph1 ph2 ph3``: exact rational positions for 10^6
  revolutions forward then back; checkpoints as text.
* ``fuzz count``: random and adversarial inputs, invariants checked on every sample.
* ``isr mode count [block]``: the snapshot under interruption (POSIX interval timer): ``mode``
  0 runs ``update`` in the signal handler and ``read`` in the main loop (re-initialising every
  ``block`` samples, never during a read: init restarts the sequence counter), 1 the other way
  round (the main loop re-initialising), 2 the main loop takes the revolutions and the
  angle from two reads (a deliberately torn reader, to show that the test sees tearing).
  Samples come from stdin (as for ``run``); every pair read is written out.

With the power-up decoder (the header defines ``<PREFIX>_POWERUP``) ``init`` takes no angle, the
flags word of ``run`` also carries ``pole_pair << 16 | identified << 31``, ``isr`` writes that
word as a third one, and two more modes exist: ``lam [block]`` (as ``run``, then the decoder's
Lambda_j as n floats after each sample) and ``lock`` (Lambda vectors in, the generated lock rule
out, one byte each).

:class:`PowerUps` simulates power-ups on the paper bench as ``benchmarks/bench_powerup.py`` does
(closed loop from a random rotor angle, f_init from y = 0), and :func:`bench_artifact` makes the
artifact of a bench motor calibrated exactly (its true flux as the model, its noise as sigma).
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np

from hallcal._constants import TWO_PI
from hallcal.sensor.flux import FluxModel, FourierBasis, sinusoidal_theta
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sensor.reconstruction import projection_matrix

CC = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
STRICT = [
    "-std=c99", "-Wall", "-Wextra", "-Wpedantic", "-Wconversion", "-Wshadow",
    "-Wdouble-promotion", "-Wfloat-equal", "-Wcast-qual", "-Wundef", "-Werror",
]  # fmt: skip

DRIVER = r"""/* Host test driver for the generated sources: -DHC_Q=0 (float), -DHC_Q=1 (fixed). */
#define _POSIX_C_SOURCE 200809L
#include <math.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/time.h>

#if HC_Q
#include "PFX_q.c"
typedef PFX_q_state st_t;
typedef PFX_q_reading rd_t;
typedef int32_t in_t;
#define INIT(s) PFX_q_init((s))
#define SET_ANGLE(s, a) PFX_q_set_angle((s), 0, (uint32_t)(a))
#define UPDATE PFX_q_update
#define READ PFX_q_read
#define ANGLE_BITS(r) ((r).angle)
#else
#include "PFX.c"
typedef PFX_state st_t;
typedef PFX_reading rd_t;
typedef float in_t;
#define INIT(s) PFX_init((s))
#define SET_ANGLE(s, a) PFX_set_angle((s), 0, (a))
#define UPDATE PFX_update
#define READ PFX_read
static uint32_t fbits(float f) { uint32_t u; memcpy(&u, &f, sizeof u); return u; }
#define ANGLE_BITS(r) fbits((r).angle)
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

static in_t *read_samples(long *count) {
    size_t cap = 1 << 16, n = 0;
    in_t *buf = malloc(cap * 3 * sizeof(in_t));
    while (buf && fread(buf + 3 * n, 3 * sizeof(in_t), 1, stdin) == 1) {
        if (++n == cap) {
            cap *= 2;
            buf = realloc(buf, cap * 3 * sizeof(in_t));
        }
    }
    *count = (long)n;
    return buf;
}

static int mode_run(long block) {
    st_t s;
    rd_t r;
    in_t d[3];
    long k = 0;
    INIT(&s);
    while (fread(d, sizeof d, 1, stdin) == 1) {
        uint32_t out[3], fl;
        if (block > 0 && k > 0 && k % block == 0) INIT(&s);
        fl = UPDATE(&s, d[0], d[1], d[2]);
        READ(&s, &r);
        if ((fl & 0xFFFFu) != r.flags) return fail("returned flags != read flags", k);
        out[0] = (uint32_t)r.revolutions;
        out[1] = ANGLE_BITS(r);
        out[2] = r.flags;
#if !HC_Q && defined(UPFX_POWERUP)
        out[2] |= (r.pole_pair << 16) | (r.identified << 31);
#endif
        fwrite(out, sizeof out, 1, stdout);
        ++k;
    }
    return 0;
}

/* trials n homed: per trial a header (3 inputs: the start angle first, float rad or Q0.32
 * turns as int32 bits) and n samples; init (and, with homed = 1, set_angle to the start) before
 * each; out per trial: the last reading (revolutions, angle bits, flags) and the OR of the
 * flags of all its samples */
static int mode_trials(long n, int homed, int every) {
    st_t s;
    rd_t r;
    in_t d[3];
    for (;;) {
        uint32_t out[4] = {0u, 0u, 0u, 0u};
        long k;
        if (fread(d, sizeof d, 1, stdin) != 1) break;
        INIT(&s);
        if (homed) (void)SET_ANGLE(&s, d[0]);
        for (k = 0; k < n; ++k) {
            if (fread(d, sizeof d, 1, stdin) != 1) return fail("short trial", k);
            out[3] |= UPDATE(&s, d[0], d[1], d[2]);
            if (every) {
                uint32_t w[4];
                READ(&s, &r);
                w[0] = (uint32_t)r.revolutions;
                w[1] = ANGLE_BITS(r);
                w[2] = r.flags;
                w[3] = out[3];
                fwrite(w, sizeof w, 1, stdout);
            }
        }
        READ(&s, &r);
        out[0] = (uint32_t)r.revolutions;
        out[1] = ANGLE_BITS(r);
        out[2] = r.flags;
        if (!every) fwrite(out, sizeof out, 1, stdout);
    }
    return 0;
}

#if !HC_Q && defined(UPFX_POWERUP)
/* lam: as run, then the decoder's Lambda_j (n floats) after each sample */
static int mode_lam(long block) {
    st_t s;
    rd_t r;
    in_t d[3];
    long k = 0;
    INIT(&s);
    while (fread(d, sizeof d, 1, stdin) == 1) {
        uint32_t out[3];
        if (block > 0 && k > 0 && k % block == 0) INIT(&s);
        (void)UPDATE(&s, d[0], d[1], d[2]);
        READ(&s, &r);
        out[0] = (uint32_t)r.revolutions;
        out[1] = ANGLE_BITS(r);
        out[2] = r.flags | (r.pole_pair << 16) | (r.identified << 31);
        fwrite(out, sizeof out, 1, stdout);
        fwrite(s.lam, sizeof s.lam, 1, stdout);
        ++k;
    }
    return 0;
}

/* lock: Lambda vectors (n floats each, the smallest 0) on stdin; the generated lock rule on
 * each, 1 byte out per vector */
static int mode_lock(void) {
    float v[UPFX_POLE_PAIRS];
    while (fread(v, sizeof v, 1, stdin) == 1) {
        unsigned j, best = 0u;
        unsigned char out;
        for (j = 1u; j < UPFX_POLE_PAIRS; ++j) if (v[j] < v[best]) best = j;
        out = (unsigned char)hc_lock_rule(v, best);
        fwrite(&out, 1, 1, stdout);
    }
    return 0;
}
#endif

static int mode_angle(void) {
    in_t v[2];
    while (fread(v, sizeof v, 1, stdin) == 1) {
        uint32_t p = hc_angle(v[0], v[1]);
        fwrite(&p, sizeof p, 1, stdout);
    }
    return 0;
}

/* long: fast spinning, exact positions pos_k = a k / b turns forward, then back */
static int mode_long(int argc, char **argv) {
    long long a, b, nfwd, ntot, every, k, an, rev, num, el, e;
    double amp, o[3], ph[3];
    int n, h;
    st_t s;
    rd_t r;
    in_t *tab;
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
    INIT(&s);
    an = (a * n) % b;
    rev = num = el = 0;
    for (k = 1; k <= ntot; ++k) {
        if (k <= nfwd) {
            num += a; if (num >= b) { num -= b; ++rev; }
            el += an; if (el >= b) el -= b;
        } else {
            num -= a; if (num < 0) { num += b; --rev; }
            el -= an; if (el < 0) el += b;
        }
        if (UPDATE(&s, tab[3 * el], tab[3 * el + 1], tab[3 * el + 2]) != 0u)
            return fail("sample rejected", k);
        if (k % every == 0 || k == ntot || k == nfwd) {
            READ(&s, &r);
            printf("%lld %lld %lld %ld %lu\n", k, rev, num, (long)r.revolutions,
                   (unsigned long)ANGLE_BITS(r));
        }
    }
    free(tab);
    return 0;
}

#if HC_Q
static int32_t adversarial(void) {
    static const int32_t special[] = {0, 1, -1, 2147483647, -2147483647 - 1, 4095, 2048, 65535,
                                      -65536, 1 << 30, -(1 << 30)};
    uint64_t q = rnd();
    switch (q % 4) {
    case 0: return special[(q >> 8) % (sizeof special / sizeof special[0])];
    case 1: return (int32_t)(uint32_t)(rnd() >> 32);
    case 2: return (int32_t)((rnd() >> 40) % 4096);
    default: return (int32_t)((rnd() >> 40) % 1048576) - 524288;
    }
}
#else
static float adversarial(void) {
    static const float special[] = {0.0f, -0.0f, 1.0f, -1.0f, 3.4028235e38f, -3.4028235e38f,
                                    1e-45f, 1e30f, -1e30f, 2000.0f, 4095.0f};
    uint64_t q = rnd();
    uint32_t bits;
    float f;
    switch (q % 6) {
    case 0: return special[(q >> 8) % (sizeof special / sizeof special[0])];
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

/* fuzz: random valid, adversarial and all-equal inputs; invariants on every sample */
static int mode_fuzz(long long count) {
    st_t s;
    rd_t r, last;
    long long k;
    INIT(&s);
    READ(&s, &last);
    for (k = 0; k < count; ++k) {
        uint64_t kind = rnd() % 8;
        in_t d[3];
        uint32_t fl;
        if (k % 100000 == 0) INIT(&s);
        if (kind < 3) {
            double th = urand() * 6.283185307179586;
            d[0] = (in_t)(2000 + 1500 * cos(th));
            d[1] = (in_t)(2000 + 1500 * cos(th - 2.0943951));
            d[2] = (in_t)(2000 + 1500 * cos(th - 4.1887902));
        } else if (kind == 3) {
            d[0] = d[1] = d[2] = adversarial();
        } else {
            d[0] = adversarial(); d[1] = adversarial(); d[2] = adversarial();
        }
        fl = UPDATE(&s, d[0], d[1], d[2]);
        READ(&s, &r);
        if (fl != r.flags) return fail("flags", k);
        if ((fl & 1u) != 0u && k % 100000 != 0) {
            if (r.revolutions != last.revolutions || ANGLE_BITS(r) != ANGLE_BITS(last))
                return fail("a rejected sample changed the reading", k);
        }
        if (s.turn < 0 || s.turn >= HC_N_FOR_TEST) return fail("turn", k);
#if !HC_Q
        if (!(r.angle >= 0.0f && r.angle < 6.2831855f)) return fail("angle range", k);
#endif
        last = r;
    }
    printf("ok %lu\n", (unsigned long)s.rejected);
    return 0;
}

/* isr: one side in a signal handler (an interrupt), the other in the main loop. Each read is
 * written as ISR_WORDS words: revolutions, angle bits and, with the power-up decoder, its
 * identification (pole_pair << 16 | identified << 31). In mode 0 the interrupt re-initialises
 * the state every isr_block samples (0: never), so that many power-ups are read. */
#if !HC_Q && defined(UPFX_POWERUP)
#define ISR_WORDS 3
#define ISR_IDENT(r) (((r).pole_pair << 16) | ((r).identified << 31))
#else
#define ISR_WORDS 2
#define ISR_IDENT(r) 0u
#endif
static long isr_block;
static volatile int isr_in_read; /* the main loop is inside a read (mode 0) */
static st_t isr_state;
static in_t *isr_samples;
static long isr_count;
static volatile long isr_next;
static volatile int isr_mode;
static uint32_t *isr_pairs;
static volatile long isr_npairs;
static long isr_cap;

static void isr_handler(int sig) {
    (void)sig;
    if (isr_mode == 1) { /* the reader is the interrupt */
        rd_t r;
        READ(&isr_state, &r);
        if (isr_npairs < isr_cap) {
            isr_pairs[ISR_WORDS * isr_npairs] = (uint32_t)r.revolutions;
            isr_pairs[ISR_WORDS * isr_npairs + 1] = ANGLE_BITS(r);
            if (ISR_WORDS > 2) isr_pairs[ISR_WORDS * isr_npairs + ISR_WORDS - 1] = ISR_IDENT(r);
            isr_npairs = isr_npairs + 1;
        }
    } else if (isr_next < isr_count) { /* the writer is the interrupt */
        long k = isr_next;
        if (isr_block > 0 && k > 0 && k % isr_block == 0) {
            /* init restarts the sequence counter: not while a read is under way (a reader
             * stalled across a whole block could see the same count again) */
            if (isr_in_read) return;
            INIT(&isr_state);
        }
        (void)UPDATE(&isr_state, isr_samples[3 * k], isr_samples[3 * k + 1],
                     isr_samples[3 * k + 2]);
        isr_next = k + 1;
    }
}

static int mode_isr(int mode, long reads, long block) {
    struct sigaction sa;
    struct itimerval it;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = isr_handler;
    sigaction(SIGALRM, &sa, NULL);
    isr_samples = read_samples(&isr_count);
    isr_cap = reads;
    isr_block = block;
    isr_pairs = malloc(sizeof(uint32_t) * ISR_WORDS * (size_t)isr_cap);
    if (!isr_samples || !isr_pairs) return fail("malloc", 0);
    INIT(&isr_state);
    isr_mode = mode;
    memset(&it, 0, sizeof it);
    it.it_interval.tv_usec = 10;
    it.it_value.tv_usec = 10;
    setitimer(ITIMER_REAL, &it, NULL);
    if (mode == 1) { /* main loop writes, with a pause between samples as an ISR has */
        long k;
        for (k = 0; k < isr_count && isr_npairs < isr_cap; ++k) {
            volatile int spin;
            if (isr_block > 0 && k > 0 && k % isr_block == 0) INIT(&isr_state);
            (void)UPDATE(&isr_state, isr_samples[3 * k], isr_samples[3 * k + 1],
                         isr_samples[3 * k + 2]);
            for (spin = 0; spin < 300; ++spin) {
            }
        }
    } else { /* main loop reads */
        long n = 0;
        while (n < isr_cap && isr_next < isr_count) {
            rd_t r;
            isr_in_read = 1;
            READ(&isr_state, &r);
            if (mode == 2) { /* torn on purpose: revolutions and angle from two reads */
                rd_t r2;
                volatile int spin;
                for (spin = 0; spin < 50; ++spin) {
                }
                READ(&isr_state, &r2);
                r.angle = r2.angle;
            }
            isr_in_read = 0;
            isr_pairs[ISR_WORDS * n] = (uint32_t)r.revolutions;
            isr_pairs[ISR_WORDS * n + 1] = ANGLE_BITS(r);
            if (ISR_WORDS > 2) isr_pairs[ISR_WORDS * n + ISR_WORDS - 1] = ISR_IDENT(r);
            ++n;
        }
        isr_npairs = n;
    }
    memset(&it, 0, sizeof it);
    setitimer(ITIMER_REAL, &it, NULL);
    fwrite(isr_pairs, sizeof(uint32_t) * ISR_WORDS, (size_t)isr_npairs, stdout);
    return 0;
}

int main(int argc, char **argv) {
    if (argc < 2) return fail("usage", 0);
    if (!strcmp(argv[1], "run")) return mode_run(argc > 2 ? atol(argv[2]) : 0);
    if (!strcmp(argv[1], "trials")) return mode_trials(atol(argv[2]), atoi(argv[3]), argc > 4);
    if (!strcmp(argv[1], "angle")) return mode_angle();
    if (!strcmp(argv[1], "long")) return mode_long(argc, argv);
    if (!strcmp(argv[1], "fuzz")) return mode_fuzz(atoll(argv[2]));
    if (!strcmp(argv[1], "isr"))
        return mode_isr(atoi(argv[2]), atol(argv[3]), argc > 4 ? atol(argv[4]) : 0);
#if !HC_Q && defined(UPFX_POWERUP)
    if (!strcmp(argv[1], "lam")) return mode_lam(argc > 2 ? atol(argv[2]) : 0);
    if (!strcmp(argv[1], "lock")) return mode_lock();
#endif
    return fail("unknown mode", 0);
}
"""


class Calibration:
    """A calibration as the pipeline would produce it (artifact dict), with its truth.

    Trapezoidal flux (electrical harmonics 3 and 5), per-magnet variation, sensors off 120
    degrees, an unequal projection and slightly wrong offsets; raw-ADC-like signals (offset
    about 2048, amplitude 1200 counts by default: 60 % of a 12-bit ADC, as designs leave room
    for drift).
    """

    def __init__(
        self, *, n=11, points=4096, amplitude=1200.0, offset=(2048.3, 2040.1, 2055.7), seed=3,
        trapezoid=1.0, noise=3.0, sample_time=2.5e-4,
    ):  # fmt: skip
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
        self.noise = noise
        self.amplitude = amplitude
        self.proj_phases = phases + np.array([0.0, 0.01, -0.005])
        P = projection_matrix(self.proj_phases)
        o_est = offset + amplitude * np.array([3e-4, -2e-4, 1e-4])
        lut = build_lut(self.truth, n, points=points, projection=P, offset=o_est)
        assert lut.bijective
        self.lut = LUT.from_arrays(n, P, o_est, lut.y_hat, lut.eta)
        floor = noise * math.sqrt(2.0 / 3.0) / amplitude / n
        self.noise_floor = floor
        from hallcal import __version__

        self.artifact = {
            "format": "hallcal-calibration/1",
            "hallcal_version": __version__,
            "pole_pairs": n,
            "reconstruction": {"projection": P.tolist(), "offset": o_est.tolist()},
            "lut": {"y_hat": lut.y_hat.tolist(), "eta": lut.eta.tolist(), "points": points},
            "model": {"basis": "fourier", "harmonics": harmonics, "theta": theta.tolist()},
            "setup": _bench_setup(n, sample_time),
            "diagnostics": {"bijective": True, "noise_floor": floor},
        }

    def signals(self, y0, *, noise=None, seed=0):
        """Hall signals (N x 3) at mechanical angles y0, with noise, rounded to counts."""
        sigma = self.noise if noise is None else noise
        rng = np.random.default_rng(seed)
        d = self.truth(np.asarray(y0, float))
        return np.round(d + rng.normal(0.0, sigma, d.shape))

    def recording(self, n_samples, *, seed, y_start=0.0):
        """Several revolutions both ways with wobble, noise and ADC rounding (counts)."""
        k = np.arange(n_samples)
        y0 = (
            y_start
            + 14.0 * np.sin(TWO_PI * 1.5 * k / n_samples)
            + 0.3 * np.sin(TWO_PI * k / 700.0)
            + 0.02 * np.sin(TWO_PI * k / 37.0)
        )
        return self.signals(y0, seed=seed)


def compile_driver(workdir: Path, prefix: str = "hallcal", *, fixed: bool, flags=(), name=None,
                   pole_pairs: int = 11) -> Path:  # fmt: skip
    """Compile DRIVER with the generated source of one variant."""
    src = workdir / f"drv_{prefix}.c"
    src.write_text(DRIVER.replace("UPFX", prefix.upper()).replace("PFX", prefix))
    exe = workdir / (name or f"drv_{prefix}_{'q' if fixed else 'f'}")
    cmd = [CC, "-std=c99", *flags, f"-DHC_Q={int(fixed)}", f"-DHC_N_FOR_TEST={pole_pairs}",
           f"-I{workdir}", str(src), "-o", str(exe), "-lm"]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return exe


def run(exe: Path, samples: np.ndarray, *, fixed: bool, block: int = 0) -> np.ndarray:
    """Readings (N x 3 uint32: revolutions, angle bits, flags) for samples (N x 3)."""
    data = np.ascontiguousarray(samples, dtype=np.int32 if fixed else np.float32)
    out = subprocess.run([str(exe), "run", str(int(block))], input=data.tobytes(),
                         capture_output=True, check=True).stdout  # fmt: skip
    return np.frombuffer(out, dtype=np.uint32).reshape(-1, 3)


def angles(raw: np.ndarray, *, fixed: bool) -> np.ndarray:
    """y_star [rad] from readings."""
    rev = raw[:, 0].view(np.int32).astype(np.float64)
    if fixed:
        return TWO_PI * (rev + raw[:, 1].astype(np.float64) / 2.0**32)
    return TWO_PI * rev + raw[:, 1].copy().view(np.float32).astype(np.float64)


def sanitizer_flags() -> list[str] | None:
    """ASan + UBSan flags the compiler accepts, or None."""
    probe = Path(os.environ.get("TMPDIR", "/tmp"))
    base = ["-O1", "-g", "-fsanitize=address,undefined", "-fno-sanitize-recover=all"]
    for extra in (["-fsanitize=float-cast-overflow"], []):
        r = subprocess.run(
            [CC, *base, *extra, "-x", "c", "-", "-o", os.devnull],
            input="int main(void){return 0;}", capture_output=True, text=True, cwd=probe,
        )  # fmt: skip
        if r.returncode == 0:
            return [*base, *extra]
    return None


# ------------------------------------------------------------------------------------------
# Power-up: bench motors and their artifacts
# ------------------------------------------------------------------------------------------


def bench_artifact(cfg, *, points: int = 4096) -> dict:
    """The artifact of a bench motor calibrated exactly: its true flux as the model, the lookup
    table of that flux, sigma the bench's noise and the identifiability analysis of the decoder
    ``hallcal calibrate`` would build (no calibration run needed)."""
    from hallcal.sensor import absolute as ab

    truth, loop, n = cfg.truth(), cfg.loop(), cfg.pole_pairs
    lut = build_lut(truth, n, points=points, projection=loop.projection, offset=loop.offset)
    dec = ab.build_decoder(truth, lut, noise_std=math.sqrt(cfg.noise_variance))
    report = ab.assess_identifiability(dec)
    from hallcal import __version__

    return {
        "format": "hallcal-calibration/1",
        "hallcal_version": __version__,
        "pole_pairs": n,
        "reconstruction": {"projection": lut.projection.tolist(), "offset": lut.offset.tolist()},
        "lut": {"y_hat": lut.y_hat.tolist(), "eta": lut.eta.tolist(), "points": points},
        "model": {"basis": "fourier", "harmonics": list(truth.basis.harmonics),
                  "theta": truth.theta.tolist()},
        "setup": _bench_setup(n, cfg.sample_time),
        "diagnostics": {"bijective": True, "noise_floor": cfg.noise_floor},
        "identifiability": report.to_dict(),
    }  # fmt: skip


def _bench_setup(n: int, sample_time: float) -> dict:
    """The default setup (the paper's controller) for n pole pairs, as an artifact stores it."""
    import dataclasses

    from hallcal.io import default_setup

    setup = default_setup()
    model = dataclasses.replace(setup.model, harmonics=tuple(range(1, n + 1)))
    return dataclasses.replace(setup, pole_pairs=n, sample_time=sample_time, model=model).to_dict()


def python_decoder(artifact: dict):
    """``(decoder, lut)`` as ``hallcal reconstruct --absolute`` builds them from an artifact."""
    from hallcal.io import validate_artifact
    from hallcal.pipeline.powerup import decoder_for, identifiability_from_artifact

    flux = FluxModel(
        FourierBasis(tuple(artifact["model"]["harmonics"])), np.array(artifact["model"]["theta"])
    )
    lut = validate_artifact(artifact).lut()
    return decoder_for(flux, lut, identifiability_from_artifact(artifact)), lut


class PowerUps:
    """Closed-loop power-ups on a bench motor, as ``benchmarks/bench_powerup.py`` simulates them
    (``hallcal.sim.bench.power_up_run`` with the truth and the loop built once): the rotor at
    ``angle`` [rad], the reference from f_init's first value at ``speed`` [rad/s]."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg
        self.truth = cfg.truth()
        self.loop = cfg.loop()
        self.sigma = math.sqrt(cfg.noise_variance)

    def run(self, angle: float, samples: int, speed: float, seed: int) -> np.ndarray:
        """Hall signals (samples x 3) after a power-up at ``angle``."""
        from hallcal.sim.loop import simulate_loop

        n = self.cfg.pole_pairs
        a, b = self.loop.projection @ (self.truth(np.array([angle]))[0] - self.loop.offset)
        y_start = (math.fmod(math.atan2(b, a) + math.pi, TWO_PI) - math.pi) / n
        r = y_start + speed * self.cfg.sample_time * np.arange(samples)
        noise = self.sigma * np.random.default_rng([seed, 1]).standard_normal((samples, 3))
        res = simulate_loop(self.loop, self.truth, r, noise=noise, initial_angle=float(angle))
        assert res.status == "ok"
        return res.d


def identify_python(decoder, d: np.ndarray) -> tuple[int | None, int, np.ndarray]:
    """``PowerUpIdentifier`` over one power-up: (lock sample or None, pole pair at the lock or
    after the last sample, the pole pair in force after each sample)."""
    from hallcal.sensor.absolute import PowerUpIdentifier

    ident = PowerUpIdentifier(decoder)
    best = np.array([ident.update(*row) for row in d.tolist()])
    return ident.lock_sample, ident.best, best


# ------------------------------------------------------------------------------------------
# Checks of the generated text
# ------------------------------------------------------------------------------------------


def c_code(text: str) -> str:
    """C text without comments."""
    return re.sub(r"/\*.*?\*/", "", text, flags=re.S)


def misra_check(d: Path, prefix: str = "hallcal") -> None:
    """The MISRA-minded patterns of every generated file in ``d`` (asserts): only <stdint.h>
    and the own header included, no function-like macro, no builtin, no dynamic memory, no
    double, no goto, no increment (so none inside a condition), no float equality, no
    assignment inside a condition, right shifts only of unsigned values; the fixed-point
    variant without float, 64-bit types or division."""
    _code = c_code
    heads = {"stdint.h", f"{prefix}.h", f"{prefix}_q.h"}
    files = [p for p in (d / f"{prefix}.h", d / f"{prefix}.c", d / f"{prefix}_q.h",
                         d / f"{prefix}_q.c") if p.exists()]  # fmt: skip
    assert files
    for p in files:
        code = _code(p.read_text())
        assert set(re.findall(r'#include [<"]([^>"]+)[>"]', code)) <= heads
        assert not re.search(r"#define\s+\w+\(", code)  # no function-like macro
        assert "__builtin" not in code and "__attribute__" not in code and "asm" not in code
        assert not re.search(r"\b(malloc|free|double|goto)\b", code)
        assert "++" not in code and "--" not in code  # so no increment inside a condition
        assert not re.search(r"[=!]=\s*-?\d+\.\d*(e-?\d+)?f", code)  # no float equality
        # every operand of && / || is a comparison or a negation, without assignment
        for cond in re.findall(r"if \((.*?)\) \{", code, flags=re.S):
            for part in re.split(r"&&|\|\|", cond):
                assert not re.search(r"[^=!<>]=[^=]", part), part
    for p in (f for f in files if f.suffix == ".c"):
        code = _code(p.read_text())
        decl: dict[str, str] = {}
        for typ, name in re.findall(r"\b(u?int32_t|float|uint16_t)\s+(\w+)\b", code):
            if decl.get(name) != "int32_t":  # a name declared signed anywhere counts as signed
                decl[name] = typ
        # right shifts only of unsigned variables, unsigned function results or parenthesised
        # expressions without a signed variable
        for m in re.finditer(r"(\w+|\))\s*>>", code):
            operand = m.group(1)
            if operand != ")":
                assert decl.get(operand, "uint32_t") != "int32_t", (p.name, operand)
                continue
            depth, j = 0, m.start(1)
            while True:  # the matching "("
                depth += {")": 1, "(": -1}.get(code[j], 0)
                if depth == 0:
                    break
                j -= 1
            func = re.search(r"(\w+)\s*$", code[:j])
            if func and decl.get(func.group(1)) is not None:  # a call: its return type
                assert decl[func.group(1)] != "int32_t", (p.name, func.group(1))
                continue
            expr = code[j : m.start(1) + 1]
            signed = [v for v in re.findall(r"[A-Za-z_]\w*", expr) if decl.get(v) == "int32_t"]
            assert not signed, (p.name, expr)
    if (d / f"{prefix}_q.c").exists():
        code_q = _code((d / f"{prefix}_q.c").read_text())
        assert not re.search(r"\b(float|double|int64_t|uint64_t)\b|\s/\s", code_q)


def observer_adversarial(d: np.ndarray, center: np.ndarray, seed: int = 5) -> np.ndarray:
    """Hostile inputs for the observer's C (float32), from ``d`` (a healthy run of at least
    6000 samples, amplitude about 1) and the channels' zero-field levels ``center``: healthy
    samples, glitches of 0.05 .. 3 on every channel at every phase of the adaptation's cycle,
    each channel stuck, at a rail, clipped, and non-finite every third sample (each followed by
    healthy samples: readmission), random readings (every sample an outlier), swapped wires
    (the model no longer fits: stale) and a healthy return with NaN sprinkled over it."""
    rng = np.random.default_rng(seed)
    parts = [d[:1000].copy()]
    g = d[1000:2000].copy()  # glitches: sizes 0.05 .. 3, every channel, every phase of 4
    for j, k in enumerate(range(0, 1000, 7)):
        g[k, j % 3] += (-1) ** j * [0.05, 0.1, 0.3, 1.0, 3.0][j % 5]
    parts.append(g)
    for kind in ("stuck", "rail", "clipped", "nan", "inf"):  # one channel failing, then healthy
        for ch in range(3):
            x = d[2000:2300].copy()
            if kind == "stuck":
                x[:, ch] = center[ch]
            elif kind == "rail":
                x[:, ch] = 1.4
            elif kind == "clipped":
                x[:, ch] = np.clip(x[:, ch], -0.75, 0.75)
            else:
                x[::3, ch] = np.nan if kind == "nan" else np.inf
            parts.append(x)
            parts.append(d[2300:2400])
    parts.append(rng.uniform(-2.0, 2.0, size=(600, 3)))  # random readings: all outliers
    parts.append(np.roll(d[3000:5000], 3, axis=1))  # wires swapped: the model no longer fits
    parts.append(d[5000:6000])  # healthy again
    out = np.concatenate(parts).astype(np.float32)
    out[-900::13, 1] = np.nan  # non-finite samples sprinkled over the healthy return
    return out
