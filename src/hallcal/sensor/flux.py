"""Flux-density models g_theta(y0) = psi(y0) theta, linear in the parameters.

Section "Model structure" of van Meer et al.: ``g_theta^T(y0) = psi(y0) theta`` with
``psi(y0) = I_3 kron beta(y0)`` and a periodic basis ``beta``. Here theta is stored as a 3 x m array
(row h holds the weights of sensor h), i.e. ``g_h(y0) = beta(y0) @ theta[h]``.

Fourier basis: ``beta = [1, sin(h_1 y0), cos(h_1 y0), ..., sin(h_n y0), cos(h_n y0)]``
with mechanical harmonics h (cycles per revolution). The periodic kernel basis of the experiment
section is, on a uniform grid of centres, diagonalized by these same Fourier modes; it is
provided by :mod:`hallcal.fit.kernel` on top of this module.

Units: y0 in rad (mechanical), g in the Hall sensor's unit (V or ADC counts).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.sensor.reconstruction import NOMINAL_PHASES

__all__ = ["FluxModel", "FourierBasis", "sinusoidal_theta"]


@dataclass(frozen=True)
class FourierBasis:
    """Fourier basis beta(y0) (eq. (basis)) with a constant term and chosen mechanical harmonics.

    Parameters
    ----------
    harmonics : sequence of int
        Distinct mechanical harmonics h >= 1 (cycles per revolution).
    """

    harmonics: tuple[int, ...]

    def __post_init__(self) -> None:
        h = tuple(int(v) for v in self.harmonics)
        if len(set(h)) != len(h) or any(v < 1 for v in h):
            raise ValueError("harmonics must be distinct integers >= 1")
        object.__setattr__(self, "harmonics", h)

    @property
    def size(self) -> int:
        """Number of basis functions m = 1 + 2 n_h."""
        return 1 + 2 * len(self.harmonics)

    @property
    def harmonic_array(self) -> NDArray[np.float64]:
        return np.asarray(self.harmonics, dtype=np.float64)

    def evaluate(self, y0: ArrayLike) -> NDArray[np.float64]:
        """beta(y0), shape (N, m)."""
        y = np.atleast_1d(np.asarray(y0, dtype=np.float64))
        arg = np.multiply.outer(y, self.harmonic_array)
        out = np.empty((y.size, self.size))
        out[:, 0] = 1.0
        out[:, 1::2] = np.sin(arg)
        out[:, 2::2] = np.cos(arg)
        return out

    def derivative(self, y0: ArrayLike) -> NDArray[np.float64]:
        """d beta / d y0, shape (N, m) [1/rad]."""
        y = np.atleast_1d(np.asarray(y0, dtype=np.float64))
        h = self.harmonic_array
        arg = np.multiply.outer(y, h)
        out = np.zeros((y.size, self.size))
        out[:, 1::2] = h * np.cos(arg)
        out[:, 2::2] = -h * np.sin(arg)
        return out

    def evaluate_with_derivative(
        self, y0: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(evaluate(y0), derivative(y0))`` from one evaluation of the sines and cosines
        (the same values, bit for bit, at half the cost)."""
        y = np.atleast_1d(np.asarray(y0, dtype=np.float64))
        h = self.harmonic_array
        arg = np.multiply.outer(y, h)
        sin, cos = np.sin(arg), np.cos(arg)
        value = np.empty((y.size, self.size))
        value[:, 0] = 1.0
        value[:, 1::2] = sin
        value[:, 2::2] = cos
        slope = np.empty((y.size, self.size))
        slope[:, 0] = 0.0
        np.multiply(h, cos, out=slope[:, 1::2])  # in place: no (N, n_h) temporaries
        np.multiply(-h, sin, out=slope[:, 2::2])
        return value, slope

    def index(self, harmonic: int) -> tuple[int, int]:
        """Columns (sin, cos) of a harmonic in beta."""
        j = self.harmonics.index(int(harmonic))
        return 1 + 2 * j, 2 + 2 * j


