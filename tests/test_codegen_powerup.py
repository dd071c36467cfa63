"""Power-up identification of the pole pair in the generated C (hallcal.output.codegen, section
"powerup"), against the Python reference ``hallcal.sensor.absolute.PowerUpIdentifier``.

The artifacts are bench motors calibrated exactly (``firmware_support.bench_artifact``: the true
flux as the model, the bench's noise as sigma, the identifiability analysis ``hallcal calibrate``
stores); the power-ups are simulated as ``benchmarks/bench_powerup.py`` does (closed loop from a
random rotor angle, f_init from y = 0). C and Python get the same float32 samples. Checked:

* on the paper bench, 200 random power-ups at standstill and 200 moving (both directions, 0.5 to
  5 rad/s): the C locks on the same pole pair at the same sample as ``PowerUpIdentifier`` every
  time, its Lambda_j agree, and its angle after the lock is within the stated bound of the
  Python absolute reconstruction;
* the lock rule in base 2 against exp() over random and near-threshold Lambda vectors;
* the identification and the angle of a reading come from the same sample under interrupts;
* hygiene: strict C99, no library symbol, the MISRA-minded patterns, sanitizers;
* no decoder when the sensors are ideal or the artifact has no analysis (the homing API, and
  the header says why); a malformed analysis is refused naming the key.
"""

from __future__ import annotations

import copy
import math
import os
import subprocess

import numpy as np
import pytest
from firmware_support import (
    CC,
    STRICT,
    PowerUps,
    angles,
    bench_artifact,
    c_code,
    compile_driver,
    identify_python,
    misra_check,
    python_decoder,
    run,
    sanitizer_flags,
)

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.output.codegen import export_c
from hallcal.sensor import absolute as ab
from hallcal.sim.bench import BenchConfig

pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler (cc, gcc or clang) on PATH")
STARTS = 200
STANDSTILL_SAMPLES = 300  # the paper bench locks within a few samples at almost every position
MOVING_SAMPLES = 600
ADC_SCALE = 2.0**14  # the bench's signals are normalized (amplitude 1): counts per unit


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    """The paper bench (11 pole pairs, magnet variation 0.04), exported with the decoder."""
    cfg = BenchConfig()
    art = bench_artifact(cfg)
    d = tmp_path_factory.mktemp("powerup")
    res = export_c(art, d, source="bench.json", adc_scale=ADC_SCALE)
    exe = compile_driver(d, fixed=False, flags=["-O2"])
    dec, lut = python_decoder(art)
    return {"cfg": cfg, "art": art, "dir": d, "res": res, "exe": exe, "dec": dec, "lut": lut,
            "starts": {}}  # fmt: skip


def _starts(paper, moving: bool):
    """200 power-ups: rotor angles uniform over the revolution; moving ones at 0.5 to 5 rad/s
    either way. Seeds fixed; simulated once per module."""
    if moving not in paper["starts"]:
        paper["starts"][moving] = _simulate(paper, moving)
    return paper["starts"][moving]


def _simulate(paper, moving: bool):
    pu = PowerUps(paper["cfg"])
    rng = np.random.default_rng(2027 if moving else 2026)
    angle = rng.uniform(0.0, TWO_PI, STARTS)
    speed = rng.uniform(0.5, 5.0, STARTS) * rng.choice([-1.0, 1.0], STARTS) if moving else None
    n = MOVING_SAMPLES if moving else STANDSTILL_SAMPLES
    runs = [
        pu.run(a, n, 0.0 if speed is None else float(speed[i]), seed=(50_000 if moving else 0) + i)
        for i, a in enumerate(angle)
    ]
    return np.stack(runs).astype(np.float32), n


