"""Band edge and static un-warping (:mod:`hallcal.fit.warp`) on synthetic curves with a known
band and a known warp, and on the virtual bench."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hallcal._constants import TWO_PI
from hallcal.fit.warp import BandEdgeStatus, band_edge, f_init_view, unwarp
from hallcal.sensor.flux import FluxModel, FourierBasis


def _curve(seed: int, n: int, edge: int) -> FluxModel:
    """Three sensors at 120 degrees of harmonic n, with content at every harmonic up to edge
    (1/10 of the fundamental, decaying) and a top harmonic edge of 4 %."""
    rng = np.random.default_rng(seed)
    basis = FourierBasis(tuple(range(1, edge + 1)))
    th = np.zeros((3, basis.size))
    for h in range(1, edge + 1):
        js, jc = basis.index(h)
        amp = 0.02 / (1.0 + (h / n) ** 2)
        th[:, js] = amp * rng.standard_normal(3)
        th[:, jc] = amp * rng.standard_normal(3)
    for s in range(3):
        js, jc = basis.index(n)
        th[s, js] += math.sin(TWO_PI * s / 3)
        th[s, jc] += math.cos(TWO_PI * s / 3)
        js, jc = basis.index(edge)
        th[s, jc] += 0.04 * math.cos(edge / n * TWO_PI * s / 3)
    return FluxModel(basis, th)


def _data(seed: int, n: int = 3, edge: int = 9, sigma: float = 1e-3, N: int = 30000):
    """Samples over 3.2 revolutions seen at a warped angle y = y0 + v(y0)."""
    rng = np.random.default_rng(seed + 100)
    flux = _curve(seed, n, edge)
    y0 = np.linspace(0.0, 3.2 * TWO_PI, N)
    v = 0.004 * np.sin(y0 + 0.3) + 0.002 * np.cos(3 * y0) + 0.001 * np.sin(2 * n * y0)
    d = flux(y0) + sigma * rng.standard_normal((N, 3))
    return flux, y0, y0 + v, d, sigma


@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_band_edge_finds_the_band_and_the_true_angle(seed):
    flux, y0, y, d, sigma = _data(seed)
    edge = band_edge(y, d, pole_pairs=3, noise_variance=sigma**2)
    assert edge.status is BandEdgeStatus.FOUND and edge.edge == 9
    x = edge.unwarp.parametrize(y)
    err = (x - y0) - np.mean(x - y0)
    # the angle noise of one sample is sigma sqrt(2/3) / (A n) = 2.7e-4 rad; the warp is
    # estimated from all samples: its error is a small fraction of that
    assert np.std(err) < 1e-4
    assert np.std(y - y0) > 2e-3  # the seen angle is far off
    # the un-warped model is the curve itself, up to the rotation by the mean shift
    shift = float(np.mean(x - y0))
    t = np.linspace(0, TWO_PI, 400)
    np.testing.assert_allclose(edge.flux(t + shift), flux(t), atol=2e-3)


def test_unwarp_residual_is_chi_square_at_the_band_and_huge_below():
    flux, y0, y, d, sigma = _data(7)
    view = f_init_view(y, d, harmonics=60, noise_variance=sigma**2)
    at = unwarp(view, 9, warp_harmonics=30)
    below = unwarp(view, 8, warp_harmonics=30)
    above = unwarp(view, 12, warp_harmonics=30)
    assert at.status.success
    # chi-square with dof degrees of freedom: within 5 standard deviations sqrt(2 dof)
    assert abs(at.residual - at.dof) < 5 * math.sqrt(2 * at.dof)
    assert below.residual > 100 * below.dof
    assert above.residual <= at.residual + 1e-6 * at.residual  # a wider band fits no worse
    with pytest.raises(ValueError):
        unwarp(view, 60, warp_harmonics=30)


def test_edge_at_the_bound_is_reported():
    flux, y0, y, d, sigma = _data(3)
    edge = band_edge(y, d, pole_pairs=3, noise_variance=sigma**2, max_edge=7)
    assert edge.edge == 7 and edge.status is BandEdgeStatus.AT_BOUND


def test_the_lagged_system_equals_the_explicit_products():
    """unwarp's Gauss-Newton system from one transform of g' (shifted transforms, prefix sums
    of lagged products) is the one of the explicit Jacobian: the same warp and residual."""
    flux, y0, y, d, sigma = _data(5)
    view = f_init_view(y, d, harmonics=60, noise_variance=sigma**2)
    for E in (8, 9, 20):
        fast = unwarp(view, E, warp_harmonics=30)
        ref = unwarp(view, E, warp_harmonics=30, reference=True)
        # the two systems differ by rounding (1e-14 relative), far below the 1e-9 ridge of
        # the step; the Gauss-Newton iterates then agree to rounding amplified by the solve
        np.testing.assert_allclose(fast.warp, ref.warp, rtol=0, atol=1e-9)
        assert fast.iterations == ref.iterations
        assert abs(fast.residual - ref.residual) <= 1e-8 * ref.residual


def test_the_narrower_view_is_the_leading_block_of_the_wider_one():
    """band_edge's view on 1..L from the probe's normal equations on 1..L0 > L is the view
    fitted on 1..L (the same moments: bit for bit)."""
    from hallcal.fit.gauss_newton import regression_normal_equations
    from hallcal.fit.warp import _view_from_normal_equations

    flux, y0, y, d, sigma = _data(2)
    M, rhs, _ = regression_normal_equations(y, d, np.arange(1, 61))
    narrow = _view_from_normal_equations(M[:41, :41], rhs[:41], sigma**2)
    direct = f_init_view(y, d, harmonics=20, noise_variance=sigma**2)
    np.testing.assert_array_equal(narrow.theta, direct.theta)
    assert narrow.coefficient_variance == direct.coefficient_variance
