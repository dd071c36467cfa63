"""The power-up decoder's common-gain profile on the Cortex-M4F under QEMU (``arm_harness``):
the same bits as the host build and the same lock as ``PowerUpIdentifier``, and what the profile
costs in cycles per sample before the lock, against the same artifact without it. Skipped only
when the ARM toolchain is absent (as ``tests/test_codegen_arm.py``).

Bench: 5 pole pairs, magnets 1 % apart, 0.9 % noise (the motors whose lock without the profile
breaks at a 0.3 % common gain, where calibrate keeps the profile), all signals 3 % weaker.
"""

from __future__ import annotations

import copy
import math

import arm_harness as ah
import firmware_support as fs
import numpy as np
import pytest

from hallcal.output.codegen import export_c
from hallcal.sensor import absolute as ab
from hallcal.sim.bench import BenchConfig

TWO_PI = 2.0 * math.pi
MISSING = ah.toolchain()
pytestmark = pytest.mark.skipif(
    MISSING is not None, reason=f"ARM toolchain incomplete ({MISSING} not found)"
)
ADC_SCALE = 2.0**14
STARTS = 8
SAMPLES = 80


@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    cfg = BenchConfig(pole_pairs=5, magnet_variation=0.01, noise_variance=8e-5)
    plain = fs.bench_artifact(cfg)
    prof = copy.deepcopy(plain)
    prof["identifiability"]["gain_sd"] = ab.DEFAULT_GAIN_SD
    d = tmp_path_factory.mktemp("pu_arm")
    out = {}
    for name, art in (("plain", plain), ("profile", prof)):
        export_c(art, d / name, source="bench.json", adc_scale=ADC_SCALE, fixed_point=False)
        out[name] = (ah.build(d / name, d / f"arm_{name}", target="m4f", fixed=False), art)
    pu = fs.PowerUps(cfg)
    rng = np.random.default_rng(505)
    x = np.stack([pu.run(float(a), SAMPLES, 0.0, seed=9000 + i)
                  for i, a in enumerate(rng.uniform(0.0, TWO_PI, STARTS))])  # fmt: skip
    x = 0.97 * x  # all gains 3 % down (the bench's offsets are 0)
    return out, x.astype(np.float32), d


def test_profiled_decoder_on_m4f_locks_like_python(builds):
    out, x, d = builds
    b, art = out["profile"]
    raw = ah.run(b, x.reshape(-1, 3), block=SAMPLES)
    assert ah.undefined_symbols(b.obj) == []
    host = fs.compile_driver(d / "profile", fixed=False, flags=["-O2"], name="host_gain")
    np.testing.assert_array_equal(fs.run(host, x.reshape(-1, 3), fixed=False, block=SAMPLES), raw)
    dec, _ = fs.python_decoder(art)
    assert dec.gain_sd > 0.0
    raw = raw.reshape(STARTS, SAMPLES, 3)
    for k in range(STARTS):
        lock, j, _ = fs.identify_python(dec, x[k].astype(np.float64))
        ident = raw[k, :, 2] >> 31
        assert (int(np.argmax(ident)) if ident.any() else None) == lock
        assert ((raw[k, -1, 2] >> 16) & 0x7FFF) == j


def test_the_profile_costs_bounded_cycles_before_the_lock(builds):
    """Cycles per sample before the lock, with and without the profile (the same samples; the
    QEMU trace with the M4 timing table): bounded, a fixed loop over the 5 hypotheses; the
    profile's per-hypothesis update (a dozen multiply-adds and two float divisions, VDIV 14
    cycles each) at most 150 cycles per hypothesis more (measured: see the print)."""
    out, x, _ = builds
    n = 5
    cycles = {}
    for name, (b, _) in out.items():
        xx = x[:, :6].reshape(-1, 3)  # the first samples of each power-up: before any lock
        raw = ah.run(b, xx, block=6)
        tr = ah.trace(b, xx, block=6)
        ident = (raw[:, 2] >> 31).reshape(-1, 6)
        pre = np.ones(len(xx), dtype=bool)
        pre.reshape(-1, 6)[:, 1:] = ident[:, :-1] == 0
        cycles[name] = tr.cycles[pre]
    p, q = cycles["plain"], cycles["profile"]
    print(
        f"M4 cycles per sample before the lock, 5 pole pairs: without the profile "
        f"{p.min()}/{int(np.median(p))}/{p.max()}, with it {q.min()}/{int(np.median(q))}/"
        f"{q.max()} (min/median/max); per hypothesis +{(np.median(q) - np.median(p)) / n:.0f}"
    )
    assert q.max() <= p.max() + 150 * n
