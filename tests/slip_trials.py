"""Adversarial trials of the generated firmware's step rule: no slip without the fault flag.

Used by ``tests/test_codegen_slip.py`` (a few thousand trials per class) and
``benchmarks/bench_slip.py`` (100 000 per class). Each trial: ``init``, ``set_angle`` to the
true position one sample before the first (homed use), then ``length`` samples of a rotor at
constant speed, with one kind of trouble (:data:`CLASSES`):

* ``overspeed``: clean signals at a speed uniform in (0, 2 w] either way (w the export's speed
  limit, ``ExportResult.glitch_safe_speed``);
* ``first-sample``: the first sample after ``set_angle`` is the signal of a random angle
  (plausible: only the step rule can catch it), speed within w;
* ``burst``: 2 to 5 such samples in a row at a random time, speed within w;
* ``stuck``: one channel frozen at its value for 2 to 40 samples, speed within w;
* ``clipped``: one channel clipped for the whole trial at a level between 30 % and 95 % of its
  amplitude from its centre (above or below), speed within w.

A trial *slips* when its last reading is more than half a pole pitch from the true angle, and is
*flagged* when the fault flag is set in its last reading (latched: set at any time during the
trial). The host build of the generated C runs the trials (``trials`` mode of the driver of
``tests/firmware_support.py``); the same C gives the same bits on the ARM targets
(``tests/test_codegen_arm.py``).
"""

from __future__ import annotations

import math
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hallcal._constants import TWO_PI

CLASSES = ("overspeed", "first-sample", "burst", "stuck", "clipped")
FAULT = 2


@dataclass(frozen=True)
class Trials:
    """One class of trials: the start of each (rad), its speed (rad per sample), the samples
    (trials x length x 3, artifact units) and the true angle of the last sample (rad)."""

    kind: str
    start: np.ndarray
    speed: np.ndarray
    d: np.ndarray
    y_end: np.ndarray


def make_trials(kind: str, flux: Callable[[np.ndarray], np.ndarray], *, n: int, w: float,
                noise: float, trials: int, length: int, seed: int) -> Trials:  # fmt: skip
    """Trials of one class (see the module docstring).

    Parameters
    ----------
    flux : callable
        y0 [rad] (N,) -> Hall signals (N, 3), artifact units (the true sensors).
    n : int
        Pole pairs.
    w : float
        The export's speed limit [rad per sample, mechanical].
    noise : float
        Hall noise sigma per channel [artifact units].
    """
    rng = np.random.default_rng(seed)
    start = rng.uniform(0.0, TWO_PI, trials)
    sign = rng.choice([-1.0, 1.0], trials)
    if kind == "overspeed":
        v = sign * rng.uniform(0.0, 2.0, trials) * w
    else:
        v = sign * rng.uniform(0.0, 1.0, trials) * w
    k = np.arange(1, length + 1)
    y0 = start[:, None] + v[:, None] * k[None, :]
    d = flux(y0.ravel()).reshape(trials, length, 3)
    d = d + rng.normal(0.0, noise, d.shape)
    rows = np.arange(trials)
    if kind in ("first-sample", "burst"):
        at = np.zeros(trials, dtype=int) if kind == "first-sample" else rng.integers(3, 16, trials)
        size = np.ones(trials, dtype=int) if kind == "first-sample" else rng.integers(2, 6, trials)
        for j in range(int(size.max())):
            sel = rows[size > j]
            bad = flux(rng.uniform(0.0, TWO_PI, sel.size)) + rng.normal(0.0, noise, (sel.size, 3))
            d[sel, at[sel] + j] = bad
    elif kind == "stuck":
        at = rng.integers(3, 16, trials)
        dur = rng.integers(2, 41, trials)
        ch = rng.integers(0, 3, trials)
        for t in range(trials):
            d[t, at[t] : at[t] + dur[t], ch[t]] = d[t, at[t], ch[t]]
    elif kind == "clipped":
        grid = flux(np.linspace(0.0, TWO_PI, 4096, endpoint=False))
        lo, hi = grid.min(axis=0), grid.max(axis=0)
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        ch = rng.integers(0, 3, trials)
        level = rng.uniform(0.3, 0.95, trials) * rng.choice([-1.0, 1.0], trials)
        for t in range(trials):
            c = centre[ch[t]] + level[t] * half[ch[t]]
            col = d[t, :, ch[t]]
            d[t, :, ch[t]] = np.minimum(col, c) if level[t] > 0 else np.maximum(col, c)
    elif kind != "overspeed":
        raise ValueError(kind)
    return Trials(kind, start, v, d, y0[:, -1])


def run_trials(exe: Path, tr: Trials, *, fixed: bool, scale: float = 1.0,
               homed: bool = True) -> dict:  # fmt: skip
    """Run the trials through the host driver; slips, flags and false alarms.

    The fixed-point variant gets ``round(scale d)`` and its start angle in Q0.32 turns; the
    float variant ``d`` as float32 and the start in rad.
    """
    trials, length, _ = tr.d.shape
    if fixed:
        head = np.zeros((trials, 1, 3), dtype=np.int64)
        q = np.round(np.mod(tr.start, TWO_PI) / TWO_PI * 2.0**32).astype(np.int64) % 2**32
        head[:, 0, 0] = q.astype(np.uint32).view(np.int32)
        body = np.round(tr.d * scale).astype(np.int64)
        x = np.concatenate([head, body], axis=1).astype(np.int32)
        start_used = q.astype(np.float64) / 2.0**32 * TWO_PI
    else:
        head = np.zeros((trials, 1, 3), dtype=np.float32)
        head[:, 0, 0] = tr.start.astype(np.float32)
        x = np.concatenate([head, tr.d.astype(np.float32)], axis=1)
        start_used = head[:, 0, 0].astype(np.float64)
    out = subprocess.run([str(exe), "trials", str(length), str(int(homed))], input=x.tobytes(),
                         capture_output=True, check=True).stdout  # fmt: skip
    r = np.frombuffer(out, dtype=np.uint32).reshape(trials, 4)
    rev = r[:, 0].view(np.int32).astype(np.float64)
    if fixed:
        y = TWO_PI * (rev + r[:, 1].astype(np.float64) / 2.0**32)
    else:
        y = TWO_PI * rev + r[:, 1].copy().view(np.float32).astype(np.float64)
    y_true = tr.y_end + (start_used - tr.start)
    return {"err": y - y_true, "flags": r[:, 2], "any_flags": r[:, 3]}


def summarize(res: dict, tr: Trials, n: int, w: float) -> dict:
    """Counts of one class: trials, slips, slips without the fault flag, faults, and for the
    overspeed class the same split at the speed limit."""
    slip = np.abs(res["err"]) > math.pi / n
    fault = (res["flags"] & FAULT) != 0
    out = {
        "trials": int(slip.size),
        "slips": int(slip.sum()),
        "silent": int(np.sum(slip & ~fault)),
        "faults": int(fault.sum()),
        "worst_unflagged": float(np.max(np.abs(res["err"][~fault]), initial=0.0)),
    }
    if tr.kind == "overspeed":
        over = np.abs(tr.speed) > w
        out["over"] = int(over.sum())
        out["faults_within"] = int(np.sum(fault & ~over))
        out["slips_within"] = int(np.sum(slip & ~over))
    return out
