"""Absolute angle at power-up: which pole pair the rotor is in, from the magnets' own signatures.

f_init (eq. fimp) only knows the electrical angle: after a power-up it starts within one
electrical period of zero, a whole number ``j`` of pole pairs ``2 pi j / n_m`` away from the
calibration's frame, and the table of eq. (f_final) is then applied to the wrong magnets. The
identified flux model g_theta knows each magnet's individual shape (the harmonics that are not
multiples of n_m, section "Model structure"), so the offset ``j`` is a parameter of the
measurement model ``d_k = g_theta(y0_k) + v_k`` (eq. d_h, white Gaussian noise) and can be
estimated by maximum likelihood among the n_m hypotheses, sample by sample, with a sequential
probability ratio test deciding when it is certain (Wald 1945; for n_m hypotheses the posterior
form of the multi-hypothesis SPRT, Baum & Veeravalli 1994, IEEE Trans. Inf. Theory 40(6)).

Geometry. Write the f_init output after power-up as ``y_k = (psi_k + 2 pi m_k) / n_m`` with the
wrapped electrical angle ``psi_k = atan2(beta_k, alpha_k)`` and f_init's integer turn count
``m_k``. Hypothesis j says the calibration frame's f_init value is ``y_k + 2 pi j / n_m``. Every
hypothesis predicts the *same* electrical angle psi_k (that is all f_init tracks), so tracking
with f_init's increments alone never separates them; what separates them is the part of
``d - o`` that f_init throws away: the radius ``rho = |P (d - o)|`` in the alpha/beta plane and
the component ``zeta = n . (d - o)`` along the null vector ``n`` of the projection P
(zero-sequence for Clarke). Both are tabulated over the revolution in the calibration frame.

Per-sample evidence (first-order profile likelihood). With the predicted point
``c_j(psi) = o + R_j(psi) u(psi) + Z_j(psi) n`` (``u = P^+ [cos psi, sin psi]``) and its
tangent ``c_j' = R_j' u + R_j v + Z_j' n`` (``v = P^+ [-sin psi, cos psi]``), the residual at
the measured angle is ``r = (rho - R_j) u + (zeta - Z_j) n`` and the sample's cost is

    e_j = r' S r - (t' S r)^2 / (t' S t),       S = Sigma^{-1},  t = c_j'

i.e. the squared Mahalanobis distance to the hypothesis's curve after minimizing over the angle
along it (one Gauss-Newton step; exact to first order in the noise). Under the true hypothesis
e_j is chi-square with 2 degrees of freedom; ``Lambda_j = sum_k e_j,k = -2 log L_j + const``.
Moving data simply contribute samples at other angles: the hypotheses stay tied to f_init's
turn count, so motion adds evidence wherever the magnets differ.

Decoder specification (for firmware; :class:`PowerUpIdentifier` is the reference)
---------------------------------------------------------------------------------
Constants (:class:`PowerUpDecoder`, all float64 in the reference):

- ``n`` pole pairs, ``L`` grid points per electrical period, ``M = n L``;
- ``P`` (2 x 3) and ``o`` (3): f_init's projection and offsets (as the lookup table's);
- ``nv`` (3): unit null vector of P, ``cross(P[0], P[1]) / |cross(P[0], P[1])|``;
- ``A`` (2 x 2, symmetric), ``B`` (2), ``C``: ``A = P+' S P+``, ``B = P+' S nv``,
  ``C = nv' S nv`` with ``P+ = pinv(P)`` and the noise precision ``S = Sigma^{-1}``
  (``Sigma = sigma^2 I`` from calibration, so costs are in noise-sigma units squared);
- tables ``R[q]``, ``Z[q]``, ``q = 0..M-1``: rho and zeta of the model flux at the calibration
  frame's f_init angle ``y_q = 2 pi q / M`` (i.e. at the true angle y0 solving
  ``f_init(g_theta(y0)) = y_q`` exactly), so ``atan2`` of the table point is ``2 pi q / L``;
- ``alpha``: accepted error probability; lock when the best posterior >= 1 - alpha;
- ``cap``: censoring level of one sample's cost, ``2 ln 100`` (a clean sample exceeds it once
  in a hundred): Huber's censored probability-ratio test (Huber 1965, Ann. Math. Statist.
  36(6)), the likelihood of Gaussian noise contaminated by rare outliers; one sample then weighs
  at most a likelihood ratio of 100 against any hypothesis, so with alpha < 1 % no single sample
  (a glitch) can lock.
- ``w``: the common-gain prior's information ``1 / gain_sd^2`` (only with the gain profile,
  ``gain_sd > 0``; see "Common gain" below); ``T``: electrical turns of motion before the lock
  (0: none; see "Sensors changed since calibration");
- ``wt``, ``kd``, ``bd``, ``bf``: the misfit test's weight ``(1 - 1 / kappa) / 2``, drift
  ``ln kappa`` and bounds ``ln(1 / beta)``, ``ln(1 / gamma)`` (:mod:`hallcal.sensor.misfit`:
  does any pole pair fit at all?);
- ``K0``, ``gz``, ``g4``: the goodness-of-fit gate at the lock (see "Sensors changed since
  calibration"): the samples of evidence before the lock ``K0`` (:data:`DEFAULT_GATE_SAMPLES`),
  and ``gz = 2 (z^2 - 1) / 3``, ``g4 = 4 z^2`` with ``z`` the standard normal quantile of
  ``1 - alpha_g`` (``alpha_g`` the gate's false-alarm rate, :data:`DEFAULT_GATE_RATE`); without
  the gate ``K0 = 0`` and step 7's gate always passes (artifacts made before it).

State: ``m`` (integer turn count, 0), ``psi_prev`` (none yet), ``Lam[j] = 0`` for j = 0..n-1,
``locked = false``, ``mismatch = false``, ``best = 0``, ``D = 0`` (misfit statistic), ``Q = 0``
(the best hypothesis's whole cost), ``k = 0`` (samples of evidence); with the gain profile
also ``s[j] = 1`` and ``I[j] = w``.

Per sample ``d = (d1, d2, d3)``:

1. ``x = d - o``; ``al = P[0].x``; ``be = P[1].x``; ``rho = sqrt(al^2 + be^2)``;
   ``psi = atan2(be, al)`` in (-pi, pi]; ``zeta = nv.x``.
2. Turn count (f_init's unwrap from y = 0 before the first sample, eq. fimp):
   first sample ``m = -floor((psi + pi) / (2 pi))``, later ``m -= floor((psi - psi_prev + pi) /
   (2 pi))``; ``psi_prev = psi``. f_init's output is ``y = (psi + 2 pi m) / n``.
3. If locked, or mismatch, or ``rho <= 1e-12 * (1 + |R[0]|)`` (no angle information), stop
   here. Else ``k += 1``.
4. ``c = al / rho``, ``s = be / rho``;
   ``Guu = A00 c^2 + 2 A01 c s + A11 s^2``, ``Gvv = A00 s^2 - 2 A01 c s + A11 c^2``,
   ``Guv = (A11 - A00) c s + A01 (c^2 - s^2)``, ``Gun = B0 c + B1 s``, ``Gvn = B1 c - B0 s``,
   ``Gnn = C``.
5. For each hypothesis j = 0..n-1:

   - table coordinate ``x_j = ((m + j) mod n) L + L psi / (2 pi)`` (mod taken into 0..n-1);
     if ``x_j < 0``: ``x_j += M``; ``i = floor(x_j)``, if ``i >= M``: ``i = M - 1``;
     ``f = x_j - i``; ``i1 = i + 1`` or 0 when ``i = M - 1``;
   - ``Rj = R[i] + f (R[i1] - R[i])``, ``Zj = Z[i] + f (Z[i1] - Z[i])``,
     ``dR = (R[i1] - R[i]) L / (2 pi)``, ``dZ = (Z[i1] - Z[i]) L / (2 pi)`` (per electrical rad);
   - ``a = rho - Rj``, ``b = zeta - Zj``;
   - ``rr = a^2 Guu + 2 a b Gun + b^2 Gnn``;
     ``tr = a (dR Guu + Rj Guv + dZ Gun) + b (dR Gun + Rj Gvn + dZ Gnn)``;
     ``tt = dR^2 Guu + Rj^2 Gvv + dZ^2 Gnn + 2 dR Rj Guv + 2 dR dZ Gun + 2 Rj dZ Gvn``;
   - without the gain profile: ``Lam[j] += min(rr - tr^2 / tt, cap)``;
   - with it (``a = rho - s[j] Rj``, ``b = zeta - s[j] Zj`` above instead):
     ``e = rr - tr^2 / tt``, ``tp = Rj (dR Guu + Rj Guv + dZ Gun) + Zj (dR Gun + Rj Gvn + dZ Gnn)``,
     ``pr = Rj (a Guu + b Gun) + Zj (a Gun + b Gnn) - tp tr / tt``,
     ``pp = Rj^2 Guu + 2 Rj Zj Gun + Zj^2 Gnn - tp^2 / tt``, ``inc = e - pr^2 / (I[j] + pp)``;
     ``u = 1`` if ``inc <= cap`` else ``cap / inc``; ``I[j] += u pp``;
     ``s[j] += u pr / I[j]``; ``Lam[j] += min(inc, cap)``.
6. ``Lmin = min_j Lam[j]``, ``best`` = the smallest j attaining it; ``Lam[j] -= Lmin`` for all j
   (keeps the numbers bounded; the posterior only depends on differences). The sum of the Lmin
   so far is the best hypothesis's whole cost: ``Q += Lmin``; ``D += wt Lmin - kd`` (the misfit
   statistic);
   if ``D >= bd``: ``mismatch = true`` (no pole pair fits: the signals do not match this
   calibration), stop here for good.
7. ``W = sum_{j != best} exp(-Lam[j] / 2)``; posterior of best ``p = 1 / (1 + W)``; lock when
   ``W <= alpha / (1 - alpha)`` (i.e. p >= 1 - alpha) and ``D <= -bf`` (the best fits) and,
   with a travel ``T > 0`` (``lock_travel``), f_init's electrical angle ``psi + 2 pi m`` has
   spanned at least ``2 pi T`` (max - min over the samples of evidence so far), and ``k >= K0``
   samples of evidence. The first time all of these hold, the gate: with ``x = Q - 2 k - gz``,
   the best fits when ``x <= 0`` or ``x^2 <= g4 k`` (Q within the chi-square(2 k) quantile of
   ``1 - alpha_g``); then lock, else ``mismatch = true`` (the data fit no pole pair as the
   calibration's noise allows), stop here for good. Margin ``sqrt(min_{j != best} Lam[j])`` in
   noise sigmas (the log-likelihood-ratio margin is half its square).

Output: the calibration frame's f_init value ``y_abs = y + 2 pi best / n``, and the corrected
angle ``y_star = y_abs + eta(y_abs)`` with the lookup table of eq. (f_final). Before the lock
``best`` is the current maximum-likelihood choice (it may still change); f_init's electrical
angle is right from the first sample either way, so commutation never waits for the decision.
The first output lies in [-pi/n, 2 pi - pi/n) (the calibration frame modulo one revolution);
later outputs are continuous.

Common gain. All sensors' signals scaled by s about f_init's offsets (the magnets'
temperature: NdFeB remanence -0.12 %/K) leave psi unchanged and scale rho, zeta and the
tangent; hypothesis j's cost over the samples so far is then ``sum_k e_jk(s) + w (s - 1)^2``,
quadratic in s, and its minimum over s is kept by a recursive least-squares update: ``s[j]`` the
estimate, ``I[j]`` its information (``w`` plus the ``pp`` of the samples), ``inc`` exactly what
the profiled cost grows by with the new sample (Laplace-equivalent to integrating s out: the
Occam factors of the hypotheses differ by their radii, about 1 %). Censoring stays per sample
(no sample brings more than cap); a censored sample still moves s, with Huber's bounded
weight ``cap / inc`` (Huber 1964, Ann. Math. Statist. 35(1)), so that one hypothesis whose
first samples were censored is not held at a wrong s for good. The price: at standstill a
common gain and a magnet's strength look alike, so only the direction of (rho, zeta) across the
curve separates the pole pairs, which one sensor's own gain or offset moves; hence the
calibration keeps the profile only where it makes the lock more robust
(:func:`analyze_calibration`). ``gain_sd = 0`` is the decoder without it (s = 1; artifacts
made before it).

Sensors changed since calibration. The decoder assumes the calibrated sensors (up to the common
gain, with the profile): a change moves the measured point off the right hypothesis's curve,
and where the magnets differ by little it can move it onto a wrong one, which then wins the
lock and passes the misfit test. :mod:`hallcal.sensor.drift_margin` measures from the tables how
large a change that takes (:attr:`IdentifiabilityReport.drift`). Where a plausible one suffices
(one sensor's gain or offset by 1 %, all by 5 %), no decoder can be certain at standstill: a
common gain looks like a magnet's strength, and once it is profiled one sensor's drift moves
the remaining evidence onto another magnet. Over one electrical revolution of motion one
sensor's change is the same pattern in the electrical angle under every hypothesis while the
magnets differ, so :func:`analyze_calibration` gives such a calibration the profile and the
travel ``T = 1`` (:data:`DEFAULT_LOCK_TRAVEL`).

Where the plain lock survives the plausible drifts, a larger change (one sensor's gain by 5-10 %,
an offset by 5 %, a 3 % common gain: tens of noise sigmas) mostly puts the point far from every
curve (the misfit test refuses), but in a few per cent of positions next to a wrong pole pair's
curve, within a noise sigma or two. Measured before the gate (``benchmarks/
bench_powerup_margin.txt``, 5 motors, 11 changes, 40 power-ups each): 73 wrong locks in 2200;
two kinds. Locks after 15-110 samples whose best cost was already 1.7-2.3 times the noise's
per degree of freedom (chi-square p-value 1e-3 to 1e-25): the misfit test accepts any cost
below 2.4 times the noise's (kappa = 8), and its statistic drifts down slowly there. And quick
locks (5-12 samples) on a wrong curve within about one sigma: at standstill nothing in 6
samples tells that from noise (a bias b per sample adds k b^2 to a chi-square(2 k) cost). Hence
the gate (step 7): the winner's whole cost against the chi-square(2 k) quantile of ``1 -
alpha_g`` (Cornish-Fisher to the constant term: the tail probability at the bound within 3 % of
alpha_g for k >= 6, 0.5 % at k = 96), once, at the first sample the lock rule holds, and not
before ``K0`` samples of evidence: at K0 = 96 it sees a constant misfit of one noise sigma per
sample (cost 1.5 times the noise's, :data:`~hallcal.sensor.misfit.CONFIRM_RATIO`) with
probability 0.86, half a sigma^2 with 0.22.
Under the calibrated noise the gate refuses a healthy power-up with probability alpha_g (the
cost of the best is at most the right hypothesis's, a chi-square(2 k) sum); the price is the
healthy lock after K0 samples instead of about 6.

Units: angles in rad (mechanical unless said electrical); d, rho, zeta in the sensor's unit;
costs in noise-sigma units squared.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import statistics
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.sensor.drift_margin import PLAUSIBLE_GAIN_CHANGE, DriftMargin, drift_margin
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT
from hallcal.sensor.misfit import (
    DEFAULT_FIT_RATE,
    DEFAULT_MISFIT_RATIO,
    DEFAULT_MISMATCH_RATE,
    MisfitTest,
)

__all__ = [
    "AbsoluteAngles",
    "Identifiability",
    "IdentifiabilityReason",
    "IdentifiabilityReport",
    "NoiseEstimate",
    "PowerUpDecoder",
    "PowerUpIdentification",
    "PowerUpIdentifier",
    "PowerUpStatus",
    "absolute_reconstruction",
    "analyze_calibration",
    "assess_identifiability",
    "build_decoder",
    "estimate_normal_noise",
    "gate_dispersion",
    "null_vector",
]

TWO_PI = 2.0 * math.pi
#: Grid sizes per electrical period tried by :func:`build_decoder` (powers of two).
GRID_CHOICES = (32, 64, 128, 256, 512, 1024)
#: Default largest linear-interpolation error of the tables, in noise sigmas.
DEFAULT_INTERPOLATION_TOLERANCE = 0.02
#: Default accepted probability of a wrong pole pair (per power-up).
DEFAULT_ERROR_TARGET = 1e-3
#: Default censoring level c of the per-sample cost: a clean sample exceeds it with probability
#: exp(-c / 2) = 1 % (chi-square, 2 degrees of freedom), so censoring costs little evidence.
DEFAULT_COST_CAP = 2.0 * math.log(100.0)
#: Default prior standard deviation of the signals' common gain s since calibration (about
#: f_init's offsets; step 5): a plausible temperature swing (NdFeB remanence, 40 K: 4.8 %,
#: :data:`~hallcal.sensor.drift_margin.PLAUSIBLE_GAIN_CHANGE`). It only keeps the first sample's
#: scale finite: one sample already carries about (R / sigma)^2 = 10^5 times its information.
#: 0 disables the profile (the decoder of artifacts made before it: s = 1).
DEFAULT_GAIN_SD = PLAUSIBLE_GAIN_CHANGE
#: Electrical turns of motion the decoder of a drift-fragile calibration waits for before the
#: lock (:func:`analyze_calibration`): over one electrical revolution one sensor's gain or
#: offset change is a fixed pattern in the electrical angle, the same under every hypothesis,
#: while the magnets' differences are not; measured on a 5-pole-pair bench whose magnets are
#: 1 % apart (30 power-ups each, 0.5 rad/s): right 30 healthy, 30 with all gains x0.97, 30 with
#: one sensor's gain x0.99 or offset +1 %, mismatch 30 with 5 %, no wrong lock (at standstill
#: the same decoder locked wrong at most positions with 1 %).
DEFAULT_LOCK_TRAVEL = 1.0
#: alpha_g: false-alarm rate of the goodness-of-fit gate at the lock (step 7) under the
#: calibrated noise; a refused healthy power-up says "mismatch" (measured: 0 in 2000 healthy
#: power-ups on five motors, ``benchmarks/bench_powerup_margin.txt``).
DEFAULT_GATE_RATE = 1e-3
#: K0: samples of evidence before the lock, so that the gate can see a wrong pole pair that fits
#: within about a noise sigma (module doc, "Sensors changed since calibration"): measured on five
#: motors and 11 sensor changes (2200 power-ups), wrong locks 73 (no gate) -> 49 (gate, lock as
#: before) -> 26 / 19 / 13 / 10 with K0 = 48 / 64 / 96 / 128; the healthy lock comes at K0 then.
DEFAULT_GATE_SAMPLES = 96


# ------------------------------------------------------------------------------------------------
# Geometry shared by tables, noise estimate and identifier
# ------------------------------------------------------------------------------------------------


def null_vector(projection: ArrayLike) -> NDArray[np.float64]:
    """Unit vector spanning the null space of f_init's 2 x 3 projection P.

    ``cross(P[0], P[1])`` normalized (for the Clarke rows: ``(1, 1, 1) / sqrt(3)``, the
    zero-sequence direction); its sign is part of the decoder's table convention.

    Parameters
    ----------
    projection : array_like, shape (2, 3)
        f_init's projection P (rank 2).

    Returns
    -------
    ndarray, shape (3,)
        The unit null vector ``nv`` with ``P @ nv = 0``.
    """
    P = np.asarray(projection, dtype=np.float64).reshape(2, 3)
    nv = np.cross(P[0], P[1])
    norm = float(np.linalg.norm(nv))
    if not norm > 0.0:
        raise ValueError("the projection has rank < 2")
    return nv / norm


def _normal_tail(x: NDArray) -> NDArray:
    """Phi(-x) = erfc(x / sqrt 2) / 2, vectorized without SciPy (keeps ``calibrate`` and
    ``reconstruct`` light): the Chebyshev fit ``erfcc`` of Press et al., Numerical Recipes,
    2nd ed., sec. 6.2, fractional error below 1.2e-7 everywhere."""
    z = np.abs(np.asarray(x, dtype=np.float64)) / math.sqrt(2.0)
    t = 1.0 / (1.0 + 0.5 * z)
    poly = -1.13520398 + t * (1.48851587 + t * (-0.82215223 + t * 0.17087277))
    poly = 0.09678418 + t * (-0.18628806 + t * (0.27886807 + t * poly))
    poly = -1.26551223 + t * (1.00002368 + t * (0.37409196 + t * poly))
    erfc = t * np.exp(-z * z + poly)
    return 0.5 * np.where(np.asarray(x) >= 0.0, erfc, 2.0 - erfc)


def _wrap(x: NDArray) -> NDArray:
    """mod(x + pi, 2 pi) - pi."""
    return np.mod(x + math.pi, TWO_PI) - math.pi


def _invert_model(
    flux: FluxModel,
    pole_pairs: int,
    projection: NDArray,
    offset: NDArray,
    y_target: NDArray,
    y0_start: NDArray,
) -> NDArray[np.float64]:
    """True angles y0 with ``f_init(g(y0)) = y_target`` in the calibration frame (Newton).

    Solves ``wrap(psi(g(y0)) - n y_target) = 0`` from ``y0_start`` (the lookup table's
    estimate, within 1e-7 rad); the model must be bijective (eq. recon_biject).
    """
    n = int(pole_pairs)
    y0 = np.array(y0_start, dtype=np.float64)
    for _ in range(8):
        g, gp = flux.value_and_derivative(y0)
        g -= offset
        ab = g @ projection.T
        dab = gp @ projection.T
        rho2 = np.maximum(np.sum(ab * ab, axis=1), np.finfo(float).tiny)
        psi = np.arctan2(ab[:, 1], ab[:, 0])
        dpsi = (ab[:, 0] * dab[:, 1] - ab[:, 1] * dab[:, 0]) / rho2
        res = _wrap(psi - n * y_target)
        step = res / np.where(np.abs(dpsi) > 0, dpsi, 1.0)
        y0 = y0 - step
        if float(np.max(np.abs(step))) < 1e-14 * max(1.0, float(np.max(np.abs(y0)))):
            break
    return y0


def _turns(psi: NDArray[np.float64]) -> NDArray[np.int64]:
    """f_init's integer turn counts m_k from y = 0 before the first sample (eq. fimp)."""
    if psi.size == 0:
        return np.zeros(0, dtype=np.int64)
    jumps = np.empty(psi.shape, dtype=np.float64)
    jumps[0] = -np.floor((psi[0] + math.pi) / TWO_PI)
    jumps[1:] = -np.floor((np.diff(psi) + math.pi) / TWO_PI)
    return np.cumsum(jumps).astype(np.int64)


