"""Excitation signals: random-phase multisines, optionally on top of a slow ramp.

The calibration run of the paper (Algorithm 1, step 1) tracks a slow ramp reference; the closed-loop
BLA experiment (section "Obtaining a Best Linear Approximation") uses several realizations of a
random-phase multisine reference, optionally on top of a slow ramp so that the rotor turns through
many positions and the position-dependent sensor errors act as nonlinear distortion.

Multisines follow Pintelon & Schoukens (2012), "System Identification: A Frequency Domain
Approach", 2nd ed., ch. 2 (periodic excitations, multisines) and ch. 3 (random-phase multisines,
which are Gaussian-like excitations for the BLA; odd and random-odd multisines with detection
lines for nonlinear distortions).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from hallcal.errors import HallcalInputError

__all__ = [
    "ExcitationStatus",
    "Multisine",
    "MultisineExperiment",
    "multisine",
    "multisine_experiment",
]

LineSpec = Literal["full", "odd", "random-odd"]


class ExcitationStatus(enum.StrEnum):
    """Status of a designed excitation signal."""

    OK = "ok"


@dataclass(frozen=True, eq=False)
class Multisine:
    """One period of a random-phase multisine with a flat amplitude spectrum.

    The signal is ``x[n] = sum_k A cos(2 pi k n / N + phi_k)``, ``n = 0 .. N-1``, over the excited
    DFT lines ``k`` (Pintelon & Schoukens 2012, ch. 2-3).

    Attributes
    ----------
    signal : ndarray, shape (N,)
        One period of the multisine.
    lines : ndarray of int, shape (F,)
        Excited DFT line indices ``k`` (frequency ``k / (N Ts)``), increasing.
    freq : ndarray, shape (F,)
        Excited frequencies [Hz].
    phases : ndarray, shape (F,)
        Phases ``phi_k`` [rad], uniform in ``[0, 2 pi)``.
    amplitudes : ndarray, shape (F,)
        Amplitudes ``A`` of the cosines (all equal: flat spectrum).
    period_samples : int
        Period ``N`` in samples.
    sample_time : float
        Sample time ``Ts`` [s].
    rms : float
        RMS value of the signal over one period (equal to the requested value).
    status : ExcitationStatus
        ``ok`` (a designed signal has nothing to report).
    """

    signal: np.ndarray
    lines: np.ndarray
    freq: np.ndarray
    phases: np.ndarray
    amplitudes: np.ndarray
    period_samples: int
    sample_time: float
    rms: float
    status: ExcitationStatus = ExcitationStatus.OK


@dataclass(frozen=True, eq=False)
class MultisineExperiment:
    """A closed-loop BLA experiment: M realizations of P periods of a random-phase multisine.

    Every realization has the same excited lines and amplitudes and new random phases
    (Pintelon & Schoukens 2012, sec. 3.8, robust method). The realizations are stacked in
    time; the reference is ``r = multisine part + trend`` where ``trend = drift * t`` is a slow
    ramp, continuous over the whole experiment, that keeps the motor turning.

    How the ramp is removed: it is a known part of ``r``, and in steady state the loop answers a
    ramp with a linear trend in ``y`` and ``u``. :func:`hallcal.identify.bla.nonparametric_bla`
    keeps only the steady-state periods of each realization and subtracts, per realization and per
    signal, the least-squares line through the period means before the DFT. A P-periodic signal has
    equal period means, so this slope estimate is not disturbed by the multisine (it is the
    least-squares estimate of the slope when the periodic part is left free); see its documentation.

    Attributes
    ----------
    r : ndarray, shape (M * P * N,)
        Reference [rad]: the multisines of all realizations, stacked, plus ``trend``.
    realization : ndarray of int, shape (M * P * N,)
        Realization index ``0 .. M-1`` of every sample.
    t : ndarray, shape (M * P * N,)
        Time [s], ``n * Ts``.
    trend : ndarray, shape (M * P * N,)
        The ramp part of ``r``, ``drift * t``.
    multisines : ndarray, shape (M, N)
        One period of the multisine of every realization.
    phases : ndarray, shape (M, F)
        Phases of every realization.
    lines, freq, amplitudes : ndarray, shape (F,)
        Excited DFT lines (same for all realizations), frequencies [Hz] and amplitudes.
    period_samples, periods, realizations : int
        ``N``, ``P`` (periods per realization, transients included) and ``M``.
    sample_time : float
        ``Ts`` [s].
    rms : float
        RMS of the multisine part.
    drift : float
        Slope of the ramp [rad/s].
    status : ExcitationStatus
        ``ok`` (a designed signal has nothing to report).
    """

    r: np.ndarray
    realization: np.ndarray
    t: np.ndarray
    trend: np.ndarray
    multisines: np.ndarray
    phases: np.ndarray
    lines: np.ndarray
    freq: np.ndarray
    amplitudes: np.ndarray
    period_samples: int
    periods: int
    realizations: int
    sample_time: float
    rms: float
    drift: float
    status: ExcitationStatus = ExcitationStatus.OK


def multisine(
    period_samples: int,
    sample_time: float,
    *,
    band: tuple[float, float],
    rms: float,
    lines: LineSpec | Sequence[int] | np.ndarray = "full",
    rng: np.random.Generator | None = None,
    seed: int | None = None,
) -> Multisine:
    """One period of a random-phase multisine with a flat amplitude spectrum.

    Pintelon & Schoukens (2012), ch. 2 (multisine, DFT lines ``k = f N Ts``) and ch. 3
    (random-phase multisine: independent phases uniform in ``[0, 2 pi)``, flat amplitudes; odd and
    random-odd multisines).

    Parameters
    ----------
    period_samples : int
        Period ``N`` in samples; the frequency resolution is ``1 / (N Ts)``.
    sample_time : float
        Sample time ``Ts`` [s].
    band : (float, float)
        Lowest and highest excited frequency [Hz], both included. DC and the Nyquist line are
        never excited.
    rms : float
        RMS value of the signal (exact over one period): every amplitude is
        ``rms * sqrt(2 / F)`` for ``F`` excited lines.
    lines : {"full", "odd", "random-odd"} or sequence of int
        ``"full"``: every line in the band. ``"odd"``: odd lines only. ``"random-odd"``: odd lines,
        where in each group of 3 consecutive odd lines of the band (counted from the lowest one)
        one line, chosen at random, is left out as a detection line for odd nonlinear distortion;
        an incomplete last group is kept whole. A sequence of int gives the excited lines directly
        (``band`` is then only checked to contain them).
    rng : numpy.random.Generator, optional
        Random generator for the phases (and the random-odd choice).
    seed : int, optional
        Seed for ``np.random.default_rng`` when ``rng`` is not given; default 0 (deterministic).

    Returns
    -------
    Multisine

    Raises
    ------
    HallcalInputError
        If an argument is out of range or the band holds no line.
    """
    n = _positive_int(period_samples, "period_samples", minimum=4)
    ts = _positive_float(sample_time, "sample_time")
    rms_f = _positive_float(rms, "rms")
    generator = _generator(rng, seed)
    k = _excited_lines(n, ts, band, lines, generator)
    phases = generator.uniform(0.0, 2.0 * np.pi, size=k.size)
    amplitude = rms_f * np.sqrt(2.0 / k.size)
    return Multisine(
        signal=_synthesize(n, k, amplitude, phases),
        lines=k,
        freq=k / (n * ts),
        phases=phases,
        amplitudes=np.full(k.size, amplitude),
        period_samples=n,
        sample_time=ts,
        rms=rms_f,
    )


def multisine_experiment(
    period_samples: int,
    sample_time: float,
    *,
    periods: int,
    realizations: int,
    band: tuple[float, float],
    rms: float,
    lines: LineSpec | Sequence[int] | np.ndarray = "random-odd",
    seed: int = 0,
    drift: float = 0.0,
) -> MultisineExperiment:
    """Reference for a closed-loop BLA experiment: M random-phase realizations of P periods.

    Implements the experiment of the paper's section "Obtaining a Best Linear Approximation"
    (Pintelon & Schoukens 2012, sec. 3.8, robust method): the excited lines
    and amplitudes are drawn once (for ``"random-odd"`` the detection lines are the same in all
    realizations), each realization gets new independent random phases. Realizations follow each
    other without pause; the first periods of each realization (``transient_periods`` of
    :func:`hallcal.identify.bla.nonparametric_bla`) absorb the transient of the switch.

    The optional slow ramp ``drift * t`` is added under the multisine (continuous over the whole
    experiment). It is removed in the BLA by subtracting, per realization, the least-squares line
    through the period means of the steady-state periods of ``r``, ``u`` and ``y`` (see
    :class:`MultisineExperiment`).

    Parameters
    ----------
    period_samples : int
        Period ``N`` in samples.
    sample_time : float
        Sample time ``Ts`` [s].
    periods : int
        Periods per realization ``P``, transient periods included.
    realizations : int
        Number of realizations ``M``.
    band, rms, lines
        As for :func:`multisine`.
    seed : int
        Seed of ``np.random.default_rng``; the whole experiment is a function of it.
    drift : float
        Slope of the ramp under the multisine [rad/s]; 0 for none.

    Returns
    -------
    MultisineExperiment
    """
    n = _positive_int(period_samples, "period_samples", minimum=4)
    ts = _positive_float(sample_time, "sample_time")
    p = _positive_int(periods, "periods")
    m = _positive_int(realizations, "realizations")
    drift_f = float(drift)
    if not np.isfinite(drift_f):
        raise HallcalInputError(f"drift must be finite, got {drift!r}")
    rng = np.random.default_rng(seed)
    first = multisine(n, ts, band=band, rms=rms, lines=lines, rng=rng)
    signals = [first.signal]
    phases = [first.phases]
    for _ in range(1, m):
        ms = multisine(n, ts, band=band, rms=rms, lines=first.lines, rng=rng)
        signals.append(ms.signal)
        phases.append(ms.phases)
    multisines = np.stack(signals)
    periodic = np.tile(multisines, (1, p)).reshape(-1)
    t = np.arange(m * p * n, dtype=np.float64) * ts
    trend = drift_f * t
    return MultisineExperiment(
        r=periodic + trend,
        realization=np.repeat(np.arange(m, dtype=np.int64), p * n),
        t=t,
        trend=trend,
        multisines=multisines,
        phases=np.stack(phases),
        lines=first.lines,
        freq=first.freq,
        amplitudes=first.amplitudes,
        period_samples=n,
        periods=p,
        realizations=m,
        sample_time=ts,
        rms=first.rms,
        drift=drift_f,
    )


# --------------------------------------------------------------------------------------------------
# helpers


def _synthesize(n: int, lines: np.ndarray, amplitude: float, phases: np.ndarray) -> np.ndarray:
    """``sum_k A cos(2 pi k n / N + phi_k)`` over one period, by an inverse real FFT."""
    spectrum = np.zeros(n // 2 + 1, dtype=np.complex128)
    spectrum[lines] = 0.5 * n * amplitude * np.exp(1j * phases)
    return np.fft.irfft(spectrum, n=n)


def _excited_lines(
    n: int,
    ts: float,
    band: tuple[float, float],
    lines: LineSpec | Sequence[int] | np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    try:
        f_lo, f_hi = (float(b) for b in band)
    except (TypeError, ValueError) as exc:
        raise HallcalInputError(f"band must be a pair (f_lo, f_hi) in Hz, got {band!r}") from exc
    if not (np.isfinite(f_lo) and np.isfinite(f_hi) and 0.0 <= f_lo <= f_hi):
        raise HallcalInputError(f"band must satisfy 0 <= f_lo <= f_hi, got {band!r}")
    candidates = np.arange(1, (n - 1) // 2 + 1, dtype=np.int64)  # no DC, no Nyquist line
    f = candidates / (n * ts)
    tol = 1e-9 / (n * ts)
    in_band = candidates[(f >= f_lo - tol) & (f <= f_hi + tol)]
    if isinstance(lines, str):
        if lines == "full":
            k = in_band
        elif lines == "odd":
            k = in_band[in_band % 2 == 1]
        elif lines == "random-odd":
            odd = in_band[in_band % 2 == 1]
            n_groups = odd.size // 3
            keep = np.ones(odd.size, dtype=bool)
            if n_groups:
                left_out = 3 * np.arange(n_groups) + rng.integers(0, 3, size=n_groups)
                keep[left_out] = False
            k = odd[keep]
        else:
            raise HallcalInputError(
                f"lines must be 'full', 'odd', 'random-odd' or a list of int, got {lines!r}"
            )
    else:
        k = np.asarray(lines)
        if k.ndim != 1 or not np.issubdtype(k.dtype, np.integer):
            raise HallcalInputError("lines must be a 1-D sequence of int DFT line indices")
        k = np.unique(k.astype(np.int64))
        if k.size and not np.all(np.isin(k, in_band)):
            raise HallcalInputError(
                f"lines must lie in the band {band!r} Hz, above DC and below the Nyquist line"
            )
    if k.size == 0:
        raise HallcalInputError(
            f"band {band!r} Hz holds no excited line at resolution {1.0 / (n * ts):g} Hz"
        )
    return k


def _generator(rng: np.random.Generator | None, seed: int | None) -> np.random.Generator:
    if rng is not None and seed is not None:
        raise HallcalInputError("give either rng or seed, not both")
    if rng is not None:
        return rng
    return np.random.default_rng(0 if seed is None else seed)


def _positive_int(value: int, name: str, *, minimum: int = 1) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < minimum:
        raise HallcalInputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _positive_float(value: float, name: str) -> float:
    v = float(value)
    if not (np.isfinite(v) and v > 0.0):
        raise HallcalInputError(f"{name} must be a positive number, got {value!r}")
    return v
