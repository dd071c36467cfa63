"""The power-up decoder of :mod:`hallcal.sensor.absolute` (its module docstring is the
specification): the tables and per-sample costs of every pole-pair hypothesis, the lock rule and
its gate, the identification over a recording and sample by sample (:class:`PowerUpIdentifier`,
the reference for the firmware), and the absolute reconstruction. The analysis of how well a
calibration identifies the pole pair is :mod:`hallcal.sensor._absolute_analysis`.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.messages import Outcome
from hallcal.sensor._absolute_gate import (
    bias_bound,
    bias_terms,
    check_bias,
    check_gate,
    within_bias_gate,
    within_gate,
)
from hallcal.sensor.drift_margin import PLAUSIBLE_GAIN_CHANGE
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT
from hallcal.sensor.misfit import (
    DEFAULT_FIT_RATE,
    DEFAULT_MISFIT_RATIO,
    DEFAULT_MISMATCH_RATE,
    MisfitTest,
)

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
#: calibrated noise; a refused healthy power-up says "mismatch". 1e-4 rather than 1e-3: on the
#: ring jig's capture 2, whose held-out revolutions cost 1.26 times the calibration's own (the
#: model fitted there; bursts), 1e-3 refused 9 of 945 healthy 200-sample power-ups, 1e-4 none
#: (the misfit test's own 3 remain); on the benches the wrong locks it lets through rise from
#: 13 to 16 of 2200 (``benchmarks/bench_powerup_margin.txt``, ``bench_powerup.txt``).
DEFAULT_GATE_RATE = 1e-4
#: K0: samples of evidence before the lock, so that the gate can see a wrong pole pair that fits
#: within about a noise sigma (module doc, "Sensors changed since calibration"): measured on five
#: motors and 11 sensor changes (2200 power-ups), wrong locks 73 (no gate) -> 49 (gate at
#: alpha_g = 1e-3, lock as before) -> 26 / 19 / 13 / 10 with K0 = 48 / 64 / 96 / 128 (at 1e-4 and
#: K0 = 96: 16); the healthy lock comes at K0 then.
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
    gate_bias_dispersion : float
        phi_b >= 1 of the gate's bias half (the winner's residual mean against the
        chi-square(2) quantile, :mod:`hallcal.sensor._absolute_gate`); the two halves then
        take alpha_g / 2 each. 0: no bias half (the decoder before it).
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
    gate_bias_dispersion: float = 0.0

    @property
    def gate_terms(self) -> tuple[float, float]:
        """(gz, g4) of step 7's gate: ``2 phi (z^2 - 1) / 3`` and ``4 phi z^2``, z the standard
        normal quantile of ``1 - alpha_g``, phi the dispersion. The chi-square(2 k) quantile of
        ``1 - alpha_g`` is ``2 k + gz + sqrt(g4 k)`` to the Cornish-Fisher expansion's constant
        term at phi = 1; a cost of mean 2 k and variance 4 k phi is ``phi`` times a
        chi-square(2 k / phi) (Satterthwaite 1946, Biometrics Bull. 2(6)), whose quantile is
        the same expression with these terms. With the bias half the chi-square half takes
        ``alpha_g / 2`` (Bonferroni)."""
        rate = self.gate_rate / 2.0 if self.gate_bias_dispersion > 0.0 else self.gate_rate
        z = statistics.NormalDist().inv_cdf(1.0 - rate)
        phi = self.gate_dispersion
        return 2.0 * phi * (z * z - 1.0) / 3.0, 4.0 * phi * z * z

    def gate_passes(self, total: ArrayLike, samples: ArrayLike) -> NDArray[np.bool_]:
        """Step 7's gate: is the best hypothesis's whole cost within the chi-square quantile?

        Parameters
        ----------
        total : array_like
            Q, the best hypothesis's cumulative cost [noise-normalized squared residual].
        samples : array_like
            k, samples of evidence behind ``total`` (broadcast against it).

        Returns
        -------
        ndarray of bool
            Q within the chi-square(2 k) quantile of ``1 - alpha_g`` (Cornish-Fisher form with
            the dispersion phi, :attr:`gate_terms`); True everywhere without the gate
            (``gate_rate`` 0).
        """
        Q = np.asarray(total, dtype=np.float64)
        k = np.asarray(samples, dtype=np.float64)
        if not self.gate_rate > 0.0:
            return np.ones(np.broadcast(Q, k).shape, dtype=bool)
        return np.asarray(within_gate(Q, k, *self.gate_terms), dtype=bool)

    @property
    def gate_bias_bound(self) -> float:
        """The bias half's bound on S, ``phi_b 2 ln(2 / alpha_g)`` (inf without it)."""
        if not (self.gate_bias_dispersion > 0.0 and self.gate_rate > 0.0):
            return math.inf
        return bias_bound(self.gate_rate, self.gate_bias_dispersion)

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
        # each table point's step to the next one around the revolution (M differences, the
        # same R[i + 1] - R[i] as taken per sample), gathered once per sample
        R, Z = self.radius, self.zero
        dR, dZ = (np.roll(R, -1) - R)[i], (np.roll(Z, -1) - Z)[i]
        k = self.grid / TWO_PI
        return R[i] + f * dR, Z[i] + f * dZ, dR * k, dZ * k

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
        j = np.mod(np.asarray(offsets, dtype=np.int64), n)
        # (m + j) mod n from m mod n and j mod n: one integer division per sample, not per
        # sample and hypothesis (the same integers)
        e = np.mod(np.asarray(m, dtype=np.int64), n)[:, None] + j[None, :]
        np.subtract(e, n, out=e, where=e >= n)
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
            **(
                {"gate_bias_dispersion": float(self.gate_bias_dispersion)}
                if self.gate_bias_dispersion > 0.0
                else {}
            ),  # fmt: skip
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