#: A float (the streaming identifier) or an array (the batch one).
_Num = Any


def gram_at(A: NDArray, B: NDArray, c: _Num, s: _Num) -> dict[str, _Num]:
    """The noise metric's terms in the frame (u, v, nv) at the angle with cosine ``c`` and sine
    ``s`` (step 5): ``guu``, ``gvv``, ``guv`` from A (2 x 2) and ``gun``, ``gvn`` from B (2,).

    Parameters
    ----------
    A : ndarray (2, 2)
        The metric's alpha-beta block.
    B : ndarray (2,)
        Its alpha-beta / null-vector terms.
    c, s : float or ndarray
        Cosine and sine of the electrical angle.

    Returns
    -------
    dict
        ``guu``, ``gvv``, ``guv``, ``gun``, ``gvn``.
    """
    return {
        "guu": A[0, 0] * c * c + 2 * A[0, 1] * c * s + A[1, 1] * s * s,
        "gvv": A[0, 0] * s * s - 2 * A[0, 1] * c * s + A[1, 1] * c * c,
        "guv": (A[1, 1] - A[0, 0]) * c * s + A[0, 1] * (c * c - s * s),
        "gun": B[0] * c + B[1] * s,
        "gvn": B[1] * c - B[0] * s,
    }


def tangent_terms(dR: _Num, Rj: _Num, dZ: _Num, gram: tuple[_Num, ...]) -> tuple[_Num, _Num, _Num]:
    """<t, u>, <t, nv> and <t, t> of the table curve's tangent t = dR u + Rj v + dZ nv in the
    noise metric (step 5).

    Parameters
    ----------
    dR, Rj, dZ : float or ndarray
        The tangent's components along u (the radius' slope), v (the radius) and nv (the null
        value's slope), per electrical rad.
    gram : tuple
        The metric's terms guu, gvv, guv, gun, gvn, gnn at the sample's angle (:func:`gram_at`).

    Returns
    -------
    (tu, tn, tt)
        <t, u>, <t, nv> and <t, t>.
    """
    guu, gvv, guv, gun, gvn, gnn = gram
    tu = dR * guu + Rj * guv + dZ * gun
    tn = dR * gun + Rj * gvn + dZ * gnn
    tt = (
        dR * dR * guu
        + Rj * Rj * gvv
        + dZ * dZ * gnn
        + 2.0 * dR * Rj * guv
        + 2.0 * dR * dZ * gun
        + 2.0 * Rj * dZ * gvn
    )
    return tu, tn, tt


def gain_terms(
    a: _Num, b: _Num, Rj: _Num, Zj: _Num, dR: _Num, dZ: _Num, gram: tuple[_Num, ...]
) -> tuple[_Num, _Num, _Num]:
    """The common-gain profile's terms of step 5 for the residual ``r = a u + b nv`` (taken at
    the hypothesis's current scale s) and its table point ``p = Rj u + Zj nv``, both with the
    curve's tangent projected out in the noise metric (``Q = S - S t t' S / t' S t``).

    Returns
    -------
    (e, pr, pp)
        ``e = r' Q r`` (the sample's cost at s, :func:`_step5_cost`), ``pr = p' Q r`` and
        ``pp = p' Q p``: the cost at s + ds is ``e - 2 ds pr + ds^2 pp``.
    """
    guu, _, _, gun, _, gnn = gram
    tu, tn, tt = tangent_terms(dR, Rj, dZ, gram)
    tr = a * tu + b * tn
    tp = Rj * tu + Zj * tn
    e = a * a * guu + 2.0 * a * b * gun + b * b * gnn - tr * tr / tt
    pr = Rj * (a * guu + b * gun) + Zj * (a * gun + b * gnn) - tp * tr / tt
    pp = Rj * Rj * guu + 2.0 * Rj * Zj * gun + Zj * Zj * gnn - tp * tp / tt
    return e, pr, pp


