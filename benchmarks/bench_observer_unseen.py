"""The observer's, the misfit check's and the power-up lock's verdicts on conditions the other
benches do not contain (audit; seeds differ from bench_observer.py and bench_powerup.py).

Signals are the bench's exact flux (``BenchConfig.truth()``) along a designed trajectory y0(t),
plus white noise, with the condition applied to the signals only; the observer's model is that
truth tabulated with the noise the calibration would estimate (noise, plus step^2 / 12 with an
ADC). So every non-``ok`` state on a healthy condition is a false alarm of the verdict itself,
not of a calibration.

Per condition (one run, 4 kHz unless said):

- ``FA %``: samples not ``ok`` where the signals truly fit the model (after the first two
  windows; not within a window after an injected disturbance), and ``FA ev``: entries into a
  non-ok state there;
- ``miss %``: samples ``ok`` where the angle error's RMS over 64 samples is above 5x the floor;
- ``err/floor``: y_obs RMS error against the floor sigma sqrt(2/3) / n_m of the signals' noise,
  where the model fits (after 0.25 s);
- ``slips``: samples with the error above half a pole pitch (a slip to the neighbouring pole);
- ``check``: the misfit check of every ``reconstruct`` (:func:`hallcal.sensor.misfit.model_misfit`
  on the first 20 000 samples): fits / mismatch (@ sample) / undecided.

Power-up: 60 power-ups at random angles per condition (400 samples), the decoder built on the
exact model: locked right / locked wrong / mismatch / undecided, and the lock's claimed error
probability (sum of 1 - posterior over the locks) against the wrong locks observed.

Real ring jig: every capture calibrated (constant speed, its first 2 revolutions), each
calibration applied to every capture: observer (misfit median, travel to ``stale``, states),
the misfit check, and 40 power-ups of 300 samples (locks on a capture that is not the
calibration's are confidently wrong answers: the ring was remounted).

Before this audit's fixes (measured on the same inputs): the check said mismatch@10 for "d2 at
its rail for the first 20 samples" and mismatch@12 for "noise 10x on the first 30 samples"
(plain ``reconstruct`` refused, "recalibrate", recordings that fit after them); and
``reconstruct --absolute`` accepted every lock (the last two columns of section 5 equalled
"right" and "wrong": 10 of 60 wrong locks with d1 and d2 swapped at 2 rad/s).

Run: ``python benchmarks/bench_observer_unseen.py``; output committed beside it
(bench_observer_unseen.txt).
"""

from __future__ import annotations

import math
import os
import sys
import time

import numpy as np
from bench_support import RINGJIG

from hallcal._constants import TWO_PI
from hallcal.io import Dataset
from hallcal.pipeline.powerup import identification_check
from hallcal.sensor import absolute as ab
from hallcal.sensor.lut import build_lut
from hallcal.sensor.misfit import model_misfit
from hallcal.sensor.observer import observer_model, run_observer
from hallcal.sim.bench import BenchConfig

TS = 2.5e-4
SIGMA = math.sqrt(7.5e-6)  # the paper's noise (0.27 % of the amplitude)
LINES: list[str] = []


def out(line: str = "") -> None:
    LINES.append(line)
    print(line, flush=True)


def wrap(x):
    return np.mod(x + math.pi, TWO_PI) - math.pi


class Motor:
    """One bench motor: its truth, its observer model and its power-up decoder."""

    def __init__(self, n: int, *, sigma: float = SIGMA, seed: int = 5, model_var=None) -> None:
        self.cfg = BenchConfig(pole_pairs=n, noise_variance=sigma**2, seed=seed)
        self.n, self.sigma = n, sigma
        self.truth = self.cfg.truth()
        var = sigma**2 if model_var is None else model_var
        self.model = observer_model(self.truth, n, var)
        self.var = var
        self._dec = None

    @property
    def decoder(self):
        if self._dec is None:
            loop = self.cfg.loop()
            lut = build_lut(self.truth, self.n, projection=loop.projection, offset=loop.offset)
            self._dec = ab.build_decoder(self.truth, lut, noise_std=math.sqrt(self.var))
            self.lut = lut
            self._proj, self._off = loop.projection, loop.offset
        return self._dec

    def signals(self, y0, seed: int, sigma: float | None = None):
        s = self.sigma if sigma is None else sigma
        rng = np.random.default_rng([seed, 77])
        return self.truth(y0) + s * rng.standard_normal((y0.size, 3))

    def right_offset(self, angle: float) -> int:
        self.decoder  # noqa: B018 (builds the projection)
        a, b = self._proj @ (self.truth(np.array([angle]))[0] - self._off)
        y_start = wrap(math.atan2(b, a)) / self.n
        return int(round((angle - y_start) * self.n / TWO_PI)) % self.n


