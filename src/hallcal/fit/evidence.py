"""Which harmonics the data support, and their prior variances: group relevance by the evidence.

The flux model is a Fourier series over mechanical harmonics; every harmonic k is a *group* of
coefficients (sin and cos for each of the three sensors; the constant term has three). In a
linear model ``z = J theta + v`` each group gets a Gaussian prior ``theta_k ~ N(0, I / alpha_k)``
(``alpha_k = inf`` removes the group), and the precisions and the noise variance are set by
maximizing the marginal likelihood (evidence): automatic relevance determination (MacKay 1992,
"Bayesian interpolation"; Tipping 2001, "Sparse Bayesian learning and the relevance vector
machine"), with the group test of Tipping & Faul 2003 ("Fast marginal likelihood maximisation for
sparse Bayesian models") generalized to blocks, by which groups leave (and, if allowed, enter).

Which linear model. The SEM's Gauss-Newton system mixes two kinds of information
(:mod:`hallcal.fit.gauss_newton`): along the tangent of the flux curve, a flux error cannot be
told from an error of the simulated motion (torque disturbance, cogging, the loop's response to
the Hall noise, a slow warp of the angle); across it only the flux shape acts. The evidence of the
full system therefore keeps harmonics that absorb the motion: measured on the rich-shape bench
(``benchmarks/bench_rich.py``), groups tested against the full Gauss-Newton system at a solution
at the noise floor entered at 21 of 22 empty harmonics 56..77. The relevance here is judged on the
normal-plane (shape) part alone, :func:`shape_system`, in the spirit of restricted maximum
likelihood (Patterson & Thompson 1971): the variance parameters are estimated from the part of the
data that the nuisance (here the motion) does not reach.

The harmonics' *band* (where the flux stops, which pins the parametrization) is found beforehand
by :mod:`hallcal.fit.warp`; within the band, the evidence drops empty harmonics (those of a
trapezoidal flux with identical magnets, say) and gives the others their prior variances.

Groups. One per harmonic (six coefficients). Measured against groups shared by the sidebands at
the same distance j from a multiple of n_m (the structure of per-pole modulations), with the band
in place and the MAP SEM after it: on the rich-shape benches (seeds 3 and 4, s = 0.075) all three
gave the same f_star (1.047x, 1.073x the floor: every harmonic of the band has content); on the
experiment-shaped bench (trapezoidal flux, harmonics 1..11, 33, 55) per harmonic 1.008x, per
(k, |j|) 1.009x, per |j| alone 1.058x (it cannot drop the empty sidebands of 33 and 55 while
keeping their centres). The sharing buys nothing once the band pins the warp, so each harmonic
has its own variance.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numba as nb
import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from hallcal.fit.gauss_newton import gram_from_moments
from hallcal.limits import one_blas_thread
from hallcal.messages import Outcome
from hallcal.sensor.flux import FluxModel, FourierBasis

__all__ = [
    "GroupEvidence",
    "GroupEvidenceStatus",
    "HarmonicRelevance",
    "ShapeSystem",
    "group_evidence",
    "harmonic_groups",
    "harmonic_relevance",
    "shape_system",
]


class GroupEvidenceStatus(Outcome):
    """Outcome of :func:`group_evidence`."""

    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    FAILED = "failed"


# ================================================================================================
# The shape (normal-plane) linear model
# ================================================================================================


@nb.njit(cache=True, nogil=True)
def _shape_moments(y0, d, theta, harm, hmax):  # pragma: no cover - numba
    """One pass over the samples: the model curve, its normal-plane projector and the moments.

    For every sample: g and g' from the trigonometric recursion, ``n = g' / |g'|``, the six
    entries w of ``I - n n^T`` and the normal residual ``e_perp = (I - n n^T)(d - g)``; returns
    ``C[w, m] = sum_k w_k cos(m y0_k)``, ``S[w, m]`` likewise (m <= 2 hmax for the six weights,
    m <= hmax for the three residual columns) and ``sum |e_perp|^2``.
    """
    N = y0.size
    nm = 2 * hmax + 1
    C = np.zeros((9, nm))
    S = np.zeros((9, nm))
    cs = np.empty(nm)
    sn = np.empty(nm)
    g = np.empty(3)
    gp = np.empty(3)
    w = np.empty(9)
    sse = 0.0
    for k in range(N):
        c1 = math.cos(y0[k])
        s1 = math.sin(y0[k])
        c = 1.0
        s = 0.0
        for m in range(nm):
            cs[m] = c
            sn[m] = s
            c, s = c * c1 - s * s1, s * c1 + c * s1
        for h in range(3):
            acc = theta[h, 0]
            dacc = 0.0
            for j in range(harm.size):
                q = harm[j]
                a = theta[h, 1 + 2 * j]
                b = theta[h, 2 + 2 * j]
                acc += a * sn[q] + b * cs[q]
                dacc += q * (a * cs[q] - b * sn[q])
            g[h] = acc
            gp[h] = dacc
        norm = math.sqrt(gp[0] * gp[0] + gp[1] * gp[1] + gp[2] * gp[2])
        if norm > 0.0:
            for h in range(3):
                gp[h] /= norm
        e0 = d[k, 0] - g[0]
        e1 = d[k, 1] - g[1]
        e2 = d[k, 2] - g[2]
        t = gp[0] * e0 + gp[1] * e1 + gp[2] * e2
        w[0] = 1.0 - gp[0] * gp[0]
        w[1] = 1.0 - gp[1] * gp[1]
        w[2] = 1.0 - gp[2] * gp[2]
        w[3] = -gp[0] * gp[1]
        w[4] = -gp[0] * gp[2]
        w[5] = -gp[1] * gp[2]
        w[6] = e0 - t * gp[0]
        w[7] = e1 - t * gp[1]
        w[8] = e2 - t * gp[2]
        sse += w[6] * w[6] + w[7] * w[7] + w[8] * w[8]
        for m in range(nm):
            cm = cs[m]
            sm = sn[m]
            for i in range(6):
                C[i, m] += w[i] * cm
                S[i, m] += w[i] * sm
        for m in range(hmax + 1):
            cm = cs[m]
            sm = sn[m]
            for i in range(6, 9):
                C[i, m] += w[i] * cm
                S[i, m] += w[i] * sm
    return C, S, sse


@dataclass(frozen=True)
class ShapeSystem:
    """Normal equations of the flux model's distance from the data, along the curve's normals.

    Attributes
    ----------
    gram : ndarray (p, p)
        ``sum_k E_k^T (I - n_k n_k^T) E_k`` with ``E_k = I_3 kron beta(y0_k)`` (theta layout,
        sensor-major, p = 3 m).
    gradient : ndarray (p,)
        ``sum_k E_k^T (I - n_k n_k^T) e_k``, e = d - g_theta(y0).
    sse : float
        ``sum_k |(I - n_k n_k^T) e_k|^2``.
    n : int
        Observations: 2 N (two normal directions per sample).
    """

    gram: NDArray[np.float64] = field(repr=False)
    gradient: NDArray[np.float64] = field(repr=False)
    sse: float
    n: int


def shape_system(
    flux: FluxModel, y0: ArrayLike, d: ArrayLike, harmonics: ArrayLike | None = None
) -> ShapeSystem:
    """The data's distance from the model curve, linear in theta: the shape part of the SEM.

    Each Gauss-Newton row block of problem (problem) splits along the tangent
    ``n_k = g'(y0_k) / |g'(y0_k)|`` of the flux curve and the plane normal to it (see
    :mod:`hallcal.fit.gauss_newton`). Along the tangent, a flux error cannot be told from an
    error of the simulated motion (a warp of the angle, a torque disturbance, cogging, the loop's
    response to the Hall noise); across it, only the flux shape and the noise act. This function
    returns the normal part alone, ``(I - n n^T)(d_k - E_k theta) ~ 0``, as normal equations on
    the harmonics ``harmonics`` (default: the flux's own; others get theta = 0), at the fixed
    angles y0 (the SEM's simulated angle). O(N max(harmonics)) by trigonometric moments; no
    loop simulation.

    Parameters
    ----------
    flux : FluxModel
        g_theta on a Fourier basis: the linearization point (its curve gives the normals).
    y0 : array_like (N,)
        Angle of every sample on the model curve [rad, mechanical].
    d : array_like (N, 3)
        Hall signals.
    harmonics : array_like of int, optional
        Harmonics of the system's unknowns; default the flux's own.

    Returns
    -------
    ShapeSystem
        Normal equations (gram, gradient, sse) and the observation count 2 N.
    """
    yy = np.ascontiguousarray(y0, dtype=np.float64)
    dd = np.ascontiguousarray(d, dtype=np.float64)
    harm = np.asarray(flux.basis.harmonics if harmonics is None else harmonics, dtype=np.int64)
    fh = np.asarray(flux.basis.harmonics, dtype=np.int64)
    hmax = int(max(harm.max() if harm.size else 0, fh.max() if fh.size else 0))
    theta = np.ascontiguousarray(flux.theta)
    half = yy.size // 2
    if yy.size >= 8192:  # two halves in two threads (numba releases the GIL)
        with ThreadPoolExecutor(1) as pool:
            fut = pool.submit(_shape_moments, yy[half:], dd[half:], theta, fh, hmax)
            C, S, sse = _shape_moments(yy[:half], dd[:half], theta, fh, hmax)
            C1, S1, sse1 = fut.result()
        C, S, sse = C + C1, S + S1, sse + sse1
    else:
        C, S, sse = _shape_moments(yy, dd, theta, fh, hmax)
    mb = 1 + 2 * harm.size
    G = np.zeros((3 * mb, 3 * mb))
    pairs = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    for w, (h1, h2) in enumerate(pairs):
        M = gram_from_moments(C[w], S[w], harm)
        G[h1 * mb : (h1 + 1) * mb, h2 * mb : (h2 + 1) * mb] = M
        if h1 != h2:
            G[h2 * mb : (h2 + 1) * mb, h1 * mb : (h1 + 1) * mb] = M.T
    grad = np.empty((3, mb))
    for h in range(3):
        grad[h, 0] = C[6 + h, 0]
        grad[h, 1::2] = S[6 + h, harm]
        grad[h, 2::2] = C[6 + h, harm]
    return ShapeSystem(G, grad.ravel(), float(sse), 2 * yy.size)


def harmonic_groups(K: int) -> NDArray[np.int64]:
    """Harmonic of every coefficient of theta (3, 2K + 1) flattened sensor-major.

    Parameters
    ----------
    K : int
        Highest harmonic; the basis is ``[1, sin 1y, cos 1y, ..., cos Ky]``.

    Returns
    -------
    ndarray of int, shape (3 (2K + 1),)
        0 for the constant, k for the sine and cosine of harmonic k: the groups of
        :func:`group_evidence`.
    """
    j = np.arange(2 * int(K) + 1)
    return np.tile((j + 1) // 2, 3)


@dataclass(frozen=True)
class GroupEvidence:
    """Outcome of :func:`group_evidence`.

    Attributes
    ----------
    precision : ndarray (G,)
        alpha_k per group (``inf``: not in the model).
    noise_variance : float
        sigma^2 at the optimum.
    mean : ndarray (p,)
        Posterior mean of theta (zero outside the model).
    gamma : ndarray (G,)
        Well-determined parameters per group, ``sum_j (1 - alpha_k Sigma_jj)``.
    gain : ndarray (G,)
        Evidence gain [nats] of each group's best precision over leaving it out, at the optimum
        (the others fixed): positive for the groups in the model, at most ``add_threshold`` for
        the others.
    log_evidence : float
        log p(z) of the linear model at the optimum.
    iterations : int
        Fixed-point iterations.
    status : GroupEvidenceStatus
    """

    precision: NDArray[np.float64]
    noise_variance: float
    mean: NDArray[np.float64] = field(repr=False)
    gamma: NDArray[np.float64]
    gain: NDArray[np.float64]
    log_evidence: float
    iterations: int
    status: GroupEvidenceStatus

    @property
    def active(self) -> NDArray[np.bool_]:
        """Groups in the model."""
        return np.isfinite(self.precision)


@dataclass
class _Posterior:
    ia: NDArray[np.int64]
    sigma: NDArray[np.float64]
    mean: NDArray[np.float64]
    gamma_j: NDArray[np.float64]
    logdet_h: float


def _posterior(G: NDArray, b: NDArray, alpha_j: NDArray, s2: float) -> _Posterior | None:
    """Sigma = (G_AA / s2 + A)^-1 and mu = Sigma b_A / s2 on the active coefficients."""
    ia = np.nonzero(np.isfinite(alpha_j))[0]
    H = G[np.ix_(ia, ia)] / s2
    H[np.diag_indices_from(H)] += alpha_j[ia]
    try:
        L = scipy.linalg.cholesky(H, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    Li = scipy.linalg.solve_triangular(L, np.eye(ia.size), lower=True, check_finite=False)
    sigma = Li.T @ Li
    mean = scipy.linalg.cho_solve((L, True), b[ia] / s2, check_finite=False)
    gamma_j = np.clip(1.0 - alpha_j[ia] * np.diag(sigma), 0.0, 1.0)
    return _Posterior(ia, sigma, mean, gamma_j, 2.0 * float(np.sum(np.log(np.diag(L)))))


def _block_gain(s: NDArray, q2: NDArray) -> tuple[NDArray, NDArray]:
    """Best precision and evidence gain of groups given the others.

    For a group with eigenvalues s_i of ``S = Phi_k^T C_-k^-1 Phi_k`` and squared projections
    q_i^2 of ``Q = Phi_k^T C_-k^-1 z`` on its eigenvectors, the log evidence as a function of the
    group's precision alpha is, up to a constant (Tipping & Faul 2003, eq. 16, for a block),

        l(alpha) = 1/2 sum_i [log(alpha / (alpha + s_i)) + q_i^2 / (alpha + s_i)],

    with l(inf) = 0 (group left out). Maximized on a grid of log alpha (0.17 apart, 1e-8..1e8
    times the largest s_i) refined by one parabolic step. ``s``, ``q2``: (G, m), zero-padded
    for smaller groups (zero s_i contribute nothing). Groups without information (all s_i = 0)
    get alpha = inf and gain 0.
    """
    G = s.shape[0]
    smax = np.max(s, axis=1)
    info = smax > 0
    alpha = np.full(G, np.inf)
    gain = np.zeros(G)
    if not np.any(info):
        return alpha, gain
    si, qi = s[info], q2[info]
    grid = np.linspace(math.log(1e-8), math.log(1e8), 97)
    la = np.log(smax[info])[:, None] + grid[None, :]

    def ell(log_alpha: NDArray) -> NDArray:
        a = np.exp(log_alpha)[..., None]
        sp = si.reshape(si.shape[0], *([1] * (log_alpha.ndim - 1)), si.shape[1])
        qp = qi.reshape(sp.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(sp > 0, np.log(a / (a + sp)) + qp / (a + sp), 0.0)
        return 0.5 * t.sum(axis=-1)

    vals = ell(la)
    i = np.argmax(vals, axis=1)
    rows = np.arange(la.shape[0])
    best_la = la[rows, i]
    best = vals[rows, i]
    inner = (i > 0) & (i < grid.size - 1)
    if np.any(inner):
        r = rows[inner]
        y0, y1, y2 = vals[r, i[r] - 1], vals[r, i[r]], vals[r, i[r] + 1]
        den = y0 - 2.0 * y1 + y2
        shift = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
        cand = best_la[r] + np.clip(shift, -1.0, 1.0) * (grid[1] - grid[0])
        sub = np.array([_ell_row(si[k], qi[k], cand[j]) for j, k in enumerate(r)])
        better = sub > best[r]
        best_la[r[better]] = cand[better]
        best[r[better]] = sub[better]
    top = i == grid.size - 1
    keep = ~top & (best > 0)
    a_out = np.where(keep, np.exp(best_la), np.inf)
    alpha[info] = a_out
    gain[info] = np.where(keep, best, 0.0)
    return alpha, gain


def _ell_row(s: NDArray, q2: NDArray, log_alpha: float) -> float:
    """``l(alpha)`` of :func:`_block_gain` for one group."""
    a = math.exp(log_alpha)
    m = s > 0
    return 0.5 * float(np.sum(np.log(a / (a + s[m])) + q2[m] / (a + s[m])))


def _group_tests(
    G: NDArray, b: NDArray, post: _Posterior, alpha: NDArray, grp: NDArray, s2: float
) -> tuple[NDArray, NDArray]:
    """(best precision, its gain) of every group, all others fixed.

    A group outside the model: ``S~ = Phi^T C^-1 Phi`` and ``Q~ = Phi^T C^-1 z`` (C with every
    group of the model) from the Gram matrix by Woodbury, ``S~ = G / s2 - G_:A Sigma G_A: / s2^2``
    and ``Q~ = (b - G_:A mu) / s2``. A group in the model has its own prior removed,
    ``S_-k = alpha S~ (alpha I - S~)^-1``, ``Q_-k = alpha (alpha I - S~)^-1 Q~`` (Tipping &
    Faul 2003, eq. 23), evaluated in the form that does not cancel: with ``S~ = alpha I -
    alpha^2 Sigma_kk`` and ``Q~ = alpha mu_k`` (Tipping 2001, appendix), ``S_-k = Sigma_kk^-1 -
    alpha I`` and ``Q_-k = Sigma_kk^-1 mu_k``. The Woodbury form subtracts two numbers of the
    order of the data precision (1e12 on a clean sensor) to get ``alpha - s_i`` of order alpha:
    measured on an 11-pole-pair bench with noise variance 2e-8, it came out non-positive for
    53 groups with content (harmonic 1 among them), which then left the model at once, the noise
    estimate jumped from 2e-8 to 8e-3 and a 1e-14 relative change of the data decided whether
    87 or 33 harmonics stayed (``tests/test_evidence.py``).
    """
    ng = alpha.size
    ia = post.ia
    X = G[:, ia] / s2
    W = X @ post.sigma
    resid = (b - G[:, ia] @ post.mean) / s2
    sizes = np.bincount(grp, minlength=ng)
    m = int(sizes.max())
    s_eff = np.zeros((ng, m))
    q2 = np.zeros((ng, m))
    act = np.isfinite(alpha)
    pos = np.full(grp.size, -1)
    pos[ia] = np.arange(ia.size)  # place of every active coefficient in the posterior
    for size in np.unique(sizes):  # one batched eigendecomposition per group size
        ks = np.nonzero(sizes == size)[0]
        out, inn = ks[~act[ks]], ks[act[ks]]
        if out.size:
            idx = np.stack([np.nonzero(grp == k)[0] for k in out])  # (g, size)
            Sk = G[idx[:, :, None], idx[:, None, :]] / s2 - np.einsum(
                "gip,gjp->gij", W[idx], X[idx]
            )
            ev, V = np.linalg.eigh(0.5 * (Sk + Sk.transpose(0, 2, 1)))
            s_eff[out, :size] = np.maximum(ev, 0.0)
            q2[out, :size] = np.einsum("gij,gi->gj", V, resid[idx]) ** 2
        if inn.size:
            idx = pos[np.stack([np.nonzero(grp == k)[0] for k in inn])]  # (g, size) in ia
            Skk = post.sigma[idx[:, :, None], idx[:, None, :]]
            P = np.linalg.inv(0.5 * (Skk + Skk.transpose(0, 2, 1)))  # Sigma_kk^-1
            Sm = 0.5 * (P + P.transpose(0, 2, 1)) - alpha[inn][:, None, None] * np.eye(size)
            Qm = np.einsum("gij,gj->gi", P, post.mean[idx])
            ev, V = np.linalg.eigh(Sm)
            s_eff[inn, :size] = np.maximum(ev, 0.0)
            q2[inn, :size] = np.einsum("gij,gi->gj", V, Qm) ** 2
    return _block_gain(s_eff, q2)


def _residual(G: NDArray, g0: NDArray, sse: float, delta: NDArray) -> float:
    """``||z - J mu||^2 = e*^T e* - 2 d^T J^T e* + d^T J^T J d`` with d = mu - theta*."""
    return sse - 2.0 * float(delta @ g0) + float(delta @ (G @ delta))


def group_evidence(
    gram: ArrayLike,
    gradient: ArrayLike,
    sse: float,
    theta: ArrayLike,
    groups: ArrayLike,
    precision: ArrayLike,
    noise_variance: float,
    *,
    n: int,
    keep: ArrayLike = (),
    add: bool = False,
    add_threshold: float = 0.0,
    update_noise: bool = True,
    max_iterations: int = 100,
    tol: float = 0.05,
    prune: float = 1e6,
) -> GroupEvidence:
    """Evidence maximization over one prior precision per group; groups leave (and may enter).

    Linear model ``z = J theta + v`` with ``z = e* + J theta*``, ``v ~ N(0, sigma^2 I_n)`` and
    ``theta_j ~ N(0, 1 / alpha_g(j))``; only ``J^T J``, ``J^T e*``, ``e*^T e*`` and theta* are
    needed. Alternates

    1. MacKay's fixed point on the groups in the model, ``gamma_j = 1 - alpha_g Sigma_jj``,
       ``alpha_g <- sum_{j in g} gamma_j / sum_{j in g} mu_j^2``,
       ``sigma^2 <- ||z - J mu||^2 / (n - sum gamma)`` (MacKay 1992; Tipping 2001, eqs. 16-18),
       groups whose precision passes ``prune`` times their data precision leaving, until the
       log-precisions of the determined groups (gamma > 0.01) move by less than tol;
    2. the group test of Tipping & Faul 2003 (sec. 3, generalized to blocks): for every group,
       the others fixed, the evidence as a function of its precision (:func:`_block_gain`);
       groups in the model whose best precision is infinite leave; with ``add``, groups outside
       whose best precision gains more than ``add_threshold`` nats enter; the moves are kept
       only when the log evidence at the new fixed point is not lower, else only the leaving
       group with the smallest share of the fit is tried, else nothing moves
       (:func:`_accepted_moves`);

    until no group leaves or enters.

    Parameters
    ----------
    gram, gradient, sse, theta
        J^T J (p, p), J^T e* (p,), e*^T e* and theta* (p,).
    groups : array_like (p,) of int
        Group 0..G-1 of every coefficient (e.g. :func:`harmonic_groups`).
    precision : array_like (G,)
        Starting alpha per group (``inf`` = out of the model).
    noise_variance : float
        Starting sigma^2.
    n : int
        Number of observations.
    keep : sequence of int
        Groups that never leave (e.g. the constant and the pole-pair harmonic).
    add : bool
        Let groups enter.
    add_threshold : float
        Evidence gain [nats] a group must bring to enter (3: "strong" evidence, a Bayes factor
        of 20, Kass & Raftery 1995).
    update_noise : bool
        Re-estimate sigma^2 (else fixed).
    max_iterations : int
        Fixed-point iterations in all.
    tol : float
        Settling threshold on the log-precisions (0.05: 5 % in the prior variance).
    prune : float
        A group leaves when its precision exceeds ``prune`` times its data precision
        (``mean diag(J^T J) / sigma^2`` over its coefficients): its posterior mean is then below
        1e-6 of its least-squares value.

    Returns
    -------
    GroupEvidence
        Precisions, noise variance, posterior mean, evidence gains and status at the optimum.
    """
    pr = _group_problem(gram, gradient, theta, groups, precision, keep)
    alpha, s2 = pr.precision, float(noise_variance)
    status, gain, it = GroupEvidenceStatus.MAX_ITERATIONS, np.zeros(pr.ng), 0
    opts: dict[str, Any] = {"sse": sse, "n": n, "update_noise": update_noise, "prune": prune,
                            "tol": tol}  # fmt: skip
    with one_blas_thread():
        while it < int(max_iterations):
            settled = _settle(pr, alpha, s2, budget=int(max_iterations) - it, **opts)
            if settled is None:
                status = GroupEvidenceStatus.FAILED
                break
            alpha, s2, k, done = settled
            it += k
            if not done:
                break
            moves = _group_moves(pr, alpha, s2, add=add, add_threshold=add_threshold)
            if moves is None:
                status = GroupEvidenceStatus.FAILED
                break
            gain = moves.gain
            if not moves.leave.any() and not moves.enter.any():
                status = GroupEvidenceStatus.CONVERGED
                break
            nxt = _accepted_moves(pr, moves, alpha, s2, budget=int(max_iterations) - it, **opts)
            if nxt is None:  # no removal raises the evidence: the optimum
                status = GroupEvidenceStatus.CONVERGED
                break
            alpha, s2, k = nxt
            it += k
        post = _posterior(pr.G, pr.b, alpha[pr.grp], s2)
    return _evidence_at(pr, post, alpha, s2, gain, it, status, sse=sse, n=n)


def _settle(
    pr: _GroupProblem, alpha: NDArray, s2: float, *, budget: int, sse: float, n: int,
    update_noise: bool, prune: float, tol: float,
) -> tuple[NDArray, float, int, bool] | None:  # fmt: skip
    """Step 1 of :func:`group_evidence` until the log-precisions settle (or ``budget`` steps).

    Returns (alpha, sigma^2, iterations, settled), None when a posterior failed.
    """
    k = 0
    while k < max(budget, 0):
        k += 1
        step = _mackay_step(pr, alpha, s2, sse, n=n, update_noise=update_noise, prune=prune)
        if step is None:
            return None
        alpha, s2 = step.precision, step.noise_variance
        if step.change < tol:
            return alpha, s2, k, True
    return alpha, s2, k, False


def _accepted_moves(
    pr: _GroupProblem, moves: _GroupMoves, alpha: NDArray, s2: float, *, budget: int,
    sse: float, n: int, update_noise: bool, prune: float, tol: float,
) -> tuple[NDArray, float, int] | None:  # fmt: skip
    """Step 2 of :func:`group_evidence` kept only when it raises the evidence.

    The group test holds the others fixed; removing many groups at once can lose evidence
    (the noise estimate and the other groups' precisions move). The moves are made and the
    fixed point settled; when the log evidence at the new point is below the old one, only the
    leaving group with the smallest share of the fit (``mu_k^T G_kk mu_k``) is tried, and when
    that loses too, nothing moves (None: the current point is the optimum). Deterministic: the
    order is by that share, then by group index.
    """
    here = _evidence_value(pr, alpha, s2, sse=sse, n=n)
    opts: dict[str, Any] = {"sse": sse, "n": n, "update_noise": update_noise, "prune": prune,
                            "tol": tol}  # fmt: skip
    trials = [moves.leave]
    if np.count_nonzero(moves.leave) > 1 or moves.enter.any():
        post = _posterior(pr.G, pr.b, alpha[pr.grp], s2)
        if post is None:
            return None
        mu, _ = _group_means(pr, post)
        share = np.bincount(pr.grp, weights=mu * (pr.G @ mu), minlength=pr.ng)
        cand = np.nonzero(moves.leave)[0]
        if cand.size:
            one = np.zeros_like(moves.leave)
            one[cand[np.lexsort((cand, share[cand]))[0]]] = True
            trials = [moves.leave, one]
    used = 0
    for i, leave in enumerate(trials):
        new = alpha.copy()
        new[leave] = np.inf
        if i == 0:
            new[moves.enter] = moves.best[moves.enter]
        settled = _settle(pr, new, s2, budget=budget - used, **opts)
        if settled is None:
            continue
        a2, v2, k, _ = settled
        used += k
        there = _evidence_value(pr, a2, v2, sse=sse, n=n)
        if math.isfinite(there) and there >= here:
            return a2, v2, used
    return None


def _evidence_value(pr: _GroupProblem, alpha: NDArray, s2: float, *, sse: float, n: int) -> float:
    """log p(z) at (alpha, sigma^2) (-inf when the posterior fails)."""
    post = _posterior(pr.G, pr.b, alpha[pr.grp], s2)
    return -math.inf if post is None else _log_evidence(pr, post, alpha, s2, sse=sse, n=n)


@dataclass(frozen=True)
class _GroupProblem:
    """The checked inputs of :func:`group_evidence`: ``J^T J``, ``J^T e*``, theta* and groups."""

    G: NDArray[np.float64]  # J^T J (p, p)
    g0: NDArray[np.float64]  # J^T e* (p,)
    th: NDArray[np.float64]  # theta* (p,)
    grp: NDArray[np.int64]  # group of every coefficient (p,)
    precision: NDArray[np.float64]  # starting alpha per group (G,), kept groups finite
    keep: NDArray[np.bool_]  # groups that never leave (G,)
    b: NDArray[np.float64]  # J^T z = J^T e* + J^T J theta*
    data_prec: NDArray[np.float64]  # mean diag(J^T J) per group

    @property
    def p(self) -> int:
        return self.G.shape[0]

    @property
    def ng(self) -> int:
        return self.precision.size


def _group_problem(
    gram: ArrayLike, gradient: ArrayLike, theta: ArrayLike, groups: ArrayLike,
    precision: ArrayLike, keep: ArrayLike,
) -> _GroupProblem:  # fmt: skip
    """Check the shapes; ``z = e* + J theta*`` enters through ``b = J^T z``."""
    G = np.asarray(gram, dtype=np.float64)
    g0 = np.asarray(gradient, dtype=np.float64).ravel()
    th = np.asarray(theta, dtype=np.float64).ravel()
    grp = np.asarray(groups, dtype=np.int64).ravel()
    alpha = np.array(precision, dtype=np.float64)
    p = G.shape[0]
    if G.shape != (p, p) or g0.size != p or th.size != p or grp.size != p:
        raise ValueError("gram, gradient, theta and groups do not match")
    ng = int(grp.max()) + 1
    if alpha.shape != (ng,):
        raise ValueError("precision must have one entry per group")
    keep_mask = np.zeros(ng, dtype=bool)
    keep_mask[np.asarray(keep, dtype=np.int64)] = True
    alpha[keep_mask & ~np.isfinite(alpha)] = 1e-12
    data_prec = np.bincount(grp, weights=np.diag(G), minlength=ng) / np.bincount(grp, minlength=ng)
    return _GroupProblem(G, g0, th, grp, alpha, keep_mask, g0 + G @ th, data_prec)


def _group_means(pr: _GroupProblem, post: _Posterior) -> tuple[NDArray, NDArray]:
    """The posterior mean mu (p,), zero outside the model, and gamma summed per group (G,)."""
    mu = np.zeros(pr.p)
    mu[post.ia] = post.mean
    gj = np.zeros(pr.p)
    gj[post.ia] = post.gamma_j
    return mu, np.bincount(pr.grp, weights=gj, minlength=pr.ng)


@dataclass(frozen=True)
class _MacKayStep:
    """One fixed-point update of :func:`group_evidence` (step 1)."""

    precision: NDArray[np.float64]
    noise_variance: float
    change: float  # largest change of the log-precisions of the determined groups


def _mackay_step(
    pr: _GroupProblem, alpha: NDArray, s2: float, sse: float, *, n: int, update_noise: bool,
    prune: float,
) -> _MacKayStep | None:  # fmt: skip
    """Step 1 of :func:`group_evidence`: MacKay's fixed point, groups pruned (None: no posterior).

    ``gamma_j = 1 - alpha_g Sigma_jj``, ``alpha_g <- sum_{j in g} gamma_j / sum_{j in g} mu_j^2``,
    ``sigma^2 <- ||z - J mu||^2 / (n - sum gamma)`` (MacKay 1992; Tipping 2001, eqs. 16-18).
    """
    post = _posterior(pr.G, pr.b, alpha[pr.grp], s2)
    if post is None:
        return None
    mu, gam = _group_means(pr, post)
    m2 = np.bincount(pr.grp, weights=mu**2, minlength=pr.ng)
    if update_noise:
        R = _residual(pr.G, pr.g0, sse, mu - pr.th)
        s2 = max(R, 1e-300) / max(n - float(gam.sum()), 1.0)
    act = np.isfinite(alpha)
    new = alpha.copy()
    new[act] = gam[act] / np.maximum(m2[act], 1e-300)
    new[pr.keep] = np.minimum(new[pr.keep], 1e300)
    # a precision above `prune` times the group's data precision holds its posterior
    # mean below 1/prune of its least-squares value: the group is out (Tipping 2001)
    with np.errstate(over="ignore"):
        limit = prune * np.maximum(pr.data_prec / s2, 1e-300)
    pruned = act & ~pr.keep & (new > limit)
    new[pruned] = np.inf
    det = act & ~pruned & (gam > 1e-2) & np.isfinite(new)
    with np.errstate(divide="ignore", invalid="ignore"):
        change = float(np.max(np.abs(np.log(new[det] / alpha[det])))) if det.any() else 0.0
    return _MacKayStep(new, s2, change)


@dataclass(frozen=True)
class _GroupMoves:
    """Step 2 of :func:`group_evidence`: the groups that leave and enter, with their tests."""

    best: NDArray[np.float64]  # best precision of every group, the others fixed
    gain: NDArray[np.float64]  # its evidence gain [nats]
    leave: NDArray[np.bool_]
    enter: NDArray[np.bool_]


def _group_moves(
    pr: _GroupProblem, alpha: NDArray, s2: float, *, add: bool, add_threshold: float
) -> _GroupMoves | None:
    """Step 2 of :func:`group_evidence`: the group test of Tipping & Faul 2003 (sec. 3, for blocks).

    Groups in the model whose best precision is infinite leave; with ``add``, groups outside
    whose best precision gains more than ``add_threshold`` nats enter. None: no posterior.
    """
    post = _posterior(pr.G, pr.b, alpha[pr.grp], s2)
    if post is None:
        return None
    best, gain = _group_tests(pr.G, pr.b, post, alpha, pr.grp, s2)
    act = np.isfinite(alpha)
    leave = act & ~np.isfinite(best) & ~pr.keep
    enter = (~act) & np.isfinite(best) & (gain > add_threshold) & bool(add)
    return _GroupMoves(best, gain, leave, enter)


def _evidence_at(
    pr: _GroupProblem, post: _Posterior | None, alpha: NDArray, s2: float, gain: NDArray,
    iterations: int, status: GroupEvidenceStatus, *, sse: float, n: int,
) -> GroupEvidence:  # fmt: skip
    """The result of :func:`group_evidence` at (alpha, sigma^2): posterior mean, gamma per group
    and the log evidence (NaN and zeros when the posterior failed)."""
    if post is None:
        return GroupEvidence(
            alpha, s2, np.zeros(pr.p), np.zeros(pr.ng), gain, math.nan, iterations, status
        )
    mu, gam = _group_means(pr, post)
    logev = _log_evidence(pr, post, alpha, s2, sse=sse, n=n)
    return GroupEvidence(alpha, s2, mu, gam, gain, logev, iterations, status)


def _log_evidence(
    pr: _GroupProblem, post: _Posterior, alpha: NDArray, s2: float, *, sse: float, n: int
) -> float:
    """``log p(z)`` of the linear model at (alpha, sigma^2), from the posterior's ``log|H|``.

    ``z^T C^-1 z = ||z - J mu||^2 / s2 + mu^T A mu`` (Tipping 2001, eq. 36 with the posterior
    mean): the form ``(z^T z - b^T mu) / s2`` subtracts two numbers of the order of the data
    (6e4 on an 11-pole-pair bench) to get the residual (1.6e-3), and its rounding moved the log
    evidence by 1.2e4 nats there.
    """
    mu = np.zeros(pr.p)
    mu[post.ia] = post.mean
    a_act = alpha[pr.grp][post.ia]
    quad = _residual(pr.G, pr.g0, sse, mu - pr.th) / s2 + float(np.sum(a_act * post.mean**2))
    if np.any(a_act <= 0.0):  # an improper (flat) prior: no finite evidence
        return -math.inf
    # log p(z) = -1/2 [n log 2 pi s2 + log|H| - sum log alpha + z^T C^-1 z]
    return -0.5 * (
        n * math.log(2.0 * math.pi * s2) + post.logdet_h - float(np.sum(np.log(a_act))) + quad
    )


# ================================================================================================
# Harmonics of a flux model
# ================================================================================================


@dataclass(frozen=True)
class HarmonicRelevance:
    """Outcome of :func:`harmonic_relevance`: a prior variance per harmonic, zero when dropped.

    Attributes
    ----------
    harmonics : tuple of int
        The harmonics examined (the constant term is group 0, always kept).
    prior_variance : ndarray (1 + len(harmonics),)
        ``1 / alpha`` of the constant and of each harmonic's coefficients (0: dropped).
    gain : ndarray (1 + len(harmonics),)
        Evidence gain [nats] of keeping each group, the others fixed (0 for dropped groups).
    noise_variance : float
        sigma^2 at the evidence optimum (from the normal-plane residual).
    evidence : GroupEvidence
    """

    harmonics: tuple[int, ...]
    prior_variance: NDArray[np.float64] = field(repr=False)
    gain: NDArray[np.float64] = field(repr=False)
    noise_variance: float
    evidence: GroupEvidence = field(repr=False)

    @property
    def active(self) -> tuple[int, ...]:
        """The harmonics kept."""
        return tuple(
            h for h, v in zip(self.harmonics, self.prior_variance[1:], strict=True) if v > 0
        )

    @property
    def status(self) -> GroupEvidenceStatus:
        return self.evidence.status

    def variance_of(self, harmonic: int) -> float:
        """Prior variance of one harmonic's coefficients (0 when dropped or not examined)."""
        if harmonic == 0:
            return float(self.prior_variance[0])
        try:
            return float(self.prior_variance[1 + self.harmonics.index(int(harmonic))])
        except ValueError:
            return 0.0

    def ridge(self, basis: FourierBasis) -> NDArray[np.float64]:
        """``sigma^2 alpha`` per coefficient of theta (3 m,) on ``basis`` (MAP regularization).

        Harmonics of the basis that were dropped or not examined get a ridge of 1e12 sigma^2
        (their coefficients held at zero).
        """
        v = np.array([self.variance_of(0)] + [self.variance_of(h) for h in basis.harmonics])
        per = np.where(
            v > 0, self.noise_variance / np.where(v > 0, v, 1.0), 1e12 * self.noise_variance
        )
        return np.tile(np.r_[per[0], np.repeat(per[1:], 2)], 3)


def harmonic_relevance(
    flux: FluxModel,
    y0: ArrayLike,
    d: ArrayLike,
    *,
    noise_variance: float,
    keep: tuple[int, ...] = (),
    prior_variance: ArrayLike | None = None,
) -> HarmonicRelevance:
    """Which of the flux model's harmonics the data's shape supports, and their prior variances.

    :func:`group_evidence` on the normal-plane system :func:`shape_system` at the angles y0
    (e.g. the un-warped angle of :mod:`hallcal.fit.warp`, or the SEM's simulated angle), groups
    = the constant and each harmonic of ``flux``; groups only leave. ``prior_variance`` starts
    the fixed point (default: each group's mean squared coefficient plus twice the
    coefficient noise ``2 sigma^2 / N``, i.e. its least-squares estimate).

    Parameters
    ----------
    flux : FluxModel
        The model and the linearization point.
    y0 : array_like (N,)
        Angle of every sample on the model curve [rad].
    d : array_like (N, 3)
        Hall signals.
    noise_variance : float
        Starting sigma^2.
    keep : tuple of int
        Harmonics that never leave (e.g. the pole-pair harmonic); the constant never leaves.
    prior_variance : array_like (1 + H,), optional
        Start per group (constant first); 0 = start outside the model.

    Returns
    -------
    HarmonicRelevance
        The harmonics, their prior variances (0: left the model), evidence gains and sigma^2.
    """
    H = tuple(int(h) for h in flux.basis.harmonics)
    sys_ = shape_system(flux, y0, d)
    th = np.asarray(flux.theta, dtype=np.float64)
    N = np.asarray(y0).size
    if prior_variance is None:
        ms = [float(np.mean(th[:, 0] ** 2))] + [
            float(np.mean(th[:, 1 + 2 * i : 3 + 2 * i] ** 2)) for i in range(len(H))
        ]
        v0 = np.asarray(ms) + 2.0 * noise_variance / max(N, 1)
    else:
        v0 = np.asarray(prior_variance, dtype=np.float64)
    alpha0 = np.where(v0 > 0, 1.0 / np.where(v0 > 0, v0, 1.0), np.inf)
    groups = harmonic_groups(len(H))
    keep_groups = (0, *[1 + H.index(h) for h in keep if h in H])
    ev = group_evidence(
        sys_.gram, sys_.gradient, sys_.sse, th.ravel(), groups, alpha0, noise_variance,
        n=sys_.n, keep=keep_groups,
    )  # fmt: skip
    pv = np.where(np.isfinite(ev.precision), 1.0 / ev.precision, 0.0)
    return HarmonicRelevance(H, pv, ev.gain, ev.noise_variance, ev)
