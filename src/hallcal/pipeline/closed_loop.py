"""Algorithm 1 on a closed-loop calibration run (the paper's setting), step by step.

(1) the calibration data: reference r, f_init output y and Hall signals d of a ramp tracked with
f_init feedback; (2) the plant: ``[plant]`` or the BLA with its gain correction
(:mod:`hallcal.pipeline.plant`); (3) simulation-error minimization of g_theta through the closed
loop (:mod:`hallcal.fit.sem`, the kernel basis in :mod:`hallcal.fit.kernel`, the automatic
harmonics in :mod:`hallcal.fit.order`); (4) the lookup table and its bijectivity check; the
model-adequacy verdict (:mod:`hallcal.fit.adequacy`); (5) validation against ``y_ref`` when the
recording has one.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalError, HallcalInputError
from hallcal.fit.adequacy import AdequacyReport, ErrorSource, assess
from hallcal.fit.cogging_search import CoggingSelection, CoggingStatus, select_cogging
from hallcal.fit.offset_variance import offset_excess, offset_loop_excess
from hallcal.fit.ramp_design import RampPrediction, plan_ramp, speed_limits
from hallcal.fit.sem import SEMResult, SEMStatus, solve_sem
from hallcal.io.dataset import Dataset
from hallcal.io.setup import Setup
from hallcal.messages import Message, MessageCode, has_warning
from hallcal.pipeline import sensors
from hallcal.pipeline.boundary import numeric_errors
from hallcal.pipeline.calibration import (
    Calibration,
    CalibrationStatus,
    Diagnostics,
    computed_calibration,
    validate,
)
from hallcal.pipeline.checks import (
    CheckStatus,
    check_direction,
    check_hall_motion,
    check_loop,
    check_pole_pairs,
    check_recording,
    hall_lag_correlation,
)
from hallcal.pipeline.observe import FOLDING_NOTE, observer_check, observer_section
from hallcal.pipeline.plant import BLAIdentification, PlantModel, closed_loop, plant_model
from hallcal.pipeline.plant_refine import PlantRefinement, refine_plant
from hallcal.pipeline.powerup import drift_message, power_up_analysis
from hallcal.pipeline.progress import Progress, say
from hallcal.pipeline.verdict import decide
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sensor.reconstruction import f_init
from hallcal.sim.loop import ClosedLoop

if TYPE_CHECKING:
    from hallcal.fit.kernel import KernelSEMResult
    from hallcal.fit.order import HarmonicSelection
    from hallcal.sensor.observer import Injectivity

__all__ = ["calibrate_closed_loop"]


@dataclass(frozen=True)
class _Signals:
    """Step 1: the recorded signals as contiguous float64 arrays."""

    r: NDArray[np.float64]
    d: NDArray[np.float64]
    y: NDArray[np.float64]
    messages: tuple[Message, ...]


def _signals(dataset: Dataset, pole_pairs: int) -> _Signals:
    """r, d and y of the run; y is recomputed from d when the column is absent.

    Raises
    ------
    HallcalInputError
        Missing columns, or a run shorter than one revolution (the flux model is periodic over
        one revolution and must see all of it).
    """
    dataset.require("r", "d1", "d2", "d3")
    d = np.ascontiguousarray(dataset.d)
    y_clarke = f_init(d, pole_pairs)
    span = float(np.ptp(y_clarke))
    if span * pole_pairs < TWO_PI:
        raise HallcalInputError(
            f"{dataset.source}: the recording covers less than one electrical period "
            f"({span * pole_pairs / TWO_PI:.2f}); nothing to calibrate"
        )
    if span < TWO_PI:
        raise HallcalInputError(
            f"{dataset.source}: the recording covers {span / TWO_PI:.2f} revolutions; the flux "
            "model is periodic over one revolution and needs at least one full revolution"
        )
    messages: tuple[Message, ...] = ()
    if "y" in dataset:
        y = np.ascontiguousarray(dataset["y"])
        mismatch = float(np.max(np.abs(y - y_clarke)))
        if mismatch > 1e-6 * max(1.0, float(np.max(np.abs(y)))) + 1e-9:
            messages = (
                Message.warning(
                    MessageCode.Y_COLUMN_MISMATCH,
                    f"column 'y' differs from the Clarke/atan2 f_init of d by up to "
                    f"{mismatch:.3g} rad; the loop is simulated with the paper's f_init",
                ),
            )
    else:
        y = y_clarke
    return _Signals(np.ascontiguousarray(dataset["r"]), d, y, messages)


#: Samples of the warm-up fit that compiles the kernels on a cold cache: enough for every code
#: path of the fit, small enough to cost a fraction of a second once compiled.
WARM_SAMPLES = 4000


def _kernels_cached() -> bool:
    """Whether numba's on-disk cache holds the loop kernels (else this run compiles them)."""
    from hallcal.sim import loop_kernel

    kernel = loop_kernel.simulate
    try:
        index = kernel._cache._cache_file._index_path  # type: ignore[attr-defined]  # numba private
    except AttributeError:  # another numba: cannot tell, so say nothing
        return True
    return bool(kernel.signatures) or os.path.exists(index)