def _c_lam(paper, d: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Readings (N x 3 words) and Lambda_j (N x n) of the C over power-ups of ``block`` samples."""
    n = paper["res"].pole_pairs
    out = subprocess.run([str(paper["exe"]), "lam", str(block)], input=d.tobytes(),
                         capture_output=True, check=True).stdout  # fmt: skip
    rec = np.frombuffer(out, dtype=np.uint8).reshape(-1, 12 + 4 * n)
    return rec[:, :12].copy().view(np.uint32), rec[:, 12:].copy().view(np.float32)


@pytest.mark.parametrize("moving", [False, True], ids=["standstill", "moving"])
def test_c_locks_like_python_on_the_paper_bench(paper, moving):
    """Every start: the same lock sample and pole pair as PowerUpIdentifier (or neither locks
    and the maximum-likelihood choices agree); nothing rejected; after the lock the reading
    within the stated float bound of the Python absolute reconstruction (the same lean path as
    ``hallcal reconstruct``, shifted by the pole pair).

    Lambda_j before the lock (those below 50, the only ones the lock rule can feel: exp(-25) is
    1e-11 of the threshold) within 5e-3 of Python's. Why: float resolves the radius (365
    sigmas) to 2^-24 of it, 2.2e-5 sigma, so a cost (up to about 10) is within about 1e-4;
    the errors vary with the noise and add up as a random walk over at most a few hundred
    samples before the lock: 2e-3, with a factor 2.5 of room."""
    dec, lut, res = paper["dec"], paper["lut"], paper["res"]
    d, n = _starts(paper, moving)
    words, lam_c = _c_lam(paper, d.reshape(-1, 3), n)
    words = words.reshape(STARTS, n, 3)
    lam_c = lam_c.reshape(STARTS, n, -1).astype(np.float64)
    assert not np.any(words[:, :, 2] & 0xFFFF)  # nothing rejected
    y_c = angles(words.reshape(-1, 3), fixed=False).reshape(STARTS, n)
    same = 0
    lock_at = []
    worst_angle = worst_lam = 0.0
    for k in range(STARTS):
        x = d[k].astype(np.float64)
        lock, j, best = identify_python(dec, x)
        ident_c = words[k, :, 2] >> 31
        pole_c = (words[k, :, 2] >> 16) & 0x7FFF
        lock_c = int(np.argmax(ident_c)) if ident_c.any() else None
        assert lock_c == lock, (k, lock_c, lock)
        stop = n if lock is None else lock + 1
        assert pole_c[stop - 1] == j, (k, pole_c[stop - 1], j)
        assert np.all(ident_c[stop:] == 1) and np.all(pole_c[stop:] == j)  # locked for good
        same += int(np.array_equal(pole_c, best))  # pre-lock choices too (not required)
        # Lambda before the lock: the reference's, recomputed from its per-sample costs
        costs = dec.sample_costs(x)[:stop]
        ref = np.empty_like(costs)
        acc = np.zeros(dec.pole_pairs)
        for i, e in enumerate(costs):  # in the identifier's order: += e, then - min
            acc = acc + e
            acc = acc - acc.min()
            ref[i] = acc
        small = ref < 50.0
        worst_lam = max(worst_lam, float(np.max(np.abs(lam_c[k, :stop] - ref)[small])))
        if lock is not None:
            lock_at.append(lock)
            y_py = ab.absolute_reconstruction(dec, lut, x).y_star
            worst_angle = max(worst_angle, float(np.max(np.abs(y_c[k, lock:] - y_py[lock:]))))
    print(f"{'moving' if moving else 'standstill'}: {len(lock_at)}/{STARTS} locked (samples "
          f"median {np.median(lock_at):.0f}, max {max(lock_at)}), same pole pair and sample as "
          f"Python every time; pre-lock choices identical on {same}/{STARTS}; max |Lambda_C - "
          f"Lambda_py| {worst_lam:.1e}; max |y_C - y_py| after the lock {worst_angle:.2e} rad "
          f"(bound {res.float_bound:.2e})")  # fmt: skip
    assert len(lock_at) >= 0.99 * STARTS  # the paper bench locks: 99.9 % within 200 samples
    assert worst_lam <= 5e-3
    assert worst_angle <= res.float_bound


def test_lock_rule_in_base_2(paper):
    """The generated lock rule (exp(-L / 2) as 2^-(L / (2 ln 2)), exponent bits and a
    polynomial) against sum(exp(-L / 2)) <= alpha / (1 - alpha) in double, on 200 000 Lambda
    vectors: random ones (half lock) and ones built to put W within 1e-3 of the threshold.
    Decisions may differ only where W is within the stated 2e-6 (relative) of the threshold."""
    from hallcal.output.codegen import POWERUP_TERM_ERROR

    n = paper["res"].pole_pairs
    theta = paper["dec"].lock_threshold
    rng = np.random.default_rng(31)
    m = 100_000
    lam = rng.uniform(12.0, 50.0, (2 * m, n))  # about half of these lock
    lam[:, 0] = 0.0
    # near the threshold: scale a random vector so that W = theta (1 + u), |u| <= 1e-3
    v = rng.exponential(1.0, (m, n - 1)) + 0.01
    w_v = np.exp(-0.5 * v).sum(axis=1)
    target = theta * (1.0 + rng.uniform(-1e-3, 1e-3, m))
    # W(c v) decreases in c: bisection for c with W(c v) = target
    lo, hi = np.full(m, 1e-3), np.full(m, 1e4)
    for _ in range(80):
        mid = np.sqrt(lo * hi)
        high = np.exp(-0.5 * mid[:, None] * v).sum(axis=1) > target
        lo, hi = np.where(high, mid, lo), np.where(high, hi, mid)
    lam[m:, 1:] = hi[:, None] * v
    del w_v
    lam = lam.astype(np.float32)
    perm = rng.permuted(np.tile(np.arange(n), (2 * m, 1)), axis=1)  # best anywhere
    lam = np.take_along_axis(lam, perm, axis=1)
    out = subprocess.run([str(paper["exe"]), "lock"], input=lam.tobytes(), capture_output=True,
                         check=True).stdout  # fmt: skip
    got = np.frombuffer(out, dtype=np.uint8).astype(bool)
    lam64 = lam.astype(np.float64)
    W = np.exp(-0.5 * lam64).sum(axis=1) - 1.0  # the best (0) contributes exp(0) = 1
    exact = W <= theta
    differ = got != exact
    rel = np.abs(W / theta - 1.0)
    print(f"lock rule: {np.mean(exact[:m]):.2f} of the random vectors lock; {int(differ.sum())} "
          f"decisions differ from exp(), the largest |W / theta - 1| among them "
          f"{rel[differ].max() if differ.any() else 0.0:.1e}")  # fmt: skip
    assert 0.1 < np.mean(exact[:m]) < 0.9 and 0.3 < np.mean(exact[m:]) < 0.7
    assert np.all(rel[differ] <= POWERUP_TERM_ERROR)


def test_identification_and_angle_are_read_together(paper):
    """A POSIX interval timer interrupts every 10 us; 200 power-ups of 24 samples each (the state
    re-initialised before each, never while a read is under way: init restarts the sequence
    counter). Mode 0: update in the interrupt, read in the main loop; mode 1: the other way
    round. Every reading (revolutions, angle, pole pair, identified) must be one published for
    one sample, also across the lock (both buffers get the identification); mode 2 pairs two
    reads and must be caught tearing (so the check can fail)."""
    d, _ = _starts(paper, moving=True)
    block = 24
    x = np.ascontiguousarray(d[:, :block].reshape(-1, 3))
    published = run(paper["exe"], x, fixed=False, block=block)
    valid = {(int(a), int(b), int(c) & 0xFFFF0000) for a, b, c in published}
    valid.add((0, 0, 0))  # the reading of init
    assert len({c >> 31 for _, _, c in valid}) == 2  # readings before and after the lock
    result = {}
    for mode in (0, 1, 2):
        out = subprocess.run([str(paper["exe"]), "isr", str(mode), "200000", str(block)],
                             input=x.tobytes(), capture_output=True, timeout=120)  # fmt: skip
        assert out.returncode == 0, out.stderr
        got = np.frombuffer(out.stdout, dtype=np.uint32).reshape(-1, 3)
        torn = sum((int(a), int(b), int(c)) not in valid for a, b, c in got)
        result[mode] = (len(got), torn)
    print(f"(reads, torn): {result}")
    # how many reads the main loop gets depends on the machine's load (103 seen on a busy
    # 2-core machine, > 10 000 on a quiet one); 100 reads spread over 200 power-ups are enough
    # because mode 2, run the same way, must be caught tearing: that shows the reads overlap
    # the interrupts often enough to see a torn reading if there were one
    assert result[0][0] > 100 and result[0][1] == 0
    assert result[1][0] > 100 and result[1][1] == 0
    assert result[2][1] > 0


def test_hygiene_and_sanitizers(paper):
    d = paper["dir"]
    obj = d / "hallcal.o"
    r = subprocess.run([CC, *STRICT, "-O2", "-c", str(d / "hallcal.c"), "-o", str(obj)],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr
    und = subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True).stdout
    assert und.split() == [], und  # no libm (exp, sqrt), no memset
    misra_check(d)
    code = c_code((d / "hallcal.c").read_text())
    assert " / " not in code  # no division anywhere in the float variant
    flags = sanitizer_flags()
    if flags is None:
        pytest.skip(f"{CC} cannot build with -fsanitize=address,undefined")
    exe = compile_driver(d, fixed=False, flags=flags, name="san_pu")
    env = dict(os.environ, UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1")
    out = subprocess.run([str(exe), "fuzz", "300000"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    x, _ = _starts(paper, moving=True)
    x = x[:20].reshape(-1, 3)
    a = run(exe, x, fixed=False, block=MOVING_SAMPLES)
    b = run(paper["exe"], x, fixed=False, block=MOVING_SAMPLES)
    np.testing.assert_array_equal(a, b)  # -O1 with sanitizers and -O2: the same bits


def test_header_documents_the_api(paper):
    h = (paper["dir"] / "hallcal.h").read_text()
    res = paper["res"]
    assert res.identifies_pole_pair and "powerup" in res.sections
    assert "void hallcal_init(hallcal_state *s);" in h
    assert "uint32_t hallcal_set_angle(hallcal_state *s, int32_t revolutions, float angle);" in h
    assert "uint32_t identified;" in h and "uint32_t pole_pair;" in h
    assert "#define HALLCAL_POWERUP 1" in h
    assert res.powerup_table_bytes == 8 * (res.pole_pairs * paper["dec"].grid + 1)
    # the fixed-point variant keeps the homing API and says why
    hq = (paper["dir"] / "hallcal_q.h").read_text()
    assert "does NOT identify the pole pair" in hq
    assert "void hallcal_q_init(hallcal_q_state *s);" in hq
    assert "hallcal_q_set_angle(hallcal_q_state *s, int32_t revolutions, uint32_t angle);" in hq


# ------------------------------------------------------------------------------------------
# No decoder
# ------------------------------------------------------------------------------------------


def test_ideal_sensors_emit_no_decoder(tmp_path):
    """Identical magnets: the analysis says "not identifiable"; the export keeps the homing API
    (init with revolutions and angle), says why in the header and in its messages, and the
    code runs as the lean variant always did."""
    art = bench_artifact(BenchConfig(magnet_variation=0.0))
    assert art["identifiability"]["status"] == "not_identifiable"
    res = export_c(art, tmp_path, source="ideal.json", adc_scale=ADC_SCALE)
    assert not res.identifies_pole_pair and "powerup" not in res.sections
    assert any("no power-up identification" in m and "NOT identifiable" in m
               for m in res.messages)  # fmt: skip
    for name in ("hallcal.h", "hallcal_q.h"):
        text = (tmp_path / name).read_text()
        assert "does NOT identify the pole pair" in text and "NOT identifiable" in text
    h = (tmp_path / "hallcal.h").read_text()
    assert "void hallcal_init(hallcal_state *s);" in h  # one init signature for every variant
    assert "uint32_t hallcal_set_angle(hallcal_state *s, int32_t revolutions, float angle);" in h
    assert "POWERUP" not in h and "identified" not in c_code(h)
    assert "hc_evidence" not in (tmp_path / "hallcal.c").read_text()
    exe = compile_driver(tmp_path, fixed=False, flags=["-O2"])
    pu = PowerUps(BenchConfig(magnet_variation=0.0))
    out = run(exe, pu.run(0.0, 100, 0.5, seed=1).astype(np.float32), fixed=False)
    assert not np.any(out[:, 2])


def test_one_pole_pair_needs_no_decoder(tmp_path):
    """With one pole pair f_init from y = 0 is already in the calibration's frame: no decoder,
    the lean API, and the header says so (not "homing")."""
    art = bench_artifact(BenchConfig(pole_pairs=1))
    res = export_c(art, tmp_path, adc_scale=ADC_SCALE)
    assert not res.identifies_pole_pair and res.powerup_table_bytes == 0
    assert not any("power-up" in m for m in res.messages)
    h = (tmp_path / "hallcal.h").read_text()
    assert "one pole pair" in h and "homed" not in h
    assert "void hallcal_init(hallcal_state *s);" in h  # one init signature for every variant
    assert "uint32_t hallcal_set_angle(hallcal_state *s, int32_t revolutions, float angle);" in h


def test_rejected_sample_before_the_lock_brings_no_evidence(paper):
    """A NaN sample right after power-up is rejected (counted, the reading held) and changes
    nothing else: the C then locks as Python does on the recording without that sample."""
    d, n = _starts(paper, moving=False)
    dec = paper["dec"]
    checked = 0
    for k in range(20):
        lock, _, _ = identify_python(dec, d[k].astype(np.float64))
        if lock is None or lock < 1:
            continue
        x = np.insert(d[k], 1, np.float32(np.nan), axis=0)  # a bad second sample
        out = run(paper["exe"], x, fixed=False)
        assert out[1, 2] & 0xFFFF == 1 | 4  # held, rejected: range (NaN)
        assert np.array_equal(out[1, :2], out[0, :2])  # the reading held
        ref_lock, ref_j, _ = identify_python(dec, np.delete(x, 1, axis=0).astype(np.float64))
        ident = out[:, 2] >> 31
        assert int(np.argmax(ident)) == ref_lock + 1  # one sample later: the rejected one
        assert (out[-1, 2] >> 16) & 0x7FFF == ref_j
        checked += 1
    assert checked >= 10


def test_no_powerup_option(paper, tmp_path):
    """``powerup=False`` (CLI ``--no-powerup``) keeps the homing API and saves the tables."""
    res = export_c(paper["art"], tmp_path, adc_scale=ADC_SCALE, powerup=False)
    assert not res.identifies_pole_pair and "powerup" not in res.sections
    h = (tmp_path / "hallcal.h").read_text()
    assert "void hallcal_init(hallcal_state *s);" in h  # one init signature for every variant
    assert "uint32_t hallcal_set_angle(hallcal_state *s, int32_t revolutions, float angle);" in h
    assert "left out on request" in h


def test_artifact_without_analysis_emits_no_decoder(paper, tmp_path):
    art = copy.deepcopy(paper["art"])
    del art["identifiability"]
    res = export_c(art, tmp_path, adc_scale=ADC_SCALE)
    assert not res.identifies_pole_pair and res.powerup_table_bytes == 0
    assert "no identifiability analysis" in (tmp_path / "hallcal.h").read_text()


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        ("identifiability", "yes", "identifiability"),
        ("identifiability.status", "maybe", "identifiability"),
        ("identifiability.pole_pairs", 7, "identifiability.pole_pairs"),
        ("identifiability.noise_std", -1.0, "identifiability.noise_std"),
        ("identifiability.gain_sd", -0.05, "gain_sd"),
        ("identifiability.lock_travel", float("nan"), "lock_travel"),
    ],
)
def test_malformed_analysis_is_refused(paper, tmp_path, key, value, named):
    art = copy.deepcopy(paper["art"])
    keys = key.split(".")
    target = art
    for k in keys[:-1]:
        target = target[k]
    target[keys[-1]] = value
    with pytest.raises(HallcalInputError, match=named.replace(".", r"\.")):
        export_c(art, tmp_path, adc_scale=ADC_SCALE)
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------------------------
# The common-gain profile (decoders whose analysis chose it: magnets nearly alike)
# ------------------------------------------------------------------------------------------------

DRIFT_STARTS = 60


@pytest.fixture(scope="module")
def alike(tmp_path_factory):
    """5 pole pairs, magnets 1 % apart, 0.9 % noise (the defect of unseen cases 202 and 213 in
    small: a common gain change of 0.34 % makes another magnet fit), exported with the
    common-gain profile (the artifact's ``gain_sd``, as calibrate stores it when it chooses
    the profile)."""
    cfg = BenchConfig(pole_pairs=5, magnet_variation=0.01, noise_variance=8e-5)
    art = bench_artifact(cfg)
    art["identifiability"]["gain_sd"] = ab.DEFAULT_GAIN_SD
    built = _exported(art, tmp_path_factory.mktemp("powerup_gain"))
    assert built["dec"].gain_sd == ab.DEFAULT_GAIN_SD
    return {"cfg": cfg, **built}


def _exported(art: dict, d) -> dict:  # noqa: ANN001
    """The artifact's C decoder exported to ``d`` and compiled (float, -O2), and its Python
    decoder: what the drift tests compare."""
    res = export_c(art, d, source="bench.json", adc_scale=ADC_SCALE)
    exe = compile_driver(d, fixed=False, flags=["-O2"])
    dec, lut = python_decoder(art)
    return {"art": art, "dir": d, "res": res, "exe": exe, "dec": dec, "lut": lut}


@pytest.mark.parametrize("gain", [1.0, 0.95, 1.05])
def test_c_profiles_the_common_gain_like_python(alike, gain):
    """60 power-ups (half at rest, half at 0.5-5 rad/s) with every signal times ``gain`` about
    f_init's offsets: the C locks on the same pole pair at the same sample as PowerUpIdentifier
    (or neither locks), and no lock is wrong; Lambda_j below 50 before the lock within 1e-2 of
    Python's: as on the paper bench, float's 2^-24 of the radius per cost, a random walk, but
    over up to 600 samples (sqrt(600) 1e-4 = 2.4e-3) and with the increment a difference of
    two terms of up to the cost's size (the profiled part subtracted): 2 x 2.4e-3, and a factor
    2 of room."""
    dec = alike["dec"]
    pu = PowerUps(alike["cfg"])
    rng = np.random.default_rng(2031)
    n = alike["cfg"].pole_pairs
    locked = worst_lam = 0
    for k in range(DRIFT_STARTS):
        angle = rng.uniform(0.0, TWO_PI)
        speed = 0.0 if k % 2 else float(rng.uniform(0.5, 5.0) * rng.choice([-1.0, 1.0]))
        x = pu.run(angle, MOVING_SAMPLES, speed, seed=70_000 + k)
        truth_j = int(np.round((angle - alike["lut"].f_init(x[:1])[0]) * n / TWO_PI)) % n
        x = (dec.offset + gain * (x - dec.offset)).astype(np.float32)
        words, lam_c = _c_lam(alike, x, MOVING_SAMPLES)
        lock, j, _ = identify_python(dec, x.astype(np.float64))
        ident_c = words[:, 2] >> 31
        lock_c = int(np.argmax(ident_c)) if ident_c.any() else None
        assert lock_c == lock, (k, lock_c, lock)
        stop = MOVING_SAMPLES if lock is None else lock + 1
        assert (words[stop - 1, 2] >> 16) & 0x7FFF == j
        if lock is not None:
            locked += 1
            assert j == truth_j, (k, j, truth_j)  # no wrong lock
        ref = _reference_lambda(dec, x.astype(np.float64)[:stop])
        small = ref < 50.0
        worst_lam = max(worst_lam, float(np.max(np.abs(lam_c[:stop] - ref)[small])))
    print(f"gain {gain}: {locked}/{DRIFT_STARTS} locked, same sample and pole pair as Python; "
          f"max |Lambda_C - Lambda_py| {worst_lam:.1e}")  # fmt: skip
    assert locked >= DRIFT_STARTS // 2  # most lock within 600 samples (measured: see print)
    assert worst_lam <= 1e-2


def _reference_lambda(dec, x: np.ndarray) -> np.ndarray:
    """PowerUpIdentifier's Lambda_j after each sample (relative to the best)."""
    ident = ab.PowerUpIdentifier(dec)
    out = np.empty((x.shape[0], dec.pole_pairs))
    for i, row in enumerate(x.tolist()):
        ident.update(*row)
        out[i] = ident.lam
    return out


