"""Cogging torque identified jointly with the flux model: which orders, and how large.

The paper's discussion attributes its experiment's residual error to "nonlinear dynamics that are
periodic in y0 with period 2 pi, such as cogging": a torque ``T_c(y0)`` at the plant input moves
the rotor in a way that a flux model alone would explain as a sensor error. hallcal puts
``T_c(y0) = sum_k a_k cos(k y0) + b_k sin(k y0)`` into the simulated loop (eq. state_eq with
``u + T_c(y0)`` as the plant input, :mod:`hallcal.sim.cogging`) and identifies its coefficients
jointly with theta by the SEM (:func:`hallcal.fit.sem.solve_sem`, exact sensitivities including
the feedback term ``dT_c/dy0 dy0``).

Choosing the orders (``cogging = "auto"``), in two tests:

1. **Evidence in the residual** (:func:`shift_spectrum`). A motion error shows in the SEM residual
   as a shift of the samples *along* the model's flux curve (the curve projection of
   :func:`hallcal.fit.adequacy.curve_projection`, which the adequacy check uses to tell motion
   from flux shape). A cogging torque of order k makes this shift periodic in the mechanical
   angle with k periods per revolution: a line in its spectrum over the angle. The spectrum is the
   least-squares amplitude of each order, weighted by the shift's inverse noise variance
   ``|g'|^2 / sigma^2``; an order is a candidate when its power stands out from the local level
   of the spectrum (the median of the neighbouring orders, robust to other lines) by more than
   the chi-square(2) quantile at the family-wise false-alarm level over the plausible orders
   (Bonferroni), and is a local maximum (a strong line leaks into its neighbours on a
   non-integer number of revolutions). The local level makes the test valid for the coloured
   spectrum that a random torque disturbance leaves (its power falls with the order).
2. **Significance of the fitted coefficients** (:func:`select_cogging`). The candidates are fitted
   jointly with theta (and the plant gain when the plant comes from the BLA). Each order is kept
   when its two coefficients differ from zero by Hotelling's T^2 test with the batch-means
   (long-run) covariance of the SEM's scores (:attr:`hallcal.fit.sem.SEMResult.batch_covariance`;
   Ljung 1999, sec. 9.3 on the covariance of prediction-error estimates under coloured
   residuals): ``T^2 (B - 2) / (2 (B - 1)) ~ F(2, B - 2)`` for B batches, Bonferroni over the
   candidates. Orders that fail are dropped and the rest refitted. Nothing is added when nothing
   passes, so a motor without cogging keeps exactly the fit it had.
3. **Related orders** (:func:`related_orders`). The first fit's flux, when rich enough, absorbs
   most of a torque's motion (a shift ``delta(y0)`` at order k moves ``g(y0)`` by ``g' delta``,
   flux content at the sidebands of k that the model holds), so a strong cogging line can sit
   far below the spectrum's test: on zoo motor 38 (3 pole pairs, 24 harmonics up to 27, true
   orders 0, 12 and 18) the line at 18 was 0.8x its local level, only its harmonic 36 stood out
   (10x, the test at 16x), and the table with the load alone came out 8.2x the noise floor
   (1.02x with 0, 12 and 18 given). So the spectrum is only a screen (family-wise level 0.1);
   the test of step 2 decides; and once orders are found, their multiples and the multiples of
   2 n_m that divide them are fitted with them (a cogging torque is periodic with its
   fundamental LCM(Q, 2 n_m) and not sinusoidal), and kept by the same test.
4. **Sidebands** (:func:`sideband_basis`). A torque of order k and a flux error differ only
   through the loop's dynamics: at constant speed the rotor's shift at order k moves the signals
   by ``g' delta``, flux content at the orders ``|k +- h|`` for the harmonics h of g. When the
   harmonic selection kept a sparse set, a torque at k is the cheapest fit of the small flux
   harmonics left out among those sidebands (each below its own test; together a line in the
   shift spectrum at k, and a T^2 far above its threshold: the residual there is not noise but
   a misfit that repeats every revolution, which no covariance shows). Each order k > 0 found
   is therefore tested again, by the same T^2, in one joint fit whose basis also holds the
   sidebands within its band, and dropped when it fails there. Measured on the unseen zoo's
   motor 179 (adc12, 14 pole pairs, no cogging in its truth, harmonics 1..70 of which 28 kept)
   over ten noise draws of the calibration run: 28 = 2 n_m was kept on two draws (T^2 103
   against 19.8 on draw 4, whose table went from 1.36x to 3.04x the noise floor), 6.8 with the
   sidebands; no order k > 0 is kept now (``benchmarks/bench_zoo_noise.txt``). The zoo's
   motors with cogging keep their orders (the sidebands of 6 n_m lie mostly above a band of
   5 n_m, where only a torque fits them). A basis that already holds every harmonic of its band
   is not refitted; there (unseen zoo 194, clip class, harmonics 1..90) a torque can still
   stand in for flux content above the band (80 and 100 are kept; the table is 1.04x the
   noise floor with them, 1.05x with ``cogging = "none"``). The check costs one SEM fit on the
   wider basis, only when an order k > 0 is found (1.6-2.4 s of a 14-26 s calibration on the
   trapezoid row of ``benchmarks/bench_cogging.py`` at load 5 on 2 cores).

**A constant load torque** (order 0: friction on a one-way ramp, gravity, a spring) leaves no
line in the shift spectrum: in a loop whose controller does not integrate it shifts the rotor
by a constant angle, which the flux model absorbs as a constant offset of the sensors' angle, a
bias of the table's offset that no covariance shows (DESIGN.md, "Numerical facts": 0.6-1.1x the
noise floor on its own). Only the start of the run, where the loop leaves rest at y0 = 0 under
the load, tells the two apart; so "auto" always fits order 0 jointly with the spectrum's
candidates and keeps it when its coefficient a_0 is significant: ``T^2 = a_0^2 / var a_0 ~
F(1, dof)`` with a heteroscedasticity-and-autocorrelation-consistent (HAC) variance (below;
:func:`load_test`), Bonferroni with the other orders. Measured on the paper's bench with a load
of 0.003 (ramp 0 -> 7 rad in 14 s, harmonics 1..11): a_0 found at 0.0030006 +- 1.2e-5, the
table's offset 0.79x -> -0.12x the noise floor, its RMS error about zero 1.28x -> 1.01x
(``tests/test_verdict.py``; HAC T^2 59 919 against 10.8). With a BLA plant whose gain c is
refined jointly (``fit_gain``) a constant torque trades off against c (both set the loop's
steady lag on a constant-speed ramp): there the calibration does not try order 0
(``load=False``).

Order 0's variance. Under a controller that integrates (the zoo's lead-lag PI) the integrator takes
up a load within the start transient, so a_0 is seen in a short stretch only (on unseen zoo motor
179: 100 % of its sensitivity in the first of 25 batches, the shift of y0 at most 2.8e-6 rad at
sample 136 for a_0 = 7e-4, 1e-12 rad after 4096 samples). The batch-means variance of the other
orders is then one batch's squared score, and at the fit that score is about zero (the residual is
orthogonal to a_0's influence where the influence lives): on 179 (adc12, no load in its truth) it
was 0.02-0.13x the white one and order 0 was kept on noise draws 3, 5, 7, 9 (T^2 19, 83, 81, 34
against 14.0; white T^2 2.4, 2.0, 1.3, 1.2). A HAC of the fitted scores themselves fails the same
way at any block size, only less (Newey-West over 64-sample blocks, Andrews' bandwidth: 179 draw 5
T^2 4.3 with 2 Satterthwaite degrees of freedom; on regressions whose regressor decays in 60-200 of
25 600 samples, 13-40 % false alarms at the 1 % level). So a_0's variance is ``sigma^2 (A^-1)_00``
times the ratio of the long-run to the lag-0 variance of ``sum_t u_t^T e_t``, with a_0's influence
``u_t = J_t A^-1 e_a0`` (two simulations along that direction) and the residual's auto- and
cross-covariances up to Andrews' (1991) bandwidth estimated over the WHOLE run (Bartlett kernel,
Newey & West 1987; :func:`hallcal.fit.long_run.hac_variance`): a localized influence is judged
against the residual's autocorrelation with ``1.5 N / S`` degrees of freedom (thousands on the zoo),
not against its own few samples. On the regression of the test: 1.3 % and 1.0 % false alarms at the
1 % level with white and with AR(1) 0.8 noise (batch means 95 %, white 36 % under the AR noise;
``tests/test_cogging_load.py``). The pass (two simulations and FFTs) is made only when the
batch-means or the white test passes order 0; the paper's run without a load (T^2 0) is not charged
(artifact bit-identical, the search 0.10 s CPU as before; with the load 0.003: 0.17 -> 0.22 s).

Measured (``benchmarks/bench_cogging_load.txt``, order 0 alone given / ``"auto"``; tables RMS
about zero over the floor): 179 draws 3, 5, 7, 9 (no load): HAC T^2 1.8, 1.5, 0.9, 0.9 against
10.8, order 0 dropped, tables 1.226x, 1.174x, 1.244x, 1.150x -> 1.246x, 1.126x, 1.304x, 1.126x.
The ``cogload`` motors' strong loads stay (HAC T^2 in "auto" 807 000, 167, 3 000, 4 200, 8 300 on
6, 22, 174, 182, 190). The true loads of 14 (0.0015) and 30 (0.019) are dropped: their runs do
not show them (HAC T^2 2.3 and 3.4, white 3.3 and 3.7 with order 0 alone: they had passed only
by the batch-means understatement), tables 1.028x -> 1.007x on 14 and 1.335x -> 1.360x on 30
(1.098x and 1.389x without any cogging). Unseen 183 (spikes, no load in its truth) kept order
0 (table 1.516x, offset -0.88x the floor): dropped (HAC T^2 3.9), table 1.480x as with
``cogging = "none"``. Unseen 193 (shape, no load) already dropped it by the drift retest below
and still does (HAC T^2 21.4 on the search's fit, 1.2 against 14.0 on the final one; table
1.239x, offset -0.70x; "none" 1.237x).

Fixed: on the zoo's drift and adc12 motors 4, 11, 12, 19 (no load) order 0 was kept for another
reason: it was tested on the search's joint fit, before the final fit that adds the sensors'
drift (:func:`hallcal.pipeline.sensors.final_fit`); there a_0 stands in for the drift's effect at
the run's start (on 4 and 12 the y0 shift the truth's drift alone causes in the first batch
projects onto a load's shift as a_0 = -0.0152 and -0.00168; fitted -0.0193 and -0.00172, T^2 22
and 117), and the final fit takes it back to about zero (19: 7.2e-4 tested, T^2 91, -6.2e-6 in
the artifact), while order 0 stayed in the model. When the drift is fitted, order 0 is now
tested again on the final fit (:meth:`CoggingSelection.load_retest`: the same T^2 with the
batch-means variance, Bonferroni over the final orders) and, when it fails there, dropped and
the final fit done again without it; the message then says so and names no load. On 4, 11, 12,
19: T^2 5.4, 1.8, 9.4, 0.9 against 14.0 on the final fit, no order 0 left; tables 1.122x,
1.005x, 1.033x, 1.026x -> 1.123x, 1.008x, 1.033x, 1.027x the noise floor (the refit, one more
SEM with the drift: calibration CPU 7.4 -> 8.2, 9.4 -> 10.4, 1.8 -> 1.9 s on 4, 11, 19). The
cogload motors and the paper's load bench fit no drift and are unchanged
(``benchmarks/bench_cogging_load.txt``). The HAC test does not replace this retest: the drift's
effect is a signal, not noise, and on the search's fit of 11, 12, 19 a_0 passes it too (HAC
T^2 105, 17, 88 against 10.8; 4: 7.7, dropped there already); the retest keeps the batch-means
variance (it can only drop the load).

Not done: the HAC's residual autocovariance is the whole run's, assumed to hold in the start
transient too (the loop leaves rest there; an ADC's quantization error at low speed is more
correlated than at the ramp's speed). Its degrees of freedom ``1.5 N / S`` count the
covariance's estimation only, and the reference is F(1, dof), about chi-square(1) on the zoo.
Screening order 0 by a score (Lagrange-multiplier) test at the fit without it, so that the
joint fit is spared when a_0 is clearly insignificant, is not done either: with the batch-means
variance the score's T^2 is about 1 whatever the load (0.86-2.1 on the cogload motors 6, 14,
22, 30, 174, 182, 190), and on the paper run the joint fit costs 0.10 s of CPU with nothing
else to save.

Orders searched by default (:func:`plausible_orders`): the multiples of 2 n_m up to 24 n_m. The
fundamental cogging order of a machine with Q stator slots and 2 n_m poles is LCM(Q, 2 n_m)
periods per revolution, followed by its multiples (for 11 pole pairs: 66 with 33 slots, 132 with
12 slots): every one of them is a multiple of the number of poles 2 n_m, whatever Q is. Other
lines in the shift spectrum are not cogging: a flux harmonic missing from the model also leaves
a line at its own order (the along-curve part of the missing content), and a torque fitted there
trades off against the flux. Measured on a random motor (11 pole pairs, 25 000 samples, flux
band 1..77 of which the model had 1..61): a line at 63 passed both tests and was fitted as a
torque of 0.2 (50 times the true cogging, which was at 66), and the table went from 21x to 28x
the noise floor. The cost does not tell them apart: there the torque at 63 fitted the data better
than the flux harmonic 63 added instead, by 1165 sigma^2, as it also absorbed part of the misfit
of the other missing harmonics. Well beyond 24 n_m the rotor's position response to a torque
(the plant falls off as 1 / frequency^2 above the loop bandwidth) is far below the Hall noise at
the usual calibration speeds. Other orders (e.g. multiples of Q from magnet-to-magnet
variation) can be given explicitly (``cogging = [orders]``).

"""