def _warm_kernels(loop: ClosedLoop, s: _Signals, setup: Setup, *, fit_gain: bool) -> None:
    """Compile the fit's kernels on a strided copy of the run (a cold numba cache only), so
    that the SEM's solve time is the solve's and not numba's compilation."""
    step = max(1, s.r.size // WARM_SAMPLES)
    small = _Signals(
        np.ascontiguousarray(s.r[::step]),
        np.ascontiguousarray(s.d[::step]),
        np.ascontiguousarray(s.y[::step]),
        (),
    )
    quick = dataclasses.replace(setup, model=dataclasses.replace(setup.model, max_iterations=2))
    try:
        with np.errstate(all="ignore"):
            fit = _fit_fourier(loop, small, quick, fit_gain=fit_gain, progress=None)
            _with_cogging(loop, small, quick, fit, fit_gain=fit_gain, progress=None)
    except (HallcalError, ArithmeticError, ValueError, np.linalg.LinAlgError):
        pass  # a warm-up only: the fit on the whole run says what is wrong, if anything


@dataclass(frozen=True)
class _ModelFit:
    """Step 3: the identified flux model and how it was found."""

    sem: SEMResult
    flux: FluxModel
    model_info: dict[str, Any]
    gain_factor: float = 1.0
    gain_factor_std: float = 0.0
    selection: HarmonicSelection | None = None
    kernel: KernelSEMResult | None = None
    adequacy: AdequacyReport | None = None
    cogging: CoggingSelection | None = None


def _fit_kernel(loop: ClosedLoop, s: _Signals, setup: Setup, *, progress: Progress) -> _ModelFit:
    from hallcal.fit.kernel import solve_kernel_sem  # loaded only for this basis

    say(progress, f"SEM with the periodic kernel basis (m = {setup.model.points})")
    kres = solve_kernel_sem(
        loop,
        s.r,
        s.d,
        points=setup.model.points,
        lengthscale=setup.model.lengthscale,
        y=s.y,
        max_iterations=setup.model.max_iterations,
    )
    info: dict[str, Any] = {
        "basis": "kernel",
        "points": int(kres.basis.points),
        "lengthscale": float(kres.lengthscale),
        "sf": float(kres.sf),
        "penalty": float(kres.penalty),
        "criterion": str(kres.criterion),
        "weights": np.asarray(kres.weights).tolist(),
        "harmonics": list(kres.flux.basis.harmonics),
        "theta": kres.flux.theta.tolist(),
    }
    return _ModelFit(sem=kres.sem, flux=kres.flux, model_info=info, kernel=kres)


def _fourier_info(flux: FluxModel) -> dict[str, Any]:
    return {
        "basis": "fourier",
        "harmonics": list(flux.basis.harmonics),
        "theta": flux.theta.tolist(),
    }


#: Iterations of the first flux-only fit when the cogging search follows (it starts the joint
#: fit; the fit is finished from there when no cogging is found).
_FIRST_ITERATIONS = 10


def _fit_fourier(
    loop: ClosedLoop, s: _Signals, setup: Setup, *, fit_gain: bool, progress: Progress
) -> _ModelFit:
    """SEM with the given harmonics, or with the harmonics chosen from the data ("auto").

    With a BLA plant (``fit_gain``) the gain c is refined jointly with theta at the end.
    """
    harmonics = setup.model.harmonics
    max_it = setup.model.max_iterations
    selection = None
    adequacy = None
    if harmonics == "auto":
        from hallcal.fit.order import select_harmonics  # loaded only for the automatic choice

        say(progress, "choosing the harmonics from the data")
        selection = select_harmonics(
            loop, s.r, s.d, y=s.y, pole_pairs=setup.pole_pairs, max_iterations=max_it,
            first_iterations=min(max_it, _FIRST_ITERATIONS) if setup.model.cogging == "auto"
            else None,
        )  # fmt: skip
        sem = selection.sem
        adequacy = selection.report
        if fit_gain:
            say(progress, "SEM with the chosen harmonics, refining the plant gain c")
            sem = solve_sem(
                loop,
                s.r,
                s.d,
                sem.flux.basis,
                theta0=sem.flux.theta,
                max_iterations=max_it,
                fit_gain=True,
            )
            adequacy = None  # judged again on the refined fit
    else:
        basis = FourierBasis(tuple(harmonics))
        gain_note = ", refining the plant gain c" if fit_gain else ""
        say(progress, f"SEM, Fourier basis with {len(harmonics)} harmonics{gain_note}")
        sem = solve_sem(loop, s.r, s.d, basis, y=s.y, max_iterations=max_it, fit_gain=fit_gain)
    return _ModelFit(
        sem=sem,
        flux=sem.flux,
        model_info=_fourier_info(sem.flux),
        gain_factor=sem.gain,
        gain_factor_std=sem.gain_std,
        selection=selection,
        adequacy=adequacy,
    )


def _with_cogging(
    loop: ClosedLoop, s: _Signals, setup: Setup, fit: _ModelFit, *, fit_gain: bool,
    progress: Progress,
) -> _ModelFit:  # fmt: skip
    """The cogging torque at the plant input, identified jointly with the flux.

    ``[model] cogging``: "none" keeps the fit; given orders are fitted jointly; "auto" looks for
    cogging in the fit's residual and keeps only orders whose coefficients are significant
    (:func:`hallcal.fit.cogging_search.select_cogging`). When cogging is found and the harmonics
    chosen from the data went beyond the band of the first fit (harmonics added from the residual
    or a widened band), they are chosen again with the identified torque in the loop (so that no
    flux harmonic is picked to absorb the cogging motion), warm from the joint fit, and the final
    fit is joint. Otherwise the joint fit of the cogging search is the final one: the band and the
    evidence within it come from f_init's view of the flux and do not see the motion.
    """
    orders = setup.model.cogging
    if orders == "none":
        return fit
    say(progress, "cogging torque" + (" (looking for it in the residual)" if orders == "auto"
                                       else f" at orders {list(orders)}"))  # fmt: skip
    # a constant load torque (order 0) is tried with a given plant only: with a BLA plant the
    # gain c refined jointly takes up its steady effect (on a constant-speed ramp a constant
    # torque and a gain error both set the loop's steady lag); fitted together, the paper
    # study's c came out 2.3 % off the truth (within 2 % without order 0)
    sel = select_cogging(
        loop, s.r, s.d, fit.sem, orders=orders, fit_gain=fit_gain,
        max_iterations=setup.model.max_iterations, load=not fit_gain,
    )  # fmt: skip
    if sel.status is CoggingStatus.NONE:
        fit = _to_convergence(loop, s, setup, fit, fit_gain=fit_gain, progress=progress,
                              why="no cogging found")  # fmt: skip
        return dataclasses.replace(fit, cogging=sel)
    sem, selection, adequacy = sel.sem, fit.selection, None
    if selection is not None and sel.cogging is not None:
        from hallcal.fit.order import select_harmonics, shape_off  # loaded with the selection

        adequacy = assess(sem, s.d, pole_pairs=setup.pole_pairs, projection=loop.projection,
                          offset=loop.offset)  # fmt: skip
    if (
        selection is not None
        and sel.cogging is not None
        and adequacy is not None
        and (
            any(c.accepted and c.stage in ("extended", "widened") for c in selection.candidates)
            or shape_off(adequacy)
        )
    ):
        say(progress, "choosing the harmonics again with the cogging torque in the loop")
        known = loop.with_plant_gain(sem.gain).with_cogging(sel.cogging)
        selection = select_harmonics(
            known, s.r, s.d, y=s.y, pole_pairs=setup.pole_pairs,
            max_iterations=setup.model.max_iterations, start=sem.flux,
        )  # fmt: skip
        sem = solve_sem(
            loop, s.r, s.d, selection.sem.flux.basis, theta0=selection.sem.flux.theta,
            fit_gain=fit_gain, gain0=sem.gain, cogging=sel.cogging,
            max_iterations=setup.model.max_iterations,
        )  # fmt: skip
        sel = dataclasses.replace(sel, sem=sem, cogging=sem.cogging)
        adequacy = None  # judged again on the final fit
    return dataclasses.replace(
        fit, sem=sem, flux=sem.flux, model_info=_fourier_info(sem.flux), gain_factor=sem.gain,
        gain_factor_std=sem.gain_std, selection=selection, adequacy=adequacy, cogging=sel,
    )  # fmt: skip


def _to_convergence(
    loop: ClosedLoop, s: _Signals, setup: Setup, fit: _ModelFit, *, fit_gain: bool,
    progress: Progress, why: str,
) -> _ModelFit:  # fmt: skip
    """The flux-only fit finished to convergence when an iteration cap below
    ``[model] max_iterations`` stopped it (the first fit's, :data:`_FIRST_ITERATIONS`, or the
    harmonic search's work budget), else ``fit``; ``why`` is said with the step."""
    capped = (
        fit.sem.status is SEMStatus.MAX_ITERATIONS
        and fit.sem.iterations < setup.model.max_iterations
    )
    if not capped:
        return fit
    say(progress, f"SEM with the chosen harmonics, to convergence ({why})")
    sem = solve_sem(
        loop, s.r, s.d, fit.sem.flux.basis, theta0=fit.sem.flux.theta, fit_gain=fit_gain,
        gain0=fit.sem.gain, max_iterations=setup.model.max_iterations,
    )  # fmt: skip
    return dataclasses.replace(
        fit, sem=sem, flux=sem.flux, model_info=_fourier_info(sem.flux), gain_factor=sem.gain,
        gain_factor_std=sem.gain_std, adequacy=None,
    )  # fmt: skip


def _cogging_unaffordable(
    loop: ClosedLoop, s: _Signals, setup: Setup, fit: _ModelFit
) -> Message | None:
    """Why the cogging search is skipped (a warning), or None to run it.

    Every step of the model choice is bounded in work (:mod:`hallcal.fit.order`), but the
    cogging search (:func:`hallcal.fit.cogging_search.select_cogging`) refits the whole model
    several times, each fit to convergence. When one SEM fit of the harmonics the data ask for
    already used up the harmonic search's work budget (:data:`hallcal.fit.order.WORK_BUDGET`,
    iterations times N p^2; the search's status WORK_BUDGET after its first fit), the cogging
    search would cost many such budgets and is skipped: the warning says so (the calibration is
    a warning at best) and how to model a known torque (given orders: one joint fit). Unmodelled
    motion, if any, still shows in the adequacy check's cost and is counted in the predicted
    error (:func:`hallcal.fit.adequacy.motion_bias`).

    Measured on the unseen zoo motor 178 (``benchmarks/bench_bigmotor.txt``: 24 pole pairs, a
    clipped sensor, 1.5 revolutions, 100 000 samples, no cogging in its truth): 192 harmonics,
    p = 1155, the first fit stopped by the budget after 3 of its 10 iterations; the search took
    8 fits of 1157-1181 parameters (94 iterations, about 200 s) to find a false torque at 48/rev:
    calibrate 292 s wall, N p^2 / stride 6.1e12; with the search skipped 49 s, 6.6e11, the same
    verdict (refused at 22x the noise floor: the run determines the table too poorly) and its
    table 14.7x the floor instead of 16.0x. No other motor of the benchmarks comes near the
    budget in one fit (the largest first fit, ``bench_bigmotor`` seed 16 on 25 000 samples:
    2.8e10 per iteration against 178's 1.3e11, room for 20).
    """
    sel = fit.selection
    if setup.model.cogging != "auto" or sel is None or sel.fits != 1:
        return None
    from hallcal.fit.order import SelectionStatus  # loaded with the selection

    if sel.status is not SelectionStatus.WORK_BUDGET:
        return None
    h = fit.sem.flux.basis.harmonics
    revs = abs(float(s.r[-1] - s.r[0])) / TWO_PI
    return Message.warning(
        MessageCode.COGGING,
        f"cogging: not searched: one SEM fit of the {len(h)} harmonics up to {max(h)} the data "
        f"ask for ({fit.sem.flux.theta.size} flux parameters, {s.r.size} samples over "
        f"{revs:.3g} revolutions) used up the harmonic search's work budget, and the search "
        "refits the model several times; a known torque can be given as cogging = [orders] "
        "(one joint fit)",
    )


def _final_fit(
    loop: ClosedLoop, s: _Signals, setup: Setup, fit: _ModelFit, found: sensors.SensorFindings,
    *, fit_gain: bool, progress: Progress,
) -> tuple[_ModelFit, _Signals]:  # fmt: skip
    """The chosen model refitted without the censored samples and with the sensors' drift
    (:func:`hallcal.pipeline.sensors.final_fit`), when there are any."""
    out = sensors.final_fit(loop, s.r, s.d, fit.sem, found, fit_gain=fit_gain, progress=progress,
                            max_iterations=setup.model.max_iterations)  # fmt: skip
    if out is None:
        return fit, s
    sem, d = out
    cog = fit.cogging.refitted(sem) if fit.cogging is not None else None
    retest = cog.load_retest(sem) if cog is not None and found.drifting else None
    if cog is not None and retest is not None:
        # the search's constant load may stand in for the drift (cogging_search, "A constant
        # load torque"): tested again with the drift, and refitted without it when it fails
        again = None if retest.significant else sensors.final_fit(
            loop, s.r, s.d, dataclasses.replace(sem, cogging=cog.without_load()), found,
            fit_gain=fit_gain, progress=progress, max_iterations=setup.model.max_iterations,
        )  # fmt: skip
        sem, d = again or (sem, d)
        cog = cog.load_retested(sem, retest)
    fit = dataclasses.replace(
        fit, sem=sem, flux=sem.flux, model_info=_fourier_info(sem.flux), gain_factor=sem.gain,
        gain_factor_std=sem.gain_std, adequacy=None, cogging=cog,
    )  # fmt: skip
    return fit, dataclasses.replace(s, d=d)


#: Predicted / floor above which calibrate says how fast a ramp would have to be.
RAMP_ADVICE = 1.5

#: A faster ramp is advised only when its prediction is below this fraction of the run's own;
#: above, the advice says speed would not help (unseen zoo motor 178, 24 pole pairs on 1.5
#: revolutions: 22.38x at the run's speed and 22.37x at four times it, which was advised as
#: "record more revolutions, faster").
FASTER_HELPS = 0.9


def _ramp_advice(
    loop: ClosedLoop, setup: Setup, s: _Signals, fit: _ModelFit, ratio: float
) -> str | None:
    """One line on the ramp speed that would determine the table (:mod:`hallcal.fit.ramp_design`).

    A slow ramp on a fast loop leaves angle warps at low spatial frequency to the loop's
    sensitivity S, which is tiny there; the same revolutions at a higher speed inform them. The
    candidates double the run's speed up to the fastest the flux band allows; the first within
    1.1 x floor is named. None for the kernel basis (no layout) or a run that is not a ramp.
    """
    sem = fit.sem
    if sem is None or sem.layout is None or setup.model.basis != "fourier":
        return None
    r = np.asarray(s.r, dtype=np.float64)
    span = abs(float(r[-1] - r[0]))
    if r.size < 2 or span <= 0:
        return None
    v0 = span / ((r.size - 1) * setup.sample_time)
    revs = span / TWO_PI
    x = sem.layout.pack(sem.flux.theta, 0.0, sem.cogging)  # the loop's plant holds the gain c
    _, v_max = speed_limits(loop, sem.layout, revs)
    speeds = v0 * 2.0 ** np.arange(1, 40)
    speeds = speeds[speeds <= v_max]
    head = (
        f"ramp speed: at {v0:.3g} rad/s the loop hides part of the sensor error (the covariance "
        f"predicts {ratio:.2g}x the noise floor)"
    )
    if speeds.size == 0:
        return (
            f"{head}; a faster ramp would leave too few samples per flux period or per "
            "parameter: record more revolutions"
        )
    plan = plan_ramp(loop, sem.layout, x, noise_variance=sem.noise_variance, revolutions=revs,
                     speeds=speeds, stop_at_target=True)  # fmt: skip
    best = plan.recommended
    if best is None:
        return None
    return f"{head}; {_speed_advice(best, ratio, revs, reaches_target=plan.status.success)}"


def _speed_advice(
    best: RampPrediction, ratio: float, revolutions: float, *, reaches_target: bool
) -> str:
    """What the ramp plan's best speed says to do next, in words that follow its numbers.

    ``ratio`` is the run's own predicted / floor; ``best`` the plan's recommended faster speed.
    Faster is advised only when it predicts less than :data:`FASTER_HELPS` x ``ratio``.
    """
    if reaches_target:
        return (
            f"the same {revolutions:.3g} revolutions at >= {best.speed:.3g} rad/s "
            f"({best.samples} samples) are predicted at {best.ratio:.2f}x: record the next "
            "run faster (hallcal plan shows the curve)"
        )
    if best.ratio > FASTER_HELPS * ratio:
        return (
            f"a faster ramp would not help (at {best.speed:.3g} rad/s: {best.ratio:.2f}x): "
            "record more revolutions (hallcal plan shows the curve)"
        )
    return (
        f"at {best.speed:.3g} rad/s it would be {best.ratio:.2f}x: record more revolutions, "
        "faster (hallcal plan shows the curve)"
    )


def _unmodelled_cogging_bias(
    loop: ClosedLoop, s: _Signals, setup: Setup, fit: _ModelFit, lut: LUT
) -> tuple[float, Message | None]:
    """How far unmodelled cogging may have moved the table, when cogging is not modelled.

    A position-periodic motion error that the model lacks is partly absorbed by flux harmonics
    at its sidebands: a bias of the table that no covariance shows (the residual no longer
    carries it). With ``cogging = "none"`` and a warning from the adequacy check, the cogging
    search is run as a diagnostic; when it finds cogging, the RMS difference (about zero: the
    offset included, as in the predicted error) between the two tables estimates that bias, and
    is added to the predicted error. ``loop``
    is the final one (a BLA plant with its refined gain), so the gain stays fixed here.
    """
    if setup.model.cogging != "none" or setup.model.basis != "fourier":
        return 0.0, None
    diag = select_cogging(loop, s.r, s.d, fit.sem, orders="auto",
                          max_iterations=setup.model.max_iterations)  # fmt: skip
    if diag.cogging is None:
        return 0.0, None
    alt = build_lut(diag.sem.flux, setup.pole_pairs, points=setup.model.lut_points,
                    projection=loop.projection, offset=loop.offset)  # fmt: skip
    bias = _table_shift(lut, alt)
    orders = ", ".join(str(k) for k in diag.orders)
    return bias, Message.warning(
        MessageCode.UNMODELLED_COGGING,
        f"the residual shows a cogging torque at {orders}/rev that is not modelled "
        f'(cogging = "none"); modelled, it moves the table by {1e3 * bias:.3g} mrad RMS, '
        'which the predicted error includes: set cogging = "auto"',
    )


def _table_shift(lut: LUT, other: LUT) -> float:
    """RMS difference of two tables over the revolution [rad], about zero (their offset
    included, as in the predicted error)."""
    y = TWO_PI * np.arange(4096) / 4096
    return float(np.sqrt(np.mean((lut.correction(y) - other.correction(y)) ** 2)))


def _refined_plant(
    pm: PlantModel, fit: _ModelFit, refinement: PlantRefinement | None = None
) -> PlantModel:
    """Apply the gain refined jointly with theta to a BLA plant (no-op for a given plant); with
    a refinement of the BLA's shape (:mod:`hallcal.pipeline.plant_refine`), to that shape."""
    if pm.gain is None or pm.bla is None:
        return pm
    c, shape = (pm.gain.c, pm.bla.plant) if refinement is None else (
        refinement.gain, refinement.shape)  # fmt: skip
    c_refined = c * fit.gain_factor
    gain = dataclasses.replace(pm.gain, c_refined=c_refined, c_refined_std=c * fit.gain_factor_std)
    return dataclasses.replace(pm, plant=shape.scaled(c_refined), gain=gain)


def _folding_ok(adequacy: AdequacyReport, observer: Injectivity | None) -> bool:
    """A table that cannot exist (folding map) keeps the model for the observer when the
    three-signal curve is injective (``observer``) and the model fits the data (the adequacy
    check's other rules)."""
    fail = adequacy.thresholds.get("fail_ratio", math.inf)
    return (
        observer is not None
        and observer.injective
        and adequacy.shape_ratio <= fail
        and not (adequacy.suggested_harmonics and adequacy.ratio > fail)
    )


def calibrate_closed_loop(
    dataset: Dataset,
    setup: Setup,
    *,
    bla_dataset: Dataset | None = None,
    bla: BLAIdentification | None = None,
    progress: Progress = None,
) -> Calibration:
    """Algorithm 1 on a closed-loop run: plant, SEM, table, verdict, validation.

    Parameters
    ----------
    dataset : Dataset
        Calibration run with columns r, d1..d3 (and y, needed with a BLA plant).
    setup : Setup
    bla_dataset : Dataset, optional
        Multisine experiment for the plant (wins over ``[plant]``, see
        :func:`~hallcal.pipeline.plant.plant_model`).
    bla : BLAIdentification, optional
        An already identified BLA.
    progress : callable, optional
        Called with a short message at each step.

    Returns
    -------
    Calibration
        Status, refusal, flux model, table, predicted error, plant and gain correction,
        messages and (with ``y_ref``) validation.
    """
    timings: dict[str, float] = {}
    dataset.require("r", "d1", "d2", "d3")
    say(progress, "checking pole pairs and direction against the reference")
    # the Hall signals' lag-1 correlation, computed once for the unit and the motion checks
    rho = hall_lag_correlation(dataset)
    preflight = check_recording(
        dataset, pole_pairs=setup.pole_pairs, sample_time=setup.sample_time, lag_correlation=rho
    ) + [check_pole_pairs(dataset, setup.pole_pairs), check_direction(dataset)]
    for check in preflight:
        check.raise_if_failed(dataset.source)
    s = _signals(dataset, setup.pole_pairs)
    # after the span check of _signals (a short run is named as such): Hall signals that are
    # noise around the origin make f_init turn at random, which no span check sees
    check_hall_motion(dataset, lag_correlation=rho).raise_if_failed(dataset.source)
    cold = setup.model.basis != "kernel" and not _kernels_cached()
    if cold:  # the first run on this machine: numba compiles before the plant's gain or SEM
        say(progress, "compiling the loop kernels once (about 15-60 s; later runs load them)")
    found = sensors.examine(s.d, s.y, pole_pairs=setup.pole_pairs, basis=setup.model.basis)

    t0 = time.perf_counter()
    harmonics = setup.model.harmonics
    pm = plant_model(
        dataset,
        setup,
        bla_dataset=bla_dataset,
        bla=bla,
        start_harmonics=None if harmonics == "auto" else tuple(harmonics),
        progress=progress,
    )
    if pm.source == "bla":
        timings["plant"] = time.perf_counter() - t0
    loop_check = check_loop(setup.controller, pm.plant, setup.sample_time, plant_name=pm.name)
    loop_check.raise_if_failed("setup")
    loop = closed_loop(setup, pm.plant)
    messages = [*s.messages, Message.info(MessageCode.PLANT, pm.note), *found.notes]
    if pm.bla is not None:
        messages += list(pm.bla.messages)
    messages += [c.to_message() for c in preflight if c.status is CheckStatus.WARNING]
    if pm.gain is not None and pm.gain.status != "ok":
        messages.append(
            Message.warning(
                MessageCode.GAIN_AT_BOUND,
                f"gain correction c = {pm.gain.c:.3g} hit its search bound",
            )
        )

    if cold:  # compile the fit's kernels on a small copy, out of the SEM's solve time
        t0 = time.perf_counter()
        _warm_kernels(loop, s, setup, fit_gain=pm.gain is not None)
        timings["compile"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with numeric_errors("setup", "model"):
        loop, d, y, d_choice, y_choice = sensors.for_choice(
            loop, s.r, s.d, s.y, found, pole_pairs=setup.pole_pairs, progress=progress
        )
        s, s_choice = (dataclasses.replace(s, d=d, y=y),
                       dataclasses.replace(s, d=d_choice, y=y_choice))  # fmt: skip
        if setup.model.basis == "kernel":
            fit = _fit_kernel(loop, s, setup, progress=progress)
        else:
            fit = _fit_fourier(
                loop, s_choice, setup, fit_gain=pm.gain is not None, progress=progress
            )
            skipped = _cogging_unaffordable(loop, s_choice, setup, fit)
            if skipped is None:
                fit = _with_cogging(
                    loop, s_choice, setup, fit, fit_gain=pm.gain is not None, progress=progress
                )
            else:
                messages.append(skipped)
            chosen = fit.sem
            fit, s = _final_fit(loop, s, setup, fit, found, progress=progress,
                                fit_gain=pm.gain is not None)  # fmt: skip
            if skipped is not None and fit.sem is chosen:  # no refit followed: finish the fit
                fit = _to_convergence(
                    loop, s_choice, setup, fit, fit_gain=pm.gain is not None,
                    progress=progress, why="the cogging search skipped",
                )  # fmt: skip
    timings["sem"] = time.perf_counter() - t0
    if fit.selection is not None:
        timings["model_selection"] = fit.selection.elapsed
        if fit.selection.budget_message is not None:
            messages.append(fit.selection.budget_message)
    if fit.kernel is not None and not fit.kernel.settled:
        messages.append(  # a note: the fit is judged by the adequacy test as always
            Message.note(
                MessageCode.KERNEL_UNSETTLED,
                f"the kernel's learned spectrum was still moving after its budget of "
                f"{fit.kernel.ard_rounds} SEM solves",
            )
        )
    refinement = refined = None
    if pm.source == "bla" and setup.model.basis == "fourier":
        say(progress, "refining the BLA's plant with the calibration run (within its uncertainty)")
        with numeric_errors("setup", "model"):
            refinement = refine_plant(setup, pm, s.r, s.d, fit.sem, found)
        refined = refinement if refinement is not None and refinement.refined else None
        if refined is not None:
            sem = refined.sem
            fit = dataclasses.replace(
                fit, sem=sem, flux=sem.flux, model_info=_fourier_info(sem.flux),
                gain_factor=sem.gain, gain_factor_std=sem.gain_std, adequacy=None,
                cogging=refined.cogging or fit.cogging,
            )  # fmt: skip
    pm = _refined_plant(pm, fit, refined)
    cogging = fit.cogging.cogging if fit.cogging is not None else None
    if fit.cogging is not None and fit.cogging.status is not CoggingStatus.NONE:
        messages.append(Message.note(MessageCode.COGGING, fit.cogging.message))
    loop = closed_loop(setup, pm.plant).with_cogging(cogging).with_rails(*found.censoring.rails)

    def assessed(
        offset_variance: float | None = None, loop_noise_variance: float | None = None
    ) -> AdequacyReport:
        return assess(
            *sensors.at_mid_run(fit.sem, s.d),
            noise=sensors.noise(found, s.d),
            pole_pairs=setup.pole_pairs,
            projection=loop.projection,
            offset=loop.offset,
            curve=fit.cogging.spectrum.curve if fit.cogging and fit.cogging.spectrum else None,
            offset_variance=offset_variance,
            loop_noise_variance=loop_noise_variance,
        )

    with numeric_errors("setup", "model"):
        # the offset with the Hall noise the drive's loop fed back (the SEM's simulation has
        # none of it): a first-order variance from the model, counted wherever it exceeds both
        # covariances' and no motion bias is predicted (zoo motor 193: 2.3x the white standard
        # deviation); from the model alone, so known before the assessment, which it enters
        loop_noise = offset_loop_excess(loop, s.r, fit.sem)
        noisy = loop_noise.variance if loop_noise.excess > 0 else None
        adequacy = (
            fit.adequacy if fit.adequacy is not None and noisy is None else assessed(None, noisy)
        )
        # the table's offset with the residual's autocorrelation over the whole run (HAC),
        # computed only where the prediction may use it (the run shows unmodelled motion: the
        # cost above its warning level, no motion bias); assessed again when it exceeds what
        # both covariances give the offset
        if adequacy.ratio > adequacy.thresholds["warn_ratio"] and adequacy.motion_bias == 0.0:
            autocorrelated = offset_excess(loop, s.r, s.d, fit.sem)
            if autocorrelated.long_run is not None and autocorrelated.excess > 0:
                adequacy = assessed(autocorrelated.long_run.variance, noisy)
        say(progress, "lookup table and bijectivity check")
        lut = build_lut(
            fit.flux,
            setup.pole_pairs,
            points=setup.model.lut_points,
            projection=loop.projection,
            offset=loop.offset,
        )
    predicted, upper = adequacy.predicted_error, adequacy.predicted_upper
    if refinement is not None:
        # the plant's remaining uncertainty moves the table mostly along one direction (its
        # offset): its 95 % quantile for one run is 1.96 times its standard deviation
        predicted = math.hypot(predicted, refinement.bias)
        upper = math.hypot(upper, 1.96 * refinement.bias)
        messages.append(refinement.message)
    if lut.bijective and adequacy.verdict == "warning":
        bias, note = _unmodelled_cogging_bias(loop, s, setup, fit, lut)
        predicted, upper = math.hypot(predicted, bias), math.hypot(upper, bias)
        if note is not None:
            messages.append(note)
    limit = adequacy.error_sources
    if (
        cogging is not None
        and 0 in cogging.orders
        and ErrorSource.OFFSET in adequacy.limited_by.kinds
    ):
        limit += ", which trades off with the constant load torque in the model (cogging 0)"
    verdict = decide(
        bijective=lut.bijective, predicted=predicted, floor=adequacy.noise_floor,
        correction_rms=adequacy.correction_rms, adequacy=str(adequacy.verdict),
        adequacy_message=adequacy.message, min_slope=lut.min_slope, predicted_upper=upper,
        limit=limit, checks_passed=not has_warning(messages),
        limited_by=adequacy.limited_by,
    )  # fmt: skip
    first = (verdict.status, verdict.refusal, verdict.leading)
    with numeric_errors("setup", "model"):
        observer = observer_check(fit.flux, setup.pole_pairs, fit.sem.noise_variance)
    if not lut.bijective and observer is not None and _folding_ok(adequacy, observer):
        folding = Message.note(MessageCode.FOLDING, FOLDING_NOTE.format(sep=observer.separation))
        first = (verdict.status, verdict.refusal, (folding,))
    # a refused table keeps the model for the observer only when the verdict said so
    observer_entry = (
        observer_section(observer, fit.sem.noise_variance)
        if first[0] is not CalibrationStatus.NOT_BIJECTIVE or first[2]
        else None
    )
    (status, refusal, leading), sensor_info = sensors.verdict(
        s.d, fit.sem, found, first, ok=CalibrationStatus.OK, warning=CalibrationStatus.WARNING
    )
    if math.isfinite(predicted) and predicted > RAMP_ADVICE * adequacy.noise_floor:
        say(progress, "how fast a ramp would determine the table (experiment design)")
        t0 = time.perf_counter()
        # the plant with the refined gain, without the cogging (the plan's layout holds it)
        plan_loop = loop.with_cogging(None)
        advice = _ramp_advice(plan_loop, setup, s, fit, predicted / adequacy.noise_floor)
        timings["ramp_plan"] = time.perf_counter() - t0
        if advice is not None:
            messages.append(Message.note(MessageCode.RAMP_ADVICE, advice))
    say(progress, "power-up identifiability of the pole pair")
    t0 = time.perf_counter()
    identifiability = power_up_analysis(fit.flux, lut, s.d)
    timings["identifiability"] = time.perf_counter() - t0
    messages.extend(m for m in [drift_message(identifiability)] if m is not None)
    validation = None
    if "y_ref" in dataset and lut.bijective:
        validation = validate(lut, dataset, noise_floor=adequacy.noise_floor)
    return computed_calibration(
        setup,
        fit.flux,
        lut,
        status,
        predicted,
        adequacy.noise_floor,
        refusal=refusal,
        messages=leading + tuple(messages),
        plant=pm.plant,
        plant_source=pm.source,
        timings=timings,
        model_info=fit.model_info,
        cogging=cogging,
        identifiability=identifiability,
        observer=observer_entry,
        sensors=sensor_info,
        computed=Diagnostics(
            sem=fit.sem,
            bla=pm.bla,
            gain=pm.gain,
            adequacy=adequacy,
            validation=validation,
            selection=fit.selection,
            kernel=fit.kernel,
            cogging_selection=fit.cogging,
        ),
    )