def rolling_rms(e, w=64):
    c = np.concatenate([[0.0], np.cumsum(e * e)])
    k = np.arange(e.size)
    lo = np.maximum(k - w + 1, 0)
    r = (c[k + 1] - c[lo]) / (k + 1 - lo)
    return np.sqrt(r)


def verdicts(motor: Motor, y0, d, *, fits=None, floor=None, check=True) -> str:
    """One row: states, false alarms, misses, error, slips, the check."""
    obs = run_observer(motor.model, d)
    N = y0.size
    fits = np.ones(N, bool) if fits is None else fits.copy()
    fits[:512] = False
    floor = motor.sigma * math.sqrt(2.0 / 3.0) / motor.n if floor is None else floor
    err = wrap(motor.n * (obs.y_obs - y0)) / motor.n
    st = obs.state_code
    nonok = st != 0
    fa = float(np.mean(nonok[fits])) if fits.any() else math.nan
    ev = int(np.sum(fits[1:] & nonok[1:] & ~nonok[:-1]))
    rr = rolling_rms(err)
    bad = rr > 5.0 * floor
    bad[:512] = False
    miss = float(np.mean(~nonok & bad)) if N > 512 else 0.0
    sel = fits.copy() if fits[512:].any() else np.ones(N, bool)  # a fault: the error throughout
    sel[: int(0.25 / TS)] = False
    e = float(np.sqrt(np.mean(err[sel] ** 2)) / floor) if sel.any() else math.nan
    slips = int(np.sum(np.abs(err) > math.pi / motor.n))
    names = "oasdf"
    frac = "".join(f"{names[c]}{np.mean(st == c) * 100:.0f} " for c in range(5) if np.any(st == c))
    chk = ""
    if check:
        m = model_misfit(motor.decoder, d[:20000])
        chk = m.status.value + (f"@{m.sample}" if m.sample is not None else "")
    return f"{fa * 100:6.2f} {ev:5d} {miss * 100:6.2f} {e:9.2f} {slips:6d}  {chk:16s} {frac}"


HEAD = (
    f"   {'condition':44s}   FA %  FA ev miss %  err/floor  slips  {'check':16s} "
    "states % (o ok, a adapting, s stale, d degraded, f fault)"
)


def speed_profile(v, n_samples):
    """y0 from a speed profile [rad/s] (array or callable of t)."""
    t = np.arange(n_samples) * TS
    vv = v(t) if callable(v) else np.asarray(v)
    return np.concatenate([[0.0], np.cumsum(vv[:-1]) * TS]), t