from __future__ import annotations

import enum
import math
import statistics
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.fit.adequacy import CurveProjection, project_fit
from hallcal.fit.gauss_newton import _moments
from hallcal.fit.long_run import INFLUENCE_STEP, LongRunVariance, functional_long_run
from hallcal.fit.sem import SEMResult, solve_sem
from hallcal.sensor.flux import FourierBasis
from hallcal.sim.cogging import CoggingTorque
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "CoggingSelection",
    "CoggingStatus",
    "LoadTest",
    "ShiftSpectrum",
    "default_max_order",
    "load_test",
    "plausible_orders",
    "related_orders",
    "select_cogging",
    "shift_spectrum",
]


def f2_isf(alpha: float, dof: float) -> float:
    """Upper alpha quantile of the F(2, dof) distribution, in closed form.

    With 2 numerator degrees of freedom the survival function is ``(1 + 2 x / dof)^(-dof / 2)``
    (Johnson, Kotz & Balakrishnan 1995, ch. 27), so ``x = dof / 2 (alpha^(-2 / dof) - 1)``.
    """
    return 0.5 * dof * (alpha ** (-2.0 / dof) - 1.0)


def f1_isf(alpha: float, dof: float) -> float:
    """Upper alpha quantile of the F(1, dof) distribution: the square of Student's t at alpha/2.

    t from the normal quantile z by the Cornish-Fisher expansion of Abramowitz & Stegun (1964),
    eq. 26.7.5 (four terms; within 0.5 % of the exact quantile for dof >= 8 at alpha >= 1e-4).
    """
    z = statistics.NormalDist().inv_cdf(1.0 - 0.5 * alpha)
    v = float(dof)
    t = (
        z
        + (z**3 + z) / (4 * v)
        + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * v**2)
        + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * v**3)
        + (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / (92160 * v**4)
    )
    return t * t


