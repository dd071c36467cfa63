"""The table's constant offset: its long-run (HAC) variance, where the residual is coloured.

The predicted table error (:mod:`hallcal.fit._table_error`) propagates the larger of the white
``sigma^2 (J^T J)^-1`` and the batch-means covariance of theta. The table's constant offset is
one linear functional of theta, ``c^T theta`` with ``c`` the mean over the revolution of
``d eta / d theta`` (:func:`hallcal.fit.sem.angle_error_gradient`). Both covariances can miss it:
the white one assumes a white residual, the batch-means one sees the offset in the few batches
where its influence lives (the start of the run). A random load torque (the paper's bench with a
torque disturbance of std 2e-3, 5 Hz low-pass, at 4 kHz) leaves in the residual a slow
component far below the Hall noise per sample but dominant at low frequencies, along which the
offset is fitted: over six bench seeds its offset was 0.65x the noise floor RMS against 0.10x
(white) and 0.04-0.07x (batch) predicted (``benchmarks/bench_offset_hac.txt``).

Its variance here is the HAC (heteroscedasticity-and-autocorrelation-consistent) variance of
:func:`hallcal.fit.long_run.hac_variance` for the functional: the influence
``u_t = J_t A^-1 c`` from two model simulations along ``A^-1 c``
(:func:`hallcal.fit.long_run.functional_long_run`, as for a constant load in
:func:`hallcal.fit.cogging_search.load_test`), the residual's auto- and cross-covariances over
the whole run, the Bartlett kernel (Newey & West 1987), and ``sigma^2 c^T A^-1 c`` times the
long-run / lag-0 ratio of ``sum_t u_t^T e_t``. The bandwidth is a fixed fraction of the run,
N / 12 (a "fixed-b" bandwidth, Kiefer & Vogelsang 2005: robust to strong autocorrelation at the
cost of a noisier estimate, 1.5 N / S = 18 degrees of freedom), not Andrews' (1991) AR(1)
plug-in: the plug-in reads the residual's lag-one autocorrelation, which the white Hall noise
dominates (0.22 on the disturbed bench), and chose S = 32 samples, where the ratio had not
levelled off (sd ratio 3.1 at S = 30, 5.7 at 300, 7.2 at 1000, 7.7 at 3000; the offsets asked
for 6.5). With it the offsets' z-scores over the six seeds have RMS 0.78 (6.46 with the white
sd), actual/predicted 1.00-1.39 -> 0.79-1.08. On the zoo's healthy motors the ratio stays at
0.93-1.05 at every bandwidth.

The prediction uses it only where the run shows unmodelled motion: the cost above its warning
level and no motion bias (:func:`hallcal.fit._table_error._table` says why: without motion the
HAC cannot tell a misfit periodic in the angle from noise, a run of one or two revolutions
being too short; with the motion bias it counts the motion twice).

Without any unmodelled motion the white covariance still misses one thing: the drive's loop ran
on f_init of the NOISY signals, so the Hall noise moved the rotor, and the SEM's noise-free
simulation has none of that motion. :func:`offset_loop_noise` gives the offset's variance with
it, to first order and from the model alone (no residual, no bandwidth), and the prediction
takes it wherever it exceeds both covariances' (:func:`offset_loop_excess`, with or without
motion). Measured with the oracle (``benchmarks/bench_bias193.txt``): zoo motor 193, whose
table was "ok" at 1.239x the floor with 1.018x predicted (offset -0.70x the floor, 3.9 white
sd's), has the truth's harmonics 1..25 in its model; its offset shrinks with the noise (-0.70,
-0.13, -0.013x the floor at 1, 0.1 and 0.01 times its sigma: no bias), over ten noise draws the
offsets were 2.29 white sd's RMS, and 0.96 when the same noise was added to signals whose loop
had run noise-free; the loop-noise sd is 2.30x the white one (RMS z 1.07). Over ten seeds of
the paper's bench with ideal sensors the offsets were 2.13 white sd's RMS and 1.06 loop-noise
sd's (1.86-2.25x the white; with the paper's magnets, six seeds: 2.52 -> 1.21). So the HAC's
2.0x the white sd on the paper's bench, once blamed on a periodic misfit, was mostly this noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.fit._table_error import _theta_covariances
from hallcal.fit.long_run import (
    INFLUENCE_STEP,
    LongRunVariance,
    functional_influence,
    functional_long_run,
)
from hallcal.fit.sem import SEMResult, angle_error_gradient
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "BANDWIDTH_FRACTION",
    "LoopNoiseExcess",
    "OffsetExcess",
    "offset_excess",
    "offset_long_run",
    "offset_loop_excess",
    "offset_loop_noise",
]

#: The HAC bandwidth as a fraction of the run's samples (module docstring; the cap of
#: :func:`hallcal.fit.long_run.hac_variance`).
BANDWIDTH_FRACTION = 1.0 / 12.0


@dataclass(frozen=True)
class OffsetExcess:
    """What the table offset's HAC variance adds to the predicted error (:func:`offset_excess`).

    Attributes
    ----------
    excess : float
        ``sqrt(max(0, hac - max(white, batch)))`` [rad]: the offset's HAC standard deviation
        beyond what the white and batch-means covariances already give it, to be added in
        quadrature to the predicted table error; 0 when the HAC variance is no larger or cannot
        be had (no covariance, a simulation or the gradient failing).
    long_run : LongRunVariance or None
        The offset's HAC variance [rad^2] (:func:`offset_long_run`); None when it cannot be had.
    """

    excess: float
    long_run: LongRunVariance | None


def _offset_functional(loop: ClosedLoop, sem: SEMResult) -> NDArray[np.float64]:
    """``c``: the table's constant offset is ``c^T theta`` to first order [rad per theta]."""
    G = angle_error_gradient(sem.flux, loop.pole_pairs, projection=loop.projection,
                             offset=loop.offset)  # fmt: skip
    return G.mean(axis=0)


