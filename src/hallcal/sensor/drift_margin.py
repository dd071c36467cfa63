"""Drift margin of the power-up lock: how far the sensors may change after calibration before
the power-up decoder (:mod:`hallcal.sensor.absolute`) can lock on a WRONG pole pair.

The decoder compares the measured ``d`` with the calibrated model g_theta under the n_m
hypotheses (maximum likelihood, module doc of :mod:`hallcal.sensor.absolute`), and the misfit
test (:mod:`hallcal.sensor.misfit`) refuses signals that no hypothesis fits. A change of the
sensors since calibration -- a common gain change from the magnets' temperature (NdFeB
remanence about -0.12 %/K), one sensor's sensitivity or offset drifting -- moves the measured
point away from the true hypothesis's curve; on motors whose magnets differ by little, it can move
it *towards* another magnet's curve, so that a wrong pole pair both fits better than the right
one and fits well enough for the misfit test to pass it. The lock then claims certainty on the
wrong pole pair (measured: ``benchmarks/bench_unseen.txt``, "power-up after calibration").

This module computes, from the calibration's decoder tables alone (noise-free, over the whole
revolution, deterministic), for a sensor change ``d' = o + G (d - o) + delta`` (G diagonal
gains about f_init's offsets o, delta added offsets):

- at every table position q (uniform over the revolution in the calibration frame) the
  per-sample costs e_j of step 5 of the decoder (the decoder's own cost function, so the
  analysis sees exactly what the decoder and its C port see), j = 0 the right pole pair;
- the position is a *wrong-lock position* when some wrong j has
  ``e_j <= e_0 - 2 ln((1 - alpha) / alpha) / K`` (at standstill the expected evidence for j
  against the right one reaches the lock's within the standstill budget K) and
  ``e_j <= ln(kappa) / lam - 2`` (the misfit test's expected drift ``lam (e + 2) - ln kappa``
  is not positive: the wrong hypothesis passes as a fit; Wald's SPRT drift, 1945);
- the *wrong-lock share*: the fraction of positions that are wrong-lock positions;
- the *margin* of a kind of change (common gain, one sensor's gain, one sensor's offset): the
  smallest size of it (both signs, the worst sensor) at which the wrong-lock share exceeds
  :data:`DEFAULT_SHARE` (a power-up at a random position then locks wrong with about that
  probability, far above the decoder's stated alpha).

Units: gains as fractions (0.018 = 1.8 %), offsets as fractions of the channel's amplitude
(sqrt(2) times the RMS of ``g_h - o_h`` over the revolution).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.sensor.misfit import MisfitTest

__all__ = [
    "DEFAULT_SHARE",
    "PLAUSIBLE_GAIN_CHANGE",
    "PLAUSIBLE_SENSOR_CHANGE",
    "DriftMargin",
    "drift_margin",
    "wrong_lock_share",
]

#: Wrong-lock share above which a change is said to break the lock: one power-up in ten at a
#: random position. Not the decoder's alpha (0.1 %): on every motor measured, a gain change of
#: 0.2-1 % already gives wrong-lock positions near the weakest separations (a few per cent of
#: the revolution on the paper bench and on 6-pole-pair motors; bench_powerup_margin.txt), so
#: a margin at alpha would be about 0.2 % everywhere and name nothing; at 10 % it separates the
#: motors whose lock breaks at a fraction of the revolution from those where it breaks at most
#: positions.
DEFAULT_SHARE = 0.1

#: Common gain change a plausible temperature change produces [fraction]: NdFeB remanence
#: about -0.12 %/K, so a 40 K swing between calibration and power-up (a motor calibrated warm
#: and started cold, or the converse) changes every sensor's signal by about 4.8 %; linear Hall
#: sensors' own sensitivity drift (datasheets: a few 0.01 %/K after compensation) adds to it.
#: A margin below this is named by ``calibrate``.
PLAUSIBLE_GAIN_CHANGE = 0.05

#: One sensor's own sensitivity or offset change that is plausible without a fault [fraction]:
#: about 1 % over 60 K measured (docs: DESIGN "Temperature"). A per-sensor margin below it
#: makes :func:`hallcal.sensor.absolute.analyze_calibration` let the lock wait for motion.
PLAUSIBLE_SENSOR_CHANGE = 0.01

#: NdFeB remanence temperature coefficient [1/K] (magnitude), to state a margin in kelvin.
REMANENCE_TEMPCO = 0.0012

#: Largest change searched [fraction], twice the plausible one; no margin within it is reported
#: as inf (None in JSON).
SEARCH_LIMIT = 0.1

#: Positions per electrical period the analysis looks at (every L // GRID th table point):
#: bounds the work on fine tables (L up to 1024) at a share resolution of 1 / (GRID n_m).
GRID = 64

#: Scan step of the search [fraction], then bisection to :data:`RESOLUTION`.
_SCAN_STEP = 0.01
#: Resolution of the reported margins [fraction].
RESOLUTION = 0.0005


class _Decoder(Protocol):  # what is used of hallcal.sensor.absolute.PowerUpDecoder (read-only)
    @property
    def pole_pairs(self) -> int: ...
    @property
    def grid(self) -> int: ...
    @property
    def projection(self) -> NDArray[np.float64]: ...
    @property
    def offset(self) -> NDArray[np.float64]: ...
    @property
    def null(self) -> NDArray[np.float64]: ...
    @property
    def radius(self) -> NDArray[np.float64]: ...
    @property
    def zero(self) -> NDArray[np.float64]: ...
    @property
    def error_target(self) -> float: ...
    @property
    def misfit(self) -> MisfitTest: ...

    def standstill_costs(self, d: ArrayLike) -> NDArray[np.float64]: ...


@dataclass(frozen=True)
class DriftMargin:
    """How far the sensors may change since calibration before the power-up lock can go wrong.

    Attributes
    ----------
    common_gain : float
        Smallest common gain change |s - 1| of the three sensors (either sign) at which the
        wrong-lock share exceeds ``share``; inf when none within :data:`SEARCH_LIMIT`.
    sensor_gain : float
        The same for one sensor's gain alone (the worst sensor).
    sensor_offset : float
        The same for one sensor's offset alone, as a fraction of its amplitude.
    share : float
        The wrong-lock share that defines the margins.
    plausible_gain : float
        The common gain change a plausible temperature change produces
        (:data:`PLAUSIBLE_GAIN_CHANGE`).
    share_at_plausible : float
        Largest wrong-lock share for common gain changes up to +-plausible_gain (scanned in
        steps of 1 %).
    """

    common_gain: float
    sensor_gain: float
    sensor_offset: float
    share: float = DEFAULT_SHARE
    plausible_gain: float = PLAUSIBLE_GAIN_CHANGE
    share_at_plausible: float = 0.0

    @property
    def fragile(self) -> bool:
        """Whether a plausible temperature change can make the lock go wrong."""
        return self.common_gain < self.plausible_gain

    @property
    def robustness(self) -> float:
        """The smallest margin as a multiple of its plausible change (common gain against
        ``plausible_gain``, one sensor's gain and offset against
        :data:`PLAUSIBLE_SENSOR_CHANGE`): below 1, a plausible drift breaks the lock; inf when
        no margin is within the search. Below 1 the calibration makes the lock wait for motion
        (:func:`hallcal.sensor.absolute.analyze_calibration`)."""
        return min(
            self.common_gain / self.plausible_gain,
            self.sensor_gain / PLAUSIBLE_SENSOR_CHANGE,
            self.sensor_offset / PLAUSIBLE_SENSOR_CHANGE,
        )

    @property
    def kelvin(self) -> float:
        """common_gain as a change of the magnets' temperature [K] (NdFeB remanence)."""
        return self.common_gain / REMANENCE_TEMPCO

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (a margin beyond the search as None)."""

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {
            "common_gain": num(self.common_gain),
            "sensor_gain": num(self.sensor_gain),
            "sensor_offset": num(self.sensor_offset),
            "share": float(self.share),
            "plausible_gain": float(self.plausible_gain),
            "share_at_plausible": float(self.share_at_plausible),
        }

    @classmethod
    def from_dict(cls, d: Any) -> DriftMargin:
        """Inverse of :meth:`to_dict`; raises ValueError naming a malformed entry."""
        if not isinstance(d, dict):
            raise ValueError("drift_margin must be an object")

        def num(key: str) -> float:
            v = d.get(key)
            return math.inf if v is None else float(v)

        return cls(
            common_gain=num("common_gain"),
            sensor_gain=num("sensor_gain"),
            sensor_offset=num("sensor_offset"),
            share=float(d.get("share", DEFAULT_SHARE)),
            plausible_gain=float(d.get("plausible_gain", PLAUSIBLE_GAIN_CHANGE)),
            share_at_plausible=float(d.get("share_at_plausible", 0.0)),
        )


def _table_signals(dec: _Decoder) -> NDArray[np.float64]:
    """Noise-free signals (M', 3) at the table points, in order around the revolution (every
    ``L // GRID`` th point: at most :data:`GRID` per electrical period).

    ``d_q = o + R_q P+ [cos psi_q, sin psi_q] + Z_q nv`` with ``psi_q = 2 pi q / L``: exact,
    since ``P+ P + nv nv'`` is the identity (nv spans P's null space).
    """
    q = np.arange(0, dec.radius.size, max(1, dec.grid // GRID))
    psi = TWO_PI * q / dec.grid
    pinv = np.linalg.pinv(dec.projection)  # (3, 2)
    planar = np.stack([np.cos(psi), np.sin(psi)], axis=1) @ pinv.T  # (M', 3)
    return dec.offset + dec.radius[q, None] * planar + dec.zero[q, None] * dec.null


def _amplitudes(signals: NDArray, offset: NDArray) -> NDArray:
    """Per channel sqrt(2) x RMS of g_h - o_h over the revolution (a sinusoid's amplitude)."""
    return np.sqrt(2.0 * np.mean(np.square(signals - offset), axis=0))


def _wrong_lock(dec: _Decoder, d: NDArray, standstill_budget: int) -> NDArray[np.bool_]:
    """Per sample of ``d`` (consecutive runs around the revolution, each from table point 0),
    whether a wrong pole pair locks there (the two conditions of the module doc)."""
    # column 0 the right pole pair (each run continuous from q = 0); with the decoder's gain
    # profile, each position's own best common gain (what samples held there converge to)
    e = dec.standstill_costs(d)
    if e.shape[1] < 2:
        return np.zeros(e.shape[0], dtype=bool)
    alpha = dec.error_target
    lock = 2.0 * math.log((1.0 - alpha) / alpha) / max(int(standstill_budget), 1)
    fit = dec.misfit.drift / dec.misfit.weight - 2.0
    wrong = np.min(e[:, 1:], axis=1)
    return (wrong <= e[:, 0] - lock) & (wrong <= fit)


def _about_offset(dec: _Decoder, sig: NDArray) -> tuple[NDArray, NDArray]:
    """``(d - o, amp)`` of the table signals: what every change of :func:`_changed` starts
    from (computed once per analysis, not once per change)."""
    return sig - dec.offset, _amplitudes(sig, dec.offset)


def _changed(
    dec: _Decoder, base: tuple[NDArray, NDArray], gains: NDArray, offsets: NDArray
) -> NDArray:
    """``o + G (d - o) + delta amp`` for one change (gains about o, offsets in amplitudes);
    ``base`` is :func:`_about_offset` of the table signals d."""
    centered, amplitudes = base
    return dec.offset + gains * centered + offsets * amplitudes


def wrong_lock_share(
    decoder: _Decoder,
    gains: ArrayLike = (1.0, 1.0, 1.0),
    offsets: ArrayLike = (0.0, 0.0, 0.0),
    *,
    standstill_budget: int = 200,
) -> float:
    """Fraction of positions where the changed sensors let a wrong pole pair lock.

    Parameters
    ----------
    decoder : PowerUpDecoder
        The calibration's decoder.
    gains : array_like (3,)
        Sensor gains since calibration, about f_init's offsets o (1 = unchanged).
    offsets : array_like (3,)
        Offsets added since calibration, as fractions of each channel's amplitude.
    standstill_budget : int, keyword-only
        K of the lock-evidence condition (the identifiability analysis's standstill budget).

    Returns
    -------
    float
        Share of the table positions that are wrong-lock positions (module doc).
    """
    sig = _table_signals(decoder)
    g = np.asarray(gains, dtype=np.float64)
    o = np.asarray(offsets, dtype=np.float64)
    changed = _changed(decoder, _about_offset(decoder, sig), g, o)
    return float(np.mean(_wrong_lock(decoder, changed, standstill_budget)))


#: The changes of each kind at size t: (gains, offsets) as functions of t (both signs; one
#: sensor at a time for the per-sensor kinds).
_Change = Callable[[float], NDArray[np.float64]]


def _gain_change(direction: NDArray[np.float64]) -> tuple[_Change, _Change]:
    """Gains 1 + t direction, offsets unchanged."""

    def gains(t: float) -> NDArray[np.float64]:
        return 1.0 + t * direction

    def offsets(t: float) -> NDArray[np.float64]:
        return np.zeros(3)

    return gains, offsets


def _offset_change(direction: NDArray[np.float64]) -> tuple[_Change, _Change]:
    """Gains unchanged, offsets t direction (fractions of each sensor's amplitude)."""

    def gains(t: float) -> NDArray[np.float64]:
        return np.ones(3)

    def offsets(t: float) -> NDArray[np.float64]:
        return t * direction

    return gains, offsets


_SIGNS = (1.0, -1.0)
_KINDS: dict[str, list[tuple[_Change, _Change]]] = {
    "common_gain": [_gain_change(np.full(3, s)) for s in _SIGNS],
    "sensor_gain": [_gain_change(s * e) for e in np.eye(3) for s in _SIGNS],
    "sensor_offset": [_offset_change(s * e) for e in np.eye(3) for s in _SIGNS],
}


def _shares(
    dec: _Decoder, base: tuple[NDArray, NDArray], t: float, kinds: list[str], budget: int
) -> list[float]:
    """Per kind, the largest wrong-lock share over its changes of size t (one cost call);
    ``base`` is :func:`_about_offset` of the table signals."""
    runs = [(k, g(t), o(t)) for k in kinds for g, o in _KINDS[k]]
    d = np.concatenate([_changed(dec, base, g, o) for _, g, o in runs])
    bad = _wrong_lock(dec, d, budget).reshape(len(runs), base[0].shape[0]).mean(axis=1)
    return [max(float(b) for (k2, _, _), b in zip(runs, bad, strict=True) if k2 == k)
            for k in kinds]  # fmt: skip


def drift_margin(
    decoder: _Decoder,
    *,
    standstill_budget: int = 200,
    share: float = DEFAULT_SHARE,
    plausible_gain: float = PLAUSIBLE_GAIN_CHANGE,
) -> DriftMargin:
    """The drift margins of a calibration's power-up lock (see the module doc).

    A scan in steps of 1 % up to :data:`SEARCH_LIMIT`, then bisection to
    :data:`RESOLUTION` below the first size whose share exceeds ``share`` (a deterministic
    count of cost evaluations: about 10 x 14 runs around the revolution).

    Parameters
    ----------
    decoder : PowerUpDecoder
        The calibration's decoder (tables, noise sigma, alpha, misfit test).
    standstill_budget : int, keyword-only
        K of the lock-evidence condition.
    share : float, keyword-only
        Wrong-lock share that defines a margin.
    plausible_gain : float, keyword-only
        Common gain change of a plausible temperature swing.

    Returns
    -------
    DriftMargin
    """
    dec, budget = decoder, standstill_budget
    base = _about_offset(dec, _table_signals(dec))
    kinds = list(_KINDS)
    margin = dict.fromkeys(kinds, math.inf)
    at_plausible = 0.0
    sizes = _SCAN_STEP * np.arange(1, round(SEARCH_LIMIT / _SCAN_STEP) + 1)
    lo = 0.0
    for t in sizes:
        open_kinds = [k for k in kinds if not math.isfinite(margin[k])]
        need_common = t <= plausible_gain + 1e-12 and "common_gain" not in open_kinds
        todo = open_kinds + (["common_gain"] if need_common else [])
        if not todo:
            break
        got = dict(zip(todo, _shares(dec, base, float(t), todo, budget), strict=True))
        if t <= plausible_gain + 1e-12:
            at_plausible = max(at_plausible, got["common_gain"])
        for k in open_kinds:
            if got[k] > share:
                margin[k] = _bisect(lambda x, k=k: _shares(dec, base, x, [k], budget)[0] > share,
                                    lo, float(t))  # fmt: skip
        lo = float(t)
    return DriftMargin(
        common_gain=margin["common_gain"],
        sensor_gain=margin["sensor_gain"],
        sensor_offset=margin["sensor_offset"],
        share=share,
        plausible_gain=plausible_gain,
        share_at_plausible=at_plausible,
    )


def _bisect(exceeds, lo: float, hi: float) -> float:
    """Smallest size in (lo, hi] (to :data:`RESOLUTION`) where ``exceeds`` holds, given it holds
    at hi and not at lo (the first crossing of the scan)."""
    while hi - lo > RESOLUTION:
        mid = 0.5 * (lo + hi)
        if exceeds(mid):
            hi = mid
        else:
            lo = mid
    return hi