def plausible_orders(pole_pairs: int, max_order: int | None = None) -> tuple[int, ...]:
    """Cogging orders searched by "auto": the multiples of 2 n_m up to ``max_order``.

    The cogging torque of Q slots against 2 n_m poles repeats LCM(Q, 2 n_m) times per
    revolution (its harmonics at the multiples), a multiple of 2 n_m for every Q.

    Parameters
    ----------
    pole_pairs : int
        n_m.
    max_order : int, optional
        Highest order (default :func:`default_max_order`).

    Returns
    -------
    tuple of int
        2 n_m, 4 n_m, ... <= max_order.
    """
    n = int(pole_pairs)
    top = default_max_order(n) if max_order is None else int(max_order)
    return tuple(range(2 * n, top + 1, 2 * n))


def default_max_order(pole_pairs: int) -> int:
    """Highest cogging order searched by default: 24 n_m (see the module docstring).

    Parameters
    ----------
    pole_pairs : int
        n_m.

    Returns
    -------
    int
        24 n_m [periods per mechanical revolution].
    """
    return 24 * int(pole_pairs)


# ------------------------------------------------------------------------------------------------
# 1. Evidence: the spectrum of the shift along the flux curve
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ShiftSpectrum:
    """Spectrum over the mechanical angle of the residual's shift along the flux curve.

    Attributes
    ----------
    orders : ndarray of int (K,)
        Orders 1..K (periods per revolution).
    amplitude : ndarray (K,)
        Least-squares amplitude of each order in the shift [rad].
    power : ndarray (K,)
        Squared amplitude.
    level : ndarray (K,)
        Local level: the median power of the ``window`` orders on each side (not the order
        itself), divided by ln 2 (the median of an exponential law is ln 2 times its mean).
    threshold : float
        Critical value of ``power / level`` (chi-square(2) / 2 at the family-wise level).
    candidates : tuple of int
        Orders whose ratio exceeds the threshold and that are local maxima of the power.
    revolutions : float
        Angle range of the run [revolutions].
    curve : CurveProjection, optional
        The projection of the signals on the fit's curve the shift comes from (reused by the
        adequacy check of the same fit, :func:`hallcal.fit.adequacy.project_fit`).
    """

    orders: NDArray[np.int64] = field(repr=False)
    amplitude: NDArray[np.float64] = field(repr=False)
    power: NDArray[np.float64] = field(repr=False)
    level: NDArray[np.float64] = field(repr=False)
    threshold: float
    candidates: tuple[int, ...]
    revolutions: float
    curve: CurveProjection | None = field(default=None, repr=False, compare=False)

    @property
    def ratio(self) -> NDArray[np.float64]:
        """power / level."""
        return self.power / np.maximum(self.level, 1e-300)

    def to_dict(self) -> dict:
        return {
            "max_order": int(self.orders[-1]) if self.orders.size else 0,
            "threshold": float(self.threshold),
            "candidates": [int(k) for k in self.candidates],
            "candidate_ratio": [float(self.ratio[k - 1]) for k in self.candidates],
            "candidate_shift_amplitude": [float(self.amplitude[k - 1]) for k in self.candidates],
        }