def bias_sums(dec: PowerUpDecoder, F: dict[str, NDArray], pos: NDArray) -> NDArray[np.float64]:
    """Cumulative sums (K, J, 5) of the gate's bias terms (:func:`~hallcal.sensor.
    _absolute_gate.bias_terms`) after each sample, for the features F (:meth:`~PowerUpDecoder.
    features`) and table coordinates ``pos`` (K, J), at s = 1; samples without angle add 0."""
    Rj, Zj, dR, dZ = dec._interp(pos)
    gram = (*(F[k][:, None] for k in ("guu", "gvv", "guv", "gun", "gvn")), dec.gram_c)
    tu, tn, tt = tangent_terms(dR, Rj, dZ, gram)
    a, b = F["rho"][:, None] - Rj, F["zeta"][:, None] - Zj
    terms = np.stack(bias_terms(a, b, tu, tn, tt, gram, dec.cost_cap), axis=-1)
    terms[~F["valid"]] = 0.0
    return np.cumsum(terms, axis=0)


def _bias_passes(dec: PowerUpDecoder, F: dict[str, NDArray], lam: NDArray, row: int) -> bool:
    """Whether the gate's bias half passes at ``row`` of the cumulative costs ``lam`` (K, n)
    for that row's best hypothesis (:mod:`hallcal.sensor._absolute_gate`; True without it):
    its sums over the samples up to that row only (the gate decides once, there)."""
    if not math.isfinite(dec.gate_bias_bound):
        return True
    G = {k: v[: row + 1] for k, v in F.items()}
    pos = dec.coordinates(G["psi"], G["m"], [int(np.argmin(lam[row]))])
    return bool(within_bias_gate(bias_sums(dec, G, pos)[-1, 0], dec.gate_bias_bound))


def _lock_rule(dec: PowerUpDecoder, lam: NDArray, used: NDArray, span: NDArray) -> _Rule:
    """Steps 6 and 7 on cumulative costs ``lam`` (K, n), with the samples of evidence ``used``
    and f_init's electrical travel ``span`` per row (:func:`_span`); the gate's chi-square
    half per row (its bias half: :func:`_bias_passes`, at the row where it decides)."""
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


def _check_options(
    gain_sd: float, lock_travel: float, error_target: float, cost_cap: float
) -> None:
    """:func:`build_decoder`'s checks of the profile, travel, alpha and cap (ValueError)."""
    if not (gain_sd >= 0.0 and math.isfinite(gain_sd)):
        raise ValueError("gain_sd must be a finite number >= 0")
    if not (lock_travel >= 0.0 and math.isfinite(lock_travel)):
        raise ValueError("lock_travel must be a finite number >= 0")
    if not 0.0 < error_target < 0.5:
        raise ValueError("error_target must be in (0, 0.5)")
    if not cost_cap > 0.0:
        raise ValueError("cost_cap must be > 0")


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
    gate_bias_dispersion: float = 0.0,
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
    gate_bias_dispersion : float
        phi_b >= 1 of the gate's bias half (:func:`~hallcal.sensor.absolute.bias_dispersion`);
        0: none. Needs the gate and no gain profile.

    Returns
    -------
    PowerUpDecoder
    """
    lut._require_bijective()
    _check_options(gain_sd, lock_travel, error_target, cost_cap)
    check_gate(gate_rate, gate_samples, gate_dispersion)
    check_bias(gate_bias_dispersion, gate_rate, gain_sd)
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
        gate_bias_dispersion=float(gate_bias_dispersion),
    )


# ------------------------------------------------------------------------------------------------
# Identification over a recording (vectorized) and sample by sample (reference)
# ------------------------------------------------------------------------------------------------


class PowerUpStatus(Outcome):
    """Outcome of a power-up identification (:attr:`success` for ``identified`` alone)."""

    IDENTIFIED = "identified"  # the sequential test locked: posterior >= 1 - alpha, and it fits
    UNDECIDED = "undecided"  # not certain yet; the offset is the current maximum-likelihood one
    MISMATCH = "mismatch"  # no pole pair fits: the signals do not match this calibration


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
        if hit.size and rule.gate[hit[0]] and _bias_passes(dec, F, lam, int(hit[0])):
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
        self._bias = dec.gate_bias_bound  # inf: no bias half
        self.bias = [[0.0] * 5 for _ in range(self._n)]  # the bias sums h, H per hypothesis
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

    def _add_bias(
        self, j: int, a: float, b: float, tangent: tuple[float, float, float], gram: tuple
    ) -> None:
        """Step 5's bias sums of hypothesis j for the residual a u + b nv."""
        tu, tn, tt = tangent
        terms = bias_terms(a, b, tu, tn, tt, gram, self._cap)
        self.bias[j] = [v + float(t) for v, t in zip(self.bias[j], terms, strict=True)]

    def _gate_fits(self) -> bool:
        """Step 7's gate at the first lock: the chi-square half, then the bias half."""
        if self._gate and not within_gate(self.total, self.samples, self._gz, self._g4):
            return False
        return not self._bias < math.inf or bool(within_bias_gate(self.bias[self.best], self._bias))

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
                if self._bias < math.inf:  # step 5's bias sums (module doc, step 7)
                    self._add_bias(j, rho - Rj, zeta - Zj, tangent_terms(dR, Rj, dZ, gram), gram)
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
            if self._gate_fits():
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