def _step5_cost(a: _Num, b: _Num, dR: _Num, Rj: _Num, dZ: _Num, gram: tuple[_Num, ...]) -> _Num:
    """e_j of step 5: the squared noise-metric norm of the residual a u + b nv off the table
    curve, less its part along the curve's tangent (`gram` as for :func:`tangent_terms`)."""
    guu, _, _, gun, _, gnn = gram
    tu, tn, tt = tangent_terms(dR, Rj, dZ, gram)
    rr = a * a * guu + 2.0 * a * b * gun + b * b * gnn
    tr = a * tu + b * tn
    return rr - tr * tr / tt


# ------------------------------------------------------------------------------------------------
# The decoder
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PowerUpDecoder:
    """Precomputed tables and constants of the power-up identification (see the module doc).

    Attributes
    ----------
    pole_pairs : int
        n.
    grid : int
        L, table points per electrical period; the tables have M = n L points.
    projection : ndarray, shape (2, 3)
        f_init's projection P (the lookup table's).
    offset : ndarray, shape (3,)
        f_init's offsets o.
    null : ndarray, shape (3,)
        nv, unit null vector of P (:func:`null_vector`).
    noise_covariance : ndarray, shape (3, 3)
        Sigma of the Hall noise (per channel, white) the costs are normalized by.
    gram_a : ndarray, shape (2, 2)
        ``A = P+' S P+``.
    gram_b : ndarray, shape (2,)
        ``B = P+' S nv``.
    gram_c : float
        ``C = nv' S nv``.
    radius : ndarray, shape (M,)
        R[q]: |P (g - o)| at the calibration frame's f_init angle 2 pi q / M.
    zero : ndarray, shape (M,)
        Z[q]: nv . (g - o) there.
    error_target : float
        alpha: lock when the best hypothesis's posterior reaches 1 - alpha.
    interpolation_error : float
        Largest error of the tables' linear interpolation (midpoints, in noise sigmas).
    cost_cap : float
        c: each sample's cost is censored at c (step 5), so that no single sample (an ADC
        glitch, a burst of rig vibration) brings more than c of evidence.
    misfit : MisfitTest
        kappa and beta of the misfit test (steps 6 and 7; :mod:`hallcal.sensor.misfit`).
    gain_sd : float
        Prior standard deviation of the signals' common gain s since calibration (step 5,
        :data:`DEFAULT_GAIN_SD`); 0: no gain profile (s = 1, the decoder before it).
    lock_travel : float
        Electrical turns f_init's angle must have spanned since power-up before the lock
        (step 7); 0: none (the decoder before it).
    gate_rate : float
        alpha_g, the false-alarm rate of the goodness-of-fit gate at the lock (step 7,
        :data:`DEFAULT_GATE_RATE`); 0: no gate (the decoder before it).
    gate_samples : int
        K0, samples of evidence before the lock (step 7, :data:`DEFAULT_GATE_SAMPLES`).
    gate_dispersion : float
        phi >= 1: the variance of the right hypothesis's cost over K0 samples on the
        calibration recording relative to chi-square's (:func:`gate_dispersion`); the gate's
        quantile is Satterthwaite's for that variance (1: white noise as calibrated).
    """

    pole_pairs: int
    grid: int
    projection: NDArray[np.float64] = field(repr=False)
    offset: NDArray[np.float64] = field(repr=False)
    null: NDArray[np.float64] = field(repr=False)
    noise_covariance: NDArray[np.float64] = field(repr=False)
    gram_a: NDArray[np.float64] = field(repr=False)
    gram_b: NDArray[np.float64] = field(repr=False)
    gram_c: float
    radius: NDArray[np.float64] = field(repr=False)
    zero: NDArray[np.float64] = field(repr=False)
    error_target: float = DEFAULT_ERROR_TARGET
    interpolation_error: float = 0.0
    cost_cap: float = DEFAULT_COST_CAP
    misfit: MisfitTest = field(default_factory=MisfitTest)
    gain_sd: float = 0.0
    lock_travel: float = 0.0
    gate_rate: float = 0.0
    gate_samples: int = 0
    gate_dispersion: float = 1.0

    @property
    def gate_terms(self) -> tuple[float, float]:
        """(gz, g4) of step 7's gate: ``2 phi (z^2 - 1) / 3`` and ``4 phi z^2``, z the standard
        normal quantile of ``1 - alpha_g``, phi the dispersion. The chi-square(2 k) quantile of
        ``1 - alpha_g`` is ``2 k + gz + sqrt(g4 k)`` to the Cornish-Fisher expansion's constant
        term at phi = 1; a cost of mean 2 k and variance 4 k phi is ``phi`` times a
        chi-square(2 k / phi) (Satterthwaite 1946, Biometrics Bull. 2(6)), whose quantile is
        the same expression with these terms."""
        z = statistics.NormalDist().inv_cdf(1.0 - self.gate_rate)
        phi = self.gate_dispersion
        return 2.0 * phi * (z * z - 1.0) / 3.0, 4.0 * phi * z * z

    def gate_passes(self, total: ArrayLike, samples: ArrayLike) -> NDArray[np.bool_]:
        """Step 7's gate: the best hypothesis's whole cost ``total`` (Q) over ``samples`` (k)
        samples of evidence within the chi-square(2 k) quantile of ``1 - alpha_g`` (True
        everywhere without the gate)."""
        Q = np.asarray(total, dtype=np.float64)
        k = np.asarray(samples, dtype=np.float64)
        if not self.gate_rate > 0.0:
            return np.ones(np.broadcast(Q, k).shape, dtype=bool)
        gz, g4 = self.gate_terms
        x = Q - 2.0 * k - gz
        return (x <= 0.0) | (x * x <= g4 * k)

    @property
    def gain_weight(self) -> float:
        """``w = 1 / gain_sd^2``: the prior's information on s, the initial ``I_j`` of step 5
        (inf without the profile)."""
        return 1.0 / self.gain_sd**2 if self.gain_sd > 0.0 else math.inf

    @property
    def table_size(self) -> int:
        """M = n L."""
        return int(self.radius.size)

    @property
    def noise_std(self) -> float:
        """sqrt of the mean channel variance of Sigma."""
        return float(math.sqrt(np.trace(self.noise_covariance) / 3.0))

    @property
    def lock_threshold(self) -> float:
        """alpha / (1 - alpha): lock when the other hypotheses' likelihood weights sum below it."""
        a = self.error_target
        return a / (1.0 - a)

    # -- vectorized evaluation --------------------------------------------------------------

    def features(self, d: ArrayLike) -> dict[str, NDArray]:
        """Per-sample quantities of steps 1, 2 and 4: rho, psi, zeta, m and the Gram terms."""
        x = np.atleast_2d(np.asarray(d, dtype=np.float64)) - self.offset
        ab = x @ self.projection.T
        al, be = ab[:, 0], ab[:, 1]
        rho = np.hypot(al, be)
        psi = np.arctan2(be, al)
        zeta = x @ self.null
        valid = rho > 1e-12 * (1.0 + abs(float(self.radius[0])))
        safe = np.where(valid, rho, 1.0)
        c, s = al / safe, be / safe
        A, B = self.gram_a, self.gram_b
        return {
            "rho": rho,
            "psi": psi,
            "zeta": zeta,
            "m": _turns(psi),
            "valid": valid,
            **gram_at(A, B, c, s),
        }

    def _interp(self, pos: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """R, Z and their slopes per electrical rad at table coordinates pos in [0, M) (step 5)."""
        M = self.table_size
        i = np.minimum(np.floor(pos).astype(np.int64), M - 1)
        f = pos - i
        i1 = np.where(i == M - 1, 0, i + 1)
        R0, R1 = self.radius[i], self.radius[i1]
        Z0, Z1 = self.zero[i], self.zero[i1]
        k = self.grid / TWO_PI
        return R0 + f * (R1 - R0), Z0 + f * (Z1 - Z0), (R1 - R0) * k, (Z1 - Z0) * k

    def tables_at(self, pos: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """R, Z and their slopes per electrical rad at table coordinates ``pos`` in [0, M)
        (linear interpolation, step 5; :meth:`coordinates` gives ``pos``)."""
        return self._interp(pos)

    def coordinates(self, psi: NDArray, m: NDArray, offsets: ArrayLike) -> NDArray:
        """Table coordinates x_j of step 5 for samples (psi, m) and hypotheses ``offsets``.

        Parameters
        ----------
        psi : ndarray, shape (K,)
            Wrapped electrical angles atan2(beta, alpha) [rad, electrical].
        m : ndarray of int, shape (K,)
            f_init's turn counts (step 2).
        offsets : array_like of int, shape (J,)
            Hypotheses j (pole pairs between power-up frame and calibration frame).

        Returns
        -------
        ndarray, shape (K, J)
            x_j in [0, M) [table points].
        """
        n, L, M = self.pole_pairs, self.grid, self.table_size
        j = np.asarray(offsets, dtype=np.int64)
        e = np.mod(np.asarray(m, dtype=np.int64)[:, None] + j[None, :], n)
        x = e * L + (L / TWO_PI) * np.asarray(psi)[:, None]
        return np.where(x < 0.0, x + M, x)

    def _costs(self, F: dict[str, NDArray], pos: NDArray) -> NDArray:
        """e_j of step 5 for features F (per row) and table coordinates pos (rows x hyps)."""
        Rj, Zj, dR, dZ = self._interp(pos)
        guu, gvv, guv = F["guu"][:, None], F["gvv"][:, None], F["guv"][:, None]
        gun, gvn, gnn = F["gun"][:, None], F["gvn"][:, None], self.gram_c
        a = F["rho"][:, None] - Rj
        b = F["zeta"][:, None] - Zj
        return _step5_cost(a, b, dR, Rj, dZ, (guu, gvv, guv, gun, gvn, gnn))

    def sample_costs(self, d: ArrayLike) -> NDArray[np.float64]:
        """Per-sample costs e_j (K, n) of every hypothesis j at the calibrated gain s = 1,
        censored at the cap (0 for samples without angle)."""
        F = self.features(d)
        pos = self.coordinates(F["psi"], F["m"], np.arange(self.pole_pairs))
        e = np.minimum(self._costs(F, pos), self.cost_cap)
        e[~F["valid"]] = 0.0
        return e

    def _gain_terms(self, F: dict[str, NDArray], pos: NDArray, scale: _Num = 1.0) -> tuple:
        """(e, pr, pp) of :func:`gain_terms` per row of F and hypothesis column of pos, with
        the residual taken at the gain ``scale`` (a number, or one per hypothesis)."""
        Rj, Zj, dR, dZ = self._interp(pos)
        gram = (F["guu"][:, None], F["gvv"][:, None], F["guv"][:, None], F["gun"][:, None],
                F["gvn"][:, None], self.gram_c)  # fmt: skip
        a = F["rho"][:, None] - scale * Rj
        b = F["zeta"][:, None] - scale * Zj
        return gain_terms(a, b, Rj, Zj, dR, dZ, gram)

    def standstill_costs(self, d: ArrayLike) -> NDArray[np.float64]:
        """Per-sample costs (K, n) as the decoder weighs one position held still: with the gain
        profile, each sample's own best common gain (``e - pr^2 / pp`` at s = 1: what many
        samples at that position converge to, the prior's weight negligible); without it,
        :meth:`sample_costs`. Censored at the cap; 0 for samples without angle."""
        if not self.gain_sd > 0.0:
            return self.sample_costs(d)
        F = self.features(d)
        pos = self.coordinates(F["psi"], F["m"], np.arange(self.pole_pairs))
        e, pr, pp = self._gain_terms(F, pos)
        out = np.minimum(e - pr * pr / np.where(pp > 0.0, pp, np.inf), self.cost_cap)
        out[~F["valid"]] = 0.0
        return out

    def cumulative_costs(self, d: ArrayLike, *, stop: bool = False) -> NDArray[np.float64]:
        """Lambda_j after each sample (K, n), as steps 5 and 6 accumulate them (before the
        renormalization: the first row is the first sample's evidence).

        Parameters
        ----------
        d : array_like, shape (K, 3)
            Hall signals from power-up.
        stop : bool, keyword-only
            Allowed to return fewer rows, once the lock or the mismatch has been reached
            within them (the sequential test looks no further).
        """
        d = np.atleast_2d(np.asarray(d, dtype=np.float64))
        if not self.gain_sd > 0.0:
            return np.cumsum(self.sample_costs(d), axis=0)
        return _profiled_lambda(self, d, stop=stop)

    def identify(self, d: ArrayLike, *, lock: bool = True) -> PowerUpIdentification:
        """Run the identification over a recording from power-up (vectorized; same decisions
        as :class:`PowerUpIdentifier` sample by sample).

        Parameters
        ----------
        d : array_like, shape (K, 3)
            Hall signals from the first sample after power-up.
        lock : bool, keyword-only
            Stop at the first sample where the posterior of the best hypothesis reaches
            1 - alpha (the sequential test); False: accumulate over all samples (plain
            maximum likelihood over the whole record).
        """
        return _identify(self, np.atleast_2d(np.asarray(d, dtype=np.float64)), lock=lock)

    def to_dict(self) -> dict[str, Any]:
        """The decoder's parameters (the tables follow from the flux model and these)."""
        return {
            "grid": int(self.grid),
            "table_size": self.table_size,
            "noise_std": self.noise_std,
            "noise_covariance": self.noise_covariance.tolist(),
            "error_target": float(self.error_target),
            "interpolation_error": float(self.interpolation_error),
            "cost_cap": float(self.cost_cap),
            "gain_sd": float(self.gain_sd),
            "lock_travel": float(self.lock_travel),
            "gate_rate": float(self.gate_rate),
            "gate_samples": int(self.gate_samples),
            "gate_dispersion": float(self.gate_dispersion),
            **self.misfit.to_dict(),
        }


#: Samples per block of the gain-profiled accumulation before the lock rule is checked.
_LAMBDA_BLOCK = 128


def _profiled_lambda(dec: PowerUpDecoder, d: NDArray, *, stop: bool) -> NDArray[np.float64]:
    """Cumulative costs of step 5 with the common gain profiled (sample by sample: the scale
    s_j and information I_j of each hypothesis carry over, and censoring depends on them)."""
    F = dec.features(d)
    n, K = dec.pole_pairs, d.shape[0]
    pos = dec.coordinates(F["psi"], F["m"], np.arange(n))
    Rj, Zj, dR, dZ = dec._interp(pos)
    g = {k: F[k] for k in ("guu", "gvv", "guv", "gun", "gvn")}
    scale, info = np.ones(n), np.full(n, dec.gain_weight)
    lam = np.zeros(n)
    out = np.empty((K, n))
    cap = dec.cost_cap
    used, span = np.cumsum(F["valid"]), _span(F)  # step 7's inputs, every prefix at once
    for k in range(K):
        if F["valid"][k]:
            gram = (g["guu"][k], g["gvv"][k], g["guv"][k], g["gun"][k], g["gvn"][k], dec.gram_c)
            a = F["rho"][k] - scale * Rj[k]
            b = F["zeta"][k] - scale * Zj[k]
            e, pr, pp = gain_terms(a, b, Rj[k], Zj[k], dR[k], dZ[k], gram)
            add, info, scale = _profile_step(e, pr, pp, info, scale, cap)
            lam = lam + add
        out[k] = lam
        if stop and (k + 1) % _LAMBDA_BLOCK == 0:
            rows = k + 1
            rule = _lock_rule(dec, out[:rows], used[:rows], span[:rows])
            if np.any(rule.mismatch) or np.any(rule.lock):
                return out[:rows]
    return out


def _profile_step(e: _Num, pr: _Num, pp: _Num, info: _Num, scale: _Num, cap: float) -> tuple:
    """Step 5 with the gain profile, one sample (numbers, or arrays over the hypotheses): the
    increment of Lambda (censored at ``cap``) and the new information I and scale s; a censored
    sample moves s with Huber's bounded weight ``cap / inc`` (module doc, "Common gain")."""
    inc = e - pr * pr / (info + pp)
    weight = cap / np.maximum(inc, cap)
    info = info + weight * pp
    return np.minimum(inc, cap), info, scale + weight * pr / info


def _span(F: dict[str, NDArray]) -> NDArray[np.float64]:
    """Per sample of the features ``F``, the range of f_init's electrical angle
    ``psi + 2 pi m`` over the samples of evidence so far [rad, electrical] (step 7's travel)."""
    y = np.where(F["valid"], F["psi"] + TWO_PI * F["m"], np.nan)
    with np.errstate(invalid="ignore"):
        span = np.fmax.accumulate(y) - np.fmin.accumulate(y)
    return np.where(np.isnan(span), -1.0, span)


@dataclass(frozen=True)
class _Rule:
    """Steps 6 and 7 on cumulative costs, per row: the best hypothesis's cost, the costs
    relative to it, the misfit statistic D, where the mismatch and the lock rule hold, and
    where the gate passes (it decides at the first row where the lock rule holds)."""

    total: NDArray[np.float64]
    relative: NDArray[np.float64]
    D: NDArray[np.float64]
    mismatch: NDArray[np.bool_]
    lock: NDArray[np.bool_]
    gate: NDArray[np.bool_]


def _lock_rule(dec: PowerUpDecoder, lam: NDArray, used: NDArray, span: NDArray) -> _Rule:
    """Steps 6 and 7 on cumulative costs ``lam`` (K, n), with the samples of evidence ``used``
    and f_init's electrical travel ``span`` per row (:func:`_span`)."""
    total = np.min(lam, axis=1)  # the best hypothesis's whole cost (sum of the Lmin, step 6)
    D = dec.misfit.statistic(total, used)
    relative = lam - total[:, None]
    W = np.sum(np.exp(-0.5 * relative), axis=1) - 1.0  # the best contributes exp(0) = 1
    lock = (W <= dec.lock_threshold) & (D <= -dec.misfit.fit_bound)
    if dec.lock_travel > 0.0:  # and f_init's angle has spanned lock_travel turns
        lock &= span >= TWO_PI * dec.lock_travel
    lock &= used >= dec.gate_samples  # and K0 samples of evidence
    return _Rule(total, relative, D, D >= dec.misfit.bound, lock, dec.gate_passes(total, used))


def _gram(
    projection: NDArray, null: NDArray, covariance: NDArray
) -> tuple[NDArray, NDArray, float]:
    S = np.linalg.inv(covariance)
    S = 0.5 * (S + S.T)
    Pp = np.linalg.pinv(projection)
    A = Pp.T @ S @ Pp
    return 0.5 * (A + A.T), Pp.T @ S @ null, float(null @ S @ null)


def _noise_covariance(noise_std: float | None, noise_covariance: ArrayLike | None) -> NDArray:
    if noise_covariance is not None:
        cov = np.asarray(noise_covariance, dtype=np.float64).reshape(3, 3)
        if not np.all(np.linalg.eigvalsh(0.5 * (cov + cov.T)) > 0):
            raise ValueError("noise_covariance must be symmetric positive definite")
        return 0.5 * (cov + cov.T)
    if noise_std is None or not (noise_std > 0 and math.isfinite(noise_std)):
        raise ValueError(f"noise_std must be a positive number, got {noise_std!r}")
    return float(noise_std) ** 2 * np.eye(3)


def _tables(flux: FluxModel, lut: LUT, y: NDArray) -> tuple[NDArray, NDArray]:
    """R and Z at calibration-frame f_init angles y (the table points are 2 pi q / M)."""
    y0 = _invert_model(flux, lut.pole_pairs, lut.projection, lut.offset, y, y + lut.correction(y))
    x = flux(y0) - lut.offset
    ab = x @ lut.projection.T
    return np.hypot(ab[:, 0], ab[:, 1]), x @ null_vector(lut.projection)


def build_decoder(
    flux: FluxModel,
    lut: LUT,
    *,
    noise_std: float | None = None,
    noise_covariance: ArrayLike | None = None,
    grid: int | None = None,
    interpolation_tolerance: float = DEFAULT_INTERPOLATION_TOLERANCE,
    error_target: float = DEFAULT_ERROR_TARGET,
    cost_cap: float = DEFAULT_COST_CAP,
    misfit_ratio: float = DEFAULT_MISFIT_RATIO,
    mismatch_rate: float = DEFAULT_MISMATCH_RATE,
    fit_rate: float = DEFAULT_FIT_RATE,
    gain_sd: float = 0.0,
    lock_travel: float = 0.0,
    gate_rate: float = 0.0,
    gate_samples: int = 0,
    gate_dispersion: float = 1.0,
) -> PowerUpDecoder:
    """Tables and constants of the power-up decoder for an identified flux model.

    Parameters
    ----------
    flux : FluxModel
        The identified g_theta (calibration frame).
    lut : LUT
        Its lookup table (f_init's projection and offsets; a start for the exact inversion).
        Must be bijective (eq. recon_biject).
    noise_std : float, keyword-only
        White Hall noise sigma per channel (Sigma = sigma^2 I); or give ``noise_covariance``.
    noise_covariance : array_like, shape (3, 3), optional
        Hall noise covariance Sigma (symmetric positive definite, sensor's unit squared);
        takes precedence over ``noise_std``.
    grid : int, optional
        L, points per electrical period. Default: the smallest of :data:`GRID_CHOICES` whose
        largest linear-interpolation error (table midpoints against the exact model, measured
        in the Mahalanobis norm of step 5) is below ``interpolation_tolerance`` noise sigmas.
        A bias b in the true hypothesis's residual changes a separation delta (per sample, in
        sigmas) by at most b; 0.02 keeps that below 10 % at the weakest separations that still
        identify in a few thousand samples (about 0.2 sigma).
    interpolation_tolerance : float
        That tolerance [noise sigmas]; used only when ``grid`` is None.
    error_target : float
        alpha of the sequential test (0 < alpha < 0.5).
    cost_cap : float
        Censoring level c of one sample's cost (> 0), see :data:`DEFAULT_COST_CAP`.
    misfit_ratio, mismatch_rate, fit_rate : float
        kappa, beta and gamma of the misfit test (:class:`~hallcal.sensor.misfit.MisfitTest`).
    gain_sd : float
        Prior standard deviation of the signals' common gain since calibration (>= 0; 0: no
        gain profile, s = 1), see :data:`DEFAULT_GAIN_SD`; :func:`analyze_calibration` chooses.
    lock_travel : float
        Electrical turns of motion before the lock (>= 0; step 7), see
        :data:`DEFAULT_LOCK_TRAVEL`.
    gate_rate : float
        alpha_g of the goodness-of-fit gate at the lock (in [0, 0.5); 0: no gate), see
        :data:`DEFAULT_GATE_RATE`; :func:`analyze_calibration` sets it.
    gate_samples : int
        K0, samples of evidence before the lock (>= 0), see :data:`DEFAULT_GATE_SAMPLES`.
    gate_dispersion : float
        phi >= 1 of the gate (:func:`gate_dispersion`; 1: white noise as calibrated).

    Returns
    -------
    PowerUpDecoder
    """
    lut._require_bijective()
    if not 0.0 <= gate_rate < 0.5:
        raise ValueError("gate_rate must be in [0, 0.5)")
    if int(gate_samples) != gate_samples or gate_samples < 0:
        raise ValueError("gate_samples must be an integer >= 0")
    if not (gate_dispersion >= 1.0 and math.isfinite(gate_dispersion)):
        raise ValueError("gate_dispersion must be a finite number >= 1")
    if not (gain_sd >= 0.0 and math.isfinite(gain_sd)):
        raise ValueError("gain_sd must be a finite number >= 0")
    if not (lock_travel >= 0.0 and math.isfinite(lock_travel)):
        raise ValueError("lock_travel must be a finite number >= 0")
    if not 0.0 < error_target < 0.5:
        raise ValueError("error_target must be in (0, 0.5)")
    if not cost_cap > 0.0:
        raise ValueError("cost_cap must be > 0")
    misfit = MisfitTest(float(misfit_ratio), float(mismatch_rate), float(fit_rate))
    n = lut.pole_pairs
    cov = _noise_covariance(noise_std, noise_covariance)
    nv = null_vector(lut.projection)
    A, B, C = _gram(lut.projection, nv, cov)
    choices = (int(grid),) if grid is not None else GRID_CHOICES
    if choices[0] < 4:
        raise ValueError("grid must be >= 4")
    L = choices[0]
    err = math.inf
    R, Z = _tables(flux, lut, TWO_PI * np.arange(n * L) / (n * L))
    Rm = Zm = np.empty(0)
    for k, L in enumerate(choices):
        if k:  # the next candidate doubles the grid: the last midpoints become table points
            R = np.column_stack([R, Rm]).ravel()
            Z = np.column_stack([Z, Zm]).ravel()
        # same expression as a table point of the doubled grid (2 q + 1) / (2 n L): bit-identical
        Rm, Zm = _tables(flux, lut, TWO_PI * (2 * np.arange(n * L) + 1) / (2 * n * L))
        # midpoint error of linear interpolation, in the metric of step 5 at the midpoint angles
        a = Rm - 0.5 * (R + np.roll(R, -1))
        b = Zm - 0.5 * (Z + np.roll(Z, -1))
        psi = TWO_PI * (np.arange(n * L) + 0.5) / L
        c, s = np.cos(psi), np.sin(psi)
        guu = A[0, 0] * c * c + 2 * A[0, 1] * c * s + A[1, 1] * s * s
        gun = B[0] * c + B[1] * s
        err = float(np.sqrt(np.max(a * a * guu + 2 * a * b * gun + b * b * C)))
        if err <= interpolation_tolerance:
            break  # L, R, Z and err are the last candidate's (the finest, if none is fine enough)
    return PowerUpDecoder(
        pole_pairs=n,
        grid=L,
        projection=np.array(lut.projection, dtype=np.float64),
        offset=np.array(lut.offset, dtype=np.float64),
        null=nv,
        noise_covariance=cov,
        gram_a=A,
        gram_b=B,
        gram_c=C,
        radius=R,
        zero=Z,
        error_target=float(error_target),
        interpolation_error=err,
        cost_cap=float(cost_cap),
        misfit=misfit,
        gain_sd=float(gain_sd),
        lock_travel=float(lock_travel),
        gate_rate=float(gate_rate),
        gate_samples=int(gate_samples),
        gate_dispersion=float(gate_dispersion),
    )


# ------------------------------------------------------------------------------------------------
# Identification over a recording (vectorized) and sample by sample (reference)
# ------------------------------------------------------------------------------------------------


class PowerUpStatus(enum.StrEnum):
    """Outcome of a power-up identification."""

    IDENTIFIED = "identified"  # the sequential test locked: posterior >= 1 - alpha, and it fits
    UNDECIDED = "undecided"  # not certain yet; the offset is the current maximum-likelihood one
    MISMATCH = "mismatch"  # no pole pair fits: the signals do not match this calibration

    @property
    def success(self) -> bool:
        return self is PowerUpStatus.IDENTIFIED


@dataclass(frozen=True)
class PowerUpIdentification:
    """Result of a power-up identification over a recording.

    Attributes
    ----------
    status : PowerUpStatus
    offset : int
        j: the calibration frame's f_init value is ``y + 2 pi j / n`` (locked, or the
        maximum-likelihood choice after the last sample).
    lock_sample : int or None
        Index of the sample after which the test locked.
    posterior : float
        Posterior probability of ``offset`` at the lock (or after the last sample), uniform prior.
    margin : float
        sqrt(Lambda_second - Lambda_best) [noise sigmas] at the same time.
    best : ndarray of int, shape (K,)
        Offset in force after each sample (current ML choice, frozen after the lock).
    log_likelihood : ndarray, shape (n,)
        -Lambda_j / 2 relative to the best, at the lock (or after the last sample).
    samples : int
        Samples used (up to and including the lock, or the mismatch).
    misfit : float
        The misfit statistic D (:mod:`hallcal.sensor.misfit`) at the same time: a log-likelihood
        ratio, ``<= -ln(1 / gamma)`` when the best fits, ``>= ln(1 / beta)`` for a mismatch.
    cost_per_dof : float
        The best hypothesis's mean cost per degree of freedom at the same time (about 1 when
        the model fits; the misfit's variance in noise variances, plus 1).
    mismatch_sample : int or None
        Index of the sample after which the misfit test said "mismatch" (status MISMATCH).
    """

    status: PowerUpStatus
    offset: int
    lock_sample: int | None
    posterior: float
    margin: float
    best: NDArray[np.int64] = field(repr=False)
    log_likelihood: NDArray[np.float64] = field(repr=False)
    samples: int
    misfit: float = math.nan
    cost_per_dof: float = math.nan
    mismatch_sample: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "status": self.status.value,
            "offset": int(self.offset),
            "lock_sample": self.lock_sample,
            "posterior": float(self.posterior),
            "margin": float(self.margin),
            "samples": int(self.samples),
            "misfit": float(self.misfit),
            "cost_per_dof": float(self.cost_per_dof),
            "mismatch_sample": self.mismatch_sample,
        }


def _posterior(lam: NDArray) -> tuple[int, float, float, float]:
    """(best, W, posterior, margin) of relative costs lam (min subtracted)."""
    best = int(np.argmin(lam))
    rel = lam - lam[best]
    others = np.delete(rel, best)
    W = float(np.sum(np.exp(-0.5 * others))) if others.size else 0.0
    margin = float(math.sqrt(max(float(np.min(others)), 0.0))) if others.size else math.inf
    return best, W, 1.0 / (1.0 + W), margin


def _identify(dec: PowerUpDecoder, d: NDArray, *, lock: bool) -> PowerUpIdentification:
    K = d.shape[0]
    n = dec.pole_pairs
    if K == 0:
        raise ValueError("no samples")
    lam = dec.cumulative_costs(d, stop=lock)  # fewer rows only when decided within them
    rows = lam.shape[0]
    F = dec.features(d)
    used = np.cumsum(F["valid"])[:rows]
    rule = _lock_rule(dec, lam, used, _span(F)[:rows])
    total, D, lam = rule.total, rule.D, rule.relative
    best = np.argmin(lam, axis=1)
    lock_at = mismatch_at = None
    if lock:
        bad = np.flatnonzero(rule.mismatch)
        if bad.size:
            mismatch_at = int(bad[0])
        limit = rows if mismatch_at is None else mismatch_at
        hit = np.flatnonzero(rule.lock[:limit])
        if hit.size and rule.gate[hit[0]]:
            lock_at = int(hit[0])
            mismatch_at = None
        elif hit.size:  # the gate refuses the first lock: no pole pair fits as the noise allows
            mismatch_at = int(hit[0])
    stop = rows - 1
    status = PowerUpStatus.UNDECIDED
    if lock_at is not None:
        stop, status = lock_at, PowerUpStatus.IDENTIFIED
    elif mismatch_at is not None:
        stop, status = mismatch_at, PowerUpStatus.MISMATCH
    final = lam[stop]
    j, _, post, margin = _posterior(final)
    b = np.full(K, j, dtype=np.int64)
    b[:rows] = best
    if lock_at is not None or mismatch_at is not None:
        b[stop:] = j
    return PowerUpIdentification(
        status=status,
        offset=j,
        lock_sample=lock_at,
        posterior=post,
        margin=margin if n > 1 else math.inf,
        best=b,
        log_likelihood=-0.5 * (final - final[j]),
        samples=stop + 1,
        misfit=float(D[stop]),
        cost_per_dof=float(total[stop]) / (2.0 * used[stop]) if used[stop] else math.nan,
        mismatch_sample=mismatch_at,
    )


class PowerUpIdentifier:
    """The decoder run one sample at a time: the reference for the firmware port.

    Follows the numbered steps of the module docstring literally, with Python floats.

    Parameters
    ----------
    decoder : PowerUpDecoder
    """

    def __init__(self, decoder: PowerUpDecoder) -> None:
        self.decoder = decoder
        dec = decoder
        self._n = dec.pole_pairs
        self._L = dec.grid
        self._M = dec.table_size
        self._P = [[float(v) for v in row] for row in dec.projection]
        self._o = [float(v) for v in dec.offset]
        self._nv = [float(v) for v in dec.null]
        self._A = [[float(v) for v in row] for row in dec.gram_a]
        self._B = [float(v) for v in dec.gram_b]
        self._C = float(dec.gram_c)
        self._R = [float(v) for v in dec.radius]
        self._Z = [float(v) for v in dec.zero]
        self._rho_min = 1e-12 * (1.0 + abs(self._R[0]))
        self._threshold = dec.lock_threshold
        self._cap = float(dec.cost_cap)
        self._wt = dec.misfit.weight
        self._kd = dec.misfit.drift
        self._bd = dec.misfit.bound
        self._bf = dec.misfit.fit_bound
        self._profile = dec.gain_sd > 0.0
        self._travel = TWO_PI * dec.lock_travel
        self._gate = dec.gate_rate > 0.0
        self._k0 = int(dec.gate_samples)
        self._gz, self._g4 = dec.gate_terms if self._gate else (0.0, 0.0)
        self.total = 0.0  # Q, the best hypothesis's whole cost (step 6)
        self._ymin = self._ymax = math.nan  # range of f_init's electrical angle (step 7)
        self.scale = [1.0] * self._n  # s_j, the common gain of each hypothesis
        self.info = [dec.gain_weight] * self._n  # I_j, its information
        self.m = 0
        self.psi = math.nan
        self.lam = [0.0] * self._n
        self.best = 0
        self.locked = False
        self.mismatch = False
        self.fit = 0.0  # D, the misfit statistic
        self.samples = 0
        self.lock_sample: int | None = None
        self.mismatch_sample: int | None = None
        self._started = False

    @property
    def y(self) -> float:
        """f_init's output after the last sample, ``(psi + 2 pi m) / n`` [rad]."""
        return (self.psi + TWO_PI * self.m) / self._n

    @property
    def posterior(self) -> float:
        """Posterior probability of ``best``."""
        W = sum(math.exp(-0.5 * v) for j, v in enumerate(self.lam) if j != self.best)
        return 1.0 / (1.0 + W)

    @property
    def margin(self) -> float:
        """sqrt(Lambda_second - Lambda_best) [noise sigmas]."""
        others = [v for j, v in enumerate(self.lam) if j != self.best]
        return math.sqrt(max(min(others), 0.0)) if others else math.inf

    def update(self, d1: float, d2: float, d3: float) -> int:
        """Process one sample (steps 1-7 of the module docstring).

        Parameters
        ----------
        d1, d2, d3 : float
            The three Hall signals of the sample (sensor's unit).

        Returns
        -------
        int
            The offset in force, ``best`` (pole pairs; final once ``locked``).
        """
        # 1. projection
        x0, x1, x2 = d1 - self._o[0], d2 - self._o[1], d3 - self._o[2]
        P, nv = self._P, self._nv
        al = P[0][0] * x0 + P[0][1] * x1 + P[0][2] * x2
        be = P[1][0] * x0 + P[1][1] * x1 + P[1][2] * x2
        rho = math.sqrt(al * al + be * be)
        psi = math.atan2(be, al)
        zeta = nv[0] * x0 + nv[1] * x1 + nv[2] * x2
        # 2. f_init's turn count
        if not self._started:
            self.m = -math.floor((psi + math.pi) / TWO_PI)
            self._started = True
        else:
            self.m -= math.floor((psi - self.psi + math.pi) / TWO_PI)
        self.psi = psi
        # 3.
        if self.locked or self.mismatch or rho <= self._rho_min:
            return self.best
        self.samples += 1
        y_el = psi + TWO_PI * self.m
        self._ymin = y_el if self.samples == 1 else min(self._ymin, y_el)
        self._ymax = y_el if self.samples == 1 else max(self._ymax, y_el)
        # 4. Gram terms at this angle
        c, s = al / rho, be / rho
        (A00, A01), (_, A11) = self._A
        B0, B1 = self._B
        Guu = A00 * c * c + 2.0 * A01 * c * s + A11 * s * s
        Gvv = A00 * s * s - 2.0 * A01 * c * s + A11 * c * c
        Guv = (A11 - A00) * c * s + A01 * (c * c - s * s)
        Gun = B0 * c + B1 * s
        Gvn = B1 * c - B0 * s
        gram = (Guu, Gvv, Guv, Gun, Gvn, self._C)
        # 5. every hypothesis
        n, L, M, R, Z = self._n, self._L, self._M, self._R, self._Z
        k = L / TWO_PI
        for j in range(n):
            x = ((self.m + j) % n) * L + k * psi
            if x < 0.0:
                x += M
            i = min(math.floor(x), M - 1)
            f = x - i
            i1 = 0 if i == M - 1 else i + 1
            Rj = R[i] + f * (R[i1] - R[i])
            Zj = Z[i] + f * (Z[i1] - Z[i])
            dR = (R[i1] - R[i]) * k
            dZ = (Z[i1] - Z[i]) * k
            if not self._profile:
                e = _step5_cost(rho - Rj, zeta - Zj, dR, Rj, dZ, gram)
                self.lam[j] += min(e, self._cap)
                continue
            sj = self.scale[j]
            e, pr, pp = gain_terms(rho - sj * Rj, zeta - sj * Zj, Rj, Zj, dR, dZ, gram)
            add, info, scale = _profile_step(e, pr, pp, self.info[j], sj, self._cap)
            self.info[j], self.scale[j] = float(info), float(scale)
            self.lam[j] += float(add)
        # 6. best, renormalize; the misfit statistic
        lmin = min(self.lam)
        self.best = self.lam.index(lmin)
        self.lam = [v - lmin for v in self.lam]
        self.total += lmin
        self.fit += self._wt * lmin - self._kd
        if self.fit >= self._bd:
            self.mismatch = True
            self.mismatch_sample = self.samples - 1
            return self.best
        # 7. sequential test
        W = sum(math.exp(-0.5 * v) for j, v in enumerate(self.lam) if j != self.best)
        moved = self._ymax - self._ymin >= self._travel
        if W <= self._threshold and self.fit <= -self._bf and moved and self.samples >= self._k0:
            x = self.total - 2.0 * self.samples - self._gz  # the gate
            if not self._gate or x <= 0.0 or x * x <= self._g4 * self.samples:
                self.locked = True
                self.lock_sample = self.samples - 1
            else:
                self.mismatch = True
                self.mismatch_sample = self.samples - 1
        return self.best


@dataclass(frozen=True)
class AbsoluteAngles:
    """Angles in the calibration's frame over a recording from power-up.

    Attributes
    ----------
    y_init : ndarray (K,)
        f_init from y = 0, plus ``2 pi best_k / n`` [rad].
    y_star : ndarray (K,)
        ``y_init + eta(y_init)`` (eq. f_final) [rad].
    identification : PowerUpIdentification
    """

    y_init: NDArray[np.float64] = field(repr=False)
    y_star: NDArray[np.float64] = field(repr=False)
    identification: PowerUpIdentification


def absolute_reconstruction(decoder: PowerUpDecoder, lut: LUT, d: ArrayLike) -> AbsoluteAngles:
    """f_init and f_star in the calibration's frame from power-up (no homing), as firmware decodes.

    Parameters
    ----------
    decoder : PowerUpDecoder
        The calibration's decoder (:func:`build_decoder`).
    lut : LUT
        The calibration's table.
    d : array_like, shape (K, 3)
        Hall signals from power-up.

    Returns
    -------
    AbsoluteAngles
        y_init and y_star in the calibration's frame [rad], and the identification.
    """
    lut._require_bijective()
    d = np.atleast_2d(np.asarray(d, dtype=np.float64))
    ident = decoder.identify(d)
    F = decoder.features(d)
    n = decoder.pole_pairs
    y = (F["psi"] + TWO_PI * F["m"]) / n
    y_abs = y + TWO_PI * ident.best / n
    return AbsoluteAngles(y_abs, y_abs + lut.correction(y_abs), ident)


# ------------------------------------------------------------------------------------------------
# Noise in the normal plane, from the calibration data
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NoiseEstimate:
    """Hall noise seen by the decoder: the part of the residual across the model curve.

    Attributes
    ----------
    total_std : float
        sqrt(mean e / 2) with e the squared residual across the curve (2 degrees of freedom,
        per channel units): white noise plus whatever model error lies across the curve.
    white_std : float
        From second differences of that residual (white noise only; slow model errors cancel).
    samples : int
    """

    total_std: float
    white_std: float
    samples: int

    @property
    def model_error_std(self) -> float:
        """sqrt(total^2 - white^2): the model's error across the curve, per channel."""
        return math.sqrt(max(self.total_std**2 - self.white_std**2, 0.0))

    def to_dict(self) -> dict[str, Any]:
        return {
            "total_std": self.total_std,
            "white_std": self.white_std,
            "model_error_std": self.model_error_std,
            "samples": self.samples,
        }


def estimate_normal_noise(
    flux: FluxModel, lut: LUT, d: ArrayLike, *, start: int = 0, stop: int | None = None
) -> NoiseEstimate:
    """Noise across the model curve on calibration data (the frame of the calibration).

    For each sample the model point at the measured f_init angle (from y = 0 before the first
    sample, the calibration frame) is found exactly, and the residual's component along the
    curve's tangent removed (isotropic metric): what remains is what the decoder's costs see.

    Parameters
    ----------
    flux : FluxModel
        The calibration's identified g_theta.
    lut : LUT
        Its table (f_init's projection and offsets, eta).
    d : array_like, shape (N, 3)
        The calibration data, f_init running from y = 0 before its first sample.
    start, stop : int, keyword-only
        The samples to use (e.g. the constant-speed part); f_init still runs from sample 0.

    Returns
    -------
    NoiseEstimate
        Total and white noise sigma across the curve, per channel (sensor's unit).
    """
    d = np.atleast_2d(np.asarray(d, dtype=np.float64))
    y = lut.f_init(d)[start:stop]
    d = d[start:stop]
    y0 = _invert_model(flux, lut.pole_pairs, lut.projection, lut.offset, y, y + lut.correction(y))
    g, t = flux.value_and_derivative(y0)
    r = d - g
    del g
    t2 = np.maximum(np.sum(t * t, axis=1), np.finfo(float).tiny)
    normal = r - (np.sum(r * t, axis=1) / t2)[:, None] * t
    N = d.shape[0]
    total = math.sqrt(float(np.sum(normal * normal)) / (2.0 * N))
    if N >= 4:
        dd = np.diff(normal, 2, axis=0)
        # a 2-D white residual's second difference has variance 6 sigma^2 per dimension
        white = math.sqrt(float(np.sum(dd * dd)) / (12.0 * (N - 2)))
    else:
        white = total
    return NoiseEstimate(total, white, N)


# ------------------------------------------------------------------------------------------------
# Identifiability (for calibrate)
# ------------------------------------------------------------------------------------------------


class Identifiability(enum.StrEnum):
    """Verdict of :func:`assess_identifiability`."""

    IDENTIFIABLE = "identifiable"  # at standstill, everywhere, within the standstill budget
    NEEDS_MOTION = "needs_motion"  # standstill is not enough everywhere; motion is
    NOT_IDENTIFIABLE = "not_identifiable"  # magnets too alike: homing stays necessary

    @property
    def success(self) -> bool:
        """Whether ``reconstruct --absolute`` may be used."""
        return self is not Identifiability.NOT_IDENTIFIABLE


class IdentifiabilityReason(enum.StrEnum):
    """Why the verdict is what it is."""

    STANDSTILL = "standstill"  # every position within the standstill budget
    WEAK_POSITIONS = "weak_positions"  # some positions need more than the standstill budget
    TOO_UNIFORM = "too_uniform"  # even one electrical revolution needs more than the motion budget
    BELOW_MODEL_UNCERTAINTY = "below_model_uncertainty"  # signature within the fit's own noise
    SENSOR_DRIFT = "sensor_drift"  # at standstill a plausible sensor drift looks like a magnet


@dataclass(frozen=True)
class IdentifiabilityReport:
    """How well the pole pair can be told at power-up with this motor's sensors.

    Separations are per sample, in noise sigmas: ``delta_j(x) = sqrt(e_j)`` for the noise-free
    measurement at true position x and the hypothesis j pole pairs away (step 5 of the module
    docstring); at standstill K samples give ``sqrt(K) delta``, and the pairwise error
    probability is ``Phi(-sqrt(K) delta / 2)``.

    Attributes
    ----------
    status : Identifiability
    reason : IdentifiabilityReason
    message : str
        One line for the user.
    pole_pairs, grid : int
        n and L of the decoder.
    noise_std : float
        Hall noise sigma per channel the separations are measured in.
    error_target : float
        Target probability of a wrong pole pair (also the decoder's alpha).
    standstill_budget, motion_budget : int
        Samples allowed at standstill, and per electrical revolution when moving.
    separation_worst, separation_p05, separation_median : float
        Over the revolution (uniform in the calibration frame): the smallest, 5th percentile
        and median of the separation from the nearest wrong pole pair.
    standstill_samples_worst, standstill_samples_median : float
        Samples at standstill for an error probability <= error_target (worst position,
        median position; exact Gaussian probability of the decision region, first order).
    standstill_error_rate : float
        Expected error probability with ``standstill_budget`` samples at a uniformly random
        position.
    standstill_fraction_ok : float
        Share of positions reaching error_target within ``standstill_budget`` samples.
    revolution_separation_worst : float
        Over all starts and wrong pole pairs, the smallest RMS separation per sample along one
        electrical revolution of motion.
    revolution_samples_needed : float
        Samples per electrical revolution for error_target with uniform motion over one
        electrical revolution from the worst start (union bound over the wrong pole pairs).
    model_floor : float or None
        Separation the calibration's own fit noise would show on identical magnets,
        ``sqrt(4 (m - 1) / N)`` (m basis functions per channel, N calibration samples);
        None when unknown.
    interpolation_error : float
        Largest table interpolation error [noise sigmas].
    cost_cap : float
        The decoder's censoring level c.
    noise : NoiseEstimate or None
        The noise estimate sigma came from.
    misfit_ratio, mismatch_rate, fit_rate : float
        kappa, beta and gamma of the decoder's misfit test (:mod:`hallcal.sensor.misfit`).
    drift : DriftMargin or None
        How far the sensors may change since calibration before a wrong pole pair can lock
        (:mod:`hallcal.sensor.drift_margin`); None in artifacts made before it existed.
    gain_sd : float
        The decoder's common-gain prior (:attr:`PowerUpDecoder.gain_sd`); 0 in artifacts made
        before the gain profile (their decoder keeps s = 1).
    lock_travel : float
        Electrical turns of motion the decoder waits for before the lock
        (:attr:`PowerUpDecoder.lock_travel`); 0 in artifacts made before it.
    gate_rate : float
        alpha_g of the decoder's goodness-of-fit gate at the lock
        (:attr:`PowerUpDecoder.gate_rate`); 0 (no gate) in artifacts made before it.
    gate_samples : int
        K0, its samples of evidence before the lock; 0 in artifacts made before it.
    gate_dispersion : float
        phi of the gate (:attr:`PowerUpDecoder.gate_dispersion`); 1 in artifacts made before
        it.
    """

    status: Identifiability
    reason: IdentifiabilityReason
    message: str
    pole_pairs: int
    grid: int
    noise_std: float
    error_target: float
    standstill_budget: int
    motion_budget: int
    separation_worst: float
    separation_p05: float
    separation_median: float
    standstill_samples_worst: float
    standstill_samples_median: float
    standstill_error_rate: float
    standstill_fraction_ok: float
    revolution_separation_worst: float
    revolution_samples_needed: float
    model_floor: float | None
    interpolation_error: float
    cost_cap: float = DEFAULT_COST_CAP
    noise: NoiseEstimate | None = None
    misfit_ratio: float = DEFAULT_MISFIT_RATIO
    mismatch_rate: float = DEFAULT_MISMATCH_RATE
    fit_rate: float = DEFAULT_FIT_RATE
    drift: DriftMargin | None = None
    gain_sd: float = 0.0
    lock_travel: float = 0.0
    gate_rate: float = 0.0
    gate_samples: int = 0
    gate_dispersion: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        """The artifact's ``"identifiability"`` entry (JSON-ready; infinities as None)."""

        def num(x: float | None) -> float | None:
            return None if x is None or not math.isfinite(x) else float(x)

        out: dict[str, Any] = {
            "status": self.status.value,
            "reason": self.reason.value,
            "message": self.message,
            "pole_pairs": int(self.pole_pairs),
            "grid": int(self.grid),
            "noise_std": float(self.noise_std),
            "error_target": float(self.error_target),
            "standstill_budget": int(self.standstill_budget),
            "motion_budget": int(self.motion_budget),
            "separation_worst": num(self.separation_worst),
            "separation_p05": num(self.separation_p05),
            "separation_median": num(self.separation_median),
            "standstill_samples_worst": num(self.standstill_samples_worst),
            "standstill_samples_median": num(self.standstill_samples_median),
            "standstill_error_rate": num(self.standstill_error_rate),
            "standstill_fraction_ok": num(self.standstill_fraction_ok),
            "revolution_separation_worst": num(self.revolution_separation_worst),
            "revolution_samples_needed": num(self.revolution_samples_needed),
            "model_floor": num(self.model_floor),
            "interpolation_error": float(self.interpolation_error),
            "cost_cap": float(self.cost_cap),
            "misfit_ratio": float(self.misfit_ratio),
            "mismatch_rate": float(self.mismatch_rate),
            "fit_rate": float(self.fit_rate),
        }
        if self.gain_sd > 0.0:  # absent: the decoder without the gain profile (older artifacts)
            out["gain_sd"] = float(self.gain_sd)
        if self.lock_travel > 0.0:  # absent: the lock at standstill (older artifacts)
            out["lock_travel"] = float(self.lock_travel)
        if self.gate_rate > 0.0:  # absent: no goodness-of-fit gate (older artifacts)
            out["gate_rate"] = float(self.gate_rate)
            out["gate_samples"] = int(self.gate_samples)
            out["gate_dispersion"] = float(self.gate_dispersion)
        if self.noise is not None:
            out["noise"] = self.noise.to_dict()
        if self.drift is not None:
            out["drift_margin"] = self.drift.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> IdentifiabilityReport:
        """Inverse of :meth:`to_dict` (an artifact's ``"identifiability"`` entry).

        Raises
        ------
        ValueError
            Naming the first missing or malformed key.
        """

        def num(key: str, default: float = math.inf) -> float:
            v = d.get(key, default)
            return default if v is None else float(v)

        try:
            noise = d.get("noise")
            drift = d.get("drift_margin")  # optional: older artifacts have none
            if not _nonnegative(d, "gate_rate") < 0.5:
                raise ValueError(f"gate_rate must be in [0, 0.5), got {d['gate_rate']!r}")
            MisfitTest(  # validates them (a ratio <= 1 or a rate outside (0, 0.5) is refused)
                float(d.get("misfit_ratio", DEFAULT_MISFIT_RATIO)),
                float(d.get("mismatch_rate", DEFAULT_MISMATCH_RATE)),
                float(d.get("fit_rate", DEFAULT_FIT_RATE)),
            )
            return cls(
                status=Identifiability(d["status"]),
                reason=IdentifiabilityReason(d["reason"]),
                message=str(d["message"]),
                pole_pairs=int(d["pole_pairs"]),
                grid=int(d["grid"]),
                noise_std=float(d["noise_std"]),
                error_target=float(d["error_target"]),
                standstill_budget=int(d["standstill_budget"]),
                motion_budget=int(d["motion_budget"]),
                separation_worst=num("separation_worst", 0.0),
                separation_p05=num("separation_p05", 0.0),
                separation_median=num("separation_median", 0.0),
                standstill_samples_worst=num("standstill_samples_worst"),
                standstill_samples_median=num("standstill_samples_median"),
                standstill_error_rate=num("standstill_error_rate", 1.0),
                standstill_fraction_ok=num("standstill_fraction_ok", 0.0),
                revolution_separation_worst=num("revolution_separation_worst", 0.0),
                revolution_samples_needed=num("revolution_samples_needed"),
                model_floor=None if d.get("model_floor") is None else float(d["model_floor"]),
                interpolation_error=float(d.get("interpolation_error", 0.0)),
                cost_cap=float(d.get("cost_cap", DEFAULT_COST_CAP)),
                misfit_ratio=float(d.get("misfit_ratio", DEFAULT_MISFIT_RATIO)),
                mismatch_rate=float(d.get("mismatch_rate", DEFAULT_MISMATCH_RATE)),
                fit_rate=float(d.get("fit_rate", DEFAULT_FIT_RATE)),
                gain_sd=_nonnegative(d, "gain_sd"),
                lock_travel=_nonnegative(d, "lock_travel"),
                gate_rate=_nonnegative(d, "gate_rate"),
                gate_samples=_count(d, "gate_samples"),
                gate_dispersion=max(_nonnegative(d, "gate_dispersion"), 1.0),
                noise=None
                if noise is None
                else NoiseEstimate(
                    float(noise["total_std"]), float(noise["white_std"]), int(noise["samples"])
                ),
                drift=None if drift is None else DriftMargin.from_dict(drift),
            )
        except KeyError as exc:
            raise ValueError(f"identifiability: missing key {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"identifiability: {exc}") from None

    def decoder(self, flux: FluxModel, lut: LUT) -> PowerUpDecoder:
        """The decoder this analysis was made for, rebuilt from the calibration's model and
        table (deterministic: same tables as at calibration time).

        Parameters
        ----------
        flux : FluxModel
            The calibration's identified g_theta.
        lut : LUT
            The calibration's table; its pole pairs must be this report's.

        Returns
        -------
        PowerUpDecoder
            :func:`build_decoder` with this report's noise sigma, grid L, error target, cost
            cap and misfit test.
        """
        if lut.pole_pairs != self.pole_pairs:
            raise ValueError("identifiability: pole pairs differ from the table's")
        return build_decoder(
            flux,
            lut,
            noise_std=self.noise_std,
            grid=self.grid,
            error_target=self.error_target,
            cost_cap=self.cost_cap,
            misfit_ratio=self.misfit_ratio,
            mismatch_rate=self.mismatch_rate,
            fit_rate=self.fit_rate,
            gain_sd=self.gain_sd,
            lock_travel=self.lock_travel,
            gate_rate=self.gate_rate,
            gate_samples=self.gate_samples,
            gate_dispersion=self.gate_dispersion,
        )


def _count(d: Mapping[str, Any], key: str) -> int:
    """``d[key]`` as an integer >= 0 (0 when absent: an artifact made before it)."""
    v = d.get(key, 0)
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise ValueError(f"{key} must be an integer >= 0, got {v!r}")
    return int(v)


def _nonnegative(d: Mapping[str, Any], key: str) -> float:
    """``d[key]`` as a finite number >= 0 (0 when absent: an artifact made before it)."""
    v = float(d.get(key, 0.0))
    if not (v >= 0.0 and math.isfinite(v)):
        raise ValueError(f"{key} must be a finite number >= 0, got {v!r}")
    return v


@dataclass(frozen=True)
class SeparationMap:
    """Per-position separations of the wrong hypotheses (noise-free measurement on the grid).

    Attributes
    ----------
    cost : ndarray (M, n - 1)
        e_j at true table position q for the hypothesis j = 1..n-1 pole pairs away.
    planar : ndarray (M, n - 1, 2)
        The same differences as 2-D vectors in the whitened plane across the true curve
        (``|planar|^2`` approximates ``cost``), for exact error probabilities.
    gain : tuple of ndarray (M, n - 1) or None
        With the decoder's gain profile: (e, pr, pp) of :func:`gain_terms` at s = 1, so that a
        stretch of positions with one common gain can be profiled (motion); ``cost`` and
        ``planar`` are then each position's own profile (standstill: the difference along
        the hypothesis's own point, a change of the gain, carries no evidence).
    """

    cost: NDArray[np.float64] = field(repr=False)
    planar: NDArray[np.float64] = field(repr=False)
    gain: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None = field(
        default=None, repr=False
    )

    @property
    def separation(self) -> NDArray[np.float64]:
        """Per position, the separation from the nearest wrong pole pair [sigmas]."""
        if self.cost.shape[1] == 0:
            return np.zeros(self.cost.shape[0])
        return np.sqrt(np.maximum(np.min(self.cost, axis=1), 0.0))


def separation_map(decoder: PowerUpDecoder) -> SeparationMap:
    """Separations at every table point from every wrong pole pair (see :class:`SeparationMap`)."""
    dec = decoder
    n, L, M = dec.pole_pairs, dec.grid, dec.table_size
    q = np.arange(M)
    psi = _wrap(TWO_PI * q / L)
    c, s = np.cos(psi), np.sin(psi)
    A, B, C = dec.gram_a, dec.gram_b, dec.gram_c
    F = {
        "rho": dec.radius,
        "zeta": dec.zero,
        **gram_at(A, B, c, s),
    }
    j = np.arange(1, n)
    pos = np.mod(q[:, None] + L * j[None, :], M).astype(np.float64)
    cost = dec._costs(F, pos) if n > 1 else np.zeros((M, 0))
    # 2-D coordinates across the true curve: r = a u + b nv; remove the true tangent (S-metric)
    R0, Z0, dR0, dZ0 = dec._interp(q.astype(np.float64))
    guu, gvv, guv, gun, gvn = F["guu"], F["gvv"], F["guv"], F["gun"], F["gvn"]
    tu, tn, tt = tangent_terms(dR0, R0, dZ0, (guu, gvv, guv, gun, gvn, C))
    g11 = guu - tu * tu / tt
    g12 = gun - tu * tn / tt
    g22 = C - tn * tn / tt
    l11 = np.sqrt(np.maximum(g11, 0.0))
    l21 = g12 / np.where(l11 > 0, l11, 1.0)
    l22 = np.sqrt(np.maximum(g22 - l21 * l21, 0.0))
    Rj, Zj, _, _ = dec._interp(pos)
    a = dec.radius[:, None] - Rj
    b = dec.zero[:, None] - Zj
    # Cholesky G2 = Lc Lc', coordinates Lc' [a, b]
    planar = np.stack([l11[:, None] * a + l21[:, None] * b, l22[:, None] * b], axis=-1)
    if not (dec.gain_sd > 0.0 and n > 1):
        return SeparationMap(cost, planar)
    # gain profile: hypothesis j is the ray s (Rj, Zj); at standstill only the distance across
    # it counts (first order), i.e. planar without its component along j's whitened point
    e, pr, pp = dec._gain_terms(F, pos)
    point = np.stack([l11[:, None] * Rj + l21[:, None] * Zj, l22[:, None] * Zj], axis=-1)
    point /= np.maximum(np.linalg.norm(point, axis=-1, keepdims=True), np.finfo(float).tiny)
    planar = planar - np.sum(planar * point, axis=-1, keepdims=True) * point
    cost = np.maximum(e - pr * pr / np.where(pp > 0.0, pp, np.inf), 0.0)
    return SeparationMap(cost, planar, (e, pr, pp))


def _standstill_radius(planar: NDArray, directions: int = 360) -> NDArray:
    """r1(q, phi): distance (for K = 1) from the origin to the decision region's boundary.

    At standstill with K samples the first-order cost differences are
    ``Lambda_j - Lambda_0 = K |w_j|^2 + 2 sqrt(K) w_j . z`` with z standard normal in the plane
    across the curve, so the right choice is made iff ``w_j . z > -sqrt(K) |w_j|^2 / 2`` for
    all j: a convex polygon. Along a direction e the boundary is at ``sqrt(K) r1(e)`` with
    ``r1(e) = min_j (|w_j|^2 / 2) / max(-w_j . e, 0)``.
    """
    phi = TWO_PI * (np.arange(directions) + 0.5) / directions
    E = np.stack([np.cos(phi), np.sin(phi)])  # (2, D)
    M = planar.shape[0]
    out = np.empty((M, directions))
    half = 0.5 * np.sum(planar * planar, axis=-1)  # (M, J)
    for s0 in range(0, M, 128):
        w = planar[s0 : s0 + 128]  # (B, J, 2)
        proj = -np.einsum("bjk,kd->bjd", w, E)  # (B, J, D)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(proj > 0, half[s0 : s0 + 128, :, None] / proj, np.inf)
        out[s0 : s0 + 128] = np.min(r, axis=1) if r.shape[1] else np.inf
    return out


def standstill_error(planar_radius: NDArray, samples: float | NDArray) -> NDArray:
    """Per position, the probability of a wrong choice after ``samples`` at standstill.

    ``P = mean_phi exp(-K r1(phi)^2 / 2)``: the 2-D standard normal's mass outside the polygon
    of :func:`_standstill_radius` (its radial tail is ``exp(-r^2 / 2)``), by the midpoint rule
    over the directions. ``samples`` is one K, or one per position.
    """
    K = np.asarray(samples, dtype=np.float64)
    radius = np.asarray(planar_radius)
    out = np.empty(radius.shape[0])
    for s0 in range(0, radius.shape[0], _ROW_BLOCK):  # bounded temporaries, same values
        r2 = np.square(radius[s0 : s0 + _ROW_BLOCK])
        if K.ndim == 0:
            k: float | NDArray = float(K)
        elif K.shape[0] == radius.shape[0]:
            k = K[s0 : s0 + _ROW_BLOCK, None]
        else:  # broadcast as given (one K for every position)
            k = K[:, None]
        out[s0 : s0 + _ROW_BLOCK] = np.mean(np.exp(-0.5 * k * r2), axis=1)
    return out


#: Positions per block in the standstill computations (1024 x 360 directions: 3 MB per array).
_ROW_BLOCK = 1024


def _samples_for(err_fn, target: float, count: int, k_max: float = 1e9) -> NDArray:
    """Smallest K >= 1 (per row, continuous) with ``err_fn(K, rows) <= target``; inf beyond
    k_max. ``err_fn`` is decreasing in K and row-wise; rows already right with one sample are
    not searched. Rows are searched in blocks (bounded temporaries; the same values)."""
    out = np.ones(count)
    for s0 in range(0, count, _ROW_BLOCK):
        block = np.arange(s0, min(s0 + _ROW_BLOCK, count))
        rows = block[err_fn(np.ones(block.size), block) > target]
        if rows.size == 0:
            continue
        lo = np.zeros(rows.size)
        hi = np.full(rows.size, math.log(k_max))
        ok_max = err_fn(np.full(rows.size, k_max), rows) <= target
        for _ in range(40):  # log K to 2e-11 of its range: far below any meaning
            mid = 0.5 * (lo + hi)
            good = err_fn(np.exp(mid), rows) <= target
            hi = np.where(good, mid, hi)
            lo = np.where(good, lo, mid)
        out[rows] = np.where(ok_max, np.exp(hi), np.inf)
    return out


def assess_identifiability(
    decoder: PowerUpDecoder,
    *,
    standstill_budget: int = 200,
    motion_budget: int = 4096,
    calibration_samples: int | None = None,
    basis_size: int | None = None,
    noise: NoiseEstimate | None = None,
    drift: bool = True,
) -> IdentifiabilityReport:
    """Identifiability analysis of the pole pair at power-up (for ``hallcal calibrate``).

    Verdict, with the target error probability alpha = ``decoder.error_target``:

    - ``IDENTIFIABLE``: at every position the standstill error probability reaches alpha within
      ``standstill_budget`` samples (default 200: 50 ms at the paper's 4 kHz, the
      standstill figure);
    - ``NEEDS_MOTION``: some positions need more, but one electrical revolution of uniform
      motion in ``motion_budget`` samples (default 4096: one electrical revolution at about
      the paper's calibration ramp speed, 0.5 rad/s at 4 kHz with 11 pole pairs) reaches alpha
      from every start;
    - ``NOT_IDENTIFIABLE``: not even that (reason ``TOO_UNIFORM``), or the weakest pair's
      revolution separation is below 5 times ``model_floor``, the separation the calibration's
      own fit noise produces on identical magnets (reason ``BELOW_MODEL_UNCERTAINTY``: such a
      signature could be an artefact of the fit; 5 sigma of the fit noise).

    Parameters
    ----------
    decoder : PowerUpDecoder
        The decoder to analyse (its noise sigma, grid, alpha and cost cap).
    standstill_budget, motion_budget : int, keyword-only
        Samples allowed at standstill, and per electrical revolution of uniform motion.
    calibration_samples, basis_size : int, optional
        N and m of the calibration (for ``model_floor``).
    noise : NoiseEstimate, optional
        Stored in the report.
    drift : bool, keyword-only
        Also compute the drift margin (:func:`hallcal.sensor.drift_margin.drift_margin`) when
        the pole pair is identifiable.

    Returns
    -------
    IdentifiabilityReport
        Verdict, reason, one-line message and the separations in noise sigmas.
    """
    dec = decoder
    smap = separation_map(dec)
    sep = smap.separation
    need = _samples_needed(dec, smap, standstill_budget)
    floor = _model_floor(calibration_samples, basis_size)
    worst_K = float(np.max(need.standstill))
    status, reason = _verdict(need, floor, standstill_budget, motion_budget)
    if dec.lock_travel > 0.0 and status.success:  # the lock waits for motion by design
        status, reason = Identifiability.NEEDS_MOTION, IdentifiabilityReason.SENSOR_DRIFT
    report: dict[str, Any] = dict(
        status=status,
        reason=reason,
        pole_pairs=dec.pole_pairs,
        grid=dec.grid,
        noise_std=dec.noise_std,
        error_target=dec.error_target,
        standstill_budget=int(standstill_budget),
        motion_budget=int(motion_budget),
        separation_worst=float(np.min(sep)),
        separation_p05=float(np.percentile(sep, 5)),
        separation_median=float(np.median(sep)),
        standstill_samples_worst=worst_K,
        standstill_samples_median=float(np.median(need.standstill)),
        standstill_error_rate=need.standstill_error,
        standstill_fraction_ok=float(np.mean(need.standstill <= standstill_budget)),
        revolution_separation_worst=need.revolution_separation,
        revolution_samples_needed=need.revolution_samples,
        model_floor=floor,
        interpolation_error=dec.interpolation_error,
        cost_cap=dec.cost_cap,
        noise=noise,
        misfit_ratio=dec.misfit.ratio,
        mismatch_rate=dec.misfit.rate,
        fit_rate=dec.misfit.fit_rate,
        gain_sd=dec.gain_sd,
        lock_travel=dec.lock_travel,
        gate_rate=dec.gate_rate,
        gate_samples=dec.gate_samples,
        gate_dispersion=dec.gate_dispersion,
        drift=drift_margin(dec, standstill_budget=standstill_budget)
        if drift and status.success and dec.pole_pairs > 1
        else None,
    )
    return IdentifiabilityReport(message=_message(report), **report)


@dataclass(frozen=True)
class _SamplesNeeded:
    """Samples for the target error probability at standstill and with motion."""

    standstill: NDArray[np.float64]  # per table position
    standstill_error: float  # mean error probability with the standstill budget
    revolution_separation: float  # smallest RMS separation per sample along one revolution
    revolution_samples: float  # per electrical revolution of uniform motion, worst start


def _samples_needed(dec: PowerUpDecoder, smap: SeparationMap, budget: int) -> _SamplesNeeded:
    """Standstill and motion needs of :func:`assess_identifiability` (one pole pair: none).

    At standstill: the exact Gaussian probability of the decision region at every position
    (first order, :func:`standstill_error`). With motion: one electrical revolution of uniform
    motion from every start, the mean (censored) cost per sample of each wrong pole pair along
    it, and a union bound over the wrong pole pairs.
    """
    n, L, M = dec.pole_pairs, dec.grid, dec.table_size
    alpha = dec.error_target
    if n <= 1:  # one pole pair: nothing to identify
        return _SamplesNeeded(np.ones(M), 0.0, math.inf, 1.0)
    r1 = _standstill_radius(smap.planar)
    r1sq = np.square(r1)
    K_pos = _samples_for(
        lambda K, rows: np.mean(np.exp(-0.5 * K[:, None] * r1sq[rows]), axis=1), alpha, M
    )
    err_budget = float(np.mean(standstill_error(r1, budget)))
    # one electrical revolution of uniform motion from every start q: mean (censored) cost
    # per sample of each wrong pole pair along it
    cost = np.clip(smap.cost if smap.gain is None else smap.gain[0], 0.0, dec.cost_cap)
    D = _window_mean(cost, L)  # (M, n - 1)
    if smap.gain is not None:  # one common gain over the revolution, profiled (uncensored)
        e, pr, pp = (_window_mean(x, L) for x in smap.gain)
        D = np.minimum(D, np.maximum(e - pr * pr / np.where(pp > 0.0, pp, np.inf), 0.0))
    rev_sep = float(math.sqrt(max(float(np.min(D)), 0.0)))

    def union(K: NDArray, rows: NDArray) -> NDArray:
        return np.sum(_normal_tail(0.5 * np.sqrt(K[:, None] * D[rows])), axis=1)

    K_rev = float(np.max(_samples_for(union, alpha, M)))
    return _SamplesNeeded(K_pos, err_budget, rev_sep, K_rev)


def _window_mean(x: NDArray, L: int) -> NDArray:
    """Mean of x (M, J) over the L rows from every start row, around the revolution."""
    M = x.shape[0]
    csum = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(np.vstack([x, x]), axis=0)])
    return (csum[L : L + M] - csum[:M]) / L