def shift_spectrum(
    sem: SEMResult,
    d: ArrayLike,
    *,
    max_order: int,
    window: int = 10,
    significance: float = 1e-3,
    max_candidates: int = 6,
    tested: tuple[int, ...] | None = None,
) -> ShiftSpectrum:
    """Candidate cogging orders: lines in the spectrum of the shift along the flux curve.

    Parameters
    ----------
    sem : SEMResult
        A fit without the cogging orders in question (its flux and simulated angle).
    d : array_like (N, 3)
        Recorded Hall signals.
    max_order : int
        Orders 1..max_order are searched.
    window : int
        Neighbouring orders on each side for the local level.
    significance : float
        Family-wise false-alarm probability over the orders searched.
    max_candidates : int
        At most this many candidates (the strongest ratios).
    tested : tuple of int, optional
        Only these orders can be candidates (default all 1..max_order); the family-wise level
        is over the orders tested, the local level uses all orders.

    Returns
    -------
    ShiftSpectrum
    """
    y0 = np.ascontiguousarray(sem.y0_sim, dtype=np.float64)
    K = int(max_order)
    if K < 1:
        raise ValueError("max_order must be >= 1")
    curve = project_fit(sem, np.ascontiguousarray(d, dtype=np.float64))
    delta, speed2 = curve.delta, curve.speed2
    w = speed2 / max(float(np.mean(speed2)), 1e-300)  # inverse noise variance of the shift
    delta = delta - float(np.sum(w * delta) / np.sum(w))
    C, S = _moments(y0, np.ascontiguousarray(np.column_stack([w * delta, w])), K)
    # per order, the weighted least-squares sinusoid: a = 2 sum w delta cos / sum w (the
    # cross terms are small over whole revolutions and vanish on average)
    wsum = C[1, 0]
    a = 2.0 * C[0, 1:] / wsum
    b = 2.0 * S[0, 1:] / wsum
    power = a * a + b * b
    level = np.empty(K)
    for i in range(K):
        lo, hi = max(0, i - window), min(K, i + window + 1)
        neighbours = np.r_[power[lo:i], power[i + 1 : hi]]
        level[i] = float(np.median(neighbours)) / math.log(2.0) if neighbours.size else math.inf
    # power / mean level ~ chi-square(2) / 2 = Exp(1) without a line; the level is estimated
    # from 2 window orders by a median (efficiency about 1 / 2.08 of a mean), hence F(2, dof)
    dof = max(2.0 * 2 * window / 2.08, 2.0)
    allowed = np.ones(K, dtype=bool)
    if tested is not None:
        allowed[:] = False
        idx = np.asarray([k - 1 for k in tested if 1 <= k <= K], dtype=np.int64)
        allowed[idx] = True
    threshold = f2_isf(significance / max(int(allowed.sum()), 1), dof)
    ratio = power / np.maximum(level, 1e-300)
    peak = np.ones(K, dtype=bool)
    peak[1:] &= power[1:] >= power[:-1]
    peak[:-1] &= power[:-1] >= power[1:]
    hits = np.flatnonzero((ratio > threshold) & peak & allowed)
    hits = hits[np.argsort(-ratio[hits])][: int(max_candidates)]
    revs = float((np.nanmax(y0) - np.nanmin(y0)) / TWO_PI) if y0.size else 0.0
    return ShiftSpectrum(
        orders=np.arange(1, K + 1),
        amplitude=np.sqrt(power),
        power=power,
        level=level,
        threshold=threshold,
        candidates=tuple(sorted(int(i) + 1 for i in hits)),
        revolutions=revs,
        curve=curve,
    )


# ------------------------------------------------------------------------------------------------
# 2. Joint fit and the significance of the fitted coefficients
# ------------------------------------------------------------------------------------------------


class CoggingStatus(enum.StrEnum):
    """How the cogging orders were settled."""

    #: no order passed the tests: nothing added
    NONE = "none"
    #: orders chosen from the data ("auto")
    FOUND = "found"
    #: orders given in the setup
    GIVEN = "given"
    #: cogging switched off ("none" in the setup)
    OFF = "off"

    @property
    def success(self) -> bool:
        return True


@dataclass(frozen=True)
class OrderTest:
    """Hotelling's T^2 test of one order's coefficients (a_k, b_k) = 0."""

    order: int
    amplitude: float
    statistic: float
    threshold: float

    @property
    def significant(self) -> bool:
        return self.statistic > self.threshold

    def to_dict(self) -> dict:
        return {
            "order": self.order,
            "amplitude": float(self.amplitude),
            "statistic": float(self.statistic),
            "threshold": float(self.threshold),
            "significant": bool(self.significant),
        }


