"""f_init (eq. fimp): Clarke, projection, unwrapping, streaming versus whole-array."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hallcal.sensor.reconstruction import (
    NOMINAL_PHASES,
    InitReconstructor,
    clarke_matrix,
    f_init,
    projection_matrix,
    unwrap_to,
)


def three_phase(y0, n, *, amplitude=1.0, phases=NOMINAL_PHASES, offset=0.0):
    return offset + amplitude * np.cos(n * np.asarray(y0)[:, None] - np.asarray(phases)[None, :])


def test_projection_of_nominal_phases_is_clarke():
    np.testing.assert_allclose(projection_matrix(), clarke_matrix()[:2], atol=1e-15)


def test_clarke_maps_three_phase_to_cos_sin():
    psi = np.linspace(-3, 3, 7)
    ab = three_phase(psi, 1) @ clarke_matrix().T
    np.testing.assert_allclose(ab[:, 0], np.cos(psi), atol=1e-14)
    np.testing.assert_allclose(ab[:, 1], np.sin(psi), atol=1e-14)
    np.testing.assert_allclose(ab[:, 2], 0.0, atol=1e-14)


@given(x=st.floats(-50, 50), ref=st.floats(-50, 50))
def test_unwrap_is_nearest_congruent_value(x, ref):
    u = unwrap_to(x, ref)
    assert -math.pi - 1e-9 <= u - ref < math.pi + 1e-9
    k = (u - x) / (2 * math.pi)
    assert abs(k - round(k)) < 1e-9


@given(
    steps=arrays(np.float64, st.integers(2, 300), elements=st.floats(-0.99, 0.99)),
    n=st.integers(1, 30),
    start=st.floats(-0.99, 0.99),
    amplitude=st.floats(0.1, 1e3),
    offset=st.floats(-1e3, 1e3),
)
def test_f_init_inverts_pure_sinusoids(steps, n, start, amplitude, offset):
    """Property: any trajectory with electrical steps below pi is recovered exactly.

    The electrical step per sample is ``steps * pi`` (|step| < pi). The start lies within
    pi / n of y = 0 (``start`` is that fraction) so the first unwrap picks the right period.
    Tolerance: atan2 and the projection are exact to a few ulp of the electrical angle, which
    grows with the path length.
    """
    y0 = (start + np.cumsum(steps) - steps[0]) * math.pi / n
    phases = np.array(NOMINAL_PHASES)
    d = three_phase(y0, n, amplitude=amplitude, phases=phases, offset=offset)
    P = projection_matrix(phases)
    y = f_init(d, n, projection=P)
    scale = 1 + np.max(np.abs(n * y0)) + abs(offset) / amplitude
    np.testing.assert_allclose(y, y0, atol=1e-12 * scale)


@given(
    steps=arrays(np.float64, st.integers(1, 200), elements=st.floats(-3.5, 3.5)),
    n=st.integers(1, 25),
    noise=st.floats(0, 0.5),
)
def test_streaming_equals_whole_array(steps, n, noise):
    """the per-sample and the vectorized f_init agree to 1e-12, even for steps > pi."""
    rng = np.random.default_rng(0)
    y0 = np.cumsum(steps) / n
    d = three_phase(y0, n) + noise * rng.standard_normal((y0.size, 3))
    y_vec = f_init(d, n, y_initial=0.1)
    rec = InitReconstructor(n, y_initial=0.1)
    y_str = np.array([rec.update(*row) for row in d])
    np.testing.assert_allclose(y_vec, y_str, rtol=0, atol=1e-12 * (1 + np.abs(y_str).max()))


def test_unequal_sensor_spacing_and_offsets():
    """With the sensors' true phases and offsets, f_init is exact again (ring jig)."""
    phases = np.radians([0.0, 101.0, 261.0])
    y0 = np.linspace(0, 4 * np.pi, 5000)
    d = three_phase(y0, 25, amplitude=1500.0, phases=phases, offset=np.array([2000, -300, 40]))
    y = f_init(d, 25, projection=projection_matrix(phases), offset=[2000, -300, 40])
    np.testing.assert_allclose(y, y0, atol=1e-12 * 25 * 4 * np.pi)
    # The Clarke f_init on the same data is off by degrees: the point of estimating the spacing.
    y_clarke = f_init(d - np.array([2000, -300, 40]), 25)
    assert np.max(np.abs(y_clarke - y0)) * 25 > np.radians(5)
