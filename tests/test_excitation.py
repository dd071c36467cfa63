"""Tests of hallcal.identify.excitation: ramps and random-phase multisines."""

from __future__ import annotations

import numpy as np
import pytest

from hallcal.errors import HallcalInputError
from hallcal.identify.excitation import multisine, multisine_experiment

N = 1000
TS = 1e-3  # resolution 1 Hz
BAND = (3.0, 120.0)


def _spectrum_lines(x: np.ndarray, rel: float = 1e-9) -> np.ndarray:
    spec = np.abs(np.fft.rfft(x))
    return np.flatnonzero(spec > rel * spec.max())


@pytest.mark.parametrize("kind", ["full", "odd", "random-odd"])
def test_rms_exact_and_spectrum_only_on_lines(kind: str) -> None:
    ms = multisine(N, TS, band=BAND, rms=0.37, lines=kind, seed=5)
    assert ms.status == "ok"
    assert ms.signal.shape == (N,)
    assert ms.signal.dtype == np.float64
    assert np.sqrt(np.mean(ms.signal**2)) == pytest.approx(0.37, rel=1e-12)
    np.testing.assert_array_equal(_spectrum_lines(ms.signal), ms.lines)
    np.testing.assert_allclose(ms.freq, ms.lines / (N * TS))
    assert ms.freq.min() >= BAND[0] and ms.freq.max() <= BAND[1]
    # flat amplitude spectrum, phases in [0, 2 pi)
    spec = np.fft.rfft(ms.signal)[ms.lines]
    np.testing.assert_allclose(np.abs(spec), 0.5 * N * ms.amplitudes, rtol=1e-10)
    np.testing.assert_allclose(ms.amplitudes, ms.amplitudes[0])
    assert np.all((ms.phases >= 0.0) & (ms.phases < 2.0 * np.pi))
    np.testing.assert_allclose(np.angle(spec * np.exp(-1j * ms.phases)), 0.0, atol=1e-9)


