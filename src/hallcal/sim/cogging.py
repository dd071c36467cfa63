"""Cogging torque: a torque periodic in the mechanical angle, added to the plant input.

The paper's discussion names cogging as the likely cause of its experiment's residual error: a
position-periodic torque moves the rotor in a way that a flux model alone attributes to the
sensors. hallcal models it as a Fourier series in the mechanical angle y0,

    T_c(y0) = sum_k a_k cos(k y0) + b_k sin(k y0) = sum_k A_k cos(k y0 - phi_k),

with ``A_k = hypot(a_k, b_k)`` and ``phi_k = atan2(b_k, a_k)``, in plant input units (the unit of
the torque command u, so that firmware can subtract it from its command as a feed-forward), added
to the plant input of eq. (state_eq): ``x_G[k+1] = A_G x_G[k] + B_G (u[k] + T_c(y0[k]))``.

Order 0 is a constant load torque ``T_c = a_0`` (friction on a ramp in one direction, a
spring or gravity load): ``cos(0 y0) = 1`` and ``sin(0 y0) = 0``, so b_0 has no effect and is
stored as 0. In a loop whose controller does not integrate (the paper's C(q), whose integrator
is cancelled) it shifts the rotor by a constant angle, which a flux model alone explains as a
constant offset of the sensors' angle: the table then carries that offset (DESIGN.md, "Numerical
facts": 0.6-1.1x the noise floor on its own).

The artifact stores it under the key ``"cogging"`` (:meth:`CoggingTorque.to_dict`). The firmware's
anticogging feed-forward tabulates it (:func:`tabulate`, :class:`CoggingTable`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI

__all__ = ["COGGING_RELATIVE_ERROR", "MAX_COGGING_POINTS", "CoggingTable", "CoggingTorque"]


@dataclass(frozen=True)
class CoggingTorque:
    """T_c(y0) = sum_k a_k cos(k y0) + b_k sin(k y0) [plant input units], y0 in mechanical rad.

    Parameters
    ----------
    orders : sequence of int
        Distinct orders k >= 0 (periods per revolution; 0: a constant load torque a_0).
    a, b : array_like (n,)
        Cosine and sine coefficients, one per order (b of order 0 has no effect: set to 0).
    covariance : array_like (2n, 2n), optional
        Covariance of the interleaved coefficients ``[a_1, b_1, a_2, b_2, ...]`` (an estimate's
        uncertainty; None for a known torque); the row and column of b_0 are set to 0.
    """

    orders: tuple[int, ...] = ()
    a: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False)
    b: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False)
    covariance: NDArray[np.float64] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        k = tuple(int(v) for v in self.orders)
        if len(set(k)) != len(k) or any(v < 0 for v in k):
            raise ValueError("cogging orders must be distinct integers >= 0")
        a = np.array(self.a, dtype=np.float64).reshape(-1)
        b = np.array(self.b, dtype=np.float64).reshape(-1)
        if a.shape != (len(k),) or b.shape != (len(k),):
            raise ValueError("cogging coefficients a and b need one entry per order")
        zero = [i for i, v in enumerate(k) if v == 0]
        b[zero] = 0.0  # sin(0 y0) = 0: b_0 has no effect
        for arr in (a, b):
            arr.setflags(write=False)
        object.__setattr__(self, "orders", k)
        object.__setattr__(self, "a", a)
        object.__setattr__(self, "b", b)
        if self.covariance is not None:
            c = np.array(self.covariance, dtype=np.float64)
            if c.shape != (2 * len(k), 2 * len(k)):
                raise ValueError("cogging covariance must be (2n, 2n) for n orders")
            for i in zero:
                c[2 * i + 1, :] = 0.0
                c[:, 2 * i + 1] = 0.0
            c.setflags(write=False)
            object.__setattr__(self, "covariance", c)

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_coefficients(
        cls, orders: ArrayLike, x: ArrayLike, covariance: ArrayLike | None = None
    ) -> CoggingTorque:
        """From interleaved coefficients ``x = [a_1, b_1, a_2, b_2, ...]``.

        Parameters
        ----------
        orders : array_like of int, shape (n,)
            Orders k (periods per mechanical revolution).
        x : array_like, shape (2n,)
            Interleaved cosine/sine coefficients [plant input units].
        covariance : array_like, shape (2n, 2n), optional
            Their covariance (an estimate's uncertainty).

        Returns
        -------
        CoggingTorque
        """
        xx = np.asarray(x, dtype=np.float64).reshape(-1)
        cov = None if covariance is None else np.asarray(covariance, dtype=np.float64)
        return cls(tuple(np.atleast_1d(orders).tolist()), xx[0::2], xx[1::2], cov)

    # -- evaluation ---------------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Number of orders n."""
        return len(self.orders)

    @property
    def coefficients(self) -> NDArray[np.float64]:
        """Interleaved ``[a_1, b_1, a_2, b_2, ...]`` (the layout of the parameter vector)."""
        x = np.empty(2 * self.size)
        x[0::2] = self.a
        x[1::2] = self.b
        return x

    @property
    def amplitude(self) -> NDArray[np.float64]:
        """A_k = hypot(a_k, b_k) per order."""
        return np.hypot(self.a, self.b)

    @property
    def phase(self) -> NDArray[np.float64]:
        """phi_k = atan2(b_k, a_k) [rad] per order: ``T_c = sum A_k cos(k y0 - phi_k)``."""
        return np.arctan2(self.b, self.a)

    def _regressors(self, y0: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
        y = np.atleast_1d(np.asarray(y0, dtype=np.float64))
        k = np.asarray(self.orders, dtype=np.float64)
        arg = np.multiply.outer(y, k)
        return y, np.cos(arg), np.sin(arg)

    def __call__(self, y0: ArrayLike) -> NDArray[np.float64]:
        """T_c(y0), shape (N,)."""
        y, c, s = self._regressors(y0)
        if not self.size:
            return np.zeros(y.size)
        return c @ self.a + s @ self.b

    def derivative(self, y0: ArrayLike) -> NDArray[np.float64]:
        """d T_c / d y0 [per rad], shape (N,)."""
        y, c, s = self._regressors(y0)
        if not self.size:
            return np.zeros(y.size)
        k = np.asarray(self.orders, dtype=np.float64)
        return s @ (-k * self.a) + c @ (k * self.b)

    def std(self, y0: ArrayLike) -> NDArray[np.float64]:
        """First-order standard deviation of T_c(y0) from :attr:`covariance` (NaN without it).

        ``var T_c(y0) = r(y0)^T Cov r(y0)`` with ``r = [cos k_1 y0, sin k_1 y0, ...]``: T_c is
        linear in the coefficients, so this is exact for Gaussian coefficients.
        """
        y, c, s = self._regressors(y0)
        if self.covariance is None:
            return np.full(y.size, math.nan)
        R = np.empty((y.size, 2 * self.size))
        R[:, 0::2] = c
        R[:, 1::2] = s
        var = np.einsum("ij,jk,ik->i", R, self.covariance, R)
        return np.sqrt(np.maximum(var, 0.0))

    def coefficient_std(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Standard deviations of a_k and b_k (NaN without a covariance)."""
        if self.covariance is None:
            nan = np.full(self.size, math.nan)
            return nan, nan.copy()
        sd = np.sqrt(np.maximum(np.diag(self.covariance), 0.0))
        return sd[0::2].copy(), sd[1::2].copy()

    # -- artifact -----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The artifact's ``"cogging"`` entry (PLAN.md): orders, a, b, their std, the unit.

        With a covariance, the full matrix of the interleaved coefficients is added under
        ``"covariance"`` (the +-2 sigma band of the map needs the correlations).
        """
        sa, sb = self.coefficient_std()
        out: dict = {
            "orders": [int(k) for k in self.orders],
            "a": [float(v) for v in self.a],
            "b": [float(v) for v in self.b],
            "std_a": [None if not math.isfinite(v) else float(v) for v in sa],
            "std_b": [None if not math.isfinite(v) else float(v) for v in sb],
            "unit": "plant input",
        }
        if self.covariance is not None and np.all(np.isfinite(self.covariance)):
            out["covariance"] = self.covariance.tolist()
        return out

    @classmethod
    def from_dict(cls, entry: dict) -> CoggingTorque:
        """Inverse of :meth:`to_dict` (without ``"covariance"``, a diagonal one from the std)."""
        orders = tuple(int(k) for k in entry.get("orders", ()))
        a = np.asarray(entry.get("a", ()), dtype=np.float64)
        b = np.asarray(entry.get("b", ()), dtype=np.float64)
        if entry.get("covariance") is not None:
            return cls(orders, a, b, np.asarray(entry["covariance"], dtype=np.float64))
        sa, sb = entry.get("std_a"), entry.get("std_b")
        cov = None
        if sa is not None and sb is not None and len(sa) == len(orders) == len(sb):
            v = np.empty(2 * len(orders))
            v[0::2] = [math.nan if s is None else float(s) for s in sa]
            v[1::2] = [math.nan if s is None else float(s) for s in sb]
            if np.all(np.isfinite(v)):
                cov = np.diag(v**2)
        return cls(orders, a, b, cov)


#: Relative accuracy of the anticogging table against the Fourier map.
COGGING_RELATIVE_ERROR = 1e-6
#: Largest anticogging table (float values).
MAX_COGGING_POINTS = 65536


@dataclass(frozen=True)
class CoggingTable:
    """The anticogging feed-forward T_c(y0) as a uniform float table, cubic interpolation.

    The map (:class:`CoggingTorque`, artifact key ``"cogging"``, y0 the mechanical angle) is
    tabulated at ``y0 = 2 pi i / N`` and interpolated by the cubic through the four nearest
    values (periodic).

    Attributes
    ----------
    torque : CoggingTorque
        The Fourier map.
    values : ndarray of float32, shape (N,)
        The table.
    error : float
        Largest |table - map| over the revolution (dense evaluation with the table's float32
        values, in double), in the map's unit.
    scale : float
        Largest |T_c| over the revolution.
    """

    torque: CoggingTorque
    values: NDArray[np.float32]
    error: float
    scale: float

    @property
    def points(self) -> int:
        return int(self.values.size)

    @property
    def slope(self) -> float:
        """Largest |d T_c / d y0| over the revolution (bound: sum of k sqrt(a_k^2 + b_k^2))."""
        return float(np.sum(np.asarray(self.torque.orders) * self.torque.amplitude))

    def interpolate(self, y0: ArrayLike) -> NDArray[np.float64]:
        """The table's value at y0 [rad] as the firmware computes it (in double)."""
        n = self.points
        pos = np.mod(np.atleast_1d(np.asarray(y0, dtype=np.float64)), TWO_PI) * (n / TWO_PI)
        return _cubic_at(self.values.astype(np.float64), pos)


def _uniform(torque: CoggingTorque, n: int) -> NDArray[np.float64]:
    """T_c on y0 = 2 pi i / n, i = 0 .. n - 1 (inverse real FFT; n > 2 max order)."""
    spec = np.zeros(n // 2 + 1, dtype=np.complex128)
    k = np.asarray(torque.orders, dtype=np.int64)
    scale = np.where(k == 0, float(n), n / 2.0)  # order 0 (a constant load torque): the DC bin
    np.add.at(spec, k, (torque.a - 1j * torque.b) * scale)
    return np.fft.irfft(spec, n)


def _cubic_at(values: NDArray[np.float64], pos: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cubic (Lagrange) through the 4 nearest of the periodic values, at positions in [0, N)."""
    n = values.size
    i = np.minimum(np.floor(pos).astype(np.int64), n - 1)
    t = pos - i
    p0, p1, p2, p3 = (values[(i + k) % n] for k in (-1, 0, 1, 2))
    return (
        -t * (t - 1) * (t - 2) / 6 * p0
        + (t + 1) * (t - 1) * (t - 2) / 2 * p1
        - (t + 1) * t * (t - 2) / 2 * p2
        + (t + 1) * t * (t - 1) / 6 * p3
    )


def tabulate(torque: CoggingTorque) -> CoggingTable:
    """Tabulate T_c within :data:`COGGING_RELATIVE_ERROR` of its largest value.

    The table has the fewest points (a power of two, 64..65536, more than twice the largest
    order) whose cubic interpolation of the float32 values stays within half of
    :data:`COGGING_RELATIVE_ERROR` of the largest |T_c| (the other half is for the firmware's
    single-precision arithmetic) at 16 points per interval (dense enough for a cubic's error
    curve); the map on uniform grids comes from an inverse FFT.

    Parameters
    ----------
    torque : CoggingTorque
        The map T_c(y0).

    Returns
    -------
    CoggingTable

    Raises
    ------
    ValueError
        No orders, or no table up to :data:`MAX_COGGING_POINTS` points reaches the accuracy
        (the message names the cause), or a map that is zero everywhere.
    """
    if not torque.size:
        raise ValueError("is empty: no map to tabulate")
    kmax = max(torque.orders)
    scale = 0.0
    m = 64
    while True:
        if 2 * kmax < m:
            sub = 16  # 16 points per interval: dense enough for a cubic's error curve
            ref = _uniform(torque, sub * m)
            scale = max(scale, float(np.max(np.abs(ref))))
            vals = ref[::sub].astype(np.float32)
            pos = np.arange(sub * m) / sub
            err = float(np.max(np.abs(_cubic_at(vals.astype(np.float64), pos) - ref)))
            if err <= 0.5 * COGGING_RELATIVE_ERROR * scale:  # half for float32 arithmetic
                break
        if m >= MAX_COGGING_POINTS:
            raise ValueError(f"needs more than {MAX_COGGING_POINTS} table points for 1e-6")
        m *= 2
    if not scale > 0.0:
        raise ValueError("is zero everywhere")
    return CoggingTable(torque, vals, err, scale)
