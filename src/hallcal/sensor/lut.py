"""The lookup-table correction f_star (section "Designing a reconstruction function").

On M equidistant grid points y0_i in [0, 2 pi) the model predicts what f_init would output,
``y_hat_i = f_init(g_theta(y0_i))`` (unwrapped around y0_i; the bijectivity condition), and the
error
``eta_i = y0_i - y_hat_i``. The correction ``eta(y_hat)`` interpolates the pairs (y_hat_i, eta_i)
piecewise linearly with wrap-around, and the table correction gives
``f_star(d) = f_init(d) + eta(f_init(d))``.

The table is only valid when y0 -> y_hat is bijective (strictly increasing over one revolution);
:func:`build_lut` reports this and :class:`LUT` refuses to correct with a non-bijective table.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal._constants import TWO_PI
from hallcal.sensor.reconstruction import (
    BLOCK_ROWS,
    InitReconstructor,
    electrical_angle,
    f_init,
    f_init_columns,
    projection_and_offset,
)

__all__ = ["LUT", "NotBijectiveError", "StarReconstructor", "build_lut"]


class NotBijectiveError(ValueError):
    """The model's map y0 -> y_hat is not bijective, so f_star = f_init + eta would give wrong
    angles."""


@dataclass(frozen=True)
class LUT:
    """Lookup table of f_star = f_init + eta and the f_init it corrects.

    Attributes
    ----------
    pole_pairs : int
        n_m.
    projection : ndarray, shape (2, 3)
        f_init's projection on the alpha/beta plane.
    offset : ndarray, shape (3,)
        Sensor offsets subtracted before projecting.
    y0 : ndarray, shape (M,)
        Grid y0_i = 2 pi i / M [rad].
    y_hat : ndarray, shape (M,)
        f_init of the model flux on the grid [rad].
    eta : ndarray, shape (M,)
        eta_i = y0_i - y_hat_i [rad].
    bijective : bool
        Whether y_hat is strictly increasing over the revolution, the bijectivity condition.
    min_slope : float
        Smallest finite-difference slope d y_hat / d y0 on the grid (> 0 when bijective).
    """

    pole_pairs: int
    projection: NDArray[np.float64] = field(repr=False)
    offset: NDArray[np.float64] = field(repr=False)
    y0: NDArray[np.float64] = field(repr=False)
    y_hat: NDArray[np.float64] = field(repr=False)
    eta: NDArray[np.float64] = field(repr=False)
    bijective: bool
    min_slope: float

    @property
    def points(self) -> int:
        return int(self.y_hat.size)

    @functools.cached_property
    def _periodic_table(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Nodes in [0, 2 pi), sorted, with one wrapped node at each end (what ``np.interp``
        with ``period`` builds on every call), so that a lookup is a plain ``np.interp``."""
        xp = np.mod(self.y_hat, TWO_PI)
        order = np.argsort(xp, kind="stable")
        xp, fp = xp[order], self.eta[order]
        xp = np.concatenate([xp[-1:] - TWO_PI, xp, xp[:1] + TWO_PI])
        fp = np.concatenate([fp[-1:], fp, fp[:1]])
        return xp, fp

    def correction(self, y: ArrayLike) -> NDArray[np.float64]:
        """eta^LUT(y): piecewise-linear interpolation with wrap-around [rad]."""
        self._require_bijective()
        xp, fp = self._periodic_table
        return np.interp(np.mod(y, TWO_PI), xp, fp)

    def f_star(self, d: ArrayLike, *, y_initial: float = 0.0) -> NDArray[np.float64]:
        """f_star over a recording: f_init(d) + eta(f_init(d)) (eq. (f_final)).

        Parameters
        ----------
        d, y_initial
            As for :meth:`f_init`.

        Returns
        -------
        ndarray, shape (N,)
            y_star [rad, mechanical].
        """
        y = self.f_init(d, y_initial=y_initial)
        return y + self.correction(y)

    def reconstruct(
        self, d1: ArrayLike, d2: ArrayLike, d3: ArrayLike, *, y_initial: float = 0.0
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """f_init and f_star, eq. (f_final), of a whole recording given as three columns.

        Block by block (:data:`~hallcal.sensor.reconstruction.BLOCK_ROWS` rows), so that the
        memory beyond the two results does not grow with the recording; the same numbers as
        :meth:`f_init` and :meth:`f_star`.

        Parameters
        ----------
        d1, d2, d3 : array_like, shape (N,)
            Hall signals.
        y_initial : float, keyword-only
            Estimate before the first sample [rad].

        Returns
        -------
        y_init, y_star : ndarray, shape (N,)
            [rad], mechanical.

        Raises
        ------
        NotBijectiveError
            When the table is not bijective.
        """
        self._require_bijective()
        y_init = f_init_columns(
            d1,
            d2,
            d3,
            self.pole_pairs,
            y_initial=y_initial,
            projection=self.projection,
            offset=self.offset,
        )
        xp, fp = self._periodic_table
        y_star = np.empty_like(y_init)
        wrapped = np.empty(min(BLOCK_ROWS, y_init.size))
        for start in range(0, y_init.size, BLOCK_ROWS):
            y = y_init[start : start + BLOCK_ROWS]
            w = wrapped[: y.size]
            # y mod 2 pi as y - 2 pi floor(y / 2 pi): three quick passes instead of np.mod; a
            # result a rounding error outside [0, 2 pi) still lies on the padded table
            np.divide(y, TWO_PI, out=w)
            np.floor(w, out=w)
            w *= -TWO_PI
            w += y
            eta = np.interp(w, xp, fp)
            np.add(y, eta, out=y_star[start : start + y.size])
        return y_init, y_star

    def f_init(self, d: ArrayLike, *, y_initial: float = 0.0) -> NDArray[np.float64]:
        """The f_init (Clarke + atan2 + unwrap, eq. (fimp)) this table corrects.

        Parameters
        ----------
        d : array_like, shape (N, 3)
            Hall signals, one row per sample.
        y_initial : float, keyword-only
            f_init's estimate before the first sample [rad, mechanical].

        Returns
        -------
        ndarray, shape (N,)
            y [rad, mechanical], with this table's projection and offsets.
        """
        return f_init(
            d, self.pole_pairs, y_initial=y_initial, projection=self.projection, offset=self.offset
        )

    def _require_bijective(self) -> None:
        if not self.bijective:
            raise NotBijectiveError(
                "the map y0 -> f_init(g(y0)) is not bijective (min slope "
                f"{self.min_slope:.3g}); the lookup table would give wrong angles"
            )

    def to_dict(self) -> dict:
        return {
            "points": self.points,
            "y0": self.y0.tolist(),
            "y_hat": self.y_hat.tolist(),
            "eta": self.eta.tolist(),
            "bijective": bool(self.bijective),
            "min_slope": float(self.min_slope),
        }

    @classmethod
    def from_arrays(
        cls,
        pole_pairs: int,
        projection: ArrayLike,
        offset: ArrayLike,
        y_hat: ArrayLike,
        eta: ArrayLike,
    ) -> LUT:
        """Rebuild a table from stored nodes (e.g. an artifact), re-checking bijectivity.

        Parameters
        ----------
        pole_pairs, projection, offset
            As the attributes of the same names (array_like here; the offset in sensor units).
        y_hat : array_like, shape (M,)
            Table nodes y_hat_i = f_init(g_theta(y0_i)) (eq. (recon_biject)) [rad].
        eta : array_like, shape (M,)
            Corrections eta_i = y0_i - y_hat_i [rad]; the grid is recovered as y_hat + eta.

        Returns
        -------
        LUT
            With ``bijective`` and ``min_slope`` recomputed from the nodes.
        """
        y_hat = np.asarray(y_hat, dtype=np.float64)
        eta = np.asarray(eta, dtype=np.float64)
        y0 = y_hat + eta
        bij, slope = _bijectivity(y0, y_hat)
        return cls(
            int(pole_pairs),
            np.asarray(projection, float).reshape(2, 3),
            np.asarray(offset, float).reshape(3),
            y0,
            y_hat,
            eta,
            bij,
            slope,
        )


def _bijectivity(y0: NDArray, y_hat: NDArray) -> tuple[bool, float]:
    steps = np.diff(np.append(y_hat, y_hat[0] + TWO_PI))
    dy0 = np.diff(np.append(y0, y0[0] + TWO_PI))
    slope = float(np.min(steps / dy0))
    # the grid itself must be increasing too (stored nodes in another order are not a table)
    ordered = bool(np.all(dy0 > 0))
    return bool(slope > 0.0 and ordered), slope if ordered else -abs(slope)


def build_lut(
    g: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    pole_pairs: int,
    *,
    points: int = 4096,
    projection: ArrayLike | None = None,
    offset: ArrayLike | None = None,
) -> LUT:
    """Build the table of section "Designing a reconstruction function".

    Parameters
    ----------
    g : callable
        Flux model, ``g(y0)`` of shape (M, 3) for y0 of shape (M,) (e.g. a
        :class:`hallcal.sensor.flux.FluxModel`).
    pole_pairs : int
        n_m.
    points : int, keyword-only
        M grid points per revolution. The interpolation error of a piecewise-linear table
        scales as (2 pi / M)^2 eta'' / 8; 4096 points keep it below 1e-7 rad for errors of the
        size seen on real sensors, far below any Hall noise floor.
    projection, offset : optional
        f_init's projection and offsets (see :mod:`hallcal.sensor.reconstruction`).

    Returns
    -------
    LUT
        With ``bijective`` set; a non-bijective table refuses to correct angles.
    """
    M = int(points)
    y0 = TWO_PI * np.arange(M) / M
    psi = electrical_angle(np.asarray(g(y0)), projection=projection, offset=offset)
    n = int(pole_pairs)
    # Gamma(psi, n y0_i): f_init with the previous estimate phi = y0_i, the bijectivity condition
    y_hat = (n * y0 + np.mod(psi - n * y0 + math.pi, TWO_PI) - math.pi) / n
    eta = y0 - y_hat
    bij, slope = _bijectivity(y0, y_hat)
    P, o = projection_and_offset(projection, offset)
    return LUT(
        n,
        P.reshape(2, 3),
        o.reshape(3),
        y0,
        y_hat,
        eta,
        bij,
        slope,
    )


class StarReconstructor:
    """Streaming f_star = f_init + eta(f_init): one sample at a time, as firmware runs it.

    Note that the f_init inside runs on its own (uncorrected) previous estimate, as in the paper:
    the table corrects the output, not the unwrapping state.

    Parameters
    ----------
    lut : LUT
        A bijective table (eq. (recon_biject)); its projection and offsets configure f_init.
    y_initial : float, keyword-only
        f_init's estimate before the first sample [rad, mechanical].
    """

    def __init__(self, lut: LUT, *, y_initial: float = 0.0) -> None:
        lut._require_bijective()
        self.lut = lut
        self._init = InitReconstructor(
            lut.pole_pairs, y_initial=y_initial, projection=lut.projection, offset=lut.offset
        )

    def update(self, d1: float, d2: float, d3: float) -> float:
        """Process one sample: y_star = y + eta(y), eq. (f_final).

        Parameters
        ----------
        d1, d2, d3
            As for :meth:`InitReconstructor.update`.

        Returns
        -------
        float
            y_star [rad, mechanical].
        """
        y = self._init.update(d1, d2, d3)
        return y + float(self.lut.correction(y))