@pytest.fixture(scope="module")
def alike_travel(alike, tmp_path_factory):
    """The same motor as calibrate exports it: the profile and the lock after one electrical
    revolution of motion (its drift robustness is below 1)."""
    art = copy.deepcopy(alike["art"])
    art["identifiability"]["lock_travel"] = ab.DEFAULT_LOCK_TRAVEL
    built = _exported(art, tmp_path_factory.mktemp("powerup_travel"))
    assert built["dec"].lock_travel == ab.DEFAULT_LOCK_TRAVEL
    return {**alike, **built}


@pytest.fixture(scope="module")
def alike_travel_plain(alike, tmp_path_factory):
    """The lock after motion without the profile, as calibrate exports it where the ADC's
    rounding decides the standstill evidence (reason quantizer)."""
    art = copy.deepcopy(alike["art"])
    art["identifiability"].pop("gain_sd", None)
    art["identifiability"]["lock_travel"] = ab.DEFAULT_LOCK_TRAVEL
    built = _exported(art, tmp_path_factory.mktemp("powerup_travel_plain"))
    assert built["dec"].lock_travel == ab.DEFAULT_LOCK_TRAVEL and built["dec"].gain_sd == 0.0
    return {**alike, **built}


@pytest.mark.parametrize(
    ("which", "drift"),
    [("alike_travel", 0.01), ("alike_travel_plain", 0.0)],
    ids=["profile", "plain"],
)
def test_c_waits_for_the_travel_like_python(which, drift, request):
    """20 power-ups of 2000 samples at 3-5 rad/s either way (one electrical revolution of the 5
    pole pairs takes 1000-1700 samples) and 4 at rest, with the profile one sensor's offset
    +1 % of the amplitude (a plausible drift; without it healthy sensors): the C locks at the
    same sample and on the same pole pair as PowerUpIdentifier, never before one electrical
    revolution, never on a wrong pole pair; at rest neither locks."""
    alike_travel = request.getfixturevalue(which)
    dec, lut = alike_travel["dec"], alike_travel["lut"]
    pu = PowerUps(alike_travel["cfg"])
    rng = np.random.default_rng(2032)
    n, samples = 5, 2000
    locked = 0
    for k in range(24):
        angle = rng.uniform(0.0, TWO_PI)
        speed = 0.0 if k >= 20 else float(rng.uniform(3.0, 5.0) * rng.choice([-1.0, 1.0]))
        x = pu.run(angle, samples, speed, seed=80_000 + k)
        truth_j = int(np.round((angle - lut.f_init(x[:1])[0]) * n / TWO_PI)) % n
        x = x.astype(np.float64) + np.array([0.0, 0.0, drift])
        x = x.astype(np.float32)
        words, _ = _c_lam(alike_travel, x, samples)
        lock, j, _ = identify_python(dec, x.astype(np.float64))
        ident_c = words[:, 2] >> 31
        lock_c = int(np.argmax(ident_c)) if ident_c.any() else None
        assert lock_c == lock, (k, lock_c, lock)
        if speed == 0.0:
            assert lock is None
        elif lock is not None:
            locked += 1
            assert j == truth_j
            y = lut.f_init(x[: lock + 1].astype(np.float64)) * n / TWO_PI  # electrical turns
            assert np.ptp(y) >= 1.0
    print(f"travel: {locked}/20 moving power-ups locked after one electrical revolution")
    assert locked >= 15