@dataclass(frozen=True)
class CoggingSelection:
    """Outcome of :func:`select_cogging`.

    Attributes
    ----------
    status : CoggingStatus
    orders : tuple of int
        Orders in the final model (empty for NONE and OFF).
    cogging : CoggingTorque or None
        The identified torque with the covariance of its coefficients.
    sem : SEMResult
        The final fit (the given one when nothing was added).
    spectrum : ShiftSpectrum or None
        The evidence (``"auto"`` only).
    tests : tuple of OrderTest
        The significance test of every fitted candidate (last fit with each order).
    message : str
        One line for the user.
    """

    status: CoggingStatus
    orders: tuple[int, ...]
    cogging: CoggingTorque | None = field(repr=False)
    sem: SEMResult = field(repr=False)
    spectrum: ShiftSpectrum | None = field(default=None, repr=False)
    tests: tuple[OrderTest, ...] = ()
    message: str = ""

    def refitted(self, sem: SEMResult) -> CoggingSelection:
        """The same orders after a later fit: its torque, and a message stating that torque.

        Zoo motor 19 (drift class): a constant load 7.2e-4 in the search's fit, -6.2e-6 after the
        final fit with the sensors' drift; the message said 7.2e-4 while the artifact held the
        refitted value.

        Parameters
        ----------
        sem : SEMResult
            The later fit with these orders (the final fit with the sensors' drift, the plant's
            refinement).

        Returns
        -------
        CoggingSelection
            Status, orders, evidence and tests as here; ``sem``, its torque and the message
            describing that torque. ``self`` when no torque was fitted.
        """
        if self.cogging is None:
            return self
        how = "given" if self.status is CoggingStatus.GIVEN else "found in the data"
        return replace(self, sem=sem, cogging=sem.cogging, message=_describe(sem.cogging, how))

    def load_retest(self, sem: SEMResult, *, significance: float = 1e-3) -> OrderTest | None:
        """Order 0's T^2 test on a later fit that holds what the search's fit lacked.

        The search tests a constant load a_0 on its joint fit; a later fit with the sensors'
        drift (:func:`hallcal.pipeline.sensors.final_fit`) holds an effect the search's fit could
        only give to a_0 (the drift's shift of y0 at the run's start; module docstring, "A
        constant load torque"). The same test (:func:`order_tests`, Bonferroni over the orders
        of ``sem``) there decides whether the load stays.

        Parameters
        ----------
        sem : SEMResult
            The later fit with this selection's orders.
        significance : float
            Family-wise false-alarm level (as :func:`select_cogging`).

        Returns
        -------
        OrderTest or None
            Order 0's test on ``sem``; None when the search did not choose order 0 (orders
            given in the setup are kept as given).
        """
        if self.status is not CoggingStatus.FOUND or 0 not in self.orders:
            return None
        return next((t for t in order_tests(sem, significance=significance) if t.order == 0),
                    None)  # fmt: skip

    def load_retested(self, sem: SEMResult, retest: OrderTest) -> CoggingSelection:
        """The selection after :meth:`load_retest`: order 0's test replaced by ``retest``, and
        order 0 dropped when it failed there.

        Parameters
        ----------
        sem : SEMResult
            The later fit: the one of the retest when it passed, refitted without order 0 when
            it failed (without cogging when 0 was the only order).
        retest : OrderTest
            Order 0's test on the later fit.

        Returns
        -------
        CoggingSelection
            Passed: :meth:`refitted` with the retest. Failed: NONE (no torque) when 0 was the
            only order, else FOUND with the other orders and ``sem``'s torque.
        """
        tests = tuple(retest if t.order == 0 else t for t in self.tests)
        if retest.significant:
            return replace(self.refitted(sem), tests=tests)
        orders = tuple(k for k in self.orders if k != 0)
        tests = tuple(t for t in tests if t.order != 0) + (retest,)
        why = (
            "the constant load torque the search found is not significant once the sensors' "
            f"drift is fitted (T^2 {retest.statistic:.3g} against {retest.threshold:.3g})"
        )
        if not orders:
            return replace(self, status=CoggingStatus.NONE, orders=(), cogging=None, sem=sem,
                           tests=tests, message=f"cogging: none found ({why})")  # fmt: skip
        found = _describe(sem.cogging, "found in the data")
        return replace(self, orders=orders, cogging=sem.cogging, sem=sem, tests=tests,
                       message=f"{found}; {why}")  # fmt: skip

    def without_load(self) -> CoggingTorque | None:
        """This selection's torque without order 0 (None when 0 is its only order): the start
        of the refit after :meth:`load_retest` failed."""
        cog = self.cogging
        if cog is None:
            return None
        keep = [i for i, k in enumerate(cog.orders) if k != 0]
        if not keep:
            return None
        return CoggingTorque(tuple(cog.orders[i] for i in keep), cog.a[keep], cog.b[keep])

    def to_dict(self) -> dict:
        out: dict = {
            "status": self.status.value,
            "orders": [int(k) for k in self.orders],
            "tests": [t.to_dict() for t in self.tests],
            "message": self.message,
        }
        if self.spectrum is not None:
            out["evidence"] = self.spectrum.to_dict()
        return out


#: Batches below which the coefficients are tested with the white covariance: B batch means
#: give a T^2 test with B - 2 denominator degrees of freedom, powerless for a few batches (with
#: 3 batches the critical value of F(2, 1) at 1e-3 is about 2e6: a zoo motor's cogging at 60/rev
#: of the size of its load, fitted on 8 430 samples, was dropped and the table's offset came
#: out 12x the noise floor).
MIN_TEST_BATCHES = 10


