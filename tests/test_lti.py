"""Exact ZOH discretization with input delay: invariants (step invariance, delay as phase lag)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal
from hypothesis import given
from hypothesis import strategies as st

from hallcal.sim.bench import PAPER_CONTROLLER, PAPER_PLANT
from hallcal.sim.lti import ContinuousTF, DiscreteTF, c2d_zoh, tf2ss

TS = 2.5e-4


def continuous_step(tf: ContinuousTF, t: np.ndarray) -> np.ndarray:
    """Reference: step response of the rational part by scipy on a fine grid, shifted by tau."""
    fine = np.linspace(0, t[-1], 200_001)
    _, yc = scipy.signal.step(scipy.signal.lti(tf.num, tf.den), T=fine)
    return np.interp(t - tf.delay, fine, yc, left=0.0)


@pytest.mark.parametrize("delay", [0.0, 1.2e-4, TS, 2.4 * TS, 5 * TS])
def test_step_invariance_with_delay(delay):
    """ZOH is step invariant: samples of the delayed continuous step response are reproduced.

    Tolerance 1e-7 relative: limited by the linear interpolation of the reference on its grid.
    """
    tf = ContinuousTF(PAPER_PLANT.num, PAPER_PLANT.den, delay)
    sysd = tf.discretize(TS)
    k = np.arange(60)
    y = sysd.simulate(np.ones(k.size))
    ref = continuous_step(tf, k * TS)
    np.testing.assert_allclose(y, ref, atol=1e-7 * np.abs(ref).max())


@given(l=st.integers(0, 6), frac=st.floats(0.0, 0.99))
def test_delay_is_a_phase_lag(l, frac):
    """Adding l whole samples of delay multiplies the discrete FRF by exactly z^-l."""
    f = np.array([0.5, 5.0, 50.0, 500.0])
    base = ContinuousTF(PAPER_PLANT.num, PAPER_PLANT.den, frac * TS).discretize(TS)
    more = ContinuousTF(PAPER_PLANT.num, PAPER_PLANT.den, (frac + l) * TS).discretize(TS)
    z = np.exp(2j * np.pi * f * TS)
    np.testing.assert_allclose(
        more.frequency_response(f), base.frequency_response(f) * z**-l, rtol=1e-8
    )


def test_fractional_delay_matches_continuous_phase_at_low_frequency():
    """Below a tenth of Nyquist the ZOH model equals G(jw) e^{-jw(tau + Ts/2)} to O((wTs)^2)."""
    f = np.array([1.0, 10.0, 50.0])
    sysd = PAPER_PLANT.discretize(TS)
    w = 2 * np.pi * f
    expect = PAPER_PLANT.frequency_response(f) * np.exp(-1j * w * TS / 2)
    rel = np.abs(sysd.frequency_response(f) / expect - 1)
    assert np.all(rel < 2 * (w * TS) ** 2 + 1e-9)


def test_controller_state_space_matches_transfer_function():
    f = np.linspace(0.1, 1900, 37)
    ss = PAPER_CONTROLLER.state_space(TS)
    np.testing.assert_allclose(
        ss.frequency_response(f), PAPER_CONTROLLER.frequency_response(f, TS), rtol=1e-9
    )


def test_static_gain_and_proper_checks():
    tf = ContinuousTF((2.0,), (1.0, 3.0))
    sysd = tf.discretize(0.1)
    assert sysd.frequency_response([0.0])[0].real == pytest.approx(2.0 / 3.0, rel=1e-12)
    with pytest.raises(ValueError):
        ContinuousTF((1.0, 0.0, 0.0), (1.0, 1.0))
    with pytest.raises(ValueError):
        ContinuousTF((1.0,), (1.0, 1.0), -1e-3)
    with pytest.raises(ValueError):
        DiscreteTF((1.0, 0.0, 0.0), (1.0, 0.5))
    with pytest.raises(ValueError):
        c2d_zoh(tf2ss([1.0], [1.0, 1.0]), 0.0)


def test_feedthrough_with_delay_moves_to_a_delayed_input():
    """A biproper G with delay: the output uses the held, delayed input (no algebraic loop)."""
    tf = ContinuousTF((1.0, 2.0), (1.0, 1.0), 0.5 * TS)  # (s + 2)/(s + 1)
    sysd = tf.discretize(TS)
    assert sysd.D == 0.0
    y = sysd.simulate(np.ones(200))
    assert y[0] == 0.0
    ref = continuous_step(tf, np.arange(200) * TS)
    # the continuous step of a biproper system jumps by 1 at t = tau: compare after the jump
    np.testing.assert_allclose(y[1:], ref[1:], atol=1e-6)


_coefficients = st.lists(
    st.floats(-1e3, 1e3, allow_nan=False).filter(lambda v: abs(v) > 1e-3), min_size=1, max_size=6
)


@given(num=_coefficients, den=_coefficients)
def test_tf2ss_matches_scipy_signal(num, den):
    """The few lines of NumPy give scipy.signal.tf2ss's controllable canonical form exactly."""
    if len(num) > len(den):
        num, den = den, num
    ss = tf2ss(num, den)
    A, B, C, D = scipy.signal.tf2ss(num, den)
    if len(den) == 1:
        assert ss.order == 0 and ss.D == pytest.approx(float(D.ravel()[0]), rel=1e-12)
        return
    np.testing.assert_allclose(ss.A, A, rtol=1e-12, atol=0)
    np.testing.assert_allclose(ss.B, B[:, 0], rtol=1e-12, atol=0)
    np.testing.assert_allclose(ss.C, C[0], rtol=1e-12, atol=1e-12 * np.abs(C).max())
    assert ss.D == pytest.approx(float(D[0, 0]), rel=1e-12, abs=1e-300)


def test_tf2ss_leading_zeros_and_scaling():
    """Leading zeros are trimmed and a non-monic denominator is normalized, as scipy does."""
    ss = tf2ss([0.0, 2.0, 4.0], [2.0, 6.0, 8.0])
    A, B, C, D = scipy.signal.tf2ss([2.0, 4.0], [2.0, 6.0, 8.0])
    np.testing.assert_array_equal(ss.A, A)
    np.testing.assert_array_equal(ss.C, C[0])
    assert ss.D == D[0, 0] == 0.0
