"""Initial angle reconstruction f_init: Clarke transform, atan2 and unwrapping.

Implements eq. (fimp) of van Meer et al., "Self-Calibrating Position Measurements: Applied to
Imperfect Hall Sensors" (section "Collecting data"): the three Hall signals d = [d1, d2, d3] are
projected on the electrical alpha/beta plane, the electrical angle atan2(beta, alpha) is unwrapped
relative to n_m times the previous estimate (the unwrapping function Gamma), and the result is
divided by the number of pole pairs n_m.

The projection generalizes the paper's Clarke matrix: for sensors at electrical phases
``phi_h`` with a common offset, ``projection_matrix(phases)`` is the least-squares left inverse
of ``d_h = o + A cos(n_m y0 - phi_h)``; for the nominal phases 0, 120 and 240 degrees it equals
the first two rows of the Clarke matrix exactly.

Units: angles in rad (mechanical for ``y``, electrical for ``n_m * y``); d in the sensor's unit.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "NOMINAL_PHASES",
    "InitReconstructor",
    "alpha_beta",
    "clarke_matrix",
    "electrical_angle",
    "f_init",
    "f_init_step",
    "projection_matrix",
    "unwrap_to",
]

TWO_PI = 2.0 * math.pi
#: Nominal electrical phases of the three sensors [rad]: 0, 120 and 240 degrees.
NOMINAL_PHASES = (0.0, TWO_PI / 3.0, 2.0 * TWO_PI / 3.0)


def clarke_matrix() -> NDArray[np.float64]:
    """The amplitude-invariant Clarke matrix C of eq. (fimp) (3 x 3).

    Rows give alpha, beta and the zero-sequence component of ``C @ d``.
    """
    s = math.sqrt(3.0) / 2.0
    return (2.0 / 3.0) * np.array([[1.0, -0.5, -0.5], [0.0, s, -s], [0.5, 0.5, 0.5]])


def projection_matrix(phases: ArrayLike = NOMINAL_PHASES) -> NDArray[np.float64]:
    """Left inverse of the sensor model mapping d to (A cos psi, A sin psi), 2 x 3.

    For ``d_h = o + A cos(psi - phi_h)`` with electrical angle psi, the rows of the pseudo-inverse
    of ``H = [1, cos phi_h, sin phi_h]`` recover ``o``, ``A cos psi`` and ``A sin psi``. The
    returned matrix is the last two rows, so ``alpha, beta = P @ d`` eliminates the common offset.
    With the nominal phases this is exactly the first two rows of :func:`clarke_matrix`.

    Parameters
    ----------
    phases : array_like, shape (3,)
        Electrical phase of each sensor [rad].
    """
    phi = np.asarray(phases, dtype=np.float64)
    if phi.shape != (3,):
        raise ValueError("phases must have shape (3,)")
    H = np.column_stack([np.ones(3), np.cos(phi), np.sin(phi)])
    return np.linalg.pinv(H)[1:3].copy()


def alpha_beta(
    d: ArrayLike,
    *,
    projection: ArrayLike | None = None,
    offset: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Project Hall signals on the electrical alpha/beta plane.

    Parameters
    ----------
    d : array_like, shape (N, 3) or (3,)
        Hall signals.
    projection : array_like, shape (2, 3), optional
        Projection matrix P; default the Clarke rows (sensors 120 electrical degrees apart).
    offset : array_like, shape (3,), optional
        Sensor offsets subtracted before projecting; default zero.

    Returns
    -------
    ndarray, shape (N, 2) or (2,)
        ``(d - offset) @ P.T``: columns alpha and beta.
    """
    P = clarke_matrix()[:2] if projection is None else np.asarray(projection, dtype=np.float64)
    x = np.asarray(d, dtype=np.float64)
    if offset is not None:
        x = x - np.asarray(offset, dtype=np.float64)
    return x @ P.T


def electrical_angle(d: ArrayLike, **kwargs) -> NDArray[np.float64]:
    """Wrapped electrical angle ``atan2(beta, alpha)`` in [-pi, pi].

    Keywords as :func:`alpha_beta`.
    """
    ab = alpha_beta(d, **kwargs)
    return np.arctan2(ab[..., 1], ab[..., 0])