def _model_floor(calibration_samples: int | None, basis_size: int | None) -> float | None:
    """``sqrt(4 (m - 1) / N)``: the separation the fit noise shows on identical magnets."""
    if calibration_samples and basis_size:
        return math.sqrt(4.0 * max(int(basis_size) - 1, 1) / int(calibration_samples))
    return None


def _verdict(
    need: _SamplesNeeded, floor: float | None, standstill_budget: int, motion_budget: int
) -> tuple[Identifiability, IdentifiabilityReason]:
    """The verdict of :func:`assess_identifiability` and its reason (see its docstring)."""
    if floor is not None and need.revolution_separation < 5.0 * floor:
        return Identifiability.NOT_IDENTIFIABLE, IdentifiabilityReason.BELOW_MODEL_UNCERTAINTY
    if float(np.max(need.standstill)) <= standstill_budget:
        return Identifiability.IDENTIFIABLE, IdentifiabilityReason.STANDSTILL
    if need.revolution_samples <= motion_budget:
        return Identifiability.NEEDS_MOTION, IdentifiabilityReason.WEAK_POSITIONS
    return Identifiability.NOT_IDENTIFIABLE, IdentifiabilityReason.TOO_UNIFORM


def _fmt_k(K: float) -> str:
    return "never" if not math.isfinite(K) else f"{K:.0f}"


