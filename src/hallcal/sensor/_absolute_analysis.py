"""How well a calibration identifies the pole pair at power-up (:mod:`hallcal.sensor.absolute`):
the noise across the model curve, the separations of the pole-pair hypotheses, the verdict and
its report (the artifact's ``"identifiability"``), the gate's dispersion, and the choice of the
decoder for a calibration (:func:`analyze_calibration`). The decoder itself is
:mod:`hallcal.sensor._absolute_decoder`.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.sensor._absolute_decoder import (
    DEFAULT_COST_CAP,
    DEFAULT_GAIN_SD,
    DEFAULT_GATE_RATE,
    DEFAULT_GATE_SAMPLES,
    DEFAULT_LOCK_TRAVEL,
    TWO_PI,
    PowerUpDecoder,
    _invert_model,
    _wrap,
    bias_sums,
    build_decoder,
    gram_at,
    tangent_terms,
)
from hallcal.sensor._absolute_gate import (
    QUANTIZER_NONCENTRALITY,
    QUANTIZER_STANDSTILL,
    bias_is_white,
    bias_statistic,
    quantizer_noncentrality,
)
from hallcal.sensor.drift_margin import DriftMargin, drift_margin
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT
from hallcal.sensor.misfit import (
    DEFAULT_FIT_RATE,
    DEFAULT_MISFIT_RATIO,
    DEFAULT_MISMATCH_RATE,
    MisfitTest,
)


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
    QUANTIZER = "quantizer"  # at standstill the ADC's rounding, not noise, decides the evidence


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
    gate_bias_dispersion : float
        phi_b of the gate's bias half (:attr:`PowerUpDecoder.gate_bias_dispersion`); 0 (no
        bias half) in artifacts made before it.
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
    gate_bias_dispersion: float = 0.0

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
        if self.gate_bias_dispersion > 0.0:  # absent: no bias half (older artifacts)
            out["gate_bias_dispersion"] = float(self.gate_bias_dispersion)
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
                gate_bias_dispersion=_bias_dispersion_key(d),
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
            gate_bias_dispersion=self.gate_bias_dispersion,
        )


def _bias_dispersion_key(d: Mapping[str, Any]) -> float:
    """``d["gate_bias_dispersion"]``: 0 when absent (an artifact made before it), else a
    finite number >= 1 with the gate and without the gain profile."""
    key = "gate_bias_dispersion"
    try:
        v = _nonnegative(d, key)
    except (TypeError, ValueError):
        v = -1.0
    if key in d and not v >= 1.0:
        raise ValueError(f"{key} must be a finite number >= 1, got {d[key]!r}")
    if v > 0.0 and not (_nonnegative(d, "gate_rate") > 0.0 and _nonnegative(d, "gain_sd") == 0):
        raise ValueError("gate_bias_dispersion needs gate_rate > 0 and no gain_sd")
    return v


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
    B = _RADIUS_BLOCK
    for s0 in range(0, M, B):
        w = planar[s0 : s0 + B]  # (B, J, 2)
        proj = -np.einsum("bjk,kd->bjd", w, E)  # (B, J, D)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(proj > 0, half[s0 : s0 + B, :, None] / proj, np.inf)
        out[s0 : s0 + B] = np.min(r, axis=1) if r.shape[1] else np.inf
    return out


#: Positions per block in :func:`_standstill_radius`: its (B, J, 360) temporaries stay in the
#: cache (32 positions x 10 wrong pole pairs: 0.9 MB each; the paper bench's 1408 positions
#: took 8.5 ms against 16 ms in blocks of 128, measured by a developer at load 1.4).
_RADIUS_BLOCK = 32


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
        ok_max = err_fn(np.full(rows.size, k_max), rows) <= target
        out[rows[~ok_max]] = np.inf  # not searched: inf whatever the bisection finds
        rows = rows[ok_max]
        lo = np.zeros(rows.size)
        hi = np.full(rows.size, math.log(k_max))
        for _ in range(40 if rows.size else 0):  # log K to 2e-11 of its range: no meaning below
            mid = 0.5 * (lo + hi)
            good = err_fn(np.exp(mid), rows) <= target
            hi = np.where(good, mid, hi)
            lo = np.where(good, lo, mid)
        out[rows] = np.exp(hi)
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
        status = Identifiability.NEEDS_MOTION
        reason = IdentifiabilityReason.SENSOR_DRIFT  # with the gain profile (analyze_calibration)
        if not dec.gain_sd > 0.0:  # without it only for the quantizer's standstill
            reason = IdentifiabilityReason.QUANTIZER
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
        gate_bias_dispersion=dec.gate_bias_dispersion,
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
    if reason is IdentifiabilityReason.QUANTIZER:
        return (
            f"pole pair identifiable at power-up with motion: the lock waits for "
            f"{r['lock_travel']:g} electrical revolution of motion, because the sensors' ADC, too "
            f"little dithered by their analog noise, rounds a standstill's samples to the same "
            f"codes: its rounding error is the same in every sample, so the evidence at rest "
            f"does not grow with the samples ({seps})"
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
    F = _fitted_features(decoder, d, start, stop)
    pos = decoder.coordinates(F["psi"], F["m"], np.zeros(1, dtype=np.int64))
    e = np.minimum(decoder._costs(F, pos)[:, 0], decoder.cost_cap)[F["valid"]]
    if samples < 1 or e.size < 2 * samples:
        return 1.0
    c = np.concatenate([[0.0], np.cumsum(e)])
    window = c[samples:] - c[:-samples]
    phi = float(np.var(window)) / (4.0 * samples)
    return max(phi, 1.0) if math.isfinite(phi) else 1.0


def _fitted_features(
    decoder: PowerUpDecoder, d: ArrayLike, start: int, stop: int | None
) -> dict[str, NDArray]:
    """The decoder's features of the calibration recording (f_init from y = 0 before its
    first sample), kept for the samples ``start:stop`` the model was fitted on."""
    d = np.atleast_2d(np.asarray(d, dtype=np.float64))
    F = decoder.features(d if stop is None else d[:stop])
    return {k: v[start:] for k, v in F.items()}


def bias_dispersion(
    decoder: PowerUpDecoder,
    d: ArrayLike,
    samples: int,
    *,
    start: int = 0,
    stop: int | None = None,
) -> float:
    """phi_b of the gate's bias half: the mean of S over the calibration recording's windows
    of ``samples`` consecutive samples (hypothesis 0, the calibration frame) over its
    chi-square(2) mean 2, at least 1.

    The model's own error along the turn is a slowly varying bias the white-noise model does
    not know; over a window it raises S by about ``k b^2``. Scaling the quantile by the
    recording's mean (as the chi-square half's :func:`gate_dispersion` does with the variance,
    Satterthwaite 1946) keeps the false alarm on that rig near alpha_g / 2, at the price of
    power there; on a bench whose model fits, phi_b is 1.

    Parameters
    ----------
    decoder : PowerUpDecoder
        The calibration's decoder (its tables, sigma and cap).
    d : array_like, shape (N, 3)
        The calibration recording (f_init from y = 0 before its first sample).
    samples : int
        K: the window (the gate's K0).
    start, stop : int, keyword-only
        The samples the model was fitted on.

    Returns
    -------
    float
        phi_b >= 1 (1 when the samples hold fewer than two windows).
    """
    F = _fitted_features(decoder, d, start, stop)
    F = {k: v[F["valid"]] for k, v in F.items()}
    if samples < 1 or F["psi"].size < 2 * samples:
        return 1.0
    pos = decoder.coordinates(F["psi"], F["m"], np.zeros(1, dtype=np.int64))
    c = np.concatenate([np.zeros((1, 5)), bias_sums(decoder, F, pos)[:, 0]])
    phi = float(np.mean(bias_statistic(c[samples:] - c[:-samples]))) / 2.0
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
    used. The standstill decoder has the goodness-of-fit gate at the lock
    (:data:`DEFAULT_GATE_RATE`, :data:`DEFAULT_GATE_SAMPLES`, :func:`gate_dispersion`): a
    sensor change the calibration does not describe is refused ("mismatch") instead of locking
    where it happens to look like another magnet. The decoder that waits for motion has none:
    its travel already keeps it from wrong locks (0 of 880 on cases 202 and 213), and over the
    thousands of samples of its lock the gate sees misfits far below the noise (measured on
    202, 20 power-ups turning 1.5 electrical revolutions with all gains x1.03, a plausible
    drift: 7 refused, 13 right; without it 20 right). The gate's bias half (the winner's
    residual mean, :mod:`hallcal.sensor._absolute_gate`) is added only where the calibration
    recording shows the right hypothesis's residual without a mean beyond white noise's
    sampling error (:func:`~hallcal.sensor._absolute_gate.bias_is_white`): on the ring jig the
    model's error moves from revolution to revolution, and the bias half refused 3-13 % of
    healthy held-out power-ups there; it has none (the gate as before). Nor where the sensors'
    quantizer, too little dithered by their analog noise, leaves a mean error at standstill
    (:func:`~hallcal.sensor._absolute_gate.quantizer_noncentrality`). Where that mean exceeds
    :data:`~hallcal.sensor._absolute_gate.QUANTIZER_STANDSTILL` the standstill lock is not
    used at all: the decoder without the gate and the profile, with the lock after
    :data:`DEFAULT_LOCK_TRAVEL` electrical revolution of motion, over which every channel sweeps
    its codes (verdict "needs motion", reason ``QUANTIZER``; unseen 174, 185, 207, 240: at rest
    false "mismatch" 0-7 of 40 and one wrong lock on 174 before).

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

    def analysis(gain_sd: float, travel: float) -> tuple[PowerUpDecoder, IdentifiabilityReport]:
        dec = build_decoder(flux, lut, noise_std=sigma, gain_sd=gain_sd, lock_travel=travel)
        if not travel > 0.0:  # the standstill lock gets the gate (module doc of absolute)
            phi = gate_dispersion(dec, d, DEFAULT_GATE_SAMPLES, start=start, stop=stop)
            dec = dataclasses.replace(dec, gate_rate=DEFAULT_GATE_RATE, gate_dispersion=phi)
            dec = dataclasses.replace(dec, gate_samples=DEFAULT_GATE_SAMPLES)
            phi_b = bias_dispersion(dec, d, DEFAULT_GATE_SAMPLES, start=start, stop=stop)
            fit = np.asarray(d, dtype=np.float64)[start:stop]
            quantizer = quantizer_noncentrality(fit, noise.white_std, sigma, DEFAULT_GATE_SAMPLES)
            white = bias_is_white(phi_b, DEFAULT_GATE_SAMPLES, used)
            if white and quantizer <= QUANTIZER_NONCENTRALITY:
                dec = dataclasses.replace(dec, gate_bias_dispersion=phi_b)
            if quantizer > QUANTIZER_STANDSTILL:  # the evidence at rest saturates: wait for motion
                dec = build_decoder(
                    flux, lut, noise_std=sigma, gain_sd=0.0, lock_travel=DEFAULT_LOCK_TRAVEL
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