def test_line_sets() -> None:
    full = multisine(N, TS, band=BAND, rms=1.0, lines="full").lines
    np.testing.assert_array_equal(full, np.arange(3, 121))
    odd = multisine(N, TS, band=BAND, rms=1.0, lines="odd").lines
    np.testing.assert_array_equal(odd, np.arange(3, 121, 2))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_random_odd_leaves_one_out_of_each_group_of_three(seed: int) -> None:
    ms = multisine(N, TS, band=BAND, rms=1.0, lines="random-odd", seed=seed)
    odd = np.arange(3, 121, 2)  # 59 odd lines: 19 full groups and an incomplete one of 2
    assert np.all(np.isin(ms.lines, odd))
    excited = np.isin(odd, ms.lines)
    groups = excited[: 3 * (odd.size // 3)].reshape(-1, 3)
    np.testing.assert_array_equal(groups.sum(axis=1), 2)
    assert np.all(excited[3 * (odd.size // 3) :])  # incomplete last group kept whole
    # the left-out position varies between groups (it is random)
    assert len(set(np.argmin(groups, axis=1).tolist())) > 1


def test_seed_reproducible_and_rng_accepted() -> None:
    a = multisine(N, TS, band=BAND, rms=1.0, lines="random-odd", seed=11)
    b = multisine(N, TS, band=BAND, rms=1.0, lines="random-odd", seed=11)
    c = multisine(N, TS, band=BAND, rms=1.0, lines="random-odd", seed=12)
    np.testing.assert_array_equal(a.signal, b.signal)
    assert not np.array_equal(a.phases, c.phases)
    d = multisine(N, TS, band=BAND, rms=1.0, lines="random-odd", rng=np.random.default_rng(11))
    np.testing.assert_array_equal(a.signal, d.signal)
    with pytest.raises(HallcalInputError):
        multisine(N, TS, band=BAND, rms=1.0, rng=np.random.default_rng(1), seed=1)


def test_explicit_lines() -> None:
    ms = multisine(N, TS, band=BAND, rms=2.0, lines=[5, 7, 40])
    np.testing.assert_array_equal(ms.lines, [5, 7, 40])
    np.testing.assert_array_equal(_spectrum_lines(ms.signal), [5, 7, 40])
    with pytest.raises(HallcalInputError):
        multisine(N, TS, band=BAND, rms=2.0, lines=[1, 5])  # line 1 is below the band


@pytest.mark.parametrize(
    "kwargs",
    [
        {"band": (600.0, 700.0)},  # above Nyquist: no line
        {"band": (10.2, 10.8)},  # between two lines
        {"band": (20.0, 10.0)},
        {"rms": -1.0},
        {"lines": "even"},
    ],
)
def test_invalid_arguments(kwargs: dict) -> None:
    args = {"band": BAND, "rms": 1.0} | kwargs
    with pytest.raises(HallcalInputError):
        multisine(N, TS, **args)


def test_nyquist_and_dc_never_excited() -> None:
    ms = multisine(8, 1.0, band=(0.0, 0.5), rms=1.0)
    np.testing.assert_array_equal(ms.lines, [1, 2, 3])


def test_experiment_layout_periodicity_and_realizations() -> None:
    m, p = 4, 3
    ex = multisine_experiment(
        N, TS, periods=p, realizations=m, band=BAND, rms=0.5, lines="random-odd", seed=7
    )
    assert ex.status == "ok"
    assert ex.r.shape == (m * p * N,)
    assert ex.realization.dtype.kind == "i"
    np.testing.assert_array_equal(np.bincount(ex.realization), np.full(m, p * N))
    np.testing.assert_array_equal(ex.realization, np.repeat(np.arange(m), p * N))
    np.testing.assert_allclose(ex.t, np.arange(m * p * N) * TS)
    blocks = ex.r.reshape(m, p, N)
    for i in range(m):
        # periodic within a realization, equal to the stored period, exact RMS
        np.testing.assert_array_equal(blocks[i], np.broadcast_to(ex.multisines[i], (p, N)))
        assert np.sqrt(np.mean(ex.multisines[i] ** 2)) == pytest.approx(0.5, rel=1e-12)
        # same excited lines in every realization (random-odd detection lines included)
        np.testing.assert_array_equal(_spectrum_lines(ex.multisines[i]), ex.lines)
    # new random phases in every realization
    assert ex.phases.shape == (m, ex.lines.size)
    for i in range(m):
        for j in range(i):
            assert np.max(np.abs(np.exp(1j * ex.phases[i]) - np.exp(1j * ex.phases[j]))) > 0.5
    # reproducible
    again = multisine_experiment(
        N, TS, periods=p, realizations=m, band=BAND, rms=0.5, lines="random-odd", seed=7
    )
    np.testing.assert_array_equal(ex.r, again.r)
    other = multisine_experiment(
        N, TS, periods=p, realizations=m, band=BAND, rms=0.5, lines="random-odd", seed=8
    )
    assert not np.array_equal(ex.r, other.r)


def test_experiment_drift_is_a_known_ramp_under_the_multisine() -> None:
    m, p, drift = 2, 3, 0.8
    ex = multisine_experiment(
        N, TS, periods=p, realizations=m, band=BAND, rms=0.5, lines="odd", seed=1, drift=drift
    )
    flat = multisine_experiment(
        N, TS, periods=p, realizations=m, band=BAND, rms=0.5, lines="odd", seed=1
    )
    assert ex.drift == drift
    np.testing.assert_allclose(ex.trend, drift * ex.t)
    np.testing.assert_allclose(ex.r - ex.trend, flat.r, atol=1e-14)
    # the ramp is continuous across realizations: slope drift over the whole experiment
    assert np.polyfit(ex.t, ex.r, 1)[0] == pytest.approx(drift, rel=1e-2)