def _message(r: dict[str, Any]) -> str:
    status, reason = r["status"], r["reason"]
    seps = (
        f"separation from the nearest wrong pole pair {r['separation_median']:.2g} noise sigmas "
        f"typical, {r['separation_worst']:.2g} at the worst position"
    )
    pct = f"{100.0 * (1.0 - r['error_target']):g}%"
    if status is Identifiability.IDENTIFIABLE:
        return (
            f"pole pair identifiable at power-up at standstill: right with probability >= {pct} "
            f"within {_fmt_k(r['standstill_samples_worst'])} samples at every position ({seps})"
        )
    if reason is IdentifiabilityReason.SENSOR_DRIFT:
        return (
            f"pole pair identifiable at power-up with motion: the lock waits for "
            f"{r['lock_travel']:g} electrical revolution of motion, because at standstill one "
            f"sensor's plausible drift (its gain or offset by about 1 %) looks like another pole "
            f"pair's magnet on this motor; the sensors' common gain (magnet temperature) is "
            f"divided out ({seps})"
        )
    if status is Identifiability.NEEDS_MOTION:
        return (
            f"pole pair identifiable at power-up with motion: at standstill "
            f"{100 * r['standstill_fraction_ok']:.1f}% of positions reach {pct} within "
            f"{r['standstill_budget']} samples (the worst needs "
            f"{_fmt_k(r['standstill_samples_worst'])}), one electrical revolution of motion "
            f"reaches it everywhere ({seps})"
        )
    why = (
        "the magnets' signatures are within the calibration's own uncertainty"
        if reason is IdentifiabilityReason.BELOW_MODEL_UNCERTAINTY
        else "the magnets are too alike"
    )
    K = r["revolution_samples_needed"]
    motion = (
        f"one electrical revolution of motion would need {K:.0f} samples"
        if math.isfinite(K)
        else "no amount of motion tells them apart"
    )
    return f"pole pair NOT identifiable at power-up: {why} ({seps}; {motion}); home the axis"


