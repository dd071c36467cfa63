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
HAC counts a misfit periodic in the angle as noise, 2.0x the white sd on the paper's bench
whose offsets follow the white one; with the motion bias it counts the motion twice).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.fit._table_error import _theta_covariances
from hallcal.fit.long_run import INFLUENCE_STEP, LongRunVariance, functional_long_run
from hallcal.fit.sem import SEMResult, angle_error_gradient
from hallcal.sim.loop import ClosedLoop

__all__ = ["BANDWIDTH_FRACTION", "OffsetExcess", "offset_excess", "offset_long_run"]

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
    layout = sem.layout
    if layout is None:
        return None
    w = np.zeros(layout.size)
    w[: c.size] = c  # theta first in the layout
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
