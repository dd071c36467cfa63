"""The predicted error of a constant-speed calibration from a held-out revolution, and the
harmonic band it chooses.

A constant-speed fit (:func:`hallcal.fit.constant_speed.calibrate_constant_speed`) gives no
covariance of the table, and its residual cannot tell what the basis misses from how the rotor
strayed off the straight line. Its prediction used to be the noise floor whatever the data said:
on spins of magnets with strong 5th and 7th electrical harmonics (``benchmarks/bench_unseen.py``,
cases 210 and 221) the default band 1..3 n_m left the table at 11x and 45x the floor, "ok".

Cross-validation answers both questions with one statistic (Stone 1974): fit on the segment
less its last revolution, apply that table to the held-out revolution and compare with the fitted
straight line ``a + b k`` extended there. The held-out error's mean square is, in expectation,

    floor^2                         (the held-out samples' own noise through f_init)
  + floor^2 p / K_train             (the training table's error from noise: p basis functions
                                     per channel, average leverage p / K of a least-squares fit)
  + m^2                             (flux content the basis misses: it stays in f_star)
  + delta^2                         (the rotor's own deviation from constant speed),

so the table fitted on the whole segment (K samples) is predicted at
``held^2 - floor^2 p (1 / K_train - 1 / K)``. delta is not an error of f_star against a true
encoder, but nothing without one tells it from m: the prediction keeps it (conservative), and a
rig that rings (the ring jig: 4-8x the floor held out, ``tests/test_real_ringjig.py``) is then
not "ok". It is delta on the *calibration* revolutions, so a rig whose motion is not stationary
is predicted from the part it calibrates on: the ring jig's captures 1 and 2 are predicted at
1.20 and 0.64 mrad (two folds within the two revolutions they calibrate on) against 0.57 and
0.28 mrad measured against the straight line on the 2.35 revolutions after them: the ring rings
most in its first two revolutions (capture 1: the fit's motion off the line 1.03 mrad there,
0.57 on the last two; delta, with m, is 78 % of the predicted mean square, the absorbed part 22
%, the floor 0.3 %). Calibrated on the last two revolutions, the same predictor is optimistic
about the first ones (actual/predicted 1.44 and 1.33); over five two-revolution windows of
each capture actual/predicted is 0.44-3.09, geometric mean 0.89: no bias to correct, and
nothing in one window tells how the others move.

With ``harmonics = "auto"`` the band 1..E n_m, E = 3, 5, 7, 9, is the narrowest whose held-out
error is within its own scatter of the lowest (:func:`held_out_choice`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.fit.constant_speed import (
    ConstantSpeedResult,
    calibrate_constant_speed,
    default_harmonics,
)
from hallcal.sensor.flux import FourierBasis

__all__ = ["ELECTRICAL_BANDS", "HeldOut", "held_out_choice", "held_out_error"]

#: Highest electrical harmonics E of the bands 1..E n_m that ``"auto"`` tries, in order (a
#: magnet's flux is odd-symmetric to first order: its strong harmonics are the odd ones).
ELECTRICAL_BANDS = (3, 5, 7, 9)

#: A band's basis may use at most this fraction of the training samples (leverage p / K: at
#: 1/8 the table's own noise adds at most 6 % to the floor).
MAX_LEVERAGE = 0.125


@dataclass(frozen=True)
class HeldOut:
    """A table fitted without the last revolution, scored on it.

    Attributes
    ----------
    harmonics : tuple of int
        The mechanical harmonics of the basis.
    train_samples : int
        Samples of each training part: the segment less its last revolution, then less its
        first (two folds).
    rms : float
        RMS of f_star minus the extended straight line on the held-out parts, each about its
        mean [rad, mechanical].
    samples : int
        Held-out samples (both folds).
    floor : float
        The training fit's angle noise floor [rad].
    absorbed : float
        S_t, the variance of a training table's error from what does not repeat (noise, the
        rotor's non-synchronous motion) [rad^2], measured from the two folds' tables: they share
        the truth and whatever repeats, so their difference is their two absorbed parts over
        the revolution each has and the other has not, ``var(eta_A - eta_B) = 2 S_t held / K_t``
        (an absorbed part's variance scales as 1 / training samples).
    tried : tuple of (int, float)
        Each band tried (E, held-out RMS [rad]) when the band was chosen.
    """

    harmonics: tuple[int, ...]
    train_samples: int
    rms: float
    samples: int
    floor: float
    absorbed: float = 0.0
    tried: tuple[tuple[int, float], ...] = ()

    def predicted(self, result: ConstantSpeedResult) -> float:
        """Predicted RMS error of ``result``'s f_star about its mean on a fresh run [rad]:
        the held-out mean square less what the training table absorbed beyond the full
        table, ``S_t (1 - K_t / K)`` (:attr:`absorbed`; for white noise alone it is
        ``floor^2 p (1 / K_t - 1 / K)``, the leverage term of the module docstring), at least
        the floor with the full fit's own leverage."""
        p = result.model.basis.size
        K = max(result.stop - result.start, 1)
        Kt = max(self.train_samples, 1)
        f2 = result.angle_noise_floor**2
        extra = self.absorbed * max(1.0 - Kt / K, 0.0)
        return math.sqrt(max(self.rms**2 - extra, f2 * (1.0 + p / K)))


def _split(start: int, stop: int, speed: float) -> int | None:
    """The training part's end: the segment less one revolution (None: under 1.5 revolutions,
    where training would not cover the ring; at least half a revolution held out)."""
    per_rev = TWO_PI / max(abs(speed), 1e-300)
    K = stop - start
    if K < 1.5 * per_rev:
        return None
    return stop - int(min(per_rev, K - per_rev))


def held_out_error(
    d: NDArray[np.float64],
    pole_pairs: int,
    harmonics: tuple[int, ...],
    *,
    start: int,
    stop: int,
    speed: float,
    max_iterations: int = 50,
    lut_points: int = 4096,
) -> HeldOut | None:
    """Fit on ``start..stop`` less its last revolution, score on that revolution; then the same
    with the first revolution held out (two folds: twice the held-out samples).

    Parameters
    ----------
    d : ndarray (N, 3)
        The recording.
    pole_pairs : int
        n_m.
    harmonics : tuple of int
        Mechanical harmonics of the basis.
    start, stop : int, keyword-only
        The constant-speed segment.
    speed : float, keyword-only
        Its speed b [rad per sample] (of the fit on the whole segment).
    max_iterations, lut_points : int, keyword-only
        As :func:`~hallcal.fit.constant_speed.calibrate_constant_speed`.

    Returns
    -------
    HeldOut or None
        None when the segment holds less than 1.5 revolutions, or when the training part is too
        short for the basis.
    """
    ts = _split(start, stop, speed)
    if ts is None or ts - start < 2 * (2 * len(harmonics) + 1):
        return None
    held = stop - ts
    sq, used, etas = 0.0, 0, []
    for lo, hi, test in (
        (start, ts, slice(ts, stop)),
        (start + held, stop, slice(start, start + held)),
    ):
        try:
            fit = calibrate_constant_speed(d, pole_pairs, FourierBasis(harmonics), start=lo,
                                           stop=hi, max_iterations=max_iterations,
                                           lut_points=lut_points)  # fmt: skip
        except ValueError:
            return None
        if not fit.lut.bijective:
            return None
        k = np.arange(test.start, test.stop, dtype=np.float64)
        e = fit.lut.f_star(d[: test.stop])[test] - fit.y0(k)
        sq += float(np.sum((e - e.mean()) ** 2))
        used += e.size
        etas.append(fit.lut.eta)
    diff = etas[0] - etas[1] if etas[0].shape == etas[1].shape else np.zeros(1)
    absorbed = float(np.var(diff)) * (ts - start) / (2.0 * held)
    return HeldOut(tuple(harmonics), int(ts - start), math.sqrt(sq / used), used,
                   fit.angle_noise_floor, absorbed)  # fmt: skip


def held_out_choice(
    d: NDArray[np.float64],
    pole_pairs: int,
    *,
    start: int,
    stop: int,
    speed: float,
    max_iterations: int = 50,
    lut_points: int = 4096,
) -> HeldOut | None:
    """The band 1..E n_m (E in :data:`ELECTRICAL_BANDS`) chosen by its held-out error.

    Every band whose basis stays within :data:`MAX_LEVERAGE` of the training samples is scored
    (the narrowest always); the narrowest whose held-out RMS is within ``3 / sqrt(samples)``
    (relative) of the lowest is chosen: the "one-standard-error rule" (Breiman et al. 1984,
    sec. 3.4.3), with the RMS of K samples scattering by about ``1 / sqrt(2 K)`` relative, so
    that a band whose gain is within the scatter is not worth its leverage. Not greedy: a band
    that misses the 7th electrical harmonic may score worse than a narrower one (measured:
    ``benchmarks/bench_unseen.py`` case 210, E = 3, 5, 7: 5.9, 14.4, 0.54x the floor).

    Parameters
    ----------
    d, pole_pairs, start, stop, speed, max_iterations, lut_points
        As :func:`held_out_error` (the band replaces its ``harmonics``).

    Returns
    -------
    HeldOut or None
        The chosen band's check (``tried`` lists every band scored, (E, RMS [rad])); None when
        even the narrowest band cannot be checked (:func:`held_out_error`).
    """
    scored: list[tuple[int, HeldOut]] = []
    ts = _split(start, stop, speed)
    for E in ELECTRICAL_BANDS:
        h = default_harmonics(pole_pairs, electrical=E)
        if scored and (ts is None or 2 * len(h) + 1 > MAX_LEVERAGE * (ts - start)):
            break
        r = held_out_error(d, pole_pairs, h, start=start, stop=stop, speed=speed,
                           max_iterations=max_iterations, lut_points=lut_points)  # fmt: skip
        if r is None:
            if not scored:
                return None
            continue
        scored.append((E, r))
    lowest = min(r.rms for _, r in scored)
    best = next(r for _, r in scored
                if r.rms <= lowest * (1.0 + 3.0 / math.sqrt(r.samples)))  # fmt: skip
    return dataclasses.replace(best, tried=tuple((E, r.rms) for E, r in scored))