def observer_motion() -> None:
    out(
        "1. observer and check: motion the other benches do not have (n_m 11, paper noise, "
        "magnet set seed 5)"
    )
    out(HEAD)
    m = Motor(11)
    N = 24000
    cases = {
        "reversals: 0.8 sin(2 pi 0.5 t) rad": lambda t: 0.8 * math.pi * np.cos(math.pi * t),
        "reversals abrupt: +-20 rad/s square, 1 Hz": lambda t: 20.0 * np.sign(np.sin(TWO_PI * t)),
        "standstill 2 s, 3 rad/s 1 s, standstill": lambda t: 3.0 * ((t > 2) & (t < 3)),
        "very slow: 0.01 rad/s": lambda t: 0.01 + 0 * t,
        "accel 1e3 rad/s^2 to 300 rad/s": lambda t: np.minimum(1e3 * t, 300.0),
        "accel 1e4 rad/s^2, +-": lambda t: 200.0 * np.sin(TWO_PI * 8.0 * t),
        "accel 4e4 rad/s^2, +-": lambda t: 400.0 * np.sin(TWO_PI * 16.0 * t),
        "accel 1e5 rad/s^2, +-": lambda t: 600.0 * np.sin(TWO_PI * 26.5 * t),
    }
    for i, (name, v) in enumerate(cases.items()):
        y0, _ = speed_profile(v, N)
        out(f"   {name:44s} " + verdicts(m, y0, m.signals(y0, 200 + i)))
    # already spinning at the first sample (a recording cut from a run, a power-up while coasting)
    for v in (60.0, 86.0, 171.0, 400.0):
        y0 = v * TS * np.arange(N)
        out(
            f"   {f'spinning from the first sample: {v:.0f} rad/s':44s} "
            + verdicts(m, y0, m.signals(y0, 250))
        )
    # fast: electrical speed per sample as a fraction of Nyquist (pi), reached by a 0.5 s ramp
    for frac in (0.1, 0.2, 0.3, 0.4, 0.5, 0.6):
        top = frac * math.pi / m.n / TS
        y0, _ = speed_profile(lambda t, top=top: top * np.minimum(t / 0.5, 1.0), N)
        out(
            f"   {f'fast: {frac:.1f} Nyquist ({top:.0f} rad/s), 0.5 s ramp':44s} "
            + verdicts(m, y0, m.signals(y0, 300))
        )


def observer_motors() -> None:
    out("2. pole pairs, noise, quantization (speed 2 + 1.5 sin(2 pi t / 3) rad/s, 6 s)")
    out(HEAD)
    N = 24000
    y0, t = speed_profile(lambda t: 2.0 + 1.5 * np.sin(TWO_PI * t / 3.0), N)
    for n in (1, 2, 14, 21):
        m = Motor(n, seed=40 + n)
        out(f"   {f'n_m {n}':44s} " + verdicts(m, y0, m.signals(y0, 400 + n)))
    for pct in (0.2, 1.0, 3.0):
        m = Motor(11, sigma=pct / 100.0)
        out(f"   {f'noise {pct} % of the amplitude':44s} " + verdicts(m, y0, m.signals(y0, 500)))
    for bits in (10, 12):
        step = 3.0 / (2**bits - 1)  # rails at +-1.5 x the amplitude
        s = 0.001
        m = Motor(11, sigma=s, model_var=s**2 + step**2 / 12.0)
        d = np.round(m.signals(y0, 600 + bits) / step) * step
        floor = math.sqrt(m.var) * math.sqrt(2.0 / 3.0) / 11
        out(f"   {f'{bits}-bit ADC (+-1.5), noise 0.1 %':44s} " + verdicts(m, y0, d, floor=floor))


def observer_faults() -> None:
    out("3. signal faults (n_m 11, paper noise, 2 + 1.5 sin(2 pi t / 3) rad/s, 6 s)")
    out(HEAD)
    m = Motor(11)
    N = 24000
    y0, t = speed_profile(lambda t: 2.0 + 1.5 * np.sin(TWO_PI * t / 3.0), N)
    W = 256
    amp = math.sqrt(2.0) * m.model.amplitude

    def run(name, d, disturbed=None, fits=True):
        f = np.full(N, fits)
        if disturbed is not None:
            for a, b in disturbed:
                f[a : b + 2 * W] = False
        out(f"   {name:44s} " + verdicts(m, y0, d, fits=f))

    base = m.signals(y0, 700)
    run("healthy (reference)", base)
    d = base.copy()
    d[:, 1] += 0.01 * t * amp[1]
    run("offset drift 1 %/s on d2", d)
    d = base.copy()
    d += 0.01 * t[:, None] * amp
    run("offset drift 1 %/s on all three", d)
    d = base.copy()
    rng = np.random.default_rng(701)
    spans = []
    for k0 in range(2000, N - 600, 1500):
        ch, L = int(rng.integers(3)), int(rng.integers(1, 6))
        d[k0 : k0 + L, ch] = m.model.center[ch] + 1.5 * amp[ch]
        spans.append((k0, k0 + L))
    run("dropouts: 1-5 samples to the rail, every 0.375 s", d, spans)
    d = base.copy()
    d[:20, 1] = m.model.center[1] + 1.5 * amp[1]
    run("d2 at its rail for the first 20 samples", d, [(0, 20)])
    d = base.copy()
    d[:30] += 9.0 * m.sigma * np.random.default_rng(704).standard_normal((30, 3))
    run("noise 10x on the first 30 samples", d, [(0, 30)])
    d = base.copy()
    d[:, 1] += 0.002 * t * amp[1]
    run("offset drift 0.2 %/s on d2", d)
    d = base.copy()
    d[8000:8200] += 9.0 * m.sigma * np.random.default_rng(702).standard_normal((200, 3))
    run("noise burst: 200 samples at 10x noise", d, [(8000, 8200)])
    d = base.copy()
    d[:, 2] += m.sigma * math.sqrt(3.0) * np.random.default_rng(703).standard_normal(N)
    run("d3 with doubled noise", d)
    d = base.copy()
    d[:, 0] = 2.0 * m.model.center[0] - d[:, 0]
    run("d1 sign-inverted (swapped polarity)", d, fits=False)
    d = base[:, [1, 0, 2]].copy()
    run("d1 and d2 swapped", d, fits=False)


