"""The oracle noise floor of a virtual-bench run: what the best possible table would achieve.

The scale on which hallcal's tables are scored (DESIGN.md, "Oracle noise floor"): the RMS error
of the exact inverse of the TRUE sensor map ``psi(y0) = f_init(g(y0))`` applied to a run's f_init,

    e_oracle = psi^-1(f_init(d)) - y0,

where g is the bench's noiseless, static sensor output (:meth:`hallcal.sim.bench.BenchConfig.truth`
limited by the ADC's rails, where a clipping sensor sits) and d the run's recorded Hall signals
(with their noise, spikes, quantization and drift). It is the table of section "Designing a
reconstruction function" (eq. recon_biject) built from the truth instead of an estimate, on a
grid fine enough that interpolation adds nothing: whatever error remains comes from the signals
themselves (Gaussian noise, spikes, quantization), not from the model. For Gaussian noise it
agrees with ``sigma sqrt(2/3) / (A n_m)`` (:func:`hallcal.sim.bench.noise_floor`) within a few
per cent (more where the flux is strongly distorted: the angle's sensitivity to the noise varies
along the curve).

The RMS is taken about zero, not about the mean (``AngleError.rms_raw``): the table's constant
offset is part of what ``reconstruct`` outputs and what a user measures, and the predicted error
of a calibration includes it too (:mod:`hallcal.fit.adequacy`). The oracle's own mean error is
that of the noise, about zero.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from hallcal.sensor.lut import LUT, build_lut
from hallcal.sensor.metrics import AngleError, angle_error
from hallcal.sim.bench import BenchConfig, BenchRun

__all__ = ["ORACLE_POINTS", "oracle_error", "oracle_floor", "oracle_table"]

#: Grid of the oracle's table per revolution: the interpolation error (2 pi / M)^2 eta'' / 8 is
#: below 1e-7 rad for flux content up to mechanical harmonic 200 at 1 % of the amplitude.
ORACLE_POINTS = 1 << 16


def oracle_table(config: BenchConfig, *, points: int = ORACLE_POINTS) -> LUT:
    """The exact inverse of the bench's true map ``psi = f_init o g`` as a fine table.

    Parameters
    ----------
    config : BenchConfig
        The bench: its truth g (noiseless sensor signals within the ADC's rails) and the loop's
        f_init (projection, offsets, n_m).
    points : int, keyword-only
        Grid points per revolution.

    Returns
    -------
    LUT
        ``f_star`` of this table is psi^-1 o f_init (``bijective`` False when the true map
        folds: then no table can invert it and the oracle is undefined).
    """
    loop = config.loop()
    truth = config.truth()
    lo = np.asarray(config.adc_low, dtype=np.float64)
    hi = np.asarray(config.adc_high, dtype=np.float64)

    def g(y0: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.clip(truth(y0), lo, hi)  # the rails are part of the static map

    return build_lut(
        g,
        config.pole_pairs,
        points=points,
        projection=loop.projection,
        offset=loop.offset,
    )


def oracle_error(run: BenchRun, *, table: LUT | None = None, y_initial: float = 0.0) -> AngleError:
    """Error of the exact inverse of the true map on a run: ``psi^-1(f_init(d)) - y0`` [rad].

    Parameters
    ----------
    run : BenchRun
        A run of the bench (its Hall signals d and true angle y0).
    table : LUT, keyword-only, optional
        :func:`oracle_table` of the run's bench, when already built.
    y_initial : float, keyword-only
        f_init's estimate before the first sample [rad] (0: the calibration convention).

    Returns
    -------
    AngleError
        ``rms_raw`` is the oracle noise floor (about zero); ``rms`` about the mean.

    Raises
    ------
    ValueError
        When the true map folds (no table can invert it).
    """
    lut = oracle_table(run.config) if table is None else table
    if not lut.bijective:
        raise ValueError("the bench's true sensor map folds: no table inverts it")
    return angle_error(lut.f_star(run.d, y_initial=y_initial), run.y0)


def oracle_floor(run: BenchRun, *, table: LUT | None = None) -> float:
    """The oracle noise floor of a run (:func:`oracle_error`, its RMS about zero).

    Parameters
    ----------
    run : BenchRun
        A run of the bench.
    table : LUT, keyword-only, optional
        :func:`oracle_table` of the run's bench, when already built.

    Returns
    -------
    float
        RMS of ``psi^-1(f_init(d)) - y0`` about zero [rad].
    """
    return oracle_error(run, table=table).rms_raw