def order_tests(sem: SEMResult, *, significance: float = 1e-3) -> tuple[OrderTest, ...]:
    """Hotelling's T^2 of each fitted cogging order with the batch-means covariance.

    ``T^2 = c_k^T V_k^-1 c_k`` for the coefficients c_k = (a_k, b_k) and their 2 x 2 block V_k of
    :attr:`SEMResult.batch_covariance`; ``T^2 (B - 2) / (2 (B - 1)) ~ F(2, B - 2)`` when c_k = 0,
    with B batches (Bonferroni over the orders). Order 0 (a constant load torque) has one
    coefficient a_0: ``T^2 = a_0^2 / V_00 ~ F(1, B - 1)`` (:func:`select_cogging` decides it with
    the HAC variance of :func:`load_test` instead). Below :data:`MIN_TEST_BATCHES`
    batches (short runs) V_k is the white covariance ``sigma^2 (J^T J)^-1`` and T^2 ~ chi^2(2)
    (chi^2(1) for order 0).
    """
    cog = sem.cogging
    layout = sem.layout
    if cog is None or layout is None:
        return ()
    B = int(sem.batches)
    white = B < MIN_TEST_BATCHES or sem.batch_covariance is None
    cov = sem.parameter_covariance if white else sem.batch_covariance
    if cov is None:
        return ()
    n = cog.size
    alpha = significance / max(n, 1)
    crit = -2.0 * math.log(alpha) if white else f2_isf(alpha, B - 2) * 2 * (B - 1) / (B - 2)
    tests = []
    x = cog.coefficients
    for i, k in enumerate(cog.orders):
        j = layout.cogging_start + 2 * i
        if k == 0:  # a constant load torque: a_0 alone (b_0 has no effect)
            v = float(cov[j, j])
            a0 = float(x[2 * i])
            t2 = a0 * a0 / v if v > 0 else 0.0
            crit0 = f1_isf(alpha, 1e9 if white else B - 1)
            tests.append(OrderTest(0, abs(a0), t2, crit0))
            continue
        V = cov[j : j + 2, j : j + 2]
        c = x[2 * i : 2 * i + 2]
        try:
            t2 = float(c @ np.linalg.solve(V, c))
        except np.linalg.LinAlgError:
            t2 = 0.0
        tests.append(OrderTest(int(k), float(np.hypot(*c)), t2, crit))
    return tuple(tests)


@dataclass(frozen=True)
class LoadTest:
    """Outcome of :func:`load_test`.

    Attributes
    ----------
    test : OrderTest
        Order 0's T^2 test with a_0's HAC variance (``threshold`` is ``inf`` when the run gives
        no long-run variance: the test cannot pass).
    long_run : LongRunVariance
        The functional's long-run variance behind it (zeros when there is none).
    """

    test: OrderTest
    long_run: LongRunVariance


def load_test(
    loop: ClosedLoop, r: ArrayLike, d: ArrayLike, sem: SEMResult, *, alpha: float,
    step: float = INFLUENCE_STEP,
) -> LoadTest:  # fmt: skip
    """Order 0's test with the HAC variance of a_0 (module docstring, "A constant load torque").

    ``a_0 - a_0* = v^T J^T e`` to first order with ``v = A^-1 e_a0``, ``A = J^T J + R``: the
    functional ``sum_t u_t^T e_t`` of the residual with the influence ``u_t = J_t v``, whose
    long-run variance :func:`hallcal.fit.long_run.functional_long_run` gives. u comes from two
    simulations of the model (central differences along v, a step moving a_0 by ``step`` times
    its white standard deviation: a relative error of order step^2). ``var a_0 = sigma^2
    (A^-1)_00`` times the functional's long-run over its lag-0 variance; ``T^2 = a_0^2 / var
    a_0 ~ F(1, dof)``.

    Parameters
    ----------
    loop : ClosedLoop
        The loop ``sem`` was solved with (no drift, no sample weights: the search's fits).
    r : array_like (N,)
        Its reference [rad].
    d : array_like (N, 3)
        Its Hall signals.
    sem : SEMResult
        A fit with order 0 among its cogging orders.
    alpha : float
        Level of this order's test (Bonferroni share).
    step : float
        Of the central differences, in a_0's white standard deviations
        (:data:`hallcal.fit.long_run.INFLUENCE_STEP`).

    Returns
    -------
    LoadTest
    """
    cog, layout, cov = sem.cogging, sem.layout, sem.parameter_covariance
    if cog is None or layout is None or cov is None or 0 not in cog.orders:
        raise ValueError("the fit has no constant load torque (order 0)")
    i = cog.orders.index(0)
    w = np.zeros(layout.size)
    w[layout.cogging_start + 2 * i] = 1.0  # a_0
    a0 = float(cog.coefficients[2 * i])
    lr = functional_long_run(loop, r, d, sem, w, step=step)
    if lr is None:
        return LoadTest(OrderTest(0, abs(a0), 0.0, math.inf), LongRunVariance(0.0, 0.0, 0.0, 0.0))
    var = lr.variance
    t2 = a0 * a0 / var if var > 0 else 0.0
    return LoadTest(OrderTest(0, abs(a0), t2, f1_isf(alpha, lr.dof)), lr)


def _with_load_test(
    loop: ClosedLoop, r: NDArray, d: NDArray, sem: SEMResult, tests: tuple[OrderTest, ...], *,
    significance: float,
) -> tuple[OrderTest, ...]:  # fmt: skip
    """``tests`` with order 0's decided by :func:`load_test` (module docstring, "A constant load
    torque"), Bonferroni over the fitted orders as :func:`order_tests`. Made when the
    batch-means or the white variance passes order 0 (else its test stands as failed): a run
    where neither does (the paper's bench without a load) is not charged the pass."""
    cog, layout, cov = sem.cogging, sem.layout, sem.parameter_covariance
    t0 = next((t for t in tests if t.order == 0), None)
    if t0 is None or cog is None or layout is None or cov is None:
        return tests
    alpha = significance / max(cog.size, 1)
    j = layout.cogging_start + 2 * cog.orders.index(0)
    vw = float(cov[j, j])  # the white variance sigma^2 (J^T J + R)^-1
    white = vw > 0 and t0.amplitude**2 / vw > f1_isf(alpha, 1e9)
    if not (t0.significant or white):
        return tests
    hac = load_test(loop, r, d, sem, alpha=alpha).test
    return tuple(hac if t.order == 0 else t for t in tests)