def eccentricity() -> None:
    out(
        "4. remount with eccentricity (n_m 11): ring off-centre by eps; the sensors (adjacent, "
        "120 deg_el apart) see"
    )
    out(
        "   the angle warped by w sin(y0 - phi_h) and the field scaled by 1 + w cos(y0 - phi_h) "
        "(air gap, flux ~ exp(-n_m gap / R):"
    )
    out(
        "   w = n_m eps / R electrical rad for both); detection = first 'stale' (and first "
        "non-ok) in revolutions of travel at 2 rad/s;"
    )
    out(
        "   5 trials per w (phase of the eccentricity and noise differ): median [max] travel to "
        "the verdict; the check's"
    )
    out("   mismatches of 5 on the first 20 000 samples; y_obs error after 512 samples (median)")
    m = Motor(11)
    N = int(round(5 * TWO_PI / 2.0 / TS))  # five revolutions
    y0, t = speed_profile(lambda t: 2.0 + 0 * t, N)
    rev = TWO_PI / (2.0 * TS)
    phi = TWO_PI * np.arange(3) / (3 * m.n)
    out(
        f"   {'w [deg_el]':>12s} {'stale after [rev]':>18s} {'non-ok after [rev]':>19s}  "
        f"{'y_obs err/floor':>15s}  check: mismatch"
    )
    floor = m.sigma * math.sqrt(2.0 / 3.0) / m.n

    def travel(idx):
        return idx / rev if idx.size else math.inf

    def fmt(x):
        med, top = np.median(x), np.max(x)
        return (
            "never"
            if math.isinf(med)
            else f"{med:.2f} [{'never' if math.isinf(top) else f'{top:.2f}'}]"
        )

    for w_deg in (0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 3.0, 10.0):
        w = math.radians(w_deg)
        stale, nonok, errs, mism = [], [], [], 0
        for trial in range(5):
            rng = np.random.default_rng([800, int(100 * w_deg), trial])
            ph = 0.4 + 1.3 * trial
            d = np.empty((N, 3))
            for h in range(3):
                ang = y0 + (w / m.n) * np.sin(y0 - phi[h] + ph)
                d[:, h] = m.model.center[h] + (1.0 + w * np.cos(y0 - phi[h] + ph)) * (
                    m.truth(ang)[:, h] - m.model.center[h]
                )
            d += m.sigma * rng.standard_normal((N, 3))
            obs = run_observer(m.model, d)
            stale.append(travel(np.flatnonzero(obs.state_code == 2)[:1]))
            nonok.append(travel(np.flatnonzero(obs.state_code[512:] != 0)[:1] + 512))
            err = wrap(m.n * (obs.y_obs - y0)) / m.n
            errs.append(np.sqrt(np.mean(err[512:] ** 2)) / floor)
            mism += model_misfit(m.decoder, d[:20000]).status.value == "mismatch"
        out(
            f"   {w_deg:12.2f} {fmt(stale):>18s} {fmt(nonok):>19s}  {np.median(errs):15.2f}  "
            f"{mism}/5"
        )


