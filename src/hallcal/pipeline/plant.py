"""Step 2 of Algorithm 1: the plant model, from the setup or from a BLA experiment.

The BLA of the plant is identified in closed loop from multisine experiments (Pintelon &
Schoukens 2012, sec. 3.8, :mod:`hallcal.identify.bla`); because the measured position comes from
the imperfect f_init, the BLA is known up to a gain c, estimated from the calibration run
(the paper's eq. for c_hat, :func:`estimate_gain`) and refined jointly with theta in SEM.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.errors import CalibrationRefused, HallcalInputError
from hallcal.fit.sem import least_squares_start
from hallcal.io.dataset import Dataset
from hallcal.io.setup import Setup
from hallcal.messages import Graded, Message, MessageCode, has_warning
from hallcal.pipeline.boundary import numeric_errors
from hallcal.pipeline.checks import (
    BLAFitCheck,
    CheckStatus,
    check_bla_fit,
    check_recording,
    raise_if_failed,
)
from hallcal.pipeline.progress import Progress, say
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sim.loop import ClosedLoop, simulate_loop
from hallcal.sim.lti import ContinuousTF

if TYPE_CHECKING:
    from hallcal.identify import bla as _bla
    from hallcal.identify import parametric as _par

__all__ = [
    "BLAIdentification",
    "BLAStatus",
    "GainCorrection",
    "PlantModel",
    "closed_loop",
    "estimate_gain",
    "identify_bla",
    "plant_model",
]


#: A fit whose weighted cost exceeds this many times the number of lines leaves structure the
#: model lacks (a good fit gives about one per line; the variance estimate from M = 8
#: realizations inflates that by about 15 %).
COST_PER_LINE_WARNING = 3.0


class BLAStatus(Graded):
    """Outcome of the BLA identification: ``ok``, ``warning`` (usable, look at the messages) or
    ``refused`` (the plant model must not be used: :attr:`BLAIdentification.refusal` says why)."""

    OK = "ok"
    WARNING = "warning"
    REFUSED = "refused"


@dataclass(frozen=True)
class BLAIdentification:
    """The nonparametric BLA, its parametric fit and the plant model G(s) with its delay.

    Attributes
    ----------
    nonparametric : NonparametricBLA
    parametric : ParametricBLA
    plant : ContinuousTF
        The fitted G(s) with its delay (before the gain correction).
    status : BLAStatus
        A plain string is accepted and converted (``"ok"``; anything else is a warning).
    messages : tuple of Message
        What was chosen (the model order) and what to look at, one line each.
    refusal : str or None
        Why the model must not be used (``status`` refused), with the fix.
    selection : OrderSelection or None
        The model orders tried when ``[bla] denominator_order = "auto"`` (or to suggest one when
        the given order gave an unstable fit).
    check : BLAFitCheck or None
        Poles of the fitted model: unstable ones, ones the data do not determine.
    """

    nonparametric: _bla.NonparametricBLA = field(repr=False)
    parametric: _par.ParametricBLA = field(repr=False)
    plant: ContinuousTF
    status: BLAStatus = BLAStatus.OK
    messages: tuple[Message, ...] = ()
    refusal: str | None = None
    selection: _par.OrderSelection | None = field(default=None, repr=False)
    check: BLAFitCheck | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.status, BLAStatus):
            value = str(self.status)
            status = BLAStatus(value) if value in BLAStatus._value2member_map_ else None
            object.__setattr__(self, "status", status or BLAStatus.WARNING)

    def to_dict(self) -> dict[str, Any]:
        """The ``hallcal-bla/1`` JSON document written by ``hallcal bla``."""
        out: dict[str, Any] = {
            "format": "hallcal-bla/1",
            "plant": {
                "num": list(self.plant.num),
                "den": list(self.plant.den),
                "delay": self.plant.delay,
            },
            "status": self.status.value,
            "refusal": self.refusal,
            "messages": [m.record() for m in self.messages],
            "nonparametric": self.nonparametric.to_dict(),
            "parametric": self.parametric.to_dict(),
        }
        if self.selection is not None:
            out["order_selection"] = self.selection.to_dict()
        if self.check is not None:
            out["poles"] = [[p.real, p.imag] for p in self.check.poles]
        return out


def _fit_with_order(
    npb: _bla.NonparametricBLA, setup: Setup
) -> tuple[_par.ParametricBLA, int, _par.OrderSelection | None, list[Message]]:
    """The parametric fit with the setup's order, or with the order chosen from the data."""
    from hallcal.identify import parametric as _par

    spec = setup.bla
    assert spec is not None
    integrator, fit_delay = spec.integrator, spec.fit_delay
    messages: list[Message] = []
    if spec.denominator_order == "auto":
        selection = _par.select_order(
            npb, numerator_order=spec.numerator_order, integrator=integrator, fit_delay=fit_delay
        )
        chosen = selection.chosen or min(selection.candidates, key=lambda c: c.criterion)
        messages.append(
            Message.info(
                MessageCode.PLANT,
                f"plant model: denominator order {chosen.denominator_order} chosen from the "
                'data ([bla] denominator_order = "auto": of the orders 0..3 the stable one with '
                f"the smallest description length; weighted cost {chosen.cost:.4g} for "
                f"{selection.lines} lines)",
            )
        )
        return chosen.fit, chosen.denominator_order, selection, messages
    order = int(spec.denominator_order)
    fit = _par.fit_parametric(
        npb,
        numerator_order=spec.numerator_order,
        denominator_order=order,
        integrator=integrator,
        fit_delay=fit_delay,
    )
    supported: _par.OrderSelection | None = None
    if not fit.stable:  # find an order the data support, for the message
        supported = _par.select_order(
            npb, numerator_order=spec.numerator_order, integrator=integrator, fit_delay=fit_delay
        )
    return fit, order, supported, messages