def standstill_error_rate(decoder: PowerUpDecoder, samples: int | ArrayLike) -> NDArray:
    """Predicted error probability at standstill after ``samples`` at a uniformly random
    position (mean over the table grid; first-order exact 2-D Gaussian probability)."""
    smap = separation_map(decoder)
    r1 = _standstill_radius(smap.planar)
    K = np.atleast_1d(np.asarray(samples, dtype=np.float64))
    return np.array([float(np.mean(standstill_error(r1, k))) for k in K])


def gate_dispersion(
    decoder: PowerUpDecoder,
    d: ArrayLike,
    samples: int,
    *,
    start: int = 0,
    stop: int | None = None,
) -> float:
    """phi of the gate at the lock (step 7): how much more the right hypothesis's cost over
    ``samples`` consecutive samples varies on the calibration recording than chi-square(2 K)
    says, at least 1.

    The gate compares the best hypothesis's whole cost with a quantile of its distribution
    under the calibrated noise; a real rig's noise is not white (vibration bursts, the model's
    own error along the turn), so windows of the calibration recording scatter more than
    chi-square (measured on the ring jig's three captures: 3.7-8.2 times its variance over 96
    samples). The variance of the sliding-window sums of the calibration frame's costs
    (hypothesis 0: f_init from y = 0 before ``d``'s first sample, censored as the decoder
    does) over ``4 K`` is phi; the gate then uses Satterthwaite's quantile
    (:attr:`PowerUpDecoder.gate_terms`), so that its false alarm on the calibration's own noise
    stays near alpha_g, at the price of its power on that rig.

    Parameters
    ----------
    decoder : PowerUpDecoder
        The calibration's decoder (its tables, sigma and cap).
    d : array_like, shape (N, 3)
        The calibration recording.
    samples : int
        K: the window (the gate's K0).
    start, stop : int, keyword-only
        The samples the model was fitted on.

    Returns
    -------
    float
        phi >= 1 (1 when the samples hold fewer than two windows).
    """
    d = np.atleast_2d(np.asarray(d, dtype=np.float64))
    F = decoder.features(d if stop is None else d[:stop])
    F = {k: v[start:] for k, v in F.items()}
    pos = decoder.coordinates(F["psi"], F["m"], np.zeros(1, dtype=np.int64))
    e = np.minimum(decoder._costs(F, pos)[:, 0], decoder.cost_cap)[F["valid"]]
    if samples < 1 or e.size < 2 * samples:
        return 1.0
    c = np.concatenate([[0.0], np.cumsum(e)])
    window = c[samples:] - c[:-samples]
    phi = float(np.var(window)) / (4.0 * samples)
    return max(phi, 1.0) if math.isfinite(phi) else 1.0