def unwrap_to(angle: float, reference: float) -> float:
    """The unwrapping function Gamma of eq. (fimp).

    ``Gamma(angle, reference) = reference + mod(angle - reference + pi, 2 pi) - pi``: the value
    congruent to ``angle`` modulo 2 pi nearest to ``reference`` (ties go to ``reference - pi``).
    """
    return (
        reference
        + math.fmod(math.fmod(angle - reference + math.pi, TWO_PI) + TWO_PI, TWO_PI)
        - (math.pi)
    )


def f_init_step(
    d_k: ArrayLike,
    y_prev: float,
    pole_pairs: int,
    *,
    projection: ArrayLike | None = None,
    offset: ArrayLike | None = None,
) -> float:
    """One sample of f_init, eq. (fimp): ``y_k = Gamma(atan2(beta, alpha), n_m y_{k-1}) / n_m``.

    Parameters
    ----------
    d_k : array_like, shape (3,)
        Hall signals at sample k.
    y_prev : float
        Previous estimate y(t_{k-1}) [rad, mechanical].
    pole_pairs : int
        n_m.
    projection, offset : array_like, optional
        As in :func:`f_init`.

    Returns
    -------
    float
        y(t_k) [rad, mechanical].
    """
    a, b = alpha_beta(d_k, projection=projection, offset=offset)
    return unwrap_to(math.atan2(b, a), pole_pairs * y_prev) / pole_pairs


class InitReconstructor:
    """Streaming f_init: feed one sample at a time, as firmware does.

    Parameters
    ----------
    pole_pairs : int
        n_m.
    y_initial : float, optional
        The estimate before the first sample [rad]; 0 by the convention of docs/design.md.
    projection, offset : optional
        As in :func:`alpha_beta`.
    """

    def __init__(
        self,
        pole_pairs: int,
        *,
        y_initial: float = 0.0,
        projection: ArrayLike | None = None,
        offset: ArrayLike | None = None,
    ) -> None:
        self.pole_pairs = int(pole_pairs)
        self.y = float(y_initial)
        P = clarke_matrix()[:2] if projection is None else np.asarray(projection, float)
        self._P = [[float(v) for v in row] for row in P]
        self._o = [0.0, 0.0, 0.0] if offset is None else [float(v) for v in offset]

    def update(self, d1: float, d2: float, d3: float) -> float:
        """Process one sample and return y(t_k) [rad]."""
        x = (d1 - self._o[0], d2 - self._o[1], d3 - self._o[2])
        (p0, p1) = self._P
        a = p0[0] * x[0] + p0[1] * x[1] + p0[2] * x[2]
        b = p1[0] * x[0] + p1[1] * x[1] + p1[2] * x[2]
        n = self.pole_pairs
        self.y = unwrap_to(math.atan2(b, a), n * self.y) / n
        return self.y


def f_init(
    d: ArrayLike,
    pole_pairs: int,
    *,
    y_initial: float = 0.0,
    projection: ArrayLike | None = None,
    offset: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """f_init over a whole recording, eq. (fimp), vectorized.

    Equal to running :class:`InitReconstructor` sample by sample (to rounding, about 1e-13
    rad): each output is ``(psi_k + 2 pi m_k) / n_m`` with the wrapped electrical angle psi_k and
    an integer turn count m_k, so no rounding error accumulates along the recording.

    Parameters
    ----------
    d : array_like, shape (N, 3)
        Hall signals.
    pole_pairs : int
        n_m >= 1.
    y_initial : float
        Estimate before the first sample [rad].
    projection : array_like (2, 3), optional
        Rows giving (alpha, beta) from the three signals; default the Clarke rows (nominal
        0/120/240 degree sensors).
    offset : array_like (3,), optional
        Sensor offsets subtracted first; default zero.

    Returns
    -------
    ndarray, shape (N,)
        y [rad, mechanical].
    """
    psi = electrical_angle(np.atleast_2d(d), projection=projection, offset=offset)
    n = int(pole_pairs)
    if psi.size == 0:
        return psi.copy()
    # The turn count follows from the wrapped differences, anchored at n*y_initial.
    e0 = n * float(y_initial)
    first = unwrap_to(float(psi[0]), e0)
    turns = np.empty(psi.shape, dtype=np.float64)
    turns[0] = np.round((first - psi[0]) / TWO_PI)
    dpsi = np.diff(psi)
    jumps = -np.floor((dpsi + math.pi) / TWO_PI)  # mod(x + pi, 2 pi) - pi = x + 2 pi * jump
    turns[1:] = turns[0] + np.cumsum(jumps)
    return (psi + TWO_PI * turns) / n
