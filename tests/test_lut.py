"""The lookup table of eq. (f_final): invariants of f_star for any bijective model."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from hallcal.sensor.flux import FluxModel, FourierBasis, sinusoidal_theta
from hallcal.sensor.lut import LUT, NotBijectiveError, StarReconstructor, build_lut
from hallcal.sensor.reconstruction import projection_matrix


@settings(max_examples=25)
@given(
    n=st.integers(1, 25),
    seed=st.integers(0, 2**31 - 1),
    size=st.floats(0.0, 0.05),
    offset=st.floats(-100, 100),
    spacing=st.floats(-20, 20),
)
def test_f_star_inverts_the_model(n, seed, size, offset, spacing):
    """For noise-free signals from the model itself, f_star returns the true angle.

    The residual is the piecewise-linear interpolation error of the table, at most
    h^2 max|eta''| / 8 with the node spacing h = 2 pi / M; eta'' is estimated from the table's
    second differences (a factor 2 of margin covers that estimate and the nonuniform nodes).
    The sensors may sit off 120 degrees and carry offsets when f_init knows them.
    """
    rng = np.random.default_rng(seed)
    harmonics = tuple(sorted({1, 2, n, 2 * n, 3 * n}))
    basis = FourierBasis(harmonics)
    phases = np.radians([0.0, 120.0 + spacing, 240.0])
    theta = sinusoidal_theta(basis, n, amplitude=1.0, offset=offset, phases=phases)
    theta[:, 1:] += size * rng.standard_normal((3, basis.size - 1)) / np.sqrt(basis.size)
    flux = FluxModel(basis, theta)
    P = projection_matrix(phases)
    lut = build_lut(flux, n, projection=P, offset=np.full(3, offset))
    # perturbations of 5 % rarely fold the map; a folded one is another test's subject
    assume(lut.bijective)
    y0 = np.cumsum(np.full(5000, 0.9 * np.pi / n / 3)) * rng.choice([-1, 1])
    y0 -= y0[0]
    y_star = lut.f_star(flux(y0))
    h = 2 * np.pi / lut.points
    eta = np.r_[lut.eta[-1], lut.eta, lut.eta[0]]
    curvature = np.max(np.abs(np.diff(eta, 2))) / h**2
    bound = 2 * h**2 * curvature / 8 + 1e-12
    assert np.max(np.abs(y_star - y0)) < bound
    assert bound < 1e-5  # and the table is fine enough to be far below any Hall noise floor
    # and the correction is periodic: the same after a whole revolution
    y = np.linspace(0, 2 * np.pi, 257)
    np.testing.assert_allclose(lut.correction(y), lut.correction(y + 2 * np.pi), atol=1e-12)


def test_rebuilt_table_equals_the_original():
    basis = FourierBasis((1, 11, 33))
    theta = sinusoidal_theta(basis, 11)
    theta[0, 1] = 0.03
    lut = build_lut(FluxModel(basis, theta), 11, points=512)
    again = LUT.from_arrays(11, lut.projection, lut.offset, lut.y_hat, lut.eta)
    d = FluxModel(basis, theta)(np.linspace(0, 9, 3000))
    np.testing.assert_array_equal(again.f_star(d), lut.f_star(d))
    rec = StarReconstructor(again)
    np.testing.assert_allclose(
        [rec.update(*row) for row in d[:500]], lut.f_star(d[:500]), atol=1e-12
    )


def test_a_folded_map_is_not_bijective_and_f_star_refuses():
    """A second electrical harmonic (negative sequence, a cos(2 (n y0 - 2 pi h / 3))) above half
    the fundamental makes d psi / d y0 change sign where the two oppose (the map folds): no
    table on f_init can be right, so the table says so and f_star refuses."""
    n = 5
    basis = FourierBasis((n, 2 * n))
    theta = sinusoidal_theta(basis, n)
    js, jc = basis.index(2 * n)
    phi = 4 * np.pi * np.arange(3) / 3
    theta[:, js], theta[:, jc] = 0.6 * np.sin(phi), 0.6 * np.cos(phi)
    lut = build_lut(FluxModel(basis, theta), n, points=512)
    assert not lut.bijective and lut.min_slope < 0
    with pytest.raises(NotBijectiveError):
        lut.f_star(FluxModel(basis, theta)(np.linspace(0, 1, 50)))


def test_flux_evaluated_in_blocks_equals_one_product():
    """Long evaluations run in blocks (bounded memory); the values are those of one product,
    and the fused value-and-derivative equals the two separate evaluations."""
    from hallcal.sensor import flux as fx

    rng = np.random.default_rng(3)
    basis = FourierBasis(tuple(range(1, 56)))
    model = FluxModel(basis, rng.standard_normal((3, basis.size)))
    for n in (1, 2, fx.EVALUATION_BLOCK, fx.EVALUATION_BLOCK + 1, 3 * fx.EVALUATION_BLOCK - 7):
        y = rng.uniform(-3.0, 25.0, n)
        g, dg = model.value_and_derivative(y)
        assert np.array_equal(g, model(y))
        assert np.array_equal(dg, model.derivative(y))
        np.testing.assert_allclose(g, basis.evaluate(y) @ model.theta.T, rtol=0, atol=1e-12)
        np.testing.assert_allclose(dg, basis.derivative(y) @ model.theta.T, rtol=0, atol=1e-11)
    assert model(0.5).shape == (1, 3)
    sizes = [b - a for a, b in fx._blocks(5 * fx.EVALUATION_BLOCK + 1)]
    assert sum(sizes) == 5 * fx.EVALUATION_BLOCK + 1 and min(sizes) > fx.EVALUATION_BLOCK // 2


def test_flux_blocks_in_two_threads_equal_the_blocks_one_after_the_other():
    """A long evaluation's blocks go to two threads: the bits of the blocks one after the other
    (each block is computed as alone, whichever thread takes it)."""
    from hallcal.sensor import flux as fx

    rng = np.random.default_rng(4)
    basis = FourierBasis(tuple(range(1, 12)))
    model = FluxModel(basis, rng.standard_normal((3, basis.size)))
    y = rng.uniform(-3.0, 25.0, 5 * fx.EVALUATION_BLOCK + 3)
    blocks = fx._blocks(y.size)
    assert len(blocks) > 2  # the threaded path
    g = np.vstack([basis.evaluate(y[a:b]) @ model.theta.T for a, b in blocks])
    dg = np.vstack([basis.derivative(y[a:b]) @ model.theta.T for a, b in blocks])
    value, slope = model.value_and_derivative(y)
    assert np.array_equal(value, g) and np.array_equal(slope, dg)
    assert np.array_equal(model(y), g) and np.array_equal(model.derivative(y), dg)
