"""Small motors and power-up truths shared by several test modules (and benchmarks)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hallcal.sensor import absolute as ab

#: A small motor with a stable discrete PID loop: 4 pole pairs at 10 kHz, G(s) = 5000 / (s (s +
#: 50)) with a 0.15 ms delay (the tests add their [model], [bla] and [bench]).
SMALL_LOOP = {
    "pole_pairs": 4,
    "sample_time": 1e-4,
    "controller": {"num": [9.8472, -19.6285, 9.7814], "den": [1.0, -1.962998, 0.962998]},
    "plant": {"num": [5000.0], "den": [1.0, 50.0, 0.0], "delay": 1.5e-4},
}


def true_offset(y0_first: float, y_first: float, n: int) -> int:
    """The offset j with y0 ~ y + 2 pi j / n at power-up (the calibration frame is the truth's)."""
    return int(np.round((y0_first - y_first) * n / (2.0 * math.pi))) % n


def remount_trials(
    decoder: Any, d: NDArray[np.float64], start: int, stop: int, *, window: int, seed: int
) -> tuple[int, int, int, list[int]]:
    """60 power-ups of `window` samples at random starts in ``d[start:stop]`` (a recording that
    does not match `decoder`'s calibration): how many the lock rule alone would have locked
    (posterior >= 1 - alpha), how many :meth:`identify` identified and refused, and after how
    many samples each refusal came."""
    rng = np.random.default_rng(seed)
    old = locked = refused = 0
    at = []
    for s in rng.integers(start, stop - window, 60):
        w = d[s : s + window]
        ident = decoder.identify(w)
        locked += ident.status is ab.PowerUpStatus.IDENTIFIED
        if ident.status is ab.PowerUpStatus.MISMATCH:
            refused += 1
            at.append(ident.mismatch_sample + 1)
        lam = np.cumsum(decoder.sample_costs(w), axis=0)  # the lock rule alone
        lam -= lam.min(axis=1, keepdims=True)
        old += bool(np.any(np.sum(np.exp(-0.5 * lam), axis=1) - 1.0 <= decoder.lock_threshold))
    return old, locked, refused, at
