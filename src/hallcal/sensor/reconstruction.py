"""Initial angle reconstruction f_init: Clarke transform, atan2 and unwrapping.

Implements f_init (Clarke + atan2 + unwrap) of van Meer et al., "Self-Calibrating Position
Measurements: Applied to
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

from hallcal._constants import TWO_PI

__all__ = [
    "NOMINAL_PHASES",
    "InitReconstructor",
    "alpha_beta",
    "clarke_matrix",
    "electrical_angle",
    "f_init",
    "f_init_columns",
    "projection_and_offset",
    "projection_matrix",
    "unwrap_to",
]

#: Rows per block of the whole-recording functions: memory beyond the result is a few work
#: arrays of this many float64 (2 MiB each), whatever the length of the recording.
BLOCK_ROWS = 1 << 18
#: Nominal electrical phases of the three sensors [rad]: 0, 120 and 240 degrees.
NOMINAL_PHASES = (0.0, TWO_PI / 3.0, 2.0 * TWO_PI / 3.0)


def clarke_matrix() -> NDArray[np.float64]:
    """The amplitude-invariant Clarke matrix C of f_init (3 x 3).

    Rows give alpha, beta and the zero-sequence component of ``C @ d``.

    Returns
    -------
    ndarray, shape (3, 3)
        C = 2/3 [[1, -1/2, -1/2], [0, sqrt(3)/2, -sqrt(3)/2], [1/2, 1/2, 1/2]] (eq. (fimp)).
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

    Returns
    -------
    ndarray, shape (2, 3)
        P with ``[A cos psi, A sin psi] = P @ d`` for offset-free ideal sensors.
    """
    phi = np.asarray(phases, dtype=np.float64)
    if phi.shape != (3,):
        raise ValueError("phases must have shape (3,)")
    H = np.column_stack([np.ones(3), np.cos(phi), np.sin(phi)])
    return np.linalg.pinv(H)[1:3].copy()


def projection_and_offset(
    projection: ArrayLike | None = None, offset: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """f_init's projection P and sensor offsets o (eq. (fimp)), with their defaults.

    Parameters
    ----------
    projection : array_like, shape (2, 3), optional
        Projection matrix P; default the Clarke rows (first two rows of :func:`clarke_matrix`).
    offset : array_like, shape (3,), optional
        Sensor offsets subtracted before projecting [sensor unit]; default zero.

    Returns
    -------
    P : ndarray, shape (2, 3)
    o : ndarray, shape (3,)
        As float64 arrays, not reshaped or checked.
    """
    P = clarke_matrix()[:2] if projection is None else np.asarray(projection, dtype=np.float64)
    o = np.zeros(3) if offset is None else np.asarray(offset, dtype=np.float64)
    return P, o


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
    P, o = projection_and_offset(projection, offset)
    x = np.asarray(d, dtype=np.float64)
    if offset is not None:
        x = x - o
    return x @ P.T


def electrical_angle(d: ArrayLike, **kwargs) -> NDArray[np.float64]:
    """Wrapped electrical angle ``atan2(beta, alpha)`` in [-pi, pi].

    Parameters
    ----------
    d : array_like, shape (N, 3) or (3,)
        Hall signals.
    **kwargs
        ``projection`` and ``offset``, as for :func:`alpha_beta`.

    Returns
    -------
    ndarray, shape (N,) or ()
        Electrical angle n_m y modulo 2 pi [rad, electrical], in [-pi, pi].
    """
    ab = alpha_beta(d, **kwargs)
    return np.arctan2(ab[..., 1], ab[..., 0])


def unwrap_to(angle: float, reference: float) -> float:
    """The unwrapping function Gamma of f_init.

    ``Gamma(angle, reference) = reference + mod(angle - reference + pi, 2 pi) - pi``: the value
    congruent to ``angle`` modulo 2 pi nearest to ``reference`` (ties go to ``reference - pi``).

    Parameters
    ----------
    angle : float
        Wrapped angle [rad] (f_init passes the electrical angle atan2(beta, alpha)).
    reference : float
        The previous unwrapped angle in the same unit (f_init: n_m y(t_k-1)) [rad].

    Returns
    -------
    float
        The unwrapped angle, within pi of ``reference`` [rad].
    """
    return (
        reference
        + math.fmod(math.fmod(angle - reference + math.pi, TWO_PI) + TWO_PI, TWO_PI)
        - (math.pi)
    )


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
        P, o = projection_and_offset(projection, offset)
        self._P = [[float(v) for v in row] for row in P]
        self._o = [float(v) for v in o]

    def update(self, d1: float, d2: float, d3: float) -> float:
        """Process one sample: y(t_k) = f_init(d(t_k)) relative to y(t_k-1) (eq. (fimp)).

        Parameters
        ----------
        d1, d2, d3 : float
            The three Hall signals of sample k (sensor's unit, e.g. V).

        Returns
        -------
        float
            The new mechanical angle estimate y(t_k) [rad], also stored in ``self.y``.
        """
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
    """f_init (Clarke + atan2 + unwrap) over a whole recording, vectorized.

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

    See Also
    --------
    f_init_columns : the same from three separate columns, block by block.
    """
    x = np.atleast_2d(np.asarray(d, dtype=np.float64))
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"d must have shape (N, 3), got {x.shape}")
    return f_init_columns(
        x[:, 0],
        x[:, 1],
        x[:, 2],
        pole_pairs,
        y_initial=y_initial,
        projection=projection,
        offset=offset,
    )


def f_init_columns(
    d1: ArrayLike,
    d2: ArrayLike,
    d3: ArrayLike,
    pole_pairs: int,
    *,
    y_initial: float = 0.0,
    projection: ArrayLike | None = None,
    offset: ArrayLike | None = None,
    out: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """f_init, eq. (fimp), of a recording given as three columns, in blocks of rows.

    The same numbers as :func:`f_init` (the projection is evaluated term by term in the order of
    :class:`InitReconstructor`), without forming the (N, 3) matrix: memory beyond the output is
    a few blocks of :data:`BLOCK_ROWS` rows, whatever the length of the recording.

    Parameters
    ----------
    d1, d2, d3 : array_like, shape (N,)
        Hall signals.
    pole_pairs : int
        n_m >= 1.
    y_initial : float
        Estimate before the first sample [rad].
    projection, offset : optional
        As in :func:`alpha_beta`.
    out : ndarray, shape (N,), optional
        float64 array to write the result into.

    Returns
    -------
    ndarray, shape (N,)
        y [rad, mechanical].
    """
    cols = [np.asarray(c, dtype=np.float64) for c in (d1, d2, d3)]
    N = cols[0].shape[0]
    if any(c.ndim != 1 or c.shape[0] != N for c in cols):
        raise ValueError("d1, d2 and d3 must be 1-D arrays of the same length")
    P, o = projection_and_offset(projection, offset)
    n = int(pole_pairs)
    y = np.empty(N) if out is None else out
    if y.shape != (N,) or y.dtype != np.float64:
        raise ValueError(f"out must be a float64 array of shape ({N},)")
    if N == 0:
        return y
    # work arrays for one block, reused: every step below writes into them
    size = min(BLOCK_ROWS, N)
    x, tmp, alpha, beta, jumps = (np.empty(size) for _ in range(5))
    turns = 0.0
    psi_last = 0.0
    for start in range(0, N, BLOCK_ROWS):
        stop = min(start + BLOCK_ROWS, N)
        k = stop - start
        xk, tk, al, be, jp = x[:k], tmp[:k], alpha[:k], beta[:k], jumps[:k]
        # alpha, beta = P (d - offset), term by term in the order of InitReconstructor
        al.fill(0.0)
        be.fill(0.0)
        for h, c in enumerate(cols):
            xh = c[start:stop] if o[h] == 0.0 else np.subtract(c[start:stop], o[h], out=xk)
            np.multiply(xh, P[0, h], out=tk)
            al += tk
            np.multiply(xh, P[1, h], out=tk)
            be += tk
        psi = np.arctan2(be, al, out=al)
        if start == 0:
            # the turn count of the first sample is anchored at n * y_initial
            first = unwrap_to(float(psi[0]), n * float(y_initial))
            turns = float(np.round((first - psi[0]) / TWO_PI))
            psi_last = float(psi[0])
        # mod(x + pi, 2 pi) - pi = x + 2 pi * jump: the turn count changes by the jumps of psi
        jp[0] = psi[0] - psi_last
        np.subtract(psi[1:], psi[:-1], out=jp[1:])
        jp += math.pi
        jp /= TWO_PI
        np.floor(jp, out=jp)
        np.negative(jp, out=jp)
        np.cumsum(jp, out=jp)
        jp += turns  # whole numbers: the sums are exact, blocks change nothing
        turns = float(jp[-1])
        psi_last = float(psi[-1])
        out_k = y[start:stop]
        np.multiply(jp, TWO_PI, out=out_k)
        out_k += psi
        out_k /= n
    return y