def identify_bla(dataset: Dataset, setup: Setup, *, progress: Progress = None) -> BLAIdentification:
    """Closed-loop BLA from a multisine dataset (Pintelon & Schoukens 2012, sec. 3.8).

    The dataset needs columns r, u, y and realization; ``[bla]`` gives the period, the number of
    transient periods and the parametric model orders (``denominator_order = "auto"``: chosen
    from the data, :func:`hallcal.identify.parametric.select_order`). The fitted model is checked
    (:func:`~hallcal.pipeline.checks.check_bla_fit`): an unstable one is refused with the order
    to use named, poles the data cannot determine give a warning.

    Parameters
    ----------
    dataset : Dataset
        The multisine experiment (r, u, y, realization).
    setup : Setup
        With a ``[bla]`` table and the sample time.
    progress : callable, keyword-only, optional
        Called with a short message at each step.

    Returns
    -------
    BLAIdentification
        Check :attr:`BLAIdentification.status`; a refused one carries the reason and the fix in
        :attr:`BLAIdentification.refusal`.
    """
    spec = setup.bla
    if spec is None:
        raise HallcalInputError(
            f"{dataset.source}: a BLA experiment needs a [bla] table in the setup", key="bla"
        )
    dataset.require("r", "u", "y", "realization")
    raise_if_failed(
        check_recording(dataset, pole_pairs=setup.pole_pairs, sample_time=setup.sample_time),
        dataset.source,
    )
    from hallcal.identify import bla as _bla  # loaded only when a BLA is identified

    say(progress, "nonparametric BLA (indirect closed-loop method)")
    with numeric_errors(dataset.source, "bla"):
        npb = _bla.nonparametric_bla(
            dataset["r"],
            dataset["u"],
            dataset["y"],
            dataset["realization"].astype(int),
            period_samples=spec.period_samples,
            transient_periods=spec.transient_periods,
            sample_time=setup.sample_time,
        )
        auto = spec.denominator_order == "auto"
        say(
            progress,
            "parametric fit of G(s) with input delay"
            + (", model orders 0..3 compared" if auto else ""),
        )
        par, order, selection, messages = _fit_with_order(npb, setup)
        plant = ContinuousTF(tuple(par.num), tuple(par.den), max(float(par.delay), 0.0))
        suggestion = None
        if selection is not None and selection.chosen is not None:
            suggestion = selection.chosen.denominator_order
        check = check_bla_fit(
            par,
            denominator_order=order,
            max_frequency=float(np.max(npb.freq)),
            suggestion=suggestion,
            chosen_from_data=auto,
        )
    if npb.status != "ok":
        messages.append(
            Message.warning(
                MessageCode.BLA_EXPERIMENT,
                f"BLA experiment: {npb.status} ({npb.realizations} realizations x "
                f"{npb.periods} steady-state periods); the variances are incomplete",
            )
        )
    if par.status != "ok":
        messages.append(
            Message.warning(MessageCode.PLANT_FIT, "the parametric fit of G(s) did not converge")
        )
    lines = int(np.size(par.freq))
    if lines >= 10 and par.cost > COST_PER_LINE_WARNING * lines:
        messages.append(
            Message.warning(
                MessageCode.PLANT_MISFIT,
                f"the plant model leaves {par.cost / lines:.3g} times the BLA's variance per "
                "line (about 1 for a model that explains it): look at the Bode plot; raise "
                '[bla] denominator_order or use "auto"',
            )
        )
    refusal = None
    if check.status is CheckStatus.FAILED:
        status, refusal = BLAStatus.REFUSED, check.text
    else:
        if check.status is CheckStatus.WARNING:
            messages.append(check.to_message(MessageCode.PLANT_FIT))
        warned = has_warning(messages)
        status = BLAStatus.WARNING if warned else BLAStatus.OK
    return BLAIdentification(
        npb,
        par,
        plant,
        status,
        messages=tuple(messages),
        refusal=refusal,
        selection=selection,
        check=check,
    )


