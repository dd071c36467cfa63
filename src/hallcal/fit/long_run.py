"""Long-run (HAC) variance of a linear functional of the SEM's parameters.

A functional ``w^T x`` of the fitted parameters x (a constant load a_0, the table's offset) moves
to first order by ``w^T A^-1 J^T e`` (``A = J^T J + R``): the functional ``sum_t u_t^T e_t`` of
the residual e with the influence ``u_t = J_t A^-1 w``. Its white variance is
``sigma^2 w^T A^-1 w``; where the residual is coloured (unmodelled motion in the closed loop) and
the influence sits in a short stretch of the run (the start transient), neither the white nor the
batch-means covariance of the scores is right: the batch-means one rests on the few batches the
influence covers. :func:`hac_variance` takes the residual's auto- and cross-covariances from the
WHOLE run (Newey & West 1987, Bartlett kernel; Andrews 1991 for the bandwidth), and
:func:`functional_long_run` applies it to a functional of a fit, with the influence from two
simulations of the model. Used by the cogging search's test of a constant load
(:func:`hallcal.fit.cogging_search.load_test`) and the table offset's variance
(:mod:`hallcal.fit.offset_variance`).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.fit.gauss_newton import simulate_model
from hallcal.fit.sem import SEMResult
from hallcal.sim.loop import ClosedLoop

__all__ = [
    "INFLUENCE_STEP",
    "FunctionalInfluence",
    "LongRunVariance",
    "functional_influence",
    "functional_long_run",
    "hac_variance",
]

#: Step of the central differences that give the influence ``u_t = J_t v`` of a functional
#: ``w^T x`` (:func:`functional_long_run`): the two simulations of the model are at ``x +- h v``,
#: ``v = A^-1 w``, with ``h`` chosen so that the functional moves by this many of its white
#: standard deviations ``sqrt(sigma^2 w^T A^-1 w)`` (dimensionless; relative to the
#: functional's own uncertainty, so the same for a load a_0 [torque] and the table's offset
#: [rad]). 0.01, a hundredth of the fit's own uncertainty: deep in the range where the model is
#: linear in x, so the central difference's relative error, of order step^2, is about 1e-4, while
#: the two simulations still differ far above float64 rounding.
INFLUENCE_STEP = 0.01


@dataclass(frozen=True)
class LongRunVariance:
    """A HAC (long-run) variance of a linear functional of the residual and its reference.

    Attributes
    ----------
    variance : float
        ``sum_|l|<S (1 - |l| / S) sum_t u_t^T Gamma(l) u_t+l`` (see :func:`hac_variance`).
    bandwidth : float
        Andrews' (1991) bandwidth S [samples] (Bartlett kernel, AR(1) plug-in).
    dof : float
        Degrees of freedom of ``variance``: ``1.5 N / S`` for N samples, the Bartlett
        kernel's (its relative variance ``(4 / 3) S / N``, Andrews 1991, Prop. 1).
    white : float
        The same functional's variance with the lag-0 covariance alone (white residual).
    """

    variance: float
    bandwidth: float
    dof: float
    white: float


def _lagged_products(a: NDArray, b: NDArray, lags: int) -> NDArray[np.float64]:
    """``P[l + lags, h, g] = sum_t a[t, h] b[t + l, g]`` for ``l = -lags..lags`` (FFT)."""
    n = a.shape[0]
    nfft = 1 << int(math.ceil(math.log2(max(n + lags + 1, 2))))
    A = np.fft.rfft(a, n=nfft, axis=0)
    B = np.fft.rfft(b, n=nfft, axis=0)
    full = np.fft.irfft(np.conj(A)[:, :, None] * B[:, None, :], n=nfft, axis=0)
    return np.concatenate([full[nfft - lags :], full[: lags + 1]], axis=0)


def hac_variance(
    u: ArrayLike, e: ArrayLike, *, dof_used: int = 0, bandwidth: float | None = None
) -> LongRunVariance:
    """Long-run variance of ``sum_t u_t^T e_t`` for a stationary residual e, Bartlett kernel.

    ``var = sum_|l|<S k(l / S) sum_{h, g} Gamma_hg(l) sum_t u_t,h u_t+l,g`` with the residual's
    auto- and cross-covariances ``Gamma_hg(l) = sum_t e_t,h e_t+l,g / (N - dof_used / c)``
    (c channels) estimated over the whole run, the Bartlett kernel ``k(x) = 1 - |x|`` (Newey &
    West 1987) and Andrews' (1991, eq. 6.4) AR(1) plug-in bandwidth
    ``S = 1.1447 (alpha(1) N)^(1/3)``, ``alpha(1) = sum_h 4 rho_h^2 s_h^4 / ((1 - rho_h)^6
    (1 + rho_h)^2) / sum_h s_h^4 / (1 - rho_h)^4`` from each channel's lag-one autocorrelation
    rho_h (within +-0.97) and variance s_h^2; S at most N / 12. It is the HAC variance of the
    score series ``psi_t = u_t^T e_t`` with its autocovariances taken as
    ``u_t^T Gamma(l) u_t+l``: a weight u that sits in a short stretch of the run (order 0 under
    an integrating controller) is judged against the residual's autocorrelation from all N
    samples (``1.5 N / S`` degrees of freedom), not against the few samples it covers.

    Parameters
    ----------
    u : array_like (N, c)
        Weights (the influence ``J_t v`` of the functional ``v^T x``).
    e : array_like (N, c)
        Residual.
    dof_used : int
        Parameters fitted to e (their share per channel is taken off N, as sigma^2 does).
    bandwidth : float, optional
        S [samples] instead of Andrews' plug-in (at most N / 12 all the same): a fixed fraction
        of N (:func:`hallcal.fit.offset_variance.offset_excess`).

    Returns
    -------
    LongRunVariance
    """
    ua = np.asarray(u, dtype=np.float64)
    ea = np.asarray(e, dtype=np.float64)
    uu = ua.reshape(ua.shape[0], -1)
    ee = ea.reshape(ea.shape[0], -1)
    n, c = ee.shape
    ee = ee - ee.mean(axis=0)
    g0 = np.einsum("th,th->h", ee, ee)
    g1 = np.einsum("th,th->h", ee[:-1], ee[1:])
    ok = g0 > 0
    if n < 12 or not ok.any():
        return LongRunVariance(0.0, 0.0, 0.0, 0.0)
    rho = np.clip(g1[ok] / g0[ok], -0.97, 0.97)
    s4 = (g0[ok] / n) ** 2
    alpha1 = float(np.sum(4 * rho**2 * s4 / ((1 - rho) ** 6 * (1 + rho) ** 2))
                   / np.sum(s4 / (1 - rho) ** 4))  # fmt: skip
    S = 1.1447 * (alpha1 * n) ** (1.0 / 3.0) if bandwidth is None else float(bandwidth)
    S = min(S, n / 12.0)
    lags = max(math.ceil(S) - 1, 0)
    norm = max(n - dof_used / c, 1.0)
    gam = _lagged_products(ee, ee, lags) / norm  # Gamma(l), l = -lags..lags
    cu = _lagged_products(uu, uu, lags)
    ell = np.arange(-lags, lags + 1)
    k = 1.0 - np.abs(ell) / S if S > 0 else (ell == 0).astype(float)
    var = float(np.einsum("l,lhg,lhg->", k, gam, cu))
    white = float(np.einsum("hg,hg->", gam[lags], cu[lags]))
    return LongRunVariance(max(var, 0.0), S, 1.5 * n / max(S, 1.0), white)


@dataclass(frozen=True)
class FunctionalInfluence:
    """Outcome of :func:`functional_influence`.

    Attributes
    ----------
    u : ndarray (N, 3)
        The influence: the functional moves by ``sum_t u_t^T e_t`` to first order for a
        residual e (Hall signal units).
    white : float
        Its white variance ``sigma^2 w^T A^-1 w`` (the functional's unit squared).
    """

    u: NDArray[np.float64]
    white: float


def functional_influence(
    loop: ClosedLoop,
    r: ArrayLike,
    sem: SEMResult,
    w: NDArray[np.float64],
    *,
    step: float = INFLUENCE_STEP,
) -> FunctionalInfluence | None:
    """The influence ``u_t = J_t A^-1 w`` of the functional ``w^T x`` and its white variance.

    ``v = A^-1 w`` from the fit's covariance, ``u`` by central differences of two simulations
    of the model along v (a step moving the functional by ``step`` times its white standard
    deviation: a relative error of order step^2).

    Parameters
    ----------
    loop, r, sem, w, step
        As :func:`functional_long_run`.

    Returns
    -------
    FunctionalInfluence or None
        None when the fit has no parameter covariance or a simulation fails.
    """
    cov, layout = sem.parameter_covariance, sem.layout
    if cov is None or layout is None or not sem.noise_variance > 0:
        return None
    v = cov @ w / sem.noise_variance  # A^-1 w
    white = float(w @ cov @ w)
    gain = math.log(sem.gain) if layout.fit_gain else 0.0
    x = layout.pack(sem.flux.theta, gain, sem.cogging, sem.drift)
    h = step * math.sqrt(max(white, 0.0)) / max(float(w @ v), 1e-300)
    if not (h > 0 and math.isfinite(h)):
        return None
    with ThreadPoolExecutor(1) as pool:  # the kernel releases the GIL: one on each core
        later = pool.submit(simulate_model, loop, layout, x - h * v, r)
        up = simulate_model(loop, layout, x + h * v, r)
        down = later.result()
    if not (up.status.success and down.status.success):
        return None
    return FunctionalInfluence((up.d - down.d) / (2.0 * h), white)


def functional_long_run(
    loop: ClosedLoop,
    r: ArrayLike,
    d: ArrayLike,
    sem: SEMResult,
    w: NDArray[np.float64],
    *,
    step: float = INFLUENCE_STEP,
    bandwidth: float | None = None,
) -> LongRunVariance | None:
    """The HAC variance of the functional ``w^T x`` of the fit's parameters (module docstring).

    ``v = A^-1 w`` from the fit's covariance, the influence ``u_t = J_t v`` by central
    differences of two simulations of the model along v (a step moving the functional by
    ``step`` times its white standard deviation: a relative error of order step^2), and the
    variance ``sigma^2 w^T A^-1 w`` times the long-run over the lag-0 variance of
    ``sum_t u_t^T e_t`` (:func:`hac_variance`): where A is nearly singular (condition 1e15 on
    the paper's bench) the computed v is off in A's near-null directions and ``|J v|^2`` is not
    ``w^T v`` (1.9x there); its shape in time is what the ratio uses.

    Parameters
    ----------
    loop : ClosedLoop
        The loop ``sem`` was solved with.
    r : array_like (N,)
        Its reference [rad].
    d : array_like (N, 3)
        The Hall signals it fitted.
    sem : SEMResult
        The fit (with its parameter covariance and layout).
    w : ndarray (P,)
        The functional over the fit's packed parameters (:class:`hallcal.fit.layout` order).
    step : float, keyword-only
        Of the central differences, in the functional's white standard deviations
        (:data:`INFLUENCE_STEP`).
    bandwidth : float, optional, keyword-only
        S [samples] for :func:`hac_variance` (default: Andrews' plug-in).

    Returns
    -------
    LongRunVariance or None
        ``variance`` the HAC one, ``white`` ``sigma^2 w^T A^-1 w``; None when the fit has no
        parameter covariance or a simulation fails.
    """
    found = functional_influence(loop, r, sem, w, step=step)
    if found is None or sem.layout is None:  # no layout: no influence either
        return None
    u, white = found.u, found.white
    e = np.asarray(d, dtype=np.float64) - sem.d_sim
    lr = hac_variance(u, e, dof_used=sem.layout.size, bandwidth=bandwidth)
    var = white * lr.variance / lr.white if lr.white > 0 else 0.0
    return LongRunVariance(var, lr.bandwidth, lr.dof, white)
