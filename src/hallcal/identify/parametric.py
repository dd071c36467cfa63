"""Parametric continuous-time model of the plant fitted to the closed-loop BLA.

Step 2 of Algorithm 1 of the paper (section "Obtaining a Best Linear Approximation"), second
half: a continuous-time model ``G(s) = exp(-s delay) num(s) / den(s)`` is fitted to the
nonparametric BLA (:mod:`hallcal.identify.bla`) with the frequency-domain estimators of Pintelon
& Schoukens (2012), ch. 9: Levy (1959) linear least squares, Sanathanan & Koerner (1963)
iterations, and a weighted nonlinear (output-error) refinement; the order can be chosen from the
data (:func:`select_order`: weighted cost against the BLA's variance with Rissanen's minimum
description length, stable fits preferred). The BLA is ``c G`` with an unknown gain c, corrected
elsewhere (:meth:`ParametricBLA.scaled`).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.identify._serial import (
    _array_from,
    _check_kind,
    _complex_pairs,
    _float_or_none,
    _floats,
    _get,
    _int_option,
)
from hallcal.identify.bla import NonparametricBLA

__all__ = [
    "FitStatus",
    "OrderCandidate",
    "OrderSelection",
    "ParametricBLA",
    "fit_parametric",
    "model_poles",
    "select_order",
]


class FitStatus(enum.StrEnum):
    """Outcome of the parametric fit of G(s)."""

    OK = "ok"
    NOT_CONVERGED = "not_converged"  # the evaluation budget ran out


@dataclass(frozen=True, eq=False)
class ParametricBLA:
    """Continuous-time model ``G(s) = exp(-s delay) num(s) / den(s)`` fitted to a BLA.

    Attributes
    ----------
    num : ndarray, shape (nb + 1,)
        Numerator coefficients in descending powers of s.
    den : ndarray, shape (na + integrator + 1,)
        Denominator coefficients in descending powers of s, monic; includes the ``integrator``
        poles at s = 0 (trailing zeros), as in the ``[plant]`` table of the setup file.
    delay : float
        Input delay [s], ``>= 0``.
    integrator : int
        Number of poles at s = 0 imposed by the model structure.
    cost : float
        Weighted least-squares cost of the fit, ``sum_k w_k |G_model - G_data|^2`` (with
        ``weights="variance"``: ``w_k = 1 / var_total``, so about the number of lines for a good
        fit). It refers to the fit, before any :meth:`scaled`.
    freq : ndarray, shape (F,)
        Frequencies [Hz] of the data the model was fitted to.
    hold : str
        ``"zoh"``: the data were a sampled FRF with a zero-order-hold input and the model is the
        continuous plant (the hold was accounted for in the fit); ``"none"``: continuous FRF data.
    sample_time : float or None
        Sample time [s] of the data (used by the hold).
    weights : str
        Weighting used: ``"variance"``, ``"relative"`` or ``"uniform"``.
    stable : bool
        Whether all poles other than the imposed integrators have negative real parts.
    nfev : int
        Model evaluations of the nonlinear least-squares refinement.
    gain_scale : float
        Product of the factors applied by :meth:`scaled` since the fit (1 for a fresh fit).
    status : FitStatus
        ``ok`` or ``not_converged`` (evaluation budget exhausted).
    deviations : tuple of (num, den, delay)
        The model moved by one standard deviation along each principal direction of the
        parameters' covariance (``sigma_i v_i`` for the eigenpairs of
        ``max(1, cost / (2 F - p)) (J^T J)^-1`` at the optimum, Pintelon & Schoukens 2012,
        sec. 9.11): what the data of the BLA leave undetermined, as whole models that a
        calibration can propagate (:func:`hallcal.pipeline.closed_loop` uses them for the table's
        bias). Empty when the Jacobian is singular.
    """

    num: np.ndarray
    den: np.ndarray
    delay: float
    integrator: int
    cost: float
    freq: np.ndarray = field(repr=False)
    hold: str = "none"
    sample_time: float | None = None
    weights: str = "variance"
    stable: bool = True
    nfev: int = 0
    gain_scale: float = 1.0
    status: FitStatus = FitStatus.OK
    deviations: tuple[tuple[np.ndarray, np.ndarray, float], ...] = field(default=(), repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", FitStatus(self.status))

    def frequency_response(self, freq_hz: np.ndarray | float, *, zoh: bool = False) -> np.ndarray:
        """``G(j 2 pi f) = exp(-j 2 pi f delay) num / den`` at the frequencies ``freq_hz`` [Hz].

        Parameters
        ----------
        freq_hz : array_like
            Frequencies [Hz]; the response is infinite at 0 with an integrator.
        zoh : bool
            Multiply by the zero-order-hold factor ``(1 - exp(-j w Ts)) / (j w Ts)`` (needs
            ``sample_time``): the FRF seen from a sampled input, aliasing neglected, comparable to
            the nonparametric BLA.
        """
        f = np.asarray(freq_hz, dtype=np.float64)
        s = 2j * np.pi * f
        with np.errstate(divide="ignore", invalid="ignore"):
            g = np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay)
            if zoh:
                if self.sample_time is None:
                    raise ValueError("zoh=True needs sample_time")
                g = g * _zoh_factor(f, self.sample_time)
        return g

    def scaled(self, c: float) -> ParametricBLA:
        """The same model with its gain multiplied by ``c`` (numerator times ``c``).

        The paper corrects the BLA gain with ``G_BLA <- G_BLA / c_hat`` (Algorithm 1, step
        "correct"; the gain-correction equation for c-hat); that is ``model.scaled(1 / c_hat)``.
        """
        c = float(c)
        if not np.isfinite(c) or c == 0.0:
            raise ValueError(f"scale factor must be finite and nonzero, got {c!r}")
        return replace(
            self,
            num=np.asarray(self.num) * c,
            gain_scale=self.gain_scale * c,
            deviations=tuple((np.asarray(n) * c, dd, t) for n, dd, t in self.deviations),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (floats and lists of floats).

        ``num``, ``den`` and ``delay`` use the names of the setup file's ``[plant]`` table.
        """
        return {
            "kind": "parametric-bla",
            "num": _floats(self.num),
            "den": _floats(self.den),
            "delay": float(self.delay),
            "integrator": int(self.integrator),
            "cost": _float_or_none(self.cost),
            "freq": _floats(self.freq),
            "hold": str(self.hold),
            "sample_time": None if self.sample_time is None else float(self.sample_time),
            "weights": str(self.weights),
            "stable": bool(self.stable),
            "nfev": int(self.nfev),
            "gain_scale": float(self.gain_scale),
            "status": str(self.status),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ParametricBLA:
        """Inverse of :meth:`to_dict`; only ``num``, ``den`` and ``delay`` are required.

        Raises
        ------
        HallcalInputError
            If a required key is missing or malformed (the message names it).
        """
        _check_kind(data, "parametric-bla")
        num = _array_from(data, "num")
        den = _array_from(data, "den")
        if den.size == 0 or den[0] == 0.0:
            raise HallcalInputError("key den: leading coefficient must be nonzero")
        num, den = num / den[0], den / den[0]
        delay = float(_get(data, "delay"))
        if not (np.isfinite(delay) and delay >= 0.0):
            raise HallcalInputError(f"key delay must be >= 0, got {delay!r}")
        integrator = data.get("integrator")
        if integrator is None:
            integrator = int(den.size - 1 - np.max(np.flatnonzero(den)))
        sample_time = data.get("sample_time")
        cost = data.get("cost")
        return cls(
            num=num,
            den=den,
            delay=delay,
            integrator=int(integrator),
            cost=float("nan") if cost is None else float(cost),
            freq=np.asarray(data.get("freq", []), dtype=np.float64),
            hold=str(data.get("hold", "none")),
            sample_time=None if sample_time is None else float(sample_time),
            weights=str(data.get("weights", "variance")),
            stable=bool(data.get("stable", True)),
            nfev=int(data.get("nfev", 0)),
            gain_scale=float(data.get("gain_scale", 1.0)),
            status=FitStatus(str(data.get("status", "ok"))),
        )


def fit_parametric(
    bla: NonparametricBLA,
    *,
    numerator_order: int,
    denominator_order: int,
    integrator: bool | int = True,
    fit_delay: bool = True,
    delay: float = 0.0,
    max_delay: float | None = None,
    weights: Literal["variance", "relative", "uniform"] = "variance",
    hold: Literal["zoh", "none"] = "zoh",
    sk_iterations: int = 5,
    delay_grid: int = 41,
) -> ParametricBLA:
    """Fit ``G(s) = exp(-s tau) B(s) / (s^I A(s))`` to a nonparametric BLA.

    Frequency-domain estimation of a continuous-time model (Pintelon & Schoukens 2012, ch. 9):

    1. scaling: ``s`` is divided by ``w0 = sqrt(w_min w_max)`` and the data by their median
       magnitude, so the regressors are of order one (numerical conditioning);
    2. start: for every delay on a grid of ``delay_grid`` values in ``[0, max_delay]`` the data
       are de-rotated by ``exp(j w tau)`` and the rational part is fitted by Levy's (1959) linear
       least squares on ``s^I A G - B``, followed by ``sk_iterations`` Sanathanan-Koerner (1963)
       iterations (equation error divided by ``|s^I A_prev|``, approximating the output error;
       ch. 9); the grid point with the smallest weighted output error is kept;
    3. refinement: all parameters (coefficients and ``tau >= 0``) by weighted nonlinear least
       squares (``scipy.optimize.least_squares``, analytic Jacobian) on the complex output error
       ``G_model - G_data`` with weight ``1 / var_total`` (the maximum-likelihood cost of
       ch. 9, with a noise-free reference and known variances).

    With ``hold="zoh"`` the data are a discrete-time FRF of the plant seen through a zero-order
    hold (as measured by :func:`nonparametric_bla`): the model response is multiplied by
    ``(1 - exp(-j w Ts)) / (j w Ts)`` in the fit, so the fitted ``num``, ``den`` and ``delay``
    describe the continuous plant and its exact zero-order-hold discretization reproduces the
    data. Aliasing (the terms at ``w + 2 pi m / Ts``, ``m != 0``) is neglected, which is accurate
    when the plant rolls off well before the Nyquist frequency.

    Parameters
    ----------
    bla : NonparametricBLA
        The data: ``freq``, ``G`` and (for ``weights="variance"``) ``var_total``.
    numerator_order : int
        Order of ``B``.
    denominator_order : int
        Order of the monic ``A`` (the integrator poles not included).
    integrator : bool or int
        Number ``I`` of poles at s = 0 imposed (True = 1).
    fit_delay : bool
        Estimate the input delay; otherwise it is fixed to ``delay``.
    delay : float
        Fixed delay [s] when ``fit_delay`` is False.
    max_delay : float, optional
        Upper end of the delay grid of the start [s]; default ``0.25 / f_max`` (a quarter period
        at the highest frequency). The refinement may leave the grid.
    weights : {"variance", "relative", "uniform"}
        ``1 / var_total``, ``1 / |G|^2`` (relative error) or 1.
    hold : {"zoh", "none"}
        Account for a zero-order hold at ``bla.sample_time`` (see above) or not (continuous
        FRF data).
    sk_iterations : int
        Sanathanan-Koerner iterations per grid point.
    delay_grid : int
        Number of delays in the start grid.

    Returns
    -------
    ParametricBLA

    Raises
    ------
    HallcalInputError
        For invalid orders, too few data or unusable weights.
    """
    nb = _int_option(numerator_order, "numerator_order", minimum=0)
    na = _int_option(denominator_order, "denominator_order", minimum=0)
    n_int = _int_option(int(integrator), "integrator", minimum=0)
    n_par = nb + 1 + na + (1 if fit_delay else 0)
    data = _fit_data(bla, weights=weights, hold=hold, parameters=n_par)
    sc = _scaled_problem(data, _OrderSpec(nb, na, n_int, fit_delay), delay=delay)  # step 1
    start = _delay_grid_start(sc, _delay_grid(sc, data, max_delay, delay_grid), sk_iterations)
    fit = _output_error_refinement(sc, start)  # step 3
    num, den, stable = _unscaled_model(sc, fit)
    return ParametricBLA(
        num=num,
        den=den,
        delay=float(fit.tau / sc.w0),
        integrator=n_int,
        cost=fit.cost,
        freq=data.f,
        hold=hold,
        sample_time=data.sample_time,
        weights=weights,
        stable=stable,
        nfev=fit.nfev,
        status=FitStatus.OK if fit.converged else FitStatus.NOT_CONVERGED,
        deviations=_deviations(sc, fit),
    )


@dataclass(frozen=True, eq=False)
class _FitData:
    """The lines :func:`fit_parametric` fits: continuous-equivalent data and their variances."""

    f: np.ndarray  # frequencies [Hz]
    g: np.ndarray  # the BLA, divided by the zero-order-hold factor with hold="zoh"
    var: np.ndarray  # variance of g (or |G|^2 or 1, as the weights say)
    sample_time: float | None  # of the hold, None with hold="none"


def _fit_data(bla: NonparametricBLA, *, weights: str, hold: str, parameters: int) -> _FitData:
    """The usable lines of ``bla`` with their weights; the hold divided out with ``"zoh"``.

    With ``hold="zoh"`` the data and their variances are divided by the zero-order-hold factor
    ``(1 - exp(-j w Ts)) / (j w Ts)``, aliasing neglected (see :func:`fit_parametric`).
    """
    if hold not in ("zoh", "none"):
        raise HallcalInputError(f"hold must be 'zoh' or 'none', got {hold!r}")
    f = np.asarray(bla.freq, dtype=np.float64)
    g_data = np.asarray(bla.G, dtype=np.complex128)
    good = np.isfinite(f) & (f > 0.0) & np.isfinite(g_data)
    if weights == "variance":
        var = np.asarray(bla.var_total, dtype=np.float64)
        good &= np.isfinite(var)
        if not np.all(var[good] > 0.0):
            raise HallcalInputError(
                "weights='variance' needs positive var_total on every line; "
                "use weights='relative' for noise-free data"
            )
    elif weights == "relative":
        var = np.abs(g_data) ** 2
        good &= var > 0.0
    elif weights == "uniform":
        var = np.ones(f.size)
    else:
        raise HallcalInputError(
            f"weights must be 'variance', 'relative' or 'uniform', got {weights!r}"
        )
    f, g_data, var = f[good], g_data[good], var[good]
    if 2 * f.size < parameters + 1:
        raise HallcalInputError(f"{f.size} frequency lines are too few for {parameters} parameters")
    ts = bla.sample_time if hold == "zoh" else None
    if hold == "zoh":
        if ts is None or not (np.isfinite(ts) and ts > 0.0):
            raise HallcalInputError("hold='zoh' needs the sample_time of the BLA")
        zf = _zoh_factor(f, ts)
        g_data = g_data / zf  # continuous-equivalent data
        var = var / np.abs(zf) ** 2
    return _FitData(f, g_data, var, None if ts is None else float(ts))


@dataclass(frozen=True)
class _OrderSpec:
    """The model structure ``exp(-s tau) B(s) / (s^I A(s))``: orders of B and A, I, delay."""

    nb: int
    na: int
    n_int: int
    fit_delay: bool


@dataclass(frozen=True, eq=False)
class _ScaledProblem:
    """Step 1 of :func:`fit_parametric`: the data in the scaled Laplace variable ``s / w0``."""

    order: _OrderSpec
    w0: float  # frequency scale [rad/s]
    g0: float  # magnitude scale of the data
    s: np.ndarray  # scaled Laplace variable j w / w0
    gd: np.ndarray  # scaled data g / g0
    inv_sigma: np.ndarray  # 1 / standard deviation of gd
    fixed_tau: float  # the fixed delay, scaled by w0 (used without fit_delay)


def _scaled_problem(data: _FitData, order: _OrderSpec, *, delay: float) -> _ScaledProblem:
    """Step 1 of :func:`fit_parametric`: ``s`` divided by ``w0 = sqrt(w_min w_max)`` and the data
    by their median magnitude, so the regressors are of order one (Pintelon & Schoukens 2012,
    ch. 9, numerical conditioning)."""
    w = 2.0 * np.pi * data.f
    w0 = math.sqrt(w.min() * w.max())
    g0 = float(np.median(np.abs(data.g)))
    if g0 == 0.0:
        raise HallcalInputError("the BLA is zero")
    sigma = np.sqrt(data.var) / g0  # standard deviation of the scaled data
    fixed_tau = float(delay) * w0
    if not order.fit_delay and not (np.isfinite(fixed_tau) and fixed_tau >= 0.0):
        raise HallcalInputError(f"delay must be >= 0, got {delay!r}")
    return _ScaledProblem(order, w0, g0, 1j * w / w0, data.g / g0, 1.0 / sigma, fixed_tau)


def _delay_grid(
    sc: _ScaledProblem, data: _FitData, max_delay: float | None, points: int
) -> np.ndarray:
    """Scaled delays of the start grid: ``[0, max_delay]`` (default a quarter period at the
    highest frequency), or the fixed delay alone."""
    if not sc.order.fit_delay:
        return np.array([sc.fixed_tau])
    tau_max = (0.25 / data.f.max() if max_delay is None else float(max_delay)) * sc.w0
    return np.linspace(0.0, tau_max, max(int(points), 1))


@dataclass(frozen=True, eq=False)
class _StartValues:
    """Step 2 of :func:`fit_parametric`: the best grid point (scaled delay and coefficients)."""

    tau: float
    b: np.ndarray  # ascending coefficients of B
    a: np.ndarray  # ascending coefficients of A without its leading 1


def _delay_grid_start(sc: _ScaledProblem, taus: np.ndarray, sk_iterations: int) -> _StartValues:
    """Step 2 of :func:`fit_parametric`: Levy and Sanathanan-Koerner on every de-rotated delay.

    For every delay the data are de-rotated by ``exp(j w tau)`` and the rational part is fitted
    by :func:`_levy_sk` (Levy 1959; Sanathanan & Koerner 1963; Pintelon & Schoukens 2012,
    ch. 9); the delay with the smallest weighted output error is kept.
    """
    o = sc.order
    best: tuple[float, np.ndarray, np.ndarray, float] | None = None
    for tau in taus:
        b, a, cost = _levy_sk(
            sc.s, sc.gd * np.exp(sc.s * tau), sc.inv_sigma, o.nb, o.na, o.n_int, sk_iterations
        )
        if best is None or cost < best[3]:
            best = (tau, b, a, cost)
    assert best is not None
    return _StartValues(best[0], best[1], best[2])


class _OutputError:
    """Weighted output error ``(G_model - G_data) / sigma`` and its analytic Jacobian.

    Parameters theta: ascending coefficients of B, of A without its leading 1, and (with
    ``fit_delay``) the scaled delay; real and imaginary parts stacked (Pintelon & Schoukens 2012,
    ch. 9, the maximum-likelihood cost with known variances).
    """

    def __init__(self, sc: _ScaledProblem) -> None:
        o = sc.order
        self.sc, self.o = sc, o
        self.pow_b = sc.s[:, None] ** np.arange(o.nb + 1)  # ascending powers
        self.pow_a = sc.s[:, None] ** np.arange(o.na + 1)
        self.s_int = sc.s**o.n_int

    def unpack(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        o = self.o
        b = theta[: o.nb + 1]
        a = theta[o.nb + 1 : o.nb + 1 + o.na]
        tau = theta[-1] if o.fit_delay else self.sc.fixed_tau
        return b, a, tau

    def model(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        b, a, tau = self.unpack(theta)
        bs = self.pow_b @ b
        as_ = self.pow_a[:, : self.o.na] @ a + self.pow_a[:, self.o.na]
        e = np.exp(-self.sc.s * tau)
        return e * bs / (self.s_int * as_), bs, as_, e

    def residual(self, theta: np.ndarray) -> np.ndarray:
        err = (self.model(theta)[0] - self.sc.gd) * self.sc.inv_sigma
        return np.concatenate([err.real, err.imag])

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        gm, _, as_, e = self.model(theta)
        cols = [
            e[:, None] * self.pow_b / (self.s_int * as_)[:, None],
            -gm[:, None] * self.pow_a[:, : self.o.na] / as_[:, None],
        ]
        if self.o.fit_delay:
            cols.append((-self.sc.s * gm)[:, None])
        jac = np.concatenate(cols, axis=1) * self.sc.inv_sigma[:, None]
        return np.concatenate([jac.real, jac.imag], axis=0)


@dataclass(frozen=True, eq=False)
class _RefinedFit:
    """Step 3 of :func:`fit_parametric`: scaled coefficients, delay, cost and solver outcome."""

    b: np.ndarray
    a: np.ndarray
    tau: float
    cost: float
    nfev: int
    converged: bool
    covariance: np.ndarray | None = None  # of (b, a, tau) (scaled), None when J^T J is singular


def _output_error_refinement(sc: _ScaledProblem, start: _StartValues) -> _RefinedFit:
    """Step 3 of :func:`fit_parametric`: weighted nonlinear least squares on the output error.

    All parameters (coefficients and ``tau >= 0``) by ``scipy.optimize.least_squares`` with the
    analytic Jacobian of :class:`_OutputError` (Pintelon & Schoukens 2012, ch. 9); never worse
    than the start.
    """
    oe = _OutputError(sc)
    fit_delay = sc.order.fit_delay
    theta0 = np.concatenate([start.b, start.a, [start.tau] if fit_delay else []])
    lower = np.full(theta0.size, -np.inf)
    if fit_delay:
        lower[-1] = 0.0
    from scipy.optimize import least_squares  # only when a BLA is fitted (0.15 s import)

    sol = least_squares(
        oe.residual,
        theta0,
        jac=oe.jacobian,
        bounds=(lower, np.full(theta0.size, np.inf)),
        method="trf",
        x_scale="jac",
        ftol=1e-14,
        xtol=1e-14,
        gtol=1e-14,
        max_nfev=200 * (theta0.size + 1),
    )
    theta = sol.x
    b, a, tau = oe.unpack(theta)
    cost = float(np.sum(oe.residual(theta) ** 2))
    start_cost = float(np.sum(oe.residual(theta0) ** 2))
    if start_cost < cost:  # never worse than the linear start
        theta = theta0
        b, a, tau = oe.unpack(theta0)
        cost = start_cost
    return _RefinedFit(b, a, tau, cost, int(sol.nfev), sol.status > 0,
                       _covariance(oe.jacobian(theta), cost))  # fmt: skip


def _covariance(jac: np.ndarray, cost: float) -> np.ndarray | None:
    """Covariance of the weighted least-squares estimate, ``s^2 (J^T J)^-1`` with
    ``s^2 = max(1, cost / (rows - p))``: the variances of the data as given, or the fit's own
    residual level when the model does not reach them (structure error; Pintelon & Schoukens
    2012, sec. 9.11). None when ``J^T J`` is singular."""
    rows, p = jac.shape
    jtj = jac.T @ jac
    if rows <= p or not np.all(np.isfinite(jtj)) or np.linalg.cond(jtj) > 1e14:
        return None
    return np.linalg.inv(jtj) * max(1.0, cost / (rows - p))


def _deviations(
    sc: _ScaledProblem, fit: _RefinedFit
) -> tuple[tuple[np.ndarray, np.ndarray, float], ...]:
    """The model moved by one standard deviation along each principal direction of its
    covariance (``num``, ``den``, delay [s] each); the delay kept >= 0."""
    if fit.covariance is None:
        return ()
    lam, vec = np.linalg.eigh(0.5 * (fit.covariance + fit.covariance.T))
    theta = np.concatenate([fit.b, fit.a, [fit.tau] if sc.order.fit_delay else []])
    nb, na = sc.order.nb, sc.order.na
    out = []
    for k in range(theta.size):
        th = theta + math.sqrt(max(float(lam[k]), 0.0)) * vec[:, k]
        tau = max(float(th[-1]), 0.0) if sc.order.fit_delay else fit.tau
        moved = replace(fit, b=th[: nb + 1], a=th[nb + 1 : nb + 1 + na], tau=tau)
        num, den, _ = _unscaled_model(sc, moved)
        out.append((num, den, tau / sc.w0))
    return tuple(out)


def _unscaled_model(sc: _ScaledProblem, fit: _RefinedFit) -> tuple[np.ndarray, np.ndarray, bool]:
    """``num``, ``den`` in descending powers of the unscaled s, and whether A is stable."""
    nb, na, n_int = sc.order.nb, sc.order.na, sc.order.n_int
    w0 = sc.w0
    num_asc = sc.g0 * fit.b * w0 ** (na + n_int - np.arange(nb + 1))
    a_full = np.concatenate([fit.a, [1.0]])
    den_asc = a_full * w0 ** (na - np.arange(na + 1))
    num = num_asc[::-1].copy()
    den = np.concatenate([den_asc[::-1], np.zeros(n_int)])
    poles = np.roots(den_asc[::-1]) if na > 0 else np.array([])
    return num, den, bool(np.all(poles.real < 0.0))


def model_poles(model: ParametricBLA) -> np.ndarray:
    """Poles [rad/s] of a fitted model other than its imposed integrators, fastest first.

    Parameters
    ----------
    model : ParametricBLA
        The parametric fit of G(s) (section "Obtaining a Best Linear Approximation").

    Returns
    -------
    ndarray of complex
        Roots of the denominator in s [rad/s] without the integrators, largest magnitude first.
    """
    den = np.asarray(model.den, dtype=np.float64)
    core = den[: den.size - int(model.integrator)] if model.integrator else den
    poles = np.roots(core) if core.size > 1 else np.array([], dtype=np.complex128)
    return poles[np.argsort(-np.abs(poles))]


@dataclass(frozen=True, eq=False)
class OrderCandidate:
    """One model structure tried by :func:`select_order`.

    Attributes
    ----------
    numerator_order, denominator_order : int
        Orders of ``B`` and of the monic ``A`` (integrators not counted).
    parameters : int
        Real parameters fitted: ``numerator_order + 1 + denominator_order`` (+ 1 for the delay).
    cost : float
        Weighted output-error cost ``V = sum_k |G_model - G_data|^2 / var_total`` at the optimum.
    criterion : float
        Minimum description length ``V + parameters / 2 * ln(2 F)`` (F lines, 2F real data).
    stable : bool
        All poles other than the integrators in the open left half-plane.
    poles : tuple of complex
        Those poles [rad/s], fastest first.
    fit : ParametricBLA
        The fitted model.
    """

    numerator_order: int
    denominator_order: int
    parameters: int
    cost: float
    criterion: float
    stable: bool
    poles: tuple[complex, ...]
    fit: ParametricBLA = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (poles as ``[re, im]`` pairs in rad/s)."""
        return {
            "numerator_order": self.numerator_order,
            "denominator_order": self.denominator_order,
            "parameters": self.parameters,
            "cost": _float_or_none(self.cost),
            "criterion": _float_or_none(self.criterion),
            "stable": self.stable,
            "poles": _complex_pairs(np.asarray(self.poles, dtype=np.complex128)),
        }


@dataclass(frozen=True, eq=False)
class OrderSelection:
    """The model order chosen from the data (:func:`select_order`).

    Attributes
    ----------
    candidates : tuple of OrderCandidate
        Every structure tried, in increasing denominator order.
    chosen : OrderCandidate or None
        The stable candidate with the smallest criterion; None when no candidate is stable.
    lines : int
        Number F of frequency lines fitted.
    """

    candidates: tuple[OrderCandidate, ...]
    chosen: OrderCandidate | None
    lines: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "criterion": "minimum description length: cost + parameters / 2 * ln(2 lines)",
            "lines": self.lines,
            "chosen_denominator_order": (
                None if self.chosen is None else self.chosen.denominator_order
            ),
            "chosen_numerator_order": None if self.chosen is None else self.chosen.numerator_order,
            "candidates": [c.to_dict() for c in self.candidates],
        }


def select_order(
    bla: NonparametricBLA,
    *,
    numerator_order: int = 0,
    denominator_orders: Sequence[int] = (0, 1, 2, 3),
    integrator: bool | int = True,
    fit_delay: bool = True,
    **options: Any,
) -> OrderSelection:
    """Choose the denominator order of ``G(s) = exp(-s tau) B(s) / (s^I A(s))`` from the data.

    Every order in ``denominator_orders`` (from ``numerator_order`` up; the integrators are
    imposed, not counted) is fitted with :func:`fit_parametric` and weights ``1 / var_total``.
    For a model that explains the BLA within its variance the cost ``V`` is about the number of
    lines F, so a structure with too few poles shows as ``V >> F`` and extra poles buy little;
    the minimum description length ``V + n / 2 * ln(2 F)`` (n parameters, 2F real data; Pintelon
    & Schoukens 2012, ch. 11, model selection) weighs the two. Unstable fits (a pole in the right
    half-plane, typically an order the data do not support) are never chosen: the stable
    candidate with the smallest criterion is.

    Parameters
    ----------
    bla : NonparametricBLA
    numerator_order : int
        Order of ``B`` for every candidate (orders below it are skipped).
    denominator_orders : sequence of int
        Orders of ``A`` to try.
    integrator, fit_delay
        As for :func:`fit_parametric`.
    **options
        Passed to :func:`fit_parametric` (``weights``, ``hold``, ...).

    Returns
    -------
    OrderSelection
    """
    nb = _int_option(numerator_order, "numerator_order", minimum=0)
    n_int = _int_option(int(integrator), "integrator", minimum=0)
    orders = sorted({int(o) for o in denominator_orders if int(o) >= 0})
    lines = int(np.count_nonzero(np.isfinite(np.asarray(bla.G)) & (np.asarray(bla.freq) > 0)))
    candidates = []
    for na in orders:
        if nb > na + n_int:
            continue  # improper
        n_par = nb + 1 + na + (1 if fit_delay else 0)
        if 2 * lines < n_par + 1:
            continue
        fit = fit_parametric(
            bla,
            numerator_order=nb,
            denominator_order=na,
            integrator=n_int,
            fit_delay=fit_delay,
            **options,
        )
        poles = model_poles(fit)
        cost = float(fit.cost) if np.isfinite(fit.cost) else math.inf
        candidates.append(
            OrderCandidate(
                numerator_order=nb,
                denominator_order=na,
                parameters=n_par,
                cost=cost,
                criterion=cost + 0.5 * n_par * math.log(2 * max(lines, 1)),
                stable=bool(np.all(poles.real < 0.0)),
                poles=tuple(complex(p) for p in poles),
                fit=fit,
            )
        )
    if not candidates:
        raise HallcalInputError(
            f"no model order in {orders} can be fitted to {lines} lines with numerator order {nb}"
        )
    stable = [c for c in candidates if c.stable]
    chosen = min(stable, key=lambda c: c.criterion) if stable else None
    return OrderSelection(tuple(candidates), chosen, lines)


def _levy_sk(
    s: np.ndarray,
    g: np.ndarray,
    inv_sigma: np.ndarray,
    nb: int,
    na: int,
    n_int: int,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Levy start and Sanathanan-Koerner iterations for ``g ~ B(s) / (s^I A(s))``, A monic.

    Linear least squares on the weighted equation error ``(s^I A g - B) / (sigma |s^I A_prev|)``
    (Levy 1959 with ``A_prev = 1``; Sanathanan & Koerner 1963; Pintelon & Schoukens 2012,
    ch. 9). Returns the ascending coefficients of B and of A without its leading 1, and the
    weighted output-error cost of the best iterate.
    """
    h = g * s**n_int
    pow_b = s[:, None] ** np.arange(nb + 1)
    pow_a = s[:, None] ** np.arange(na + 1)
    phi = np.concatenate([pow_b, -h[:, None] * pow_a[:, :na]], axis=1)
    rhs = h * pow_a[:, na]
    weight = inv_sigma.copy()
    best: tuple[np.ndarray, np.ndarray, float] | None = None
    for _ in range(max(iterations, 0) + 1):
        mat = phi * weight[:, None]
        vec = rhs * weight
        mat_r = np.concatenate([mat.real, mat.imag])
        vec_r = np.concatenate([vec.real, vec.imag])
        norms = np.linalg.norm(mat_r, axis=0)
        norms[norms == 0.0] = 1.0
        theta = np.linalg.lstsq(mat_r / norms, vec_r, rcond=None)[0] / norms
        b = theta[: nb + 1]
        a = theta[nb + 1 :]
        a_s = pow_a[:, :na] @ a + pow_a[:, na]
        with np.errstate(divide="ignore", invalid="ignore"):
            out_err = (pow_b @ b / (s**n_int * a_s) - g) * inv_sigma
            cost = float(np.sum(np.abs(out_err) ** 2))
        if not np.isfinite(cost):
            cost = np.inf
        if best is None or cost < best[2]:
            best = (b, a, cost)
        if na == 0:
            break
        denom = np.abs(s**n_int * a_s)
        if not np.all(np.isfinite(denom) & (denom > 0.0)):
            break
        weight = inv_sigma / denom
    assert best is not None
    return best


def _zoh_factor(f: np.ndarray, ts: float) -> np.ndarray:
    """Zero-order-hold factor ``(1 - exp(-j w Ts)) / (j w Ts)`` (1 at w = 0)."""
    x = 2j * np.pi * np.asarray(f, dtype=np.float64) * ts
    out = np.ones(x.shape, dtype=np.complex128)
    nz = x != 0
    out[nz] = -np.expm1(-x[nz]) / x[nz]
    return out