@dataclass(frozen=True)
class GainCorrection:
    """The gain correction c_hat of the paper: the BLA is known up to a constant c.

    Attributes
    ----------
    c : float
        Estimated factor; the corrected plant is c_hat * G_BLA (the paper writes
        G_BLA / c_hat with c the BLA's error; same thing).
    cost : float
        Mean square mismatch of y_sim and y [rad^2] at c.
    cost_unit : float
        The same at c = 1.
    rotations_data, rotations_sim : int
        Full rotations of the data and of the simulation at c (the paper's check).
    status : {"ok", "at-bound"}
        "at-bound" when the search ended on its bound (c outside the plausible range).
    c_refined, c_refined_std : float or None
        c after joint refinement with theta in SEM (``solve_sem(fit_gain=True)``) and its
        standard deviation: at the SEM optimum the flux model no longer masks the loop gain.
    """

    c: float
    cost: float
    cost_unit: float
    rotations_data: int
    rotations_sim: int
    status: Literal["ok", "at-bound"]
    c_refined: float | None = None
    c_refined_std: float | None = None

    @property
    def value(self) -> float:
        """The factor applied to the BLA: refined jointly with theta when available."""
        return self.c if self.c_refined is None else self.c_refined

    def to_dict(self) -> dict[str, Any]:
        return {
            k: getattr(self, k)
            for k in (
                "c",
                "c_refined",
                "c_refined_std",
                "cost",
                "cost_unit",
                "rotations_data",
                "rotations_sim",
                "status",
            )
        }