def _over_parameters(sem: SEMResult, c: NDArray) -> NDArray[np.float64] | None:
    """The offset functional ``c`` (over theta) over the fit's packed parameters (theta first in
    :class:`hallcal.fit.layout`); None without a layout."""
    if sem.layout is None:
        return None
    w = np.zeros(sem.layout.size)
    w[: c.size] = c
    return w


def offset_long_run(
    loop: ClosedLoop, r: ArrayLike, d: ArrayLike, sem: SEMResult, *, step: float = INFLUENCE_STEP
) -> LongRunVariance | None:
    """The HAC variance [rad^2] of the table's constant offset ``c^T theta`` (module docstring).

    Parameters
    ----------
    loop : ClosedLoop
        The loop ``sem`` was solved with (its projection and offset are f_init's).
    r : array_like (N,)
        Its reference [rad].
    d : array_like (N, 3)
        The Hall signals it fitted.
    sem : SEMResult
        The final fit.
    step : float, keyword-only
        Of the central differences along ``A^-1 c``, in the offset's white standard deviations
        (:data:`hallcal.fit.long_run.INFLUENCE_STEP`).

    Returns
    -------
    LongRunVariance or None
        ``variance`` the HAC one, ``white`` ``sigma^2 c^T A^-1 c``; None when the fit has no
        parameter covariance or a simulation fails.
    """
    return _long_run(loop, r, d, sem, _offset_functional(loop, sem), step=step)


def _long_run(
    loop: ClosedLoop, r: ArrayLike, d: ArrayLike, sem: SEMResult, c: NDArray, *, step: float
) -> LongRunVariance | None:
    """:func:`offset_long_run` with the offset functional ``c`` already formed."""
    w = _over_parameters(sem, c)
    if w is None:
        return None
    return functional_long_run(
        loop, r, d, sem, w, step=step, bandwidth=BANDWIDTH_FRACTION * np.shape(d)[0]
    )


