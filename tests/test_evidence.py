"""Group relevance by the evidence (:mod:`hallcal.fit.evidence`): the fixed point and the group
test against brute-force Gaussian log-densities, the normal-plane system against its definition,
and what the relevance keeps on the virtual bench."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hallcal._constants import TWO_PI
from hallcal.fit.evidence import (
    GroupEvidenceStatus,
    _block_gain,
    group_evidence,
    harmonic_groups,
    harmonic_relevance,
    shape_system,
)
from hallcal.sensor.flux import FluxModel, FourierBasis


def _problem(seed=0, n_angles=400, K=8, sigma=0.05, zero=(2, 5, 7)):
    """Linear regression of three sensors on harmonics 1..K; no content at ``zero``."""
    rng = np.random.default_rng(seed)
    basis = FourierBasis(tuple(range(1, K + 1)))
    y = rng.uniform(0, TWO_PI, n_angles)
    J = np.kron(np.eye(3), basis.evaluate(y))
    theta = rng.standard_normal((3, 2 * K + 1)) * 0.3
    for k in zero:
        theta[:, 2 * k - 1 : 2 * k + 1] = 0.0
    z = J @ theta.ravel() + sigma * rng.standard_normal(J.shape[0])
    return J, z, K, theta


def _log_evidence(J, z, alpha_j, s2):
    """log N(z; 0, s2 I + J A^-1 J^T) by brute force (coefficients with finite alpha only)."""
    act = np.isfinite(alpha_j)
    Ja = J[:, act]
    C = s2 * np.eye(z.size) + (Ja / alpha_j[act]) @ Ja.T
    _, logdet = np.linalg.slogdet(C)
    return -0.5 * (z.size * math.log(TWO_PI) + logdet + z @ np.linalg.solve(C, z))


def test_fixed_point_is_the_evidence_maximum_and_reports_it():
    """At convergence each group's precision maximizes the brute-force evidence (others fixed);
    the posterior mean is the linear MAP; the reported log evidence is the brute-force one; the
    result does not depend on the linearization point."""
    J, z, K, _ = _problem()
    s2 = 0.05**2
    G, b = J.T @ J, J.T @ z
    grp = harmonic_groups(K)
    a = group_evidence(G, b, float(z @ z), np.zeros(G.shape[0]), grp, np.ones(K + 1), s2,
                       n=z.size, update_noise=False, tol=1e-8, max_iterations=5000)  # fmt: skip
    assert a.status is GroupEvidenceStatus.CONVERGED
    alpha_j = a.precision[grp]
    act = np.isfinite(alpha_j)
    A = G[np.ix_(act, act)] / s2 + np.diag(alpha_j[act])
    np.testing.assert_allclose(a.mean[act], np.linalg.solve(A, b[act] / s2), rtol=1e-8)
    assert np.all(a.mean[~act] == 0.0)
    best = _log_evidence(J, z, alpha_j, s2)
    assert a.log_evidence == pytest.approx(best, abs=1e-6)
    for k in np.nonzero(np.isfinite(a.precision))[0]:
        for f in (0.7, 1.4):  # 1e-9: rounding of the two log-determinants
            alt = a.precision.copy()
            alt[k] *= f
            assert _log_evidence(J, z, alt[grp], s2) <= best + 1e-9
    th_star = np.random.default_rng(1).standard_normal(G.shape[0]) * 0.1
    e_star = z - J @ th_star
    b2 = group_evidence(G, J.T @ e_star, float(e_star @ e_star), th_star, grp,
                        np.ones(K + 1), s2, n=z.size, update_noise=False, tol=1e-8,
                        max_iterations=5000)  # fmt: skip
    np.testing.assert_allclose(b2.mean, a.mean, atol=1e-8)
    np.testing.assert_array_equal(np.isfinite(b2.precision), np.isfinite(a.precision))


def test_empty_groups_leave_and_the_noise_is_estimated():
    J, z, K, _ = _problem(n_angles=2000, sigma=0.05, zero=(2, 5, 7))
    G, b = J.T @ J, J.T @ z
    a = group_evidence(G, b, float(z @ z), np.zeros(G.shape[0]), harmonic_groups(K),
                       np.ones(K + 1), 1.0, n=z.size, keep=(0,))  # fmt: skip
    assert a.status.success
    # empty groups leave, or stay with a prior far below the noise of their estimate
    # (0.05 / sqrt(1000): a group whose data happen to exceed their noise keeps a small
    # variance, the evidence's own verdict on chance content, Tipping & Faul 2003 eq. 20)
    prior_sd = np.where(a.active, 1.0 / np.sqrt(a.precision), 0.0)
    assert np.all(prior_sd[[2, 5, 7]] < 0.5 * 0.05 / math.sqrt(1000))
    assert np.all(a.gain[[2, 5, 7]] < 3.0)
    present = [k for k in range(1, K + 1) if k not in (2, 5, 7)]
    assert np.all(a.active[present]) and np.all(a.gain[present] > 100.0)
    assert np.all(a.gamma[present] > 5.9)  # six well-determined coefficients each
    # 3 N = 6000 residuals: relative std of the variance estimate sqrt(2 / 6000) = 1.8 %
    assert a.noise_variance == pytest.approx(0.05**2, rel=0.06)
    with pytest.raises(ValueError):
        group_evidence(G, b, 1.0, np.zeros(G.shape[0]), harmonic_groups(K), np.ones(K), 1.0,
                       n=z.size)  # fmt: skip


def test_a_group_with_content_enters():
    """Started without harmonic 3, which has content, the group test lets it in."""
    J, z, K, _ = _problem(n_angles=1000, zero=(5,))
    G, b = J.T @ J, J.T @ z
    start = np.ones(K + 1)
    start[3] = np.inf
    kw = {"n": z.size, "keep": (0,)}
    out = group_evidence(G, b, float(z @ z), np.zeros(G.shape[0]), harmonic_groups(K), start,
                         0.05**2, **kw)  # fmt: skip
    assert not out.active[3]  # entering needs add=True
    inn = group_evidence(G, b, float(z @ z), np.zeros(G.shape[0]), harmonic_groups(K), start,
                         0.05**2, add=True, add_threshold=3.0, **kw)  # fmt: skip
    assert inn.active[3] and inn.gain[3] > 100.0


@settings(max_examples=25, deadline=None)
@given(
    s=st.lists(st.floats(0.01, 100.0), min_size=1, max_size=6),
    q=st.lists(st.floats(-30.0, 30.0), min_size=6, max_size=6),
)
def test_block_gain_is_the_maximum_over_alpha(s, q):
    """The gain of the best precision is at least the gain of any precision on a fine grid
    (within the parabolic step's resolution: 0.17 in log alpha costs at most 1e-3 relative),
    and 0 (alpha = inf) exactly when no finite precision gains."""
    s = np.asarray(s)
    q2 = np.asarray(q[: s.size]) ** 2
    alpha, gain = _block_gain(s[None, :], q2[None, :])
    grid = np.exp(np.linspace(math.log(1e-6 * s.max()), math.log(1e6 * s.max()), 4001))
    ell = 0.5 * np.sum(np.log(grid[:, None] / (grid[:, None] + s)) + q2 / (grid[:, None] + s),
                       axis=1)  # fmt: skip
    top = max(float(ell.max()), 0.0)
    assert gain[0] >= top - 1e-3 * max(abs(top), 1.0) - 1e-9
    if np.isfinite(alpha[0]):
        assert gain[0] > 0
    else:
        assert gain[0] == 0.0


def test_shape_system_is_the_normal_plane_projection():
    """Against the definition: rows (I - n n^T) E_k with n the unit tangent of the curve."""
    rng = np.random.default_rng(3)
    basis = FourierBasis((1, 2, 3, 5))
    th = rng.standard_normal((3, basis.size))
    th[:, basis.index(3)[1]] += 2.0  # a curve with a clear tangent everywhere
    flux = FluxModel(basis, th)
    y0 = rng.uniform(0, 20, 500)
    d = flux(y0 + 0.01 * rng.standard_normal(500)) + 0.01 * rng.standard_normal((500, 3))
    harm = (1, 2, 3, 4, 5, 7)
    sys_ = shape_system(flux, y0, d, harmonics=harm)
    B = FourierBasis(harm).evaluate(y0)
    gp = flux.derivative(y0)
    n = gp / np.linalg.norm(gp, axis=1, keepdims=True)
    P = np.eye(3)[None] - n[:, :, None] * n[:, None, :]  # (N, 3, 3)
    E = np.einsum("hc,kj->khcj", np.eye(3), B).reshape(500, 3, -1)  # (N, 3, 3 m)
    PE = np.einsum("kab,kbj->kaj", P, E)
    e = d - flux(y0)
    Pe = np.einsum("kab,kb->ka", P, e)
    np.testing.assert_allclose(sys_.gram, np.einsum("kaj,kai->ji", PE, PE), rtol=1e-10,
                               atol=1e-10)  # fmt: skip
    np.testing.assert_allclose(sys_.gradient, np.einsum("kaj,ka->j", PE, Pe), rtol=1e-10,
                               atol=1e-12)  # fmt: skip
    assert sys_.sse == pytest.approx(float(np.sum(Pe * Pe)), rel=1e-12)
    assert sys_.n == 1000


def test_relevance_drops_empty_harmonics_and_ignores_motion():
    """A curve with content at 1, 2, 3 and 6 (not 4, 5): seen at angles that are off by a slow
    warp (a motion error: along the curve), the shape evidence still keeps exactly the
    harmonics with content."""
    rng = np.random.default_rng(5)
    basis = FourierBasis((1, 2, 3, 4, 5, 6))
    th = np.zeros((3, basis.size))
    for h, amp in ((1, 0.2), (2, 0.1), (3, 1.0), (6, 0.05)):
        js, jc = basis.index(h)
        th[:, js] = amp * rng.standard_normal(3)
        th[:, jc] = amp * rng.standard_normal(3)
    th[:, basis.index(3)[1]] += [1.0, -0.5, -0.5]
    flux = FluxModel(basis, th)
    y0 = np.linspace(0, 30, 20000)
    sigma = 0.01
    d = flux(y0) + sigma * rng.standard_normal((y0.size, 3))
    seen = y0 + 0.003 * np.sin(y0)  # the simulated angle is off by 3 mrad at harmonic 1
    rel = harmonic_relevance(flux, seen, d, noise_variance=sigma**2, keep=(3,))
    assert rel.active == (1, 2, 3, 6)
    assert rel.noise_variance == pytest.approx(sigma**2, rel=0.05)
    ridge = rel.ridge(basis)
    assert ridge.shape == (3 * basis.size,)
    j4 = list(basis.index(4))
    assert np.all(ridge[j4] > 1e11 * rel.noise_variance)  # dropped: held at zero


def test_the_evidence_does_not_move_with_the_rounding_of_the_data():
    """A clean sensor (noise variance 2e-8) on 30 000 samples: the data precision of a group is
    about 1e12 while its prior precision is about 1. The group test of a group in the model and
    the log evidence are formed without subtracting numbers of the data's size, so a 1e-14
    relative change of the data moves neither the harmonics kept nor the log evidence (the
    subtracting forms moved the log evidence by 1e3 nats here, and to -inf once)."""
    rng = np.random.default_rng(3)
    basis = FourierBasis(tuple(range(1, 41)))
    th = np.zeros((3, basis.size))
    for h in range(1, 31):  # content at 1..30, none above
        js, jc = basis.index(h)
        th[:, js] = 0.05 / h * rng.standard_normal(3)
        th[:, jc] = 0.05 / h * rng.standard_normal(3)
    th[:, basis.index(1)[1]] += [1.0, -0.5, -0.5]
    th[:, basis.index(1)[0]] += [0.0, 0.866, -0.866]
    flux = FluxModel(basis, th)
    y0 = np.linspace(0.0, 3 * TWO_PI, 30000)
    sigma = 1.4e-4
    d = flux(y0) + sigma * rng.standard_normal((y0.size, 3))
    rels = [
        harmonic_relevance(flux, y0, d * (1.0 + eps), noise_variance=sigma**2, keep=(1,))
        for eps in (0.0, 1e-14, 2e-14, -1e-14, 3e-14)
    ]
    assert set(range(1, 31)) <= set(rels[0].active)  # every harmonic with content is kept
    assert all(r.active == rels[0].active for r in rels)
    logev = np.array([r.evidence.log_evidence for r in rels])
    # 1e-9 relative: 4e-4 nats of 4.5e5, far below the 3 nats that decide a group
    assert np.all(np.isfinite(logev)) and np.ptp(logev) < 1e-9 * abs(logev[0])
    assert rels[0].noise_variance == pytest.approx(sigma**2, rel=0.05)
