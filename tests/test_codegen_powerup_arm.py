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

from hallcal._constants import TWO_PI
from hallcal.output.codegen import export_c
from hallcal.sensor import absolute as ab
from hallcal.sim.bench import BenchConfig

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
    d = tmp_path_factory.mktemp("pu_arm")
    out = _build_variants(d, plain, {"profile": {"gain_sd": ab.DEFAULT_GAIN_SD}})
    x = _power_ups_at_rest(cfg, STARTS, SAMPLES, rng_seed=505, seed0=9000)
    x = 0.97 * x  # all gains 3 % down (the bench's offsets are 0)
    return out, x.astype(np.float32), d


def _build_variants(d, plain: dict, variants: dict[str, dict]) -> dict:
    """``plain`` and each variant (``plain`` with these ``identifiability`` keys), exported and
    built for the M4F under ``d``: name -> (build, artifact)."""
    arts = {"plain": plain}
    for name, keys in variants.items():
        arts[name] = copy.deepcopy(plain)
        arts[name]["identifiability"].update(keys)
    out = {}
    for name, art in arts.items():
        export_c(art, d / name, source="bench.json", adc_scale=ADC_SCALE, fixed_point=False)
        out[name] = (ah.build(d / name, d / f"arm_{name}", target="m4f", fixed=False), art)
    return out


def _power_ups_at_rest(cfg, starts: int, samples: int, *, rng_seed: int, seed0: int):
    """``starts`` power-ups at rest at random angles, ``samples`` each: (starts, samples, 3)."""
    pu = fs.PowerUps(cfg)
    rng = np.random.default_rng(rng_seed)
    return np.stack([pu.run(float(a), samples, 0.0, seed=seed0 + i)
                     for i, a in enumerate(rng.uniform(0.0, TWO_PI, starts))])  # fmt: skip


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


GATE_STARTS = 4
GATE_SAMPLES = 128  # > K0 = 96: the gate decides within the record