@dataclass(frozen=True)
class FluxModel:
    """g_theta(y0) for the three sensors.

    Parameters
    ----------
    basis : FourierBasis
        The periodic basis beta.
    theta : array_like, shape (3, m)
        Weights, row h for sensor h.
    """

    basis: FourierBasis
    theta: NDArray[np.float64] = field(repr=False)

    def __post_init__(self) -> None:
        th = np.array(self.theta, dtype=np.float64)
        if th.shape != (3, self.basis.size):
            raise ValueError(f"theta must have shape (3, {self.basis.size}), got {th.shape}")
        th.setflags(write=False)
        object.__setattr__(self, "theta", th)

    def __call__(self, y0: ArrayLike) -> NDArray[np.float64]:
        """g(y0), shape (N, 3)."""
        return self._evaluate(y0, self.basis.evaluate)

    def derivative(self, y0: ArrayLike) -> NDArray[np.float64]:
        """dg/dy0, shape (N, 3)."""
        return self._evaluate(y0, self.basis.derivative)

    def value_and_derivative(
        self, y0: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(g(y0), dg/dy0)``, each of shape (N, 3): the same values as ``self(y0)`` and
        ``self.derivative(y0)``, with the sines and cosines of a Fourier basis evaluated once."""
        fused = getattr(self.basis, "evaluate_with_derivative", None)
        y = np.atleast_1d(np.asarray(y0, dtype=np.float64))
        if fused is None or y.ndim != 1:
            return self(y), self.derivative(y)
        value, slope = np.empty((y.size, 3)), np.empty((y.size, 3))

        def fill(a: int, b: int) -> None:
            B, dB = fused(y[a:b])
            value[a:b] = B @ self.theta.T
            slope[a:b] = dB @ self.theta.T

        _over_blocks(y.size, fill)
        return value, slope

    def _evaluate(
        self, y0: ArrayLike, basis: Callable[[NDArray[np.float64]], NDArray[np.float64]]
    ) -> NDArray[np.float64]:
        """``basis(y) @ theta.T`` on blocks of samples (see :func:`_blocks`)."""
        y = np.atleast_1d(np.asarray(y0, dtype=np.float64))
        if y.ndim != 1 or y.size <= EVALUATION_BLOCK:
            return basis(y) @ self.theta.T
        out = np.empty((y.size, 3))

        def fill(a: int, b: int) -> None:
            out[a:b] = basis(y[a:b]) @ self.theta.T

        _over_blocks(y.size, fill)
        return out


#: Samples per block when a flux model is evaluated on many angles: bounds the (rows, m) basis
#: matrices (8192 x 111 float64, 7 MB, for 55 harmonics) instead of building them for all N.
EVALUATION_BLOCK = 8192


def _blocks(n: int) -> list[tuple[int, int]]:
    """Row ranges of nearly equal sizes, about :data:`EVALUATION_BLOCK` each, covering n rows.

    Never a single row (unless n = 1), which BLAS would multiply through another kernel: the
    blocks' products are the same, bit for bit, as the product on all rows at once.
    """
    count = max(-(-n // EVALUATION_BLOCK), 1)
    edges = [(k * n) // count for k in range(count + 1)]
    return list(zip(edges[:-1], edges[1:], strict=True))


def _over_blocks(n: int, fill: Callable[[int, int], None]) -> None:
    """``fill(a, b)`` on each row range of :func:`_blocks`: with several blocks, the second half
    of them in a second thread (NumPy releases the GIL in its array operations; each block is
    computed as it is alone, so the result is the same to the bit in either thread)."""
    blocks = _blocks(n)
    if len(blocks) < 2:
        for a, b in blocks:
            fill(a, b)
        return

    def run(part: list[tuple[int, int]]) -> None:
        for a, b in part:
            fill(a, b)

    from concurrent.futures import ThreadPoolExecutor  # here: the short evaluations need none

    half = len(blocks) // 2
    with ThreadPoolExecutor(1) as pool:
        later = pool.submit(run, blocks[half:])
        run(blocks[:half])
        later.result()


def sinusoidal_theta(
    basis: FourierBasis,
    pole_pairs: int,
    *,
    amplitude: ArrayLike = 1.0,
    offset: ArrayLike = 0.0,
    phases: ArrayLike = NOMINAL_PHASES,
) -> NDArray[np.float64]:
    """theta for pure sinusoids ``d_h = o_h + A_h cos(n_m y0 - phi_h)``: the inverse of f_init.

    This is the paper's starting point theta_0 of the SEM problem (section "Identification").
    Requires n_m in the harmonics of the basis.

    Parameters
    ----------
    basis : FourierBasis
        The basis theta is expressed in; must contain the harmonic n_m.
    pole_pairs : int
        n_m: the electrical angle is n_m y0.
    amplitude : array_like, scalar or shape (3,), keyword-only
        A_h per sensor (sensor's unit).
    offset : array_like, scalar or shape (3,), keyword-only
        o_h per sensor (sensor's unit).
    phases : array_like, shape (3,), keyword-only
        Electrical phases phi_h [rad, electrical]; default 0, 120 and 240 degrees.

    Returns
    -------
    ndarray, shape (3, m)
        theta_0, one row per sensor: constant o_h and the sin/cos pair of harmonic n_m.
    """
    if pole_pairs not in basis.harmonics:
        raise ValueError(f"the basis must contain the pole-pair harmonic {pole_pairs}")
    A = np.broadcast_to(np.asarray(amplitude, float), (3,))
    o = np.broadcast_to(np.asarray(offset, float), (3,))
    phi = np.asarray(phases, float)
    th = np.zeros((3, basis.size))
    js, jc = basis.index(pole_pairs)
    th[:, 0] = o
    th[:, js] = A * np.sin(phi)  # cos(x - phi) = cos(phi) cos x + sin(phi) sin x
    th[:, jc] = A * np.cos(phi)
    return th