def analyze_calibration(
    flux: FluxModel,
    lut: LUT,
    d: ArrayLike,
    *,
    start: int = 0,
    stop: int | None = None,
    basis_size: int | None = None,
    standstill_budget: int = 200,
    motion_budget: int = 4096,
) -> tuple[PowerUpDecoder, IdentifiabilityReport]:
    """Noise estimate, decoder and identifiability report for a calibration, in one call.

    Which decoder (measured: ``benchmarks/bench_powerup_margin.txt``). The decoder without the
    common-gain profile and with the lock at standstill is analysed first, and kept unless a
    plausible drift breaks its lock (:attr:`DriftMargin.robustness` below 1: a 5 % common gain
    or a 1 % change of one sensor makes a wrong pole pair lock at 10 % of positions). Then
    the pole pairs cannot be told at standstill with certainty: a common gain and a magnet's
    strength look alike, and with the gain profiled one sensor's drift moves the remaining
    evidence (the direction of (rho, zeta) across the curve) onto another magnet (unseen case
    202: wrong locks under a 1 % offset of one sensor 6 of 40 without the profile, 28 with it).
    So that calibration gets the profile and a lock that waits for
    :data:`DEFAULT_LOCK_TRAVEL` electrical revolution of motion (verdict "needs motion",
    reason ``SENSOR_DRIFT``). Where the magnets differ in strength (the paper bench) the
    profile would cost the standstill separation (8.1 to 1.8 noise sigmas typical) and is not
    used. Either decoder has the goodness-of-fit gate at the lock (:data:`DEFAULT_GATE_RATE`,
    :data:`DEFAULT_GATE_SAMPLES`): a sensor change the calibration does not describe is refused
    ("mismatch") instead of locking where it happens to look like another magnet.

    Sigma is the total noise across the model curve on the calibration samples
    (:func:`estimate_normal_noise`): white noise plus the model's own error there, so the
    decoder is not told the model is better than it is.

    Parameters
    ----------
    flux : FluxModel
        The calibration's identified g_theta.
    lut : LUT
        Its (bijective) table.
    d : array_like, shape (N, 3)
        The calibration recording (f_init from y = 0 before its first sample).
    start, stop : int, keyword-only
        The samples the model was fitted on.
    basis_size : int, optional
        m, basis functions per channel (for the model floor).
    standstill_budget, motion_budget : int
        Samples allowed at standstill, and per electrical revolution of motion; see
        :func:`assess_identifiability`.

    Returns
    -------
    decoder : PowerUpDecoder
        Built with sigma = the total noise across the model curve.
    report : IdentifiabilityReport
        The verdict and separations for that decoder.
    """
    noise = estimate_normal_noise(flux, lut, d, start=start, stop=stop)
    sigma = noise.total_std
    if not sigma > 0.0:  # noise-free data: fall back to a tiny sigma relative to the signals
        sigma = 1e-9 * max(float(np.std(np.asarray(d, dtype=np.float64))), 1e-300)
    used = len(range(*slice(start, stop).indices(np.shape(d)[0])))

    phi: list[float] = []  # the gate's dispersion: the same tables and sigma either way

    def analysis(gain_sd: float, travel: float) -> tuple[PowerUpDecoder, IdentifiabilityReport]:
        dec = build_decoder(flux, lut, noise_std=sigma, gain_sd=gain_sd, lock_travel=travel)
        if not phi:
            phi.append(gate_dispersion(dec, d, DEFAULT_GATE_SAMPLES, start=start, stop=stop))
        dec = dataclasses.replace(
            dec,
            gate_rate=DEFAULT_GATE_RATE,
            gate_samples=DEFAULT_GATE_SAMPLES,
            gate_dispersion=phi[0],
        )
        return dec, assess_identifiability(
            dec,
            standstill_budget=standstill_budget,
            motion_budget=motion_budget,
            calibration_samples=used,
            basis_size=basis_size,
            noise=noise,
        )

    dec, rep = analysis(0.0, 0.0)
    if rep.drift is None or not rep.drift.robustness < 1.0:
        return dec, rep  # no plausible drift breaks the lock: keep the standstill evidence
    return analysis(DEFAULT_GAIN_SD, DEFAULT_LOCK_TRAVEL)