@pytest.fixture(scope="module")
def gate_builds(tmp_path_factory):
    """A 5-pole-pair bench (magnets 4 % apart: the plain lock) exported without and with the
    goodness-of-fit gate at the lock (as calibrate stores it), built for the M4F; power-ups at
    rest with one sensor's gain 5 % low for half of them (some refused by the gate)."""
    cfg = BenchConfig(pole_pairs=5)
    plain = fs.bench_artifact(cfg)
    gate = {"gate_rate": ab.DEFAULT_GATE_RATE, "gate_samples": ab.DEFAULT_GATE_SAMPLES,
            "gate_dispersion": 1.0}  # fmt: skip
    out = _build_variants(tmp_path_factory.mktemp("pu_gate_arm"), plain, {"gate": gate})
    x = _power_ups_at_rest(cfg, GATE_STARTS, GATE_SAMPLES, rng_seed=506, seed0=9100)
    x[GATE_STARTS // 2 :, :, 0] *= 0.95
    return out, x.astype(np.float32)


def test_the_gate_on_m4f_locks_like_python_and_costs_few_cycles(gate_builds):
    """The gated decoder on the M4F: the same lock sample and pole pair as PowerUpIdentifier
    (or neither locks). Cycles per sample (QEMU trace, M4 timing table) before the decision,
    with and without the gate on the same samples: the gate adds one float addition and one
    integer comparison per sample, and the check at the first lock (two multiplications, a
    comparison) once: at most 40 cycles more at any sample before the decision, and the
    decision's sample within 60 of the plain decoder's lock sample (measured: see the print).
    The real price is the evidence loop for K0 samples instead of about 6 (the print's
    totals)."""
    out, x = gate_builds
    b, art = out["gate"]
    raw = ah.run(b, x.reshape(-1, 3), block=GATE_SAMPLES).reshape(GATE_STARTS, GATE_SAMPLES, 3)
    assert ah.undefined_symbols(b.obj) == []
    dec, _ = fs.python_decoder(art)
    assert dec.gate_samples == ab.DEFAULT_GATE_SAMPLES
    for k in range(GATE_STARTS):
        lock, j, _ = fs.identify_python(dec, x[k].astype(np.float64))
        ident = raw[k, :, 2] >> 31
        assert (int(np.argmax(ident)) if ident.any() else None) == lock
        assert ((raw[k, -1, 2] >> 16) & 0x7FFF) == j
    cycles = {}
    for name, (bb, _) in out.items():
        xx = x[:, : ab.DEFAULT_GATE_SAMPLES].reshape(-1, 3)  # up to the gate's decision
        tr = ah.trace(bb, xx, block=ab.DEFAULT_GATE_SAMPLES)
        cycles[name] = tr.cycles.reshape(GATE_STARTS, -1)
    p, g = cycles["plain"], cycles["gate"]
    # before the plain decoder's lock both run the same evidence: compare there, and the
    # gate's decision sample (the last one here) on its own
    plain_dec, _ = fs.python_decoder(out["plain"][1])
    before = np.zeros_like(p, dtype=bool)
    at_lock = []  # the plain decoder's lock sample: the lock rule and the publication
    for k in range(GATE_STARTS):
        lock, _, _ = fs.identify_python(plain_dec, x[k].astype(np.float64))
        before[k, : (lock if lock is not None else p.shape[1])] = True
        at_lock += [] if lock is None else [p[k, lock]]
    diff = (g - p)[before]
    last = g[:, -1]
    print(
        f"M4 cycles per sample before the lock, 5 pole pairs: without the gate "
        f"{int(np.median(p[before]))}/{p[before].max()}, with it {int(np.median(g[before]))}/"
        f"{g[before].max()} (median/max); per sample +{int(np.median(diff))} (max "
        f"+{diff.max()}); at the decision (the lock or the gate's refusal at sample 96) "
        f"{last.min()}-{last.max()} with the gate, at the plain decoder's lock "
        f"{min(at_lock)}-{max(at_lock)}; the "
        f"first 96 samples in all: {int(np.median(p.sum(axis=1)))} without the gate (lean path "
        f"after its lock), {int(np.median(g.sum(axis=1)))} with it (median over the starts)"
    )
    assert diff.max() <= 40
    assert last.max() <= max(at_lock) + 60


@pytest.fixture(scope="module")
def bias_builds(tmp_path_factory):
    """The same bench exported with the gate alone and with its bias half
    (``gate_bias_dispersion``, as calibrate stores it where the calibration's residual is
    white), built for the M4F; power-ups at rest, one sensor's offset +1 % for half of them."""
    cfg = BenchConfig(pole_pairs=5)
    plain = fs.bench_artifact(cfg)
    gate = {"gate_rate": ab.DEFAULT_GATE_RATE, "gate_samples": ab.DEFAULT_GATE_SAMPLES,
            "gate_dispersion": 1.0}  # fmt: skip
    variants = {"gate": gate, "bias": {**gate, "gate_bias_dispersion": 1.0}}
    out = _build_variants(tmp_path_factory.mktemp("pu_bias_arm"), plain, variants)
    x = _power_ups_at_rest(cfg, GATE_STARTS, GATE_SAMPLES, rng_seed=507, seed0=9200)
    x[GATE_STARTS // 2 :, :, 2] += 0.01
    return out, x.astype(np.float32)


def test_the_bias_half_on_m4f_decides_like_python_and_costs_bounded_cycles(bias_builds):
    """The gate with its bias half on the M4F: the same lock sample and pole pair as
    PowerUpIdentifier (or neither locks). Cycles per sample before the decision against the
    gate alone on the same samples: five Huber-weighted sums per hypothesis (about 17 float
    operations, five loads and stores, a division only for a censored sample) and the check at
    the first lock once: measured +69-70 cycles per hypothesis and sample (836 -> 1181 per
    sample, 5 pole pairs); bound 80 (room for the toolchain's scheduling)."""
    out, x = bias_builds
    b, art = out["bias"]
    raw = ah.run(b, x.reshape(-1, 3), block=GATE_SAMPLES).reshape(GATE_STARTS, GATE_SAMPLES, 3)
    assert ah.undefined_symbols(b.obj) == []
    dec, _ = fs.python_decoder(art)
    assert math.isfinite(dec.gate_bias_bound)
    for k in range(GATE_STARTS):
        lock, j, _ = fs.identify_python(dec, x[k].astype(np.float64))
        ident = raw[k, :, 2] >> 31
        assert (int(np.argmax(ident)) if ident.any() else None) == lock
        assert ((raw[k, -1, 2] >> 16) & 0x7FFF) == j
    cycles = {}
    for name in ("gate", "bias"):
        xx = x[:, : ab.DEFAULT_GATE_SAMPLES - 1].reshape(-1, 3)  # before the decision
        tr = ah.trace(out[name][0], xx, block=ab.DEFAULT_GATE_SAMPLES - 1)
        cycles[name] = tr.cycles.reshape(GATE_STARTS, -1)
    diff = cycles["bias"] - cycles["gate"]
    n = dec.pole_pairs
    print(
        f"M4 cycles per sample before the decision, {n} pole pairs: gate alone "
        f"{int(np.median(cycles['gate']))}, with the bias half {int(np.median(cycles['bias']))} "
        f"(median); per hypothesis +{np.median(diff) / n:.0f} (max +{diff.max() / n:.0f})"
    )
    assert diff.max() <= 80 * n