def estimate_gain(
    loop: ClosedLoop,
    r: NDArray[np.float64],
    y: NDArray[np.float64],
    flux: FluxModel,
    *,
    bounds: tuple[float, float] = (0.2, 5.0),
) -> GainCorrection:
    """Estimate the plant gain factor c (the paper's c_hat) from the calibration run.

    The paper matches the instant of the last full rotation between the closed-loop simulation
    (with theta_0 and the plant scaled by c) and the data. In a type-1 loop tracking a ramp the
    lag of y behind r is inversely proportional to the loop gain, so that instant moves with c.
    Here the whole trajectory is matched instead of one instant: ``c = argmin mean (y_sim,c -
    y)^2`` (a bounded scalar search on log c), which uses the same information with all samples
    and is insensitive to where the last rotation falls; the number of full rotations of both is
    reported as the paper's check.

    Parameters
    ----------
    loop : ClosedLoop
        The loop with the BLA plant (c = 1).
    r : ndarray (N,)
        Recorded reference [rad].
    y : ndarray (N,)
        Recorded f_init output [rad].
    flux : FluxModel
        The flux model of the simulation: the paper uses theta_0 (pure sinusoids), the
        pipeline the least-squares start (:func:`~hallcal.fit.sem.least_squares_start`).
    bounds : (float, float), keyword-only
        Search range of c.

    Returns
    -------
    GainCorrection
        c, the costs at c and at 1, both rotation counts and whether c hit a bound.
    """

    def cost(logc: float) -> float:
        res = simulate_loop(loop.with_plant_gain(math.exp(logc)), flux, r)
        if res.status != "ok":
            return 1e6
        return float(np.mean((res.y - y) ** 2))

    lo, hi = math.log(bounds[0]), math.log(bounds[1])
    grid = np.linspace(lo, hi, 13)
    vals = [cost(g) for g in grid]
    i = int(np.argmin(vals))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    import scipy.optimize  # only when a gain is estimated (0.15 s import)

    opt = scipy.optimize.minimize_scalar(
        cost, bounds=(a, b), method="bounded", options={"xatol": 1e-5}
    )
    c = float(math.exp(opt.x))
    sim = simulate_loop(loop.with_plant_gain(c), flux, r)
    at_edge = abs(opt.x - lo) < 1e-3 or abs(opt.x - hi) < 1e-3
    return GainCorrection(
        c=c,
        cost=float(opt.fun),
        cost_unit=cost(0.0),
        rotations_data=_full_rotations(y),
        rotations_sim=_full_rotations(sim.y) if sim.status == "ok" else -1,
        status="at-bound" if at_edge else "ok",
    )


def _full_rotations(y: NDArray[np.float64]) -> int:
    return int(math.floor(np.max(y) / TWO_PI))


def closed_loop(setup: Setup, plant: ContinuousTF) -> ClosedLoop:
    """The loop of the setup's controller around ``plant`` (exact ZOH with delay).

    Parameters
    ----------
    setup : Setup
        Gives C(q), T_s and n_m.
    plant : ContinuousTF
        G(s) (known, or the BLA's parametric model).

    Returns
    -------
    ClosedLoop
        The loop of eq. (state_eq) with f_init on the Clarke rows.

    Raises
    ------
    HallcalInputError
        No ``[controller]``, or a plant/controller the loop cannot use (named).
    """
    if setup.controller is None:
        raise HallcalInputError(
            "setup: closed-loop calibration needs a [controller] table", key="controller"
        )
    try:
        return ClosedLoop.from_transfer_functions(
            plant, setup.controller, setup.sample_time, setup.pole_pairs
        )
    except ValueError as exc:
        raise HallcalInputError(f"setup: [plant] and [controller]: {exc}", key="plant") from None


