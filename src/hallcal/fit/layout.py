"""The SEM parameter vector: flux theta, plant gain, cogging torque and sensor drift.

Problem (problem) of van Meer et al. with the extensions of :mod:`hallcal.fit.sem`: theta of
the flux model (eq. basis), optionally ``log c`` (the BLA gain of eq. c_hat), the coefficients
of a cogging torque at the plant input (:mod:`hallcal.sim.cogging`) and the sensors' gain and
offset linear in time (:mod:`hallcal.fit.drift`). :mod:`hallcal.fit.gauss_newton` forms the
Gauss-Newton system over this layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.sensor.flux import FourierBasis
from hallcal.sim.cogging import CoggingTorque

__all__ = ["ParameterLayout"]


@dataclass(frozen=True)
class ParameterLayout:
    """Layout of the SEM parameter vector ``x = [theta, log c, a_1, b_1, a_2, b_2, ...]``.

    Parameters
    ----------
    basis : FourierBasis
        The flux model's basis (any set of harmonics); theta occupies ``3 m`` entries,
        sensor-major (row h of the (3, m) theta is sensor h).
    fit_gain : bool
        Whether ``log c`` (a factor c on the plant input matrix) follows theta.
    cogging_orders : tuple of int
        Orders k of the cogging torque whose coefficients ``(a_k, b_k)`` follow; order 0 is
        a constant load torque a_0 (its b_0 has a zero column: :attr:`inert` lists it).
    fit_drift : bool
        Whether the sensors' gain and offset drifts ``(gamma_1, delta_1, ..., gamma_3,
        delta_3)`` come last: the model signal of sensor h is
        ``(1 + gamma_h tau) g_h(y0) + delta_h tau`` with ``tau = k / (N - 1) - 1/2`` over the
        run (:mod:`hallcal.fit.drift`), so theta is the sensors at the run's middle.
    """

    basis: FourierBasis
    fit_gain: bool = False
    cogging_orders: tuple[int, ...] = ()
    fit_drift: bool = False

    def __post_init__(self) -> None:
        k = tuple(int(v) for v in self.cogging_orders)
        if len(set(k)) != len(k) or any(v < 0 for v in k):
            raise ValueError("cogging orders must be distinct integers >= 0")
        object.__setattr__(self, "cogging_orders", k)
        object.__setattr__(self, "fit_gain", bool(self.fit_gain))
        object.__setattr__(self, "fit_drift", bool(self.fit_drift))

    @property
    def n_theta(self) -> int:
        """3 m."""
        return 3 * self.basis.size

    @property
    def gain_index(self) -> int:
        """Index of log c (-1 without it)."""
        return self.n_theta if self.fit_gain else -1

    @property
    def cogging_start(self) -> int:
        """Index of a_1."""
        return self.n_theta + (1 if self.fit_gain else 0)

    @property
    def cogging_stop(self) -> int:
        """One past the last cogging coefficient."""
        return self.cogging_start + 2 * len(self.cogging_orders)

    @property
    def inert(self) -> tuple[int, ...]:
        """Indices of x without effect on the loop: b_0 of a cogging order 0 (sin 0 = 0)."""
        return tuple(
            self.cogging_start + 2 * i + 1 for i, k in enumerate(self.cogging_orders) if k == 0
        )

    @property
    def drift_start(self) -> int:
        """Index of gamma_1 (-1 without the drift)."""
        return self.cogging_stop if self.fit_drift else -1

    @property
    def size(self) -> int:
        """p."""
        return self.cogging_stop + (6 if self.fit_drift else 0)

    def drift(self, x: ArrayLike) -> NDArray[np.float64]:
        """(3, 2): per sensor the gain change gamma_h and the offset change delta_h over the
        run (zeros without the drift)."""
        if not self.fit_drift:
            return np.zeros((3, 2))
        j = self.drift_start
        return np.asarray(x, dtype=np.float64)[j : j + 6].reshape(3, 2).copy()

    def theta(self, x: ArrayLike) -> NDArray[np.float64]:
        """theta (3, m) from x."""
        return np.asarray(x, dtype=np.float64)[: self.n_theta].reshape(3, self.basis.size)

    def log_gain(self, x: ArrayLike) -> float:
        """log c from x (0 without it)."""
        return float(np.asarray(x)[self.gain_index]) if self.fit_gain else 0.0

    def cogging(self, x: ArrayLike, covariance: ArrayLike | None = None) -> CoggingTorque:
        """The cogging torque of x (with the covariance block of its coefficients, if given).

        Parameters
        ----------
        x : array_like, shape (p,)
            A parameter vector of this layout.
        covariance : array_like, shape (p, p), optional
            Covariance of x; its cogging block is attached to the torque.

        Returns
        -------
        CoggingTorque
            T_c(y0) of the orders ``cogging_orders`` [plant input units].
        """
        xx = np.asarray(x, dtype=np.float64)
        sl = slice(self.cogging_start, self.cogging_stop)
        cov = None if covariance is None else np.asarray(covariance, dtype=np.float64)[sl, sl]
        return CoggingTorque.from_coefficients(self.cogging_orders, xx[sl], cov)

    def pack(
        self, theta: ArrayLike, log_gain: float = 0.0, cogging: CoggingTorque | None = None,
        drift: ArrayLike | None = None,
    ) -> NDArray[np.float64]:  # fmt: skip
        """x from its parts (cogging coefficients of orders not in ``cogging`` are zero).

        Parameters
        ----------
        theta : array_like, shape (3, m)
            Flux parameters on ``basis``.
        log_gain : float
            log c, the plant input gain factor (ignored unless ``fit_gain``).
        cogging : CoggingTorque, optional
            Known cogging coefficients to place at their orders.
        drift : array_like (3, 2), optional
            Per sensor (gamma_h, delta_h) (ignored unless ``fit_drift``; default zero).

        Returns
        -------
        ndarray, shape (p,)
            ``x = [theta, log c, a_1, b_1, ..., gamma_1, delta_1, ...]``.
        """
        x = np.zeros(self.size)
        x[: self.n_theta] = np.asarray(theta, dtype=np.float64).reshape(-1)
        if self.fit_gain:
            x[self.gain_index] = float(log_gain)
        if cogging is not None:
            known = dict(zip(cogging.orders, zip(cogging.a, cogging.b, strict=True), strict=True))
            for i, k in enumerate(self.cogging_orders):
                if k in known:
                    x[self.cogging_start + 2 * i : self.cogging_start + 2 * i + 2] = known[k]
        if self.fit_drift and drift is not None:
            x[self.drift_start :] = np.asarray(drift, dtype=np.float64).reshape(6)
        return x
