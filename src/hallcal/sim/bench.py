"""The virtual bench: a motor with imperfect Hall sensors in the closed loop of the paper.

Built-in defaults are the paper's simulation setup (section "Simulation setup"): n_m = 11 pole
pairs, Ts = 1/4000 s, G(s) = 1.663e5 / (s^3 + 632.6 s^2 + 2702 s) with an input delay of 1.2e-4 s
(exact ZOH, see :mod:`hallcal.sim.lti`), the controller C(q) of eq. (controller), a Fourier truth
with mechanical harmonics 1..11 where the 11th dominates and the others make each magnet slightly
different, Hall noise variance 7.5e-6 per channel, and a ramp 0 -> 13 rad in 26 s.

The truth is always expressed exactly as a :class:`~hallcal.sensor.flux.FluxModel` (Fourier series
in the mechanical angle), built from physical knobs:

``d_h(y0) = o_h + A (1 + gain_h) (1 + a_h(y0)) s(n_m y0 - phi_h) + b_h(y0) + v_h``

- ``phi_h = 2 pi (h-1)/3 + misalignment_h`` (electrical), sensor misalignment;
- ``s(psi) = cos psi + sum_k c_k cos(k psi)``, higher electrical harmonics (trapezoidal flux);
- ``b_h(y0)``: additive mechanical harmonics 1..n_m-1 of relative size ``magnet_variation``
  (each magnet slightly different; the paper's truth lies in harmonics 1..11);
- ``a_h(y0)``: amplitude modulation by mechanical harmonics 1..3 of relative size
  ``pole_modulation`` (per-pole strength differences: sidebands k n_m +- j);
- ``A (1 + gain_h) delta(y0 - phi_h / n_m)``: per-magnet shape variation of relative size
  ``shape_variation`` (see :func:`shape_deformation`): a random deformation of the rotor's flux
  pattern, different under every pole pair, seen by each sensor at its own position; energy at all
  mechanical harmonics 1..``shape_harmonics`` n_m, every sideband k n_m +- j included;
- Hall noise ``v_h`` with variance ``noise_variance``, a random low-frequency torque disturbance
  and a cogging torque ``cogging sin(cogging_periods y0) + sum A cos(k y0 - phase)``
  (``cogging_terms``) added to the plant input (:class:`~hallcal.sim.cogging.CoggingTorque`).

Sensor imperfections in time (all off by default), applied inside the closed loop so that the
loop's ``y = f_init(d)`` is computed from the very values recorded as ``d``:

``d_h[k] = ADC_h((1 + gd_h (t_k - t_ref)) d_h(y0[k]) + od_h (t_k - t_ref) + spike_h[k])``

- ``gd_h`` = ``gain_drift`` [1/s], ``od_h`` = ``offset_drift`` [Hall unit/s]: a sensor warming
  up; ``t_ref`` = ``drift_reference_time`` [s], where the sensor is the static truth;
- ``spike_h[k]``: impulsive outliers, each sample and channel hit with probability
  ``spike_rate``, of size ``+-spike_size`` (random sign; own random stream per run seed);
- ``ADC_h``: quantization to ``adc_step`` (or ``adc_bits`` codes spanning the rails), then the
  rails ``adc_low``/``adc_high`` (:class:`~hallcal.sim.loop.SensorADC`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.reconstruction import unwrap_to
from hallcal.sim.bench_spec import BenchSpec
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import ClosedLoop, LoopStatus, SensorADC, simulate_loop
from hallcal.sim.lti import ContinuousTF, DiscreteTF

__all__ = [
    "PAPER_CONTROLLER",
    "PAPER_PLANT",
    "BenchConfig",
    "BenchRun",
    "noise_floor",
    "position_controller",
    "power_up_run",
    "power_up_start",
    "ramp_run",
    "shape_deformation",
    "simulate_run",
]

#: G(s) of the paper's simulation (with the physical sign of the delay, see docs/design.md).
PAPER_PLANT = ContinuousTF((1.663e5,), (1.0, 632.6, 2702.0, 0.0), 1.2e-4)
#: C(q) of eq. (controller).
PAPER_CONTROLLER = DiscreteTF((2.94, -3.29, -2.10, 2.45), (1.0, -3.45, 4.52, -2.68, 0.61))


def position_controller(plant: ContinuousTF, sample_time: float, crossover_hz: float) -> DiscreteTF:
    """A lead-lag PI position controller for a type-1 plant, for benches unlike the paper's.

    ``C(s) = k (s + w_i)(s + w_z) / (s (s + w_p))`` with the integrator zero at ``w_c / 8``,
    the lead between ``w_c / 3`` and ``3 w_c`` (about 50 degrees of phase lead), k such that
    ``|C(j w_c) G(j w_c)| = 1``; discretized by Tustin (bilinear) at ``sample_time``. The loop is
    type 2: a ramp is tracked without steady error (Franklin, Powell & Emami-Naeini, "Feedback
    Control of Dynamic Systems", sec. 6.7, lead and lag compensation).

    Parameters
    ----------
    plant : ContinuousTF
        G(s) from torque command to angle [rad], with one integrator.
    sample_time : float
        T_s [s].
    crossover_hz : float
        Crossover frequency f_c of the loop [Hz], well below the Nyquist frequency.

    Returns
    -------
    DiscreteTF
        C(q) in descending powers of q.
    """
    wc = TWO_PI * float(crossover_hz)
    wi, wz, wp = wc / 8.0, wc / 3.0, 3.0 * wc
    num_s = np.polymul([1.0, wi], [1.0, wz])
    den_s = np.polymul([1.0, 0.0], [1.0, wp])
    c_wc = np.polyval(num_s, 1j * wc) / np.polyval(den_s, 1j * wc)
    g_wc = plant.frequency_response(np.array([crossover_hz]))[0]
    k = 1.0 / abs(c_wc * g_wc)
    import scipy.signal  # here: importing it costs 0.7 s of CPU, paid by the commands that use it

    numd, dend, _ = scipy.signal.cont2discrete((k * num_s, den_s), sample_time, method="bilinear")
    numd = np.atleast_1d(np.squeeze(numd))
    return DiscreteTF(tuple(float(v) for v in numd), tuple(float(v) for v in dend))


def noise_floor(noise_variance: float, pole_pairs: int, amplitude: float = 1.0) -> float:
    """RMS angle error [rad] that white Hall noise alone causes in any reconstruction.

    The alpha/beta projection of three channels with variance sigma^2 has variance
    (2/3) sigma^2 per component; the tangential part gives an electrical angle error of
    sigma sqrt(2/3) / A, i.e. sigma sqrt(2/3) / (A n_m) mechanical (docs/design.md).

    Parameters
    ----------
    noise_variance : float
        sigma^2 per Hall channel (sensor's unit squared, V^2 on the paper's bench).
    pole_pairs : int
        n_m.
    amplitude : float
        A, amplitude of the Hall signals' fundamental (sensor's unit).

    Returns
    -------
    float
        sigma sqrt(2/3) / (A n_m) [rad, mechanical, RMS].
    """
    return math.sqrt(noise_variance) * math.sqrt(2.0 / 3.0) / (amplitude * pole_pairs)


@dataclass(frozen=True)
class BenchConfig(BenchSpec):
    """Knobs of the virtual bench (defaults: the paper's simulation setup).

    The setup's ``[bench]`` keys (amplitude, noise, magnet and sensor imperfections, cogging,
    seed, the ramp) are the inherited fields of :class:`~hallcal.sim.bench_spec.BenchSpec`,
    declared there once with their units and meanings. Added here:

    Attributes
    ----------
    pole_pairs : int
        n_m.
    sample_time : float
        Ts [s].
    plant : ContinuousTF
        G(s) from torque to angle, with input delay.
    controller : DiscreteTF
        C(q).
    cogging_terms : tuple of (int, float, float)
        Further cogging terms ``(k, A, phase_deg)``, each ``A cos(k y0 - phase)`` (plant input
        units), besides ``cogging sin(cogging_periods y0)`` (``cogging_periods`` 0 = 6 n_m, the
        sixth electrical harmonic of a three-phase machine): real cogging has several orders
        (multiples of the slot/pole pattern) with phases.
    adc_low, adc_high : tuple of 3 float
        Rails of each sensor's ADC [Hall signal unit]: values below/above are recorded (and
        seen by f_init in the loop) as the rail (a clipping sensor); default -inf/+inf, none.
    adc_step : float
        Quantization step, one ADC code [Hall signal unit], the same for the three sensors;
        0 = none. The code grid contains ``adc_low`` when it is finite, else 0.
    adc_bits : int
        Alternatively the ADC's resolution: ``2**adc_bits`` codes from ``adc_low`` to
        ``adc_high`` inclusive (both must be finite), step ``(high - low) / (2**bits - 1)`` per
        sensor; 0 = use ``adc_step``. Setting both is an error.
    gain_drift : tuple of 3 float
        Relative sensitivity change of each sensor per second [1/s]: the whole signal of sensor h
        is multiplied by ``1 + gain_drift_h (t - drift_reference_time)`` (a sensor warming up;
        0.02 / 26 = 2 % over the paper's 26 s ramp).
    offset_drift : tuple of 3 float
        Additive offset change of each sensor per second [Hall signal unit / s], times
        ``t - drift_reference_time``.
    drift_reference_time : float
        Time [s] (from the run's first sample) at which the drifting sensors equal the static
        truth :meth:`truth` (e.g. the middle of the calibration run); default 0.
    spike_rate : float
        Probability per sample and channel of an impulsive outlier, in [0, 1]; default 0.
    spike_size : float
        Size of each outlier [Hall signal unit], random sign (before the ADC).

    Notes
    -----
    ``seed`` seeds the truth (magnet variations) and, unless given per run, the noise;
    ``ramp_end`` and ``duration`` are the defaults of :func:`ramp_run`.
    """

    pole_pairs: int = 11
    sample_time: float = 2.5e-4
    plant: ContinuousTF = PAPER_PLANT
    controller: DiscreteTF = PAPER_CONTROLLER
    cogging_terms: tuple[tuple[int, float, float], ...] = ()
    adc_low: tuple[float, float, float] = (-math.inf, -math.inf, -math.inf)
    adc_high: tuple[float, float, float] = (math.inf, math.inf, math.inf)
    adc_step: float = 0.0
    adc_bits: int = 0
    gain_drift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset_drift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    drift_reference_time: float = 0.0
    spike_rate: float = 0.0
    spike_size: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.pole_pairs < 1:
            raise ValueError("pole_pairs must be >= 1")
        if not self.sample_time > 0:
            raise ValueError("sample_time must be > 0")
        if self.noise_variance < 0:
            raise ValueError("noise_variance must be >= 0")
        if not (self.shape_variation >= 0 and math.isfinite(self.shape_variation)):
            raise ValueError("shape_variation must be a finite number >= 0")
        if int(self.shape_harmonics) < 1:
            raise ValueError("shape_harmonics must be >= 1")
        lo, hi = np.asarray(self.adc_low, float), np.asarray(self.adc_high, float)
        if lo.shape != (3,) or hi.shape != (3,) or np.isnan(lo).any() or not (lo < hi).all():
            raise ValueError("adc_low and adc_high must be 3 values each with adc_low < adc_high")
        if not (self.adc_step >= 0 and math.isfinite(self.adc_step)):
            raise ValueError("adc_step must be a finite number >= 0")
        if not 0 <= int(self.adc_bits) <= 32:
            raise ValueError("adc_bits must be in 0..32")
        if self.adc_bits and (self.adc_step or not np.isfinite(np.r_[lo, hi]).all()):
            raise ValueError("adc_bits needs finite adc_low/adc_high and adc_step = 0")
        if not 0.0 <= self.spike_rate <= 1.0:
            raise ValueError("spike_rate must be in [0, 1]")
        drifts = np.r_[self.gain_drift, self.offset_drift, self.drift_reference_time]
        if (
            drifts.shape != (7,)
            or not np.isfinite(drifts).all()
            or not math.isfinite(self.spike_size)
        ):
            raise ValueError("gain_drift and offset_drift must be 3 finite values each")

    @classmethod
    def from_spec(
        cls,
        spec: BenchSpec,
        *,
        pole_pairs: int,
        sample_time: float,
        plant: ContinuousTF,
        controller: DiscreteTF,
    ) -> BenchConfig:
        """The bench of a setup: its ``[bench]`` knobs `spec` in the given loop.

        Parameters
        ----------
        spec : BenchSpec
            The setup's ``[bench]`` table (every one of its keys is carried over).
        pole_pairs : int
            n_m.
        sample_time : float
            Ts [s].
        plant : ContinuousTF
            The true G(s).
        controller : DiscreteTF
            C(q).

        Returns
        -------
        BenchConfig
            The other knobs (ADC, drifts, spikes, further cogging terms) at their defaults.
        """
        knobs = {f.name: getattr(spec, f.name) for f in fields(BenchSpec)}
        return cls(
            pole_pairs=pole_pairs,
            sample_time=sample_time,
            plant=plant,
            controller=controller,
            **knobs,
        )

    @property
    def noise_floor(self) -> float:
        """RMS angle error [rad] from Hall noise alone (see :func:`noise_floor`)."""
        return noise_floor(self.noise_variance, self.pole_pairs, self.amplitude)

    def adc(self) -> SensorADC | None:
        """The ADC between the sensors and f_init (rails, quantizer), None when it is ideal."""
        lo, hi = np.asarray(self.adc_low, float), np.asarray(self.adc_high, float)
        if self.adc_bits:
            step = (hi - lo) / (2.0 ** int(self.adc_bits) - 1.0)
        else:
            step = np.full(3, float(self.adc_step))
        if not (step > 0).any() and np.isinf(lo).all() and np.isinf(hi).all():
            return None
        return SensorADC(lo, hi, step, np.where(np.isfinite(lo), lo, 0.0))

    @property
    def quantization_step(self) -> NDArray[np.float64]:
        """One ADC code of each sensor [Hall signal unit] (0 without quantization)."""
        adc = self.adc()
        return np.zeros(3) if adc is None else np.asarray(adc.step, dtype=np.float64)

    def loop(self) -> ClosedLoop:
        """The true closed loop (Clarke-based f_init, as in the paper)."""
        return ClosedLoop.from_transfer_functions(
            self.plant, self.controller, self.sample_time, self.pole_pairs
        )

    def truth(self) -> FluxModel:
        """The true flux g(y0) as an exact Fourier series (see the module docstring)."""
        return _truth(self)

    def cogging_torque(self) -> CoggingTorque:
        """The true cogging torque T_c(y0): ``cogging`` and ``cogging_terms`` summed per order."""
        coef: dict[int, complex] = {}
        if self.cogging:
            k = int(self.cogging_periods or 6 * self.pole_pairs)
            coef[k] = coef.get(k, 0j) + 1j * float(self.cogging)  # sin: b = amplitude
        for k, amp, phase_deg in self.cogging_terms:
            z = float(amp) * complex(math.cos(math.radians(phase_deg)),
                                     math.sin(math.radians(phase_deg)))  # fmt: skip
            coef[int(k)] = coef.get(int(k), 0j) + z
        orders = tuple(sorted(coef))
        a = np.array([coef[k].real for k in orders], dtype=np.float64)
        b = np.array([coef[k].imag for k in orders], dtype=np.float64)
        return CoggingTorque(orders, a, b)


def shape_deformation(
    pole_pairs: int,
    strength: float,
    *,
    electrical_harmonics: int = 5,
    rng: np.random.Generator,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Random per-magnet deformation of the rotor's flux pattern, as an exact Fourier series.

    ``delta(x) = sum_{m=1}^{K n_m} a_m cos(m x) + b_m sin(m x)`` in the rotor coordinate x
    [mechanical rad], with independent ``a_m, b_m ~ N(0, S_m)`` and

        S_m = s^2 w_m / sum_m w_m,   w_m = 1 / (1 + (m / n_m)^2),

    so that ``E[delta^2] = s^2`` (s = ``strength``, relative to the fundamental amplitude A).
    Over one pole pair, as a function of the electrical angle ``psi = n_m x``, this is a random
    smooth waveform with the spectrum of an Ornstein-Uhlenbeck (Matern-1/2) process truncated at
    the K-th electrical harmonic: correlation ``exp(-|psi - psi'|)``, i.e. about one electrical
    radian. Two pole pairs lie 2 pi electrical rad apart (correlation e^{-2 pi} = 0.002): every
    pole pair, every magnet, gets its own deformation, independent of its neighbours. The
    spectrum is flat within each band around a multiple k n_m, so the truth has energy at every
    mechanical harmonic 1..K n_m, the sidebands k n_m +- j of every order j included: the flux
    signature of a real rotor (DESIGN.md, "Numerical facts"), unlike ``magnet_variation``
    (harmonics 1..n_m-1) and ``pole_modulation`` (sidebands +-1..3).

    Physical meaning. s is the magnet shape tolerance expressed in flux: each pole pair's
    waveform deviates from the nominal one by s A RMS (s = 0.02: 2 % of the fundamental's
    amplitude at the sensor) with a shape of its own (width, position, edges, strength and
    magnetization angle all mixed). Its effect on f_init: the deformation's component along the
    flux curve turns into an angle error of about 0.8 s / n_m rad RMS on top of the nominal
    waveform's (the three sensors see the same pattern, so its triplen bands are nearly common
    mode and do not count). Measured on the rich-shape bench (paper loop, 11 pole pairs,
    trapezoidal flux with electrical harmonics 3 and 5 at 10 % and 4 %, 2 degrees misalignment,
    seeds 1..5, ``benchmarks/bench_rich.txt``): f_init 2.6 mrad RMS without shape variation,
    2.8-3.1 mrad at s = 0.02, 5.2-6.8 mrad at s = 0.075; the map y0 -> f_init stays monotone
    (minimum slope 0.42-0.65 at s = 0.07, 0.27-0.59 at s = 0.1).

    Parameters
    ----------
    pole_pairs : int
        n_m.
    strength : float
        s >= 0.
    electrical_harmonics : int, keyword-only
        K >= 1.
    rng : numpy.random.Generator
        Source of the coefficients (drawn in the order of the harmonics, cos then sin).

    Returns
    -------
    harmonics : ndarray (K n_m,) of int
        1..K n_m.
    a, b : ndarray (K n_m,)
        Coefficients of cos(m x) and sin(m x), relative to A.
    """
    n = int(pole_pairs)
    K = int(electrical_harmonics)
    if n < 1 or K < 1:
        raise ValueError("pole_pairs and electrical_harmonics must be >= 1")
    m = np.arange(1, K * n + 1)
    w = 1.0 / (1.0 + (m / n) ** 2)
    std = float(strength) * np.sqrt(w / w.sum())
    ab = rng.standard_normal((2, m.size)) * std
    return m, ab[0], ab[1]


def _truth(cfg: BenchConfig) -> FluxModel:
    n = cfg.pole_pairs
    rng = np.random.default_rng([cfg.seed, 0])
    # Electrical shape s(psi) = sum_k c_k cos(k psi), c_1 = 1.
    elec = {1: 1.0}
    for k, c in cfg.electrical_harmonics:
        elec[int(k)] = elec.get(int(k), 0.0) + float(c)
    # Amplitude modulation a_h(y0) = sum_j alpha_hj cos(j y0) + beta_hj sin(j y0), j = 1..3.
    jm = np.arange(1, 4)
    am = cfg.pole_modulation * rng.standard_normal((3, 2, jm.size)) / math.sqrt(jm.size)
    # Additive mechanical harmonics 1..n-1.
    jb = np.arange(1, n)
    bm = cfg.magnet_variation * rng.standard_normal((3, 2, jb.size)) / math.sqrt(max(jb.size, 1))
    # Per-magnet shape variation: one rotor pattern, seen by each sensor at its position (own
    # random stream, so the other knobs' draws do not change when it is switched on).
    shape = None
    if cfg.shape_variation > 0:
        shape = shape_deformation(
            n,
            cfg.shape_variation,
            electrical_harmonics=cfg.shape_harmonics,
            rng=np.random.default_rng([cfg.seed, 2]),
        )

    # Collect the series on a dense grid and project exactly: every term is a finite Fourier
    # series in y0, so sampling at more points than twice the highest harmonic is exact.
    harmonics = sorted(
        {h for h in range(1, n)} | {k * n + s for k in elec for s in (-3, -2, -1, 0, 1, 2, 3)}
    )
    harmonics = [h for h in harmonics if h >= 1]
    if not cfg.pole_modulation:
        harmonics = sorted(set(range(1, n)) | {k * n for k in elec})
    if shape is not None:
        harmonics = sorted(set(harmonics) | {int(h) for h in shape[0]})
    basis = FourierBasis(tuple(harmonics))
    hmax = max(elec) * n + (3 if cfg.pole_modulation else 0) + n
    M = 4 * max(hmax, max(harmonics)) + 16
    y0 = TWO_PI * np.arange(M) / M
    theta = np.zeros((3, basis.size))
    Phi = basis.evaluate(y0)
    for h in range(3):
        phi = TWO_PI * h / 3.0 + math.radians(cfg.misalignment_deg[h])
        psi = n * y0 - phi
        shape_h = sum(c * np.cos(k * psi) for k, c in elec.items())
        a = am[h, 0] @ np.cos(np.outer(jm, y0)) + am[h, 1] @ np.sin(np.outer(jm, y0))
        b = bm[h, 0] @ np.cos(np.outer(jb, y0)) + bm[h, 1] @ np.sin(np.outer(jb, y0))
        if shape is not None:  # the rotor pattern under sensor h: x = y0 - phi / n
            x = np.outer(shape[0], y0 - phi / n)
            shape_h = shape_h + shape[1] @ np.cos(x) + shape[2] @ np.sin(x)
        g = cfg.offset[h] + cfg.amplitude * (
            (1 + cfg.gain_mismatch[h]) * (1 + a) * shape_h + (b if jb.size else 0.0)
        )
        theta[h] = np.linalg.lstsq(Phi, g, rcond=None)[0]
    return FluxModel(basis, theta)


@dataclass(frozen=True)
class BenchRun:
    """One experiment on the virtual bench.

    Attributes
    ----------
    t, r, y, u : ndarray (N,)
        Time [s], reference [rad], f_init output [rad], torque command.
    d : ndarray (N, 3)
        Hall signals with noise.
    y0 : ndarray (N,)
        True angle [rad] (the virtual encoder).
    truth : FluxModel
        True flux g.
    config : BenchConfig
    realization : ndarray (N,) of int or None
        Multisine realization index (BLA experiments).
    status : LoopStatus
        OK or DIVERGED (a str enum: "ok", "diverged").
    """

    t: NDArray[np.float64] = field(repr=False)
    r: NDArray[np.float64] = field(repr=False)
    y: NDArray[np.float64] = field(repr=False)
    u: NDArray[np.float64] = field(repr=False)
    d: NDArray[np.float64] = field(repr=False)
    y0: NDArray[np.float64] = field(repr=False)
    truth: FluxModel = field(repr=False)
    config: BenchConfig
    realization: NDArray[np.float64] | None = field(default=None, repr=False)
    status: LoopStatus = LoopStatus.OK

    @property
    def n_samples(self) -> int:
        return int(self.r.size)

    def columns(self, *, with_encoder: bool = True) -> dict[str, NDArray[np.float64]]:
        """Dataset columns of docs/design.md (``y_ref`` = the true angle, validation only)."""
        cols = {
            "t": self.t,
            "r": self.r,
            "y": self.y,
            "u": self.u,
            "d1": self.d[:, 0],
            "d2": self.d[:, 1],
            "d3": self.d[:, 2],
        }
        if with_encoder:
            cols["y_ref"] = self.y0
        if self.realization is not None:
            cols["realization"] = self.realization
        return cols

    def truth_dict(self) -> dict:
        """The truth for a sidecar file: flux model, noise level and noise floor."""
        cfg = self.config
        return {
            "format": "hallcal-truth/1",
            "pole_pairs": cfg.pole_pairs,
            "harmonics": list(self.truth.basis.harmonics),
            "theta": self.truth.theta.tolist(),
            "noise_variance": cfg.noise_variance,
            "noise_floor": cfg.noise_floor,
            "seed": cfg.seed,
            "plant": {
                "num": list(cfg.plant.num),
                "den": list(cfg.plant.den),
                "delay": cfg.plant.delay,
            },
        }


def _lowpass_noise(rng: np.random.Generator, n: int, std: float, ts: float, fc: float = 5.0):
    if std == 0.0:
        return np.zeros(n)
    a = math.exp(-TWO_PI * fc * ts)
    w = rng.standard_normal(n) * std * math.sqrt(1 - a * a)
    import scipy.signal  # here: see position_controller

    return scipy.signal.lfilter([1.0], [1.0, -a], w)


def _sensor_in_time(
    config: BenchConfig, noise: NDArray[np.float64], *, seed: int
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The additive sensor terms (noise, offset drift, spikes) and the gain per sample and
    sensor (None: 1) of the module docstring's time-varying sensor model."""
    N = noise.shape[0]
    t = config.sample_time * np.arange(N) - float(config.drift_reference_time)
    gain = None
    if any(config.gain_drift):
        gain = 1.0 + np.outer(t, np.asarray(config.gain_drift, dtype=np.float64))
    if any(config.offset_drift):
        noise = noise + np.outer(t, np.asarray(config.offset_drift, dtype=np.float64))
    if config.spike_rate > 0 and config.spike_size != 0:
        rng = np.random.default_rng([seed, 3])
        hit = rng.random((N, 3)) < config.spike_rate
        sign = np.where(rng.random((N, 3)) < 0.5, -1.0, 1.0)
        noise = noise + np.where(hit, sign * float(config.spike_size), 0.0)
    return noise, gain


def simulate_run(
    config: BenchConfig,
    r: ArrayLike,
    *,
    seed: int | None = None,
    realization: ArrayLike | None = None,
    initial_angle: float = 0.0,
) -> BenchRun:
    """Run the closed loop of the bench on a reference r.

    Parameters
    ----------
    config : BenchConfig
    r : array_like (N,)
        Reference [rad].
    seed : int, keyword-only
        Seed of this run's noise and disturbance (default: ``config.seed``); the truth depends on
        ``config.seed`` only, so runs with other seeds are fresh realizations on the same motor.
    realization : array_like (N,) of int, keyword-only, optional
        Multisine realization index per sample, stored in the run (BLA experiments).
    initial_angle : float, keyword-only
        True rotor angle at the first sample [rad, in the truth's frame]: a power-up wherever
        the rotor stopped. f_init (and so the loop) still starts from y = 0 before the first
        sample, i.e. from its own atan2 within one electrical period, so ``y`` and ``y0`` differ
        by about a whole number of pole pairs ``2 pi j / n_m``. The reference should start
        near f_init's first value (:func:`power_up_start`) to avoid a step. Default 0: the
        calibration convention (y0 = 0 at the first sample).

    Returns
    -------
    BenchRun
        r, y, u, the noisy Hall signals d and the true angle y0 of the run.
    """
    r = np.asarray(r, dtype=np.float64)
    N = r.size
    rng = np.random.default_rng([config.seed if seed is None else seed, 1])
    sigma = math.sqrt(config.noise_variance)
    noise = sigma * rng.standard_normal((N, 3))
    td = _lowpass_noise(rng, N, config.torque_disturbance, config.sample_time)
    truth = config.truth()
    noise, gain = _sensor_in_time(config, noise, seed=config.seed if seed is None else seed)
    res = simulate_loop(
        config.loop(),
        truth,
        r,
        noise=noise,
        torque_disturbance=td,
        cogging=config.cogging_torque(),
        initial_angle=float(initial_angle),
        sensor_gain=gain,
        adc=config.adc(),
    )
    return BenchRun(
        t=config.sample_time * np.arange(N, dtype=np.float64),
        r=r,
        y=res.y,
        u=res.u,
        d=res.d,
        y0=res.y0,
        truth=truth,
        config=config,
        realization=None if realization is None else np.asarray(realization, dtype=np.float64),
        status=res.status,
    )


def ramp_run(
    config: BenchConfig,
    *,
    ramp_end: float | None = None,
    duration: float | None = None,
    seed: int | None = None,
) -> BenchRun:
    """The calibration experiment: a ramp reference 0 -> ``ramp_end`` [rad] in ``duration`` [s].

    Step 1 of Algorithm 1 on the virtual bench; the defaults are the bench's ``ramp_end`` and
    ``duration`` (the paper's simulation, section "Simulation results": 0 -> 13 rad in 26 s).

    Parameters
    ----------
    config : BenchConfig
        The bench.
    ramp_end : float, keyword-only, optional
        Final reference [rad, mechanical]; default ``config.ramp_end``.
    duration : float, keyword-only, optional
        Length of the run [s], ``round(duration / T_s)`` samples; default ``config.duration``.
    seed : int, keyword-only, optional
        Seed of the noise and disturbance; default ``config.seed``.

    Returns
    -------
    BenchRun
        The calibration recording with its true angle y0.
    """
    end = config.ramp_end if ramp_end is None else ramp_end
    N = int(round((config.duration if duration is None else duration) / config.sample_time))
    r = np.linspace(0.0, end, N, endpoint=False)
    return simulate_run(config, r, seed=seed)


def power_up_start(config: BenchConfig, initial_angle: float) -> float:
    """f_init's noise-free first output [rad] when the rotor powers up at ``initial_angle``.

    f_init starts from y = 0, so this is the true flux's electrical angle at ``initial_angle``
    unwrapped into [-pi/n_m, pi/n_m): the value a power-up reference should start from.

    Parameters
    ----------
    config : BenchConfig
        The bench (truth flux, f_init's projection and offsets, n_m).
    initial_angle : float
        True rotor angle at power-up [rad, mechanical, truth's frame].

    Returns
    -------
    float
        f_init's first output [rad, mechanical], in [-pi/n_m, pi/n_m).
    """
    g = config.truth()(np.array([float(initial_angle)]))[0]
    P = config.loop().projection
    a, b = P @ (g - config.loop().offset)
    n = config.pole_pairs
    return unwrap_to(math.atan2(b, a), 0.0) / n


def power_up_run(
    config: BenchConfig,
    initial_angle: float,
    *,
    samples: int,
    speed: float = 0.0,
    seed: int | None = None,
) -> BenchRun:
    """A run after a power-up at ``initial_angle`` [rad]: hold still (speed 0) or ramp.

    The reference starts at f_init's first value (:func:`power_up_start`) and moves at
    ``speed`` [rad/s] relative to f_init's frame, so the loop starts without a step. The true
    angle ``y0`` is in the truth's frame (the calibration's frame when the calibration run
    started at y0 = 0), while f_init starts within one electrical period of zero.

    Parameters
    ----------
    config : BenchConfig
        The bench (truth, loop, noise).
    initial_angle : float
        True rotor angle at power-up [rad, mechanical, truth's frame].
    samples : int, keyword-only
        Length of the run [samples].
    speed : float, keyword-only
        Reference speed [rad/s, mechanical]; 0 holds still.
    seed : int, keyword-only, optional
        Seed of the noise and disturbance; default ``config.seed``.

    Returns
    -------
    BenchRun
        The run; ``y`` is f_init's output from y = 0, ``y0`` the true angle.
    """
    y_start = power_up_start(config, initial_angle)
    r = y_start + speed * config.sample_time * np.arange(int(samples))
    return simulate_run(config, r, seed=seed, initial_angle=initial_angle)