def offset_excess(loop: ClosedLoop, r: ArrayLike, d: ArrayLike, sem: SEMResult) -> OffsetExcess:
    """What the offset's HAC variance adds to the predicted table error [rad].

    The offset part of the prediction is the largest of its white, batch-means
    (:func:`hallcal.fit._table_error._theta_covariances`) and HAC (:func:`offset_long_run`)
    variances; the first two are in the prediction already, so this is
    ``sqrt(max(0, hac - max(white, batch)))``, to be added in quadrature to the predicted error
    (a constant over the revolution: about zero it adds its variance to the mean square).

    Parameters
    ----------
    loop, r, d, sem
        As :func:`offset_long_run`.

    Returns
    -------
    OffsetExcess
        The excess [rad] and the offset's HAC variance it rests on.
    """
    try:
        c = _offset_functional(loop, sem)  # formed once for the HAC and both covariances
        lr = _long_run(loop, r, d, sem, c, step=INFLUENCE_STEP)
        if lr is None or not math.isfinite(lr.variance):
            return OffsetExcess(0.0, lr)
        now = max(float(c @ C @ c) for C in _theta_covariances(sem))
    except (ValueError, np.linalg.LinAlgError):  # the prediction stands as it was
        return OffsetExcess(0.0, None)
    return OffsetExcess(math.sqrt(max(lr.variance - now, 0.0)), lr)


def _noise_to_angle(loop: ClosedLoop, n: int) -> NDArray[np.float64]:
    """Impulse response (n samples) of the closed loop from an angle error added to f_init's
    output to the rotor angle y0: ``-C G / (1 + C G)`` with unit slope of the sensor map, the
    controller acting on ``e_k = r_k - y_k`` within the sample. From the state space (the
    paper's C(q) cancels the plant's integrator: a transfer function's polynomials would carry
    the cancelled mode), its Markov parameters ``C A^(k-1) B`` by doubling."""
    p, c = loop.plant, loop.controller
    a, m = p.order, c.order
    A = np.zeros((a + m, a + m))
    A[:a, :a] = p.A - c.D * np.outer(p.B, p.C)
    A[:a, a:] = np.outer(p.B, c.C)
    A[a:, :a] = -np.outer(c.B, p.C)
    A[a:, a:] = c.A
    X = np.concatenate([-c.D * p.B, -c.B])[:, None]  # A^j B, j = 0 .. cols - 1
    power = A
    while X.shape[1] < n - 1:
        X = np.hstack([X, power @ X])
        power = power @ power
    h = np.zeros(n)
    h[1:] = (np.concatenate([p.C, np.zeros(m)]) @ X)[: n - 1]  # no feedthrough: h_0 = 0
    return h


def offset_loop_noise(loop: ClosedLoop, r: ArrayLike, sem: SEMResult) -> float | None:
    """Variance [rad^2] of the table's constant offset with the Hall noise fed back by the loop.

    The SEM simulates the loop without noise, but the drive's loop acted on f_init of the NOISY
    signals: the rotor moved by ``delta = M nu`` away from the noise-free simulation (``nu_t =
    K_t^T n_t`` the angle noise, K the gradient of f_init, M the closed loop
    :func:`_noise_to_angle`), so the data are ``d_t = g(y0_sim,t) + g'_t delta_t + n_t`` and the
    offset ``c^T theta`` moves by ``sum_t u_t^T (n_t + g'_t delta_t)`` (u its influence,
    :func:`hallcal.fit.long_run.functional_influence`) ``= sum_s (u_s + K_s b_s)^T n_s`` with
    ``b = M^T a``, ``a_t = u_t^T g'_t`` (the adjoint of the loop: M run backwards in time). Its
    variance is ``sigma^2 sum_s |u_s + K_s b_s|^2``, reported as the white ``sigma^2 c^T A^-1 c``
    times ``sum |u + K b|^2 / sum |u|^2`` (as :func:`hallcal.fit.long_run.functional_long_run`
    scales its ratio). A first-order variance from the model and the noise level, not estimated
    from the residual: it needs no bandwidth and mistakes no periodic misfit for noise. The
    offset is where it matters: only the start of the run informs it, where the rotor's
    noise-driven wander is not averaged out, and the batch-means covariance sees that stretch
    in one batch.

    Measured on zoo motor 193 (``benchmarks/bench_zoo.py``; 5 pole pairs, fs 16 kHz, 25 000
    samples, the model holding the truth's harmonics 1..25): over ten noise draws the offsets
    were 2.29 white standard deviations RMS, 0.96 with the same noise added to signals whose
    loop ran noise-free (the premise of the white covariance); this variance puts the offset's
    standard deviation at 2.30x the white one, and the offsets at 1.07 of it RMS
    (``benchmarks/bench_bias193.txt``).

    Parameters
    ----------
    loop : ClosedLoop
        The loop ``sem`` was solved with.
    r : array_like (N,)
        Its reference [rad].
    sem : SEMResult
        The final fit.

    Returns
    -------
    float or None
        The variance; None when the fit has no covariance or a simulation fails.
    """
    try:
        return _loop_noise(loop, r, sem, _offset_functional(loop, sem))
    except (ValueError, np.linalg.LinAlgError):
        return None


