"""Linear time-invariant models: transfer functions, state space, exact ZOH with input delay.

The plant G(s) of the paper (section "Simulation setup") has an input delay that is a fraction of a
sample. Its exact zero-order-hold discretization (Franklin, Powell & Workman, "Digital Control of
Dynamic Systems", 3rd ed., sec. 4.3.4) with delay ``tau = l Ts + tau_f``, ``0 <= tau_f < Ts``, is

    x[k+1] = Phi x[k] + Gamma0 u[k-l] + Gamma1 u[k-l-1],
    Phi = e^{A Ts},  Gamma0 = int_0^{Ts - tau_f} e^{A s} ds B,
    Gamma1 = e^{A (Ts - tau_f)} int_0^{tau_f} e^{A s} ds B,

realized here as one discrete state space whose state holds x and the past inputs. No Pade
approximation is involved: the discrete step response equals the continuous one delayed by tau at
every sample. Transfer functions use descending powers of s (continuous) or q (discrete).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hallcal.formatting import polynomial_text

__all__ = [
    "ContinuousTF",
    "DiscreteTF",
    "StateSpace",
    "c2d_zoh",
    "polynomial_text",
    "tf2ss",
]


def _trim(c: ArrayLike) -> NDArray[np.float64]:
    a = np.atleast_1d(np.asarray(c, dtype=np.float64))
    nz = np.flatnonzero(a)
    return a[nz[0] :] if nz.size else np.zeros(1)


@dataclass(frozen=True)
class StateSpace:
    """x[k+1] = A x + B u, y = C x + D u (discrete, ``dt`` in s) or dx/dt = ... (``dt = None``).

    Single input, single output. Arrays are float64: A (n, n), B (n,), C (n,), D scalar.
    """

    A: NDArray[np.float64] = field(repr=False)
    B: NDArray[np.float64] = field(repr=False)
    C: NDArray[np.float64] = field(repr=False)
    D: float
    dt: float | None = None

    @property
    def order(self) -> int:
        return int(self.A.shape[0])

    def frequency_response(self, freq_hz: ArrayLike) -> NDArray[np.complex128]:
        """C (zI - A)^-1 B + D at z = e^{j w dt} (or s = j w when continuous)."""
        w = 2 * np.pi * np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
        z = np.exp(1j * w * self.dt) if self.dt is not None else 1j * w
        n = self.order
        out = np.empty(z.shape, dtype=np.complex128)
        for i, zi in enumerate(z):
            out[i] = self.C @ np.linalg.solve(zi * np.eye(n) - self.A, self.B) + self.D
        return out

    def simulate(self, u: ArrayLike, *, x0: ArrayLike | None = None) -> NDArray[np.float64]:
        """Discrete response y[k] to the input sequence u[k] from state x0 (default zero).

        Parameters
        ----------
        u : array_like, shape (N,)
            Input sequence.
        x0 : array_like, shape (n,), keyword-only, optional
            Initial state; default zero.

        Returns
        -------
        ndarray, shape (N,)
            y[k] = C x[k] + D u[k].
        """
        if self.dt is None:
            raise ValueError("simulate() is for discrete systems")
        u = np.asarray(u, dtype=np.float64)
        x = np.zeros(self.order) if x0 is None else np.array(x0, dtype=np.float64)
        y = np.empty(u.size)
        for k, uk in enumerate(u):
            y[k] = self.C @ x + self.D * uk
            x = self.A @ x + self.B * uk
        return y


def tf2ss(num: ArrayLike, den: ArrayLike, *, dt: float | None = None) -> StateSpace:
    """Controllable-canonical state space of num/den (descending powers), proper only.

    Parameters
    ----------
    num, den : array_like
        Polynomial coefficients in descending powers of s (or of q); leading zeros ignored.
    dt : float, keyword-only, optional
        Sample time [s] of a discrete system; None for a continuous one.

    Returns
    -------
    StateSpace
        A = [-den[1:]; I 0], B = e_1, C = num[1:] - num[0] den[1:], D = num[0] (den made
        monic), the form of ``scipy.signal.tf2ss``.
    """
    b, a = _trim(num), _trim(den)
    if b.size > a.size:
        raise ValueError("transfer function must be proper (deg num <= deg den)")
    if a.size == 1:
        return StateSpace(np.zeros((0, 0)), np.zeros(0), np.zeros(0), float(b[-1] / a[0]), dt)
    # Controllable canonical form (the one of scipy.signal.tf2ss, which the tests use as the
    # oracle): with den monic of degree n and num padded to n + 1 coefficients,
    # A = [-den[1:]; I 0], B = e_1, D = num[0], C = num[1:] - num[0] den[1:].
    n = a.size - 1
    b = np.concatenate([np.zeros(a.size - b.size), b]) / a[0]
    a = a / a[0]
    A = np.zeros((n, n))
    A[0] = -a[1:]
    A[1:, :-1] = np.eye(n - 1)
    B = np.zeros(n)
    B[0] = 1.0
    C = b[1:] - b[0] * a[1:]
    return StateSpace(A, B, C, float(b[0]), dt)


@dataclass(frozen=True)
class ContinuousTF:
    """G(s) = exp(-delay s) num(s) / den(s), coefficients in descending powers of s.

    Parameters
    ----------
    num, den : sequence of float
        Polynomial coefficients.
    delay : float
        Input delay tau >= 0 [s]. (The paper prints exp(+1.2e-4 s); a physical delay is
        exp(-tau s), see docs/design.md.)
    """

    num: tuple[float, ...]
    den: tuple[float, ...]
    delay: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "num", tuple(float(v) for v in _trim(self.num)))
        object.__setattr__(self, "den", tuple(float(v) for v in _trim(self.den)))
        if self.delay < 0 or not math.isfinite(self.delay):
            raise ValueError("delay must be finite and >= 0")
        if len(self.num) > len(self.den):
            raise ValueError("G(s) must be proper")

    def frequency_response(self, freq_hz: ArrayLike) -> NDArray[np.complex128]:
        """G(j 2 pi f) including the delay."""
        s = 2j * np.pi * np.atleast_1d(np.asarray(freq_hz, dtype=np.float64))
        return np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay)

    def scaled(self, c: float) -> ContinuousTF:
        """c G(s) (the gain correction c-hat multiplies the plant by a constant)."""
        return ContinuousTF(tuple(c * v for v in self.num), self.den, self.delay)

    def discretize(self, sample_time: float) -> StateSpace:
        """Exact ZOH equivalent with the input delay, see :func:`c2d_zoh`."""
        return c2d_zoh(tf2ss(self.num, self.den), sample_time, delay=self.delay)


@dataclass(frozen=True)
class DiscreteTF:
    """C(q) = num(q) / den(q), descending powers of the shift operator q."""

    num: tuple[float, ...]
    den: tuple[float, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "num", tuple(float(v) for v in _trim(self.num)))
        object.__setattr__(self, "den", tuple(float(v) for v in _trim(self.den)))
        if len(self.num) > len(self.den):
            raise ValueError("C(q) must be proper (causal)")

    def state_space(self, sample_time: float) -> StateSpace:
        return tf2ss(self.num, self.den, dt=sample_time)

    def frequency_response(self, freq_hz: ArrayLike, sample_time: float) -> NDArray[np.complex128]:
        """C(z) at z = exp(j 2 pi f T_s).

        Parameters
        ----------
        freq_hz : array_like
            Frequencies f [Hz].
        sample_time : float
            T_s [s].

        Returns
        -------
        ndarray of complex, shape (F,)
            num(z) / den(z), one value per frequency.
        """
        z = np.exp(2j * np.pi * np.atleast_1d(np.asarray(freq_hz, float)) * sample_time)
        return np.polyval(self.num, z) / np.polyval(self.den, z)


def _zoh_integrals(A: NDArray, B: NDArray, t: float) -> tuple[NDArray, NDArray]:
    """(e^{A t}, int_0^t e^{A s} ds B) from one matrix exponential (Van Loan 1978)."""
    import scipy.linalg  # here, not at module level: reading a setup should not load it

    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A * t
    M[:n, n] = B * t
    E = scipy.linalg.expm(M)
    return E[:n, :n], E[:n, n].copy()


def c2d_zoh(ss: StateSpace, sample_time: float, *, delay: float = 0.0) -> StateSpace:
    """Exact zero-order-hold discretization with an input delay of any size.

    Parameters
    ----------
    ss : StateSpace
        Continuous system (``dt is None``).
    sample_time : float
        Ts [s].
    delay : float, keyword-only
        Input delay tau >= 0 [s], any multiple or fraction of Ts.

    Returns
    -------
    StateSpace
        Discrete system with state [x; u[k-1]; ...; u[k-l-1]] (only the delay states that are
        needed), input u[k] and output y[k] = C x[k] + D u(kTs - tau).

    Notes
    -----
    Franklin, Powell & Workman, sec. 4.3.4 (eqs. 4.63-4.65), with ``tau = l Ts + tau_f``.
    """
    if ss.dt is not None:
        raise ValueError("c2d_zoh needs a continuous system")
    Ts = float(sample_time)
    if not (Ts > 0 and math.isfinite(Ts)):
        raise ValueError("sample_time must be > 0")
    if delay < 0 or not math.isfinite(delay):
        raise ValueError("delay must be finite and >= 0")
    l = int(math.floor(delay / Ts + 1e-12))
    tau_f = delay - l * Ts
    if tau_f < 1e-12 * Ts:
        tau_f = 0.0
    n = ss.order
    if n:
        Phi, Gam_full = _zoh_integrals(ss.A, ss.B, Ts)
        E0, Gamma0 = _zoh_integrals(ss.A, ss.B, Ts - tau_f)
        _, I1 = _zoh_integrals(ss.A, ss.B, tau_f)
        Gamma1 = E0 @ I1
        if tau_f == 0.0:
            Gamma0, Gamma1 = Gam_full, np.zeros(n)
    else:
        Phi, Gamma0, Gamma1 = np.zeros((0, 0)), np.zeros(0), np.zeros(0)
    # Inputs needed: u[k-l] (Gamma0) and, if tau_f > 0, u[k-l-1] (Gamma1). Delay chain length:
    nd = l + (1 if tau_f > 0 else 0)
    N = n + nd
    A = np.zeros((N, N))
    B = np.zeros(N)
    C = np.zeros(N)
    A[:n, :n] = Phi
    # chain: state n + j holds u[k-1-j], j = 0..nd-1
    for j in range(1, nd):
        A[n + j, n + j - 1] = 1.0
    if nd:
        B[n] = 1.0

    def add_input(lag: int, vec: NDArray) -> None:
        # contribution vec * u[k - lag] to x[k+1]
        if lag == 0:
            B[:n] += vec
        else:
            A[:n, n + lag - 1] += vec

    add_input(l, Gamma0)
    if tau_f > 0:
        add_input(l + 1, Gamma1)
    C[:n] = ss.C
    # y(kTs) = C x[k] + D u(kTs - tau): the held input at t = kTs - tau is u[k - l - (tau_f > 0)]
    lag_out = l + (1 if tau_f > 0 else 0)
    D = 0.0
    if ss.D != 0.0:
        if lag_out == 0:
            D = ss.D
        else:
            C[n + lag_out - 1] += ss.D
    return StateSpace(A, B, C, D, Ts)