def _fit(
    loop: ClosedLoop,
    r: NDArray,
    d: NDArray,
    start: SEMResult,
    orders: tuple[int, ...],
    *,
    fit_gain: bool,
    max_iterations: int,
    covariance: str = "moved",
) -> SEMResult:
    """SEM with the start's flux (and gain) and cogging at ``orders``, each order's coefficients
    from the start's torque where it has them (zero otherwise).

    In the search, a fit from a zero torque that takes no step keeps it at zero (every order's
    statistic is zero and the fit is not kept): its covariance then comes from the iterations'
    system, without a pass for the exact one (``covariance="moved"``,
    :func:`~hallcal.fit.sem.solve_sem`); a warm start always gets the exact one.
    """
    known = start.cogging
    a, b = np.zeros(len(orders)), np.zeros(len(orders))
    if known is not None:
        for i, k in enumerate(orders):
            if k in known.orders:
                j = known.orders.index(k)
                a[i], b[i] = known.a[j], known.b[j]
    warm = bool(np.any(a) or np.any(b))
    return solve_sem(
        loop, r, d, start.flux.basis, theta0=start.flux.theta, fit_gain=fit_gain,
        gain0=start.gain if fit_gain else 1.0, cogging=CoggingTorque(orders, a, b),
        max_iterations=max_iterations, covariance="exact" if warm else covariance,
    )  # fmt: skip


#: Rounds of :func:`related_orders` after the first choice (each one joint fit or more).
MAX_EXPANSIONS = 2


def _pruned(
    loop: ClosedLoop, r: NDArray, d: NDArray, sem: SEMResult, candidates: tuple[int, ...], *,
    fit_gain: bool, max_iterations: int, significance: float,
) -> tuple[SEMResult, tuple[OrderTest, ...], tuple[int, ...]]:  # fmt: skip
    """Fit the candidates jointly, drop the orders whose T^2 test fails and refit until every
    order left is significant: (fit, its tests, orders); ``(sem, (), ())`` when none is."""
    tests: tuple[OrderTest, ...] = ()
    joint = sem
    while candidates:
        joint = _fit(loop, r, d, sem, candidates, fit_gain=fit_gain,
                     max_iterations=max_iterations)  # fmt: skip
        tests = _with_load_test(loop, r, d, joint, order_tests(joint, significance=significance),
                                significance=significance)  # fmt: skip
        kept = tuple(t.order for t in tests if t.significant)
        if kept == candidates:
            return joint, tests, candidates
        candidates = kept
    return sem, tests, ()


def select_cogging(
    loop: ClosedLoop,
    r: ArrayLike,
    d: ArrayLike,
    sem: SEMResult,
    *,
    orders: str | tuple[int, ...] = "auto",
    fit_gain: bool = False,
    max_order: int | None = None,
    significance: float = 1e-3,
    max_iterations: int = 50,
    load: bool = True,
    screen: float = 0.1,
) -> CoggingSelection:
    """Cogging orders and coefficients, identified jointly with theta (see the module docstring).

    Parameters
    ----------
    loop : ClosedLoop
        The loop model of ``sem`` (plant, controller, f_init).
    r, d : array_like
        Recorded reference (N,) and Hall signals (N, 3).
    sem : SEMResult
        The fit of the flux without cogging (its basis and theta start the joint fit).
    orders : "auto", "none" or tuple of int
        Choose the orders from the data, add nothing, or fit the given orders.
    fit_gain : bool
        Refine the plant input gain jointly (a BLA plant); ``loop`` is the loop ``sem`` was
        solved with, and the result's gain is relative to it.
    max_order : int, optional
        Highest order searched by "auto" (default :func:`default_max_order`).
    significance : float
        Family-wise false-alarm level of the test of the fitted coefficients.
    max_iterations : int
        Of each SEM.
    load : bool
        With "auto", also try a constant load torque (order 0; see the module docstring).
    screen : float
        Family-wise level of the spectrum's screen: a line passing it is only a candidate,
        kept when its fitted coefficients pass the test at ``significance``.

    Returns
    -------
    CoggingSelection
    """
    rr = np.ascontiguousarray(r, dtype=np.float64)
    dd = np.ascontiguousarray(d, dtype=np.float64)
    if orders == "none":
        return CoggingSelection(CoggingStatus.OFF, (), None, sem, message="cogging: not modelled")
    if orders != "auto":
        given = tuple(int(k) for k in orders)
        joint = _fit(loop, rr, dd, sem, given, fit_gain=fit_gain, max_iterations=max_iterations,
                     covariance="exact")  # fmt: skip
        return CoggingSelection(
            CoggingStatus.GIVEN, given, joint.cogging, joint, None,
            order_tests(joint, significance=significance), _describe(joint.cogging, "given"),
        )  # fmt: skip
    if not sem.status.success and not np.isfinite(sem.cost):
        return CoggingSelection(CoggingStatus.NONE, (), None, sem,
                                message="cogging: no search (the SEM fit failed)")  # fmt: skip
    K = int(max_order) if max_order else default_max_order(loop.pole_pairs)
    spectrum = shift_spectrum(sem, dd, max_order=K, significance=screen,
                              tested=plausible_orders(loop.pole_pairs, K))  # fmt: skip
    # a constant load torque (order 0) leaves no line in the spectrum: always tried
    zero = (0,) if load else ()
    candidates = tuple(sorted({*zero, *spectrum.candidates}))
    joint, tests, candidates = _pruned(
        loop,
        rr,
        dd,
        sem,
        candidates,
        fit_gain=fit_gain,
        max_iterations=max_iterations,
        significance=significance,
    )
    for _ in range(MAX_EXPANSIONS):
        # the harmonics of a found order and the fundamentals it may be a harmonic of, with the
        # load again: a flux model rich enough absorbs most of a torque's motion in the first
        # fit, so its line can be far below the screen (see the module docstring)
        related = related_orders(candidates, loop.pole_pairs, K)
        if not related:
            break
        wider = tuple(sorted({*candidates, *related, *zero}))
        # warm from the fit with the found orders (flux, gain and their coefficients)
        trial, trial_tests, kept = _pruned(loop, rr, dd, joint, wider, fit_gain=fit_gain,
                                           max_iterations=max_iterations,
                                           significance=significance)  # fmt: skip
        if kept == candidates or not kept:
            break
        joint, tests, candidates = trial, trial_tests, kept
    if any(k > 0 for k in candidates):
        joint, tests, candidates = _confirmed(loop, rr, dd, sem, joint, tests, candidates,
                                              fit_gain=fit_gain, max_iterations=max_iterations,
                                              significance=significance)  # fmt: skip
    if not candidates:
        msg = "cogging: none found (no line in the residual's shift along the flux curve"
        msg += " passed both tests" if spectrum.candidates else ""
        msg += "; no significant constant load torque)" if load else ")"
        return CoggingSelection(CoggingStatus.NONE, (), None, sem, spectrum, tests, msg)
    return CoggingSelection(
        CoggingStatus.FOUND, candidates, joint.cogging, joint, spectrum, tests,
        _describe(joint.cogging, "found in the data"),
    )  # fmt: skip