def _loop_noise(loop: ClosedLoop, r: ArrayLike, sem: SEMResult, c: NDArray) -> float | None:
    """:func:`offset_loop_noise` with the offset functional ``c`` already formed."""
    w = _over_parameters(sem, c)
    if w is None:
        return None
    found = functional_influence(loop, r, sem, w)
    if found is None:
        return None
    u, white = found.u, found.white
    a = np.einsum("th,th->t", u, sem.flux.derivative(sem.y0_sim))  # u_t^T g'_t
    with np.errstate(over="ignore", invalid="ignore"):  # an unstable linearization: None below
        h = _noise_to_angle(loop, a.size)
    if not np.all(np.isfinite(h)):
        return None
    nfft = 1 << int(math.ceil(math.log2(2 * a.size)))  # linear, not circular, convolution
    # M^T a: M run backwards in time (numpy's FFT: calibrate loads no scipy.signal)
    b = np.fft.irfft(np.fft.rfft(a[::-1], nfft) * np.fft.rfft(h, nfft), nfft)[: a.size][::-1]
    ab = (np.asarray(sem.d_sim, dtype=np.float64) - loop.offset) @ loop.projection.T
    rho2 = np.maximum(np.einsum("tk,tk->t", ab, ab), 1e-300)
    # K_t = d f_init / d d at the model's signals: d atan2(beta, alpha) / n_m
    K = (ab[:, :1] * loop.projection[1] - ab[:, 1:] * loop.projection[0]) / (
        rho2[:, None] * loop.pole_pairs
    )
    uu = float(np.sum(u * u))
    v = u + K * b[:, None]
    ratio = float(np.sum(v * v)) / uu if uu > 0 else math.nan
    return white * ratio if math.isfinite(ratio) else None


@dataclass(frozen=True)
class LoopNoiseExcess:
    """Outcome of :func:`offset_loop_excess`.

    Attributes
    ----------
    excess : float
        How far the loop-noise variance exceeds both covariances' offset variance [rad^2]; 0
        when it does not or cannot be had.
    variance : float or None
        The loop-noise variance of the offset [rad^2] (:func:`offset_loop_noise`); None when it
        cannot be had.
    """

    excess: float
    variance: float | None


def offset_loop_excess(loop: ClosedLoop, r: ArrayLike, sem: SEMResult) -> LoopNoiseExcess:
    """How far the offset's loop-noise variance (:func:`offset_loop_noise`) exceeds the offset
    variance of both covariances (:func:`hallcal.fit._table_error._theta_covariances`).

    Parameters
    ----------
    loop, r, sem
        As :func:`offset_loop_noise`.

    Returns
    -------
    LoopNoiseExcess
    """
    try:
        c = _offset_functional(loop, sem)
        var = _loop_noise(loop, r, sem, c)
        if var is None:
            return LoopNoiseExcess(0.0, None)
        now = max(float(c @ C @ c) for C in _theta_covariances(sem))
    except (ValueError, np.linalg.LinAlgError):
        return LoopNoiseExcess(0.0, None)
    return LoopNoiseExcess(max(var - now, 0.0), var)