# ------------------------------------------------------------------------------------------------
# The goodness-of-fit gate at the lock (step 7), as calibrate exports it
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def paper_gate(paper, tmp_path_factory):
    """The paper bench's artifact with the gate calibrate stores (alpha_g, K0)."""
    art = copy.deepcopy(paper["art"])
    art["identifiability"]["gate_rate"] = ab.DEFAULT_GATE_RATE
    art["identifiability"]["gate_samples"] = ab.DEFAULT_GATE_SAMPLES
    built = _exported(art, tmp_path_factory.mktemp("powerup_gate"))
    assert built["dec"].gate_samples == ab.DEFAULT_GATE_SAMPLES
    return {"cfg": paper["cfg"], **built}


@pytest.mark.parametrize(
    ("gains", "offsets"),
    [((1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), ((0.95, 1.0, 1.0), (0.0, 0.0, 0.0)),
     ((1.0, 1.10, 1.0), (0.0, 0.0, 0.0)), ((1.0, 1.0, 1.0), (0.0, 0.0, 0.05))],
    ids=["healthy", "d1 x0.95", "d2 x1.10", "d3 +0.05"],
)  # fmt: skip
def test_c_gates_the_lock_like_python(paper_gate, gains, offsets):
    """40 power-ups at standstill (300 samples) with the sensors as calibrated or changed: the C
    locks at the same sample on the same pole pair as PowerUpIdentifier, never before K0
    samples; where Python says "mismatch" the C never identifies and takes no evidence after
    that sample (its Lambda_j frozen: the mismatch flag stops the evidence). Healthy: all lock
    (the gate's false alarm is 1e-4 per power-up, and these seeds show none)."""
    dec = paper_gate["dec"]
    pu = PowerUps(paper_gate["cfg"])
    rng = np.random.default_rng(2033)
    starts, samples = 40, STANDSTILL_SAMPLES
    counts = {"locked": 0, "gate": 0, "mismatch": 0}
    for k in range(starts):
        x = pu.run(float(rng.uniform(0.0, TWO_PI)), samples, 0.0, seed=90_000 + k)
        x = (x.astype(np.float64) * np.array(gains) + np.array(offsets)).astype(np.float32)
        words, lam_c = _c_lam(paper_gate, x, samples)
        ident = ab.PowerUpIdentifier(dec)
        for row in x.astype(np.float64).tolist():
            ident.update(*row)
        ident_c = words[:, 2] >> 31
        lock_c = int(np.argmax(ident_c)) if ident_c.any() else None
        assert lock_c == ident.lock_sample, (k, lock_c, ident.lock_sample)
        if ident.locked:
            counts["locked"] += 1
            assert ident.lock_sample >= ab.DEFAULT_GATE_SAMPLES - 1
            assert (words[ident.lock_sample, 2] >> 16) & 0x7FFF == ident.best
        if ident.mismatch:
            m = ident.mismatch_sample
            counts["mismatch"] += 1
            counts["gate"] += int(m >= ab.DEFAULT_GATE_SAMPLES - 1)
            assert np.all(lam_c[m:] == lam_c[m]), k  # no evidence after the mismatch
    print(f"gains {gains} offsets {offsets}: {counts} of {starts}, C as Python")
    if gains == (1.0, 1.0, 1.0) and offsets == (0.0, 0.0, 0.0):
        assert counts["locked"] == starts
    else:  # the gate's own refusal (at or after K0) is among them (measured: 1, 3, 1)
        assert counts["gate"] >= 1


# ------------------------------------------------------------------------------------------------
# The gate's bias half (step 7: the winner's residual mean), as calibrate exports it
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def paper_bias(paper, tmp_path_factory):
    """The paper bench's artifact with the gate and its bias half (``gate_bias_dispersion``)."""
    art = copy.deepcopy(paper["art"])
    art["identifiability"]["gate_rate"] = ab.DEFAULT_GATE_RATE
    art["identifiability"]["gate_samples"] = ab.DEFAULT_GATE_SAMPLES
    art["identifiability"]["gate_bias_dispersion"] = 1.0
    built = _exported(art, tmp_path_factory.mktemp("powerup_bias"))
    assert math.isfinite(built["dec"].gate_bias_bound)
    return {"cfg": paper["cfg"], **built}


@pytest.mark.parametrize(
    ("gains", "offsets"),
    [((1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), ((0.95, 1.0, 1.0), (0.0, 0.0, 0.0)),
     ((1.0, 1.0, 1.0), (0.0, 0.0, 0.01)), ((0.995, 0.995, 0.995), (0.0, 0.0, 0.0))],
    ids=["healthy", "d1 x0.95", "d3 +0.01", "all x0.995"],
)  # fmt: skip
def test_c_gates_the_residual_mean_like_python(paper_bias, gains, offsets):
    """40 power-ups (half at rest, half at 2 rad/s; 300 samples) with the sensors as
    calibrated or changed: the C decides (lock or mismatch) at the same sample as
    PowerUpIdentifier, on the same pole pair, and takes no evidence after a mismatch. The bias
    half's sums are float32 in the C: a decision could differ only where S is within float
    rounding of its bound, which these seeds do not reach (every decision compared)."""
    dec = paper_bias["dec"]
    pu = PowerUps(paper_bias["cfg"])
    rng = np.random.default_rng(2034)
    starts, samples = 40, STANDSTILL_SAMPLES
    counts = {"locked": 0, "mismatch": 0}
    for k in range(starts):
        speed = 0.0 if k % 2 else 2.0
        x = pu.run(float(rng.uniform(0.0, TWO_PI)), samples, speed, seed=91_000 + k)
        x = (x.astype(np.float64) * np.array(gains) + np.array(offsets)).astype(np.float32)
        words, lam_c = _c_lam(paper_bias, x, samples)
        ident = ab.PowerUpIdentifier(dec)
        for row in x.astype(np.float64).tolist():
            ident.update(*row)
        ident_c = words[:, 2] >> 31
        lock_c = int(np.argmax(ident_c)) if ident_c.any() else None
        assert lock_c == ident.lock_sample, (k, lock_c, ident.lock_sample)
        if ident.locked:
            counts["locked"] += 1
            assert (words[ident.lock_sample, 2] >> 16) & 0x7FFF == ident.best
        if ident.mismatch:
            counts["mismatch"] += 1
            m = ident.mismatch_sample
            assert np.all(lam_c[m:] == lam_c[m]), k  # no evidence after the mismatch
    print(f"gains {gains} offsets {offsets}: {counts} of {starts}, C as Python")
    if gains == (1.0, 1.0, 1.0) and offsets == (0.0, 0.0, 0.0):
        assert counts["locked"] == starts  # false alarm <= 1e-4 per power-up