def sideband_basis(basis: FourierBasis, orders: tuple[int, ...]) -> FourierBasis:
    """The flux basis with the sidebands of the cogging orders that lie within its band.

    A rotor shift ``delta(y0)`` at order k moves the signals by ``g'(y0) delta(y0)``: content at
    the orders ``|k +- h|`` for the harmonics h of g. Where the basis lacks such an order but its
    band covers it (the harmonic selection keeps a sparse set), a torque at k is the cheapest
    way to fit the flux content there, whatever moved the rotor.

    Parameters
    ----------
    basis : FourierBasis
        The flux basis of the joint fit.
    orders : tuple of int
        Cogging orders (0 is ignored).

    Returns
    -------
    FourierBasis
        ``basis`` with every ``|k +- h| <= max(basis.harmonics)`` added (the same basis when
        none is missing).
    """
    have = set(basis.harmonics)
    top = max(have, default=0)
    add = {
        j
        for k in orders
        if k > 0
        for h in have
        for j in (abs(k - h), k + h)
        if 1 <= j <= top and j not in have
    }
    return basis if not add else FourierBasis(tuple(sorted(have | add)))


def _confirmed(
    loop: ClosedLoop, r: NDArray, d: NDArray, sem: SEMResult, joint: SEMResult,
    tests: tuple[OrderTest, ...], candidates: tuple[int, ...], *, fit_gain: bool,
    max_iterations: int, significance: float,
) -> tuple[SEMResult, tuple[OrderTest, ...], tuple[int, ...]]:  # fmt: skip
    """The orders k > 0 that stay significant when the flux basis holds their sidebands.

    A torque of order k and a flux error differ only through the loop's dynamics (the motion a
    torque causes passes the loop's sensitivity at k times the speed): in a constant-speed run
    the torque's shift is, to first order, flux content at the sidebands ``|k +- h|``. With a
    sparse flux basis, a torque at k collects the small flux harmonics the selection left out
    (each below its own test, together a line in the shift spectrum). Measured on the unseen
    zoo's motor 179 (adc12, 14 pole pairs, no cogging in its truth; noise draw 4, 28 harmonics
    up to 70): a torque at 28 = 2 n_m passed with T^2 = 103 (threshold 19.8) and left the table
    3.0x the noise floor (1.36x without it); refitted with the 27 sideband harmonics of 28 in
    the band added, T^2 = 6.8. So every order k > 0 is tested again in one joint fit on
    :func:`sideband_basis` (warm from the joint fit); the orders failing there are dropped and
    the rest refitted on the original basis (:func:`_pruned`). The order 0 (a constant load)
    has no sidebands and is not retested.
    """
    wide = sideband_basis(sem.flux.basis, candidates)
    if wide is sem.flux.basis:
        return joint, tests, candidates
    from hallcal.fit.order import restrict_theta  # the harmonic search's module, loaded lazily

    torque = candidates if joint.cogging is None else joint.cogging  # warm: the joint torque
    check = solve_sem(
        loop, r, d, wide, theta0=restrict_theta(joint.flux, wide), fit_gain=fit_gain,
        gain0=joint.gain if fit_gain else 1.0, cogging=torque, max_iterations=max_iterations,
    )  # fmt: skip
    failed = {t.order for t in order_tests(check, significance=significance)
              if t.order > 0 and not t.significant}  # fmt: skip
    if not failed:
        return joint, tests, candidates
    kept = tuple(k for k in candidates if k not in failed)
    return _pruned(loop, r, d, sem, kept, fit_gain=fit_gain, max_iterations=max_iterations,
                   significance=significance)  # fmt: skip


def related_orders(found: tuple[int, ...], pole_pairs: int, max_order: int) -> tuple[int, ...]:
    """Orders a cogging torque with lines at ``found`` is likely to have as well.

    The cogging torque of Q slots against 2 n_m poles repeats LCM(Q, 2 n_m) times per revolution
    and is not sinusoidal, so its lines lie at the multiples of that fundamental (Zhu & Howe
    2000, "Influence of design parameters on cogging torque in permanent magnet machines"). A
    found order k > 0 is either the fundamental (its multiples follow) or one of its harmonics
    (the fundamental is a divisor of k that is a multiple of 2 n_m). Measured on zoo motor 94
    (2 pole pairs, true orders 0, 12 and 24): the first fit's flux absorbed most of the motion at
    12/rev (its line 3x the local level, the test at 16x), only 24 was found and the table came
    out 9.2x the noise floor; with 0 and 12 fitted as well, 1.7x.

    Parameters
    ----------
    found : tuple of int
        Orders found (0, a load, is ignored).
    pole_pairs : int
        n_m.
    max_order : int
        Highest order.

    Returns
    -------
    tuple of int
        The multiples of 2 n_m up to ``max_order`` that divide or are multiples of a found order,
        without the found ones.
    """
    out: set[int] = set()
    for k in (int(v) for v in found if int(v) > 0):
        out.update(j for j in plausible_orders(pole_pairs, max_order) if k % j == 0 or j % k == 0)
    return tuple(sorted(out - {int(v) for v in found}))


def _describe(cog: CoggingTorque | None, how: str) -> str:
    if cog is None or not cog.size:
        return "cogging: none"
    parts = [
        f"constant load {a:.3g}" if k == 0 else f"{k}/rev {A:.3g} at {math.degrees(p):.1f} deg"
        for k, A, p, a in zip(cog.orders, cog.amplitude, cog.phase, cog.a, strict=True)
    ]
    return f"cogging torque ({how}, plant input units): " + ", ".join(parts)