def power_up() -> None:
    out("5. power-up lock (exact model, 60 power-ups of 400 samples at random angles)")
    out(
        f"   {'condition':40s} right  wrong  mismatch  undecided  claimed wrong (sum 1-posterior)"
        "  median samples to lock"
        "   after the whole-recording check (reconstruct --absolute): right  wrong"
    )

    def trial(m: Motor, name: str, v, alter=None, seed=900, rewired=False):
        rng = np.random.default_rng(seed)
        right = wrong = mism = und = kept_right = kept_wrong = 0
        claimed = 0.0
        at = []
        for i in range(60):
            a = float(rng.uniform(0, TWO_PI))
            y0, t = speed_profile(v, 400)
            y0 = y0 + a
            d = m.signals(y0, seed * 1000 + i)
            if alter is not None:
                d = alter(d, t, rng)
            j = -1 if rewired else m.right_offset(a)  # rewired: every lock is a wrong answer
            angles = ab.absolute_reconstruction(m.decoder, m.lut, d)
            ident = angles.identification
            if ident.status is ab.PowerUpStatus.IDENTIFIED:
                right += ident.offset == j
                wrong += ident.offset != j
                claimed += 1.0 - ident.posterior
                at.append(ident.lock_sample + 1)
                ds = Dataset.from_columns({f"d{h + 1}": d[:, h] for h in range(3)})
                if identification_check(m.decoder, ds, angles).status.success:
                    kept_right += ident.offset == j
                    kept_wrong += ident.offset != j
            elif ident.status is ab.PowerUpStatus.MISMATCH:
                mism += 1
            else:
                und += 1
        med = f"{np.median(at):.0f}" if at else "-"
        out(
            f"   {name:40s} {right:5d} {wrong:6d} {mism:9d} {und:10d}  {claimed:30.3g}"
            f"  {med:>22s}   {kept_right:5d} {kept_wrong:5d}"
        )

    m = Motor(11, seed=6)
    amp = math.sqrt(2.0) * m.model.amplitude
    rest = lambda t: 0.0 * t  # noqa: E731
    trial(m, "at rest", rest)
    trial(m, "2 rad/s", lambda t: 2.0 + 0 * t)
    trial(
        m, "reversing: 0.3 sin(2 pi 5 t) rad", lambda t: 0.3 * TWO_PI * 5 * np.cos(TWO_PI * 5 * t)
    )
    trial(m, "fast: 300 rad/s", lambda t: 300.0 + 0 * t)

    def dropout(d, t, rng):
        ch = int(rng.integers(3))
        d[3:5, ch] = m.model.center[ch] + 1.5 * amp[ch]
        return d

    trial(m, "at rest, 2 samples to the rail at 3", rest, dropout)

    def burst(d, t, rng):
        d[:30] += 9.0 * m.sigma * rng.standard_normal((30, 3))
        return d

    trial(m, "at rest, noise 10x on the first 30", rest, burst)
    trial(
        m,
        "at rest, d3 doubled noise",
        rest,
        lambda d, t, rng: d + [0, 0, math.sqrt(3) * m.sigma] * rng.standard_normal(d.shape),
    )
    trial(
        m,
        "at rest, d2 offset +2 % (2 s of 1 %/s)",
        rest,
        lambda d, t, rng: d + [0, 0.02 * amp[1], 0],
    )
    trial(
        m,
        "2 rad/s, d2 offset +2 %",
        lambda t: 2.0 + 0 * t,
        lambda d, t, rng: d + [0, 0.02 * amp[1], 0],
    )
    trial(
        m,
        "at rest, d1 sign-inverted",
        rest,
        lambda d, t, rng: np.column_stack([2 * m.model.center[0] - d[:, 0], d[:, 1:]]),
        rewired=True,
    )
    trial(
        m,
        "2 rad/s, d1 sign-inverted",
        lambda t: 2.0 + 0 * t,
        lambda d, t, rng: np.column_stack([2 * m.model.center[0] - d[:, 0], d[:, 1:]]),
        rewired=True,
    )
    swap = lambda d, t, rng: d[:, [1, 0, 2]]  # noqa: E731
    trial(m, "at rest, d1 and d2 swapped", rest, swap, rewired=True)
    trial(m, "2 rad/s, d1 and d2 swapped", lambda t: 2.0 + 0 * t, swap, rewired=True)
    m3 = Motor(11, sigma=0.03, seed=6)
    trial(m3, "noise 3 %, 2 rad/s", lambda t: 2.0 + 0 * t)
    step = 3.0 / 1023
    mq = Motor(11, sigma=0.001, seed=6, model_var=1e-6 + step**2 / 12)
    trial(mq, "10-bit ADC, noise 0.1 %, at rest", rest, lambda d, t, rng: np.round(d / step) * step)
    for n in (2, 21):
        mn = Motor(n, seed=60 + n)
        trial(mn, f"n_m {n}, at rest", rest)
        trial(mn, f"n_m {n}, 2 rad/s", lambda t: 2.0 + 0 * t)