@dataclass(frozen=True)
class PlantModel:
    """The plant the calibration simulates, and where it came from.

    Attributes
    ----------
    plant : ContinuousTF
        G(s) with its delay, the gain correction applied.
    source : {"setup", "bla"}
        ``[plant]`` of the setup, or the BLA of a multisine experiment.
    note : str
        One sentence for the user: which plant is used and why.
    bla : BLAIdentification or None
    gain : GainCorrection or None
        Gain correction of the BLA (None for a given plant).
    where : str
        The BLA experiment's file (or ``"[plant]"``), for messages.
    """

    plant: ContinuousTF
    source: Literal["setup", "bla"]
    note: str
    bla: BLAIdentification | None = None
    gain: GainCorrection | None = None
    where: str = "[plant]"

    def deviations(self) -> tuple[ContinuousTF, ...]:
        """The plant moved by one standard deviation of its BLA fit along each principal
        direction of the fit's covariance (:attr:`ParametricBLA.deviations`), with the same gain
        correction; empty for a given ``[plant]``."""
        if self.bla is None or self.gain is None:
            return ()
        return tuple(
            ContinuousTF(tuple(num), tuple(den), max(float(delay), 0.0)).scaled(self.gain.value)
            for num, den, delay in self.bla.parametric.deviations
        )

    @property
    def name(self) -> str:
        """How messages name this plant: ``[plant]`` or ``the BLA of FILE (c = ...)``."""
        if self.source == "setup":
            return "[plant]"
        c = "" if self.gain is None else f", gain-corrected with c = {self.gain.value:.4g}"
        return f"the BLA of {self.where}{c}"


def plant_model(
    dataset: Dataset,
    setup: Setup,
    *,
    bla_dataset: Dataset | None = None,
    bla: BLAIdentification | None = None,
    start_harmonics: tuple[int, ...] | None = None,
    progress: Progress = None,
) -> PlantModel:
    """Choose and, if needed, identify the plant model (step 2 of Algorithm 1).

    A BLA experiment (``bla_dataset`` or an identified ``bla``) wins over ``[plant]``: it is the
    measurement of this motor, while ``[plant]`` also serves the virtual bench; the returned
    :attr:`PlantModel.note` says which one is used. Without either, the plant is unknown.

    Parameters
    ----------
    dataset : Dataset
        The calibration run (columns r, y, d1..d3) for the gain correction c_hat.
    setup : Setup
    bla_dataset : Dataset, optional
        Multisine experiment.
    bla : BLAIdentification, optional
        An already identified BLA.
    start_harmonics : tuple of int, optional
        Harmonics of the least-squares flux model used for the gain search (default 1..n_m).
    progress : callable, optional
        Called with a short message per step.

    Returns
    -------
    PlantModel
    """
    if bla is None and bla_dataset is None:
        if setup.plant is None:
            raise HallcalInputError(
                "setup: no [plant] table and no BLA experiment (--bla-data): the plant model G "
                "is unknown",
                key="plant",
            )
        return PlantModel(setup.plant, "setup", "plant: G(s) from the setup's [plant] table")
    if bla is None:
        assert bla_dataset is not None
        bla = identify_bla(bla_dataset, setup, progress=progress)
        where = bla_dataset.source
    else:
        where = "the given BLA"
    if bla.status is BLAStatus.REFUSED:
        raise CalibrationRefused(
            f"{where}: {bla.refusal} (nothing was calibrated)", key="bla.denominator_order"
        )
    if "y" not in dataset:
        raise HallcalInputError(
            f"{dataset.source}: column 'y' is missing (needed for the gain correction c)",
            key="y",
        )
    say(progress, "gain correction c of the BLA (the paper's c-hat)")
    n_m = setup.pole_pairs
    basis = FourierBasis(start_harmonics or tuple(range(1, n_m + 1)))
    d = np.ascontiguousarray(dataset.d)
    y = np.ascontiguousarray(dataset["y"])
    loop = closed_loop(setup, bla.plant)
    with numeric_errors(dataset.source, "plant"):
        flux0 = FluxModel(basis, least_squares_start(basis, d, y))
        gain = estimate_gain(loop, dataset["r"], y, flux0)
    named = where if where != "<dataset>" else "the multisine experiment"  # in-memory data
    note = f"plant: the BLA identified from {named}, gain-corrected with the calibration run"
    if setup.plant is not None:
        note += (
            " (it wins over the setup's [plant], which is not used for calibration and serves "
            "only the virtual bench of `hallcal simulate`)"
        )
    return PlantModel(bla.plant.scaled(gain.c), "bla", note, bla=bla, gain=gain, where=where)