def ring_jig() -> None:
    import hallcal
    from hallcal.fit.constant_speed import find_constant_speed
    from hallcal.pipeline.observe import observer_for

    out("6. real ring jig (25 pole pairs): calibration of capture c applied to capture d")
    caps = [
        np.loadtxt(RINGJIG / f"hall_calibration_one_rotation_{i}.txt", dtype=np.int64).astype(
            np.float64
        )
        for i in (1, 2, 3)
    ]
    cals = []
    for d in caps:
        start, mid, stop = find_constant_speed(d, 25).split(2.0)
        setup = {
            "pole_pairs": 25,
            "sample_time": 1.0,
            "trajectory": {"kind": "constant-speed", "start": start, "stop": mid},
        }
        cals.append((hallcal.calibrate({f"d{h + 1}": d[:, h] for h in range(3)}, setup), mid))
    out(
        f"   {'c d':5s} {'observer: misfit median':>24s} {'stale after':>12s}  {'states %':28s}"
        f" {'check':18s} power-ups (40 x 300 samples): locked, agree with capture's ML, mismatch"
    )
    for c, (cal, mid) in enumerate(cals):
        model = observer_for(cal)
        dec = cal.identifiability.decoder(cal.flux, cal.lut)
        for k, d in enumerate(caps):
            obs = run_observer(model, d)
            spr = 1294.0
            stale = np.flatnonzero(obs.state == "stale")
            s = f"{(stale[0] - 110) / spr:.2f} rev" if stale.size else "never"
            part = obs.misfit[mid:] if c == k else obs.misfit[600:]
            st = obs.state_code
            frac = " ".join(
                f"{'oasdf'[q]}{np.mean(st == q) * 100:.0f}" for q in range(5) if np.any(st == q)
            )
            chk = model_misfit(dec, d)
            ch = chk.status.value + (f"@{chk.sample}" if chk.sample is not None else "")
            rng = np.random.default_rng(950 + 3 * c + k)
            locked = agree = mism = 0
            for _ in range(40):
                s0 = int(rng.integers(200, d.shape[0] - 400))
                seg = d[s0 : s0 + 300]
                ident = dec.identify(seg)
                ml = dec.identify(d[s0:], lock=False)  # the capture's own ML from s0 to the end
                if ident.status is ab.PowerUpStatus.IDENTIFIED:
                    locked += 1
                    agree += ident.offset == ml.offset
                mism += ident.status is ab.PowerUpStatus.MISMATCH
            out(
                f"   {c + 1} {k + 1}   {np.median(part):24.2f} {s:>12s}  {frac:28s} {ch:18s} "
                f"{locked:2d} locked, {agree:2d} agree, {mism:2d} mismatch"
            )


SECTIONS = {
    "motion": observer_motion,
    "motors": observer_motors,
    "faults": observer_faults,
    "ecc": eccentricity,
    "powerup": power_up,
    "ring": ring_jig,
}


if __name__ == "__main__":
    t0 = time.perf_counter()
    which = sys.argv[1:] or list(SECTIONS)
    for name in which:
        SECTIONS[name]()
    out(f"total {time.perf_counter() - t0:.0f} s")
    load = os.getloadavg()
    out(f"load average at the end: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
