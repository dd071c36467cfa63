"""Algorithm 1 of van Meer et al. end to end, on top of the numeric modules.

Steps (Algorithm 1): (1) the calibration data D (closed-loop ramp with f_init feedback);
(2) the BLA of the plant from multisine experiments, corrected by the gain c_hat of eq. (c_hat);
(3) simulation-error minimization of g_theta, eq. (problem); (4) the lookup table and f_star,
eq. (f_final); (5) validation against an encoder when one was logged.

This module has no printing and no file I/O: it takes :class:`~hallcal.io.Dataset` and
:class:`~hallcal.io.Setup` objects and returns result dataclasses; :mod:`hallcal.cli` and
:mod:`hallcal.output.report` sit on top. ``progress`` callbacks receive one short message per step.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.optimize
from numpy.typing import NDArray

from hallcal.errors import HallcalInputError
from hallcal.fit.adequacy import assess
from hallcal.fit.order import select_harmonics
from hallcal.fit.sem import SEMResult, least_squares_start, predicted_angle_error, solve_sem
from hallcal.identify import bla as _bla
from hallcal.identify.excitation import multisine_experiment
from hallcal.io import Dataset, Setup
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.lut import LUT, build_lut
from hallcal.sensor.metrics import AngleError, SpatialSpectrum, angle_error, spatial_spectrum
from hallcal.sensor.reconstruction import f_init
from hallcal.sim.bench import PAPER_CONTROLLER, BenchConfig, BenchRun, simulate_run
from hallcal.sim.loop import ClosedLoop, simulate_loop
from hallcal.sim.lti import ContinuousTF

__all__ = [
    "BLAIdentification",
    "Calibration",
    "GainCorrection",
    "Reconstruction",
    "Validation",
    "artifact_from_calibration",
    "bench_config",
    "calibrate",
    "identify_bla",
    "estimate_gain",
    "lut_from_artifact",
    "reconstruct",
    "simulate",
    "validate",
]

Progress = Callable[[str], None] | None
TWO_PI = 2.0 * math.pi


def _say(progress: Progress, message: str) -> None:
    if progress is not None:
        progress(message)


# ------------------------------------------------------------------------------------------------
# Virtual bench
# ------------------------------------------------------------------------------------------------


def bench_config(setup: Setup) -> BenchConfig:
    """The virtual bench described by a setup (``[bench]`` knobs, plant and controller)."""
    b = setup.bench
    if setup.plant is None:
        raise HallcalInputError(
            "setup: the virtual bench needs a [plant] table (the true G(s) of the simulated motor)"
        )
    return BenchConfig(
        pole_pairs=setup.pole_pairs,
        sample_time=setup.sample_time,
        plant=setup.plant,
        controller=setup.controller or PAPER_CONTROLLER,
        amplitude=b.amplitude,
        noise_variance=b.noise_variance,
        magnet_variation=b.magnet_variation,
        pole_modulation=getattr(b, "pole_modulation", 0.0),
        misalignment_deg=b.misalignment_deg,
        gain_mismatch=b.gain_mismatch,
        offset=b.offset,
        electrical_harmonics=b.electrical_harmonics,
        torque_disturbance=b.torque_disturbance,
        cogging=b.cogging,
        cogging_periods=b.cogging_periods,
        seed=b.seed,
    )


def simulate(
    setup: Setup,
    *,
    experiment: str | None = None,
    seed: int | None = None,
    ramp_end: float | None = None,
    duration: float | None = None,
) -> BenchRun:
    """Run the virtual bench: the calibration ramp or the BLA multisine experiment.

    Parameters
    ----------
    setup : Setup
        ``[bench]`` gives the motor and sensors, ``[bla]`` the multisine experiment.
    experiment : {"ramp", "multisine"}, optional
        Overrides ``setup.bench.experiment``.
    seed : int, optional
        Noise seed of this run (the motor's truth stays that of ``setup.bench.seed``).
    ramp_end, duration : float, optional
        Override the ramp [rad] and its duration [s].
    """
    cfg = bench_config(setup)
    kind = experiment or setup.bench.experiment
    if kind == "ramp":
        b = setup.bench
        end = b.ramp_end if ramp_end is None else ramp_end
        dur = b.duration if duration is None else duration
        n = int(round(dur / setup.sample_time))
        r = end * np.arange(n) / n
        return simulate_run(cfg, r, seed=seed)
    if kind == "multisine":
        spec = setup.bla
        if spec is None:
            raise HallcalInputError("setup: the multisine experiment needs a [bla] table")
        exp = multisine_experiment(
            spec.period_samples,
            setup.sample_time,
            periods=spec.periods,
            realizations=spec.realizations,
            band=spec.band,
            rms=spec.rms,
            lines=spec.lines,
            seed=setup.bench.seed if seed is None else seed,
            drift=spec.drift,
        )
        return simulate_run(cfg, exp.r, seed=seed, realization=exp.realization)
    raise HallcalInputError(f"setup: unknown experiment '{kind}'")


# ------------------------------------------------------------------------------------------------
# BLA and gain correction
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BLAIdentification:
    """Step 2 of Algorithm 1: nonparametric BLA, parametric fit and the plant model.

    Attributes
    ----------
    nonparametric : NonparametricBLA
    parametric : ParametricBLA
    plant : ContinuousTF
        The fitted G(s) with its delay (before the gain correction).
    status : str
    """

    nonparametric: _bla.NonparametricBLA = field(repr=False)
    parametric: _bla.ParametricBLA = field(repr=False)
    plant: ContinuousTF
    status: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": "hallcal-bla/1",
            "plant": {
                "num": list(self.plant.num),
                "den": list(self.plant.den),
                "delay": self.plant.delay,
            },
            "status": self.status,
            "nonparametric": self.nonparametric.to_dict(),
            "parametric": self.parametric.to_dict(),
        }


def identify_bla(dataset: Dataset, setup: Setup, *, progress: Progress = None) -> BLAIdentification:
    """Closed-loop BLA from a multisine dataset (Pintelon & Schoukens 2012, sec. 3.8).

    The dataset needs columns r, u, y and realization; ``[bla]`` gives the period, the number of
    transient periods and the parametric model orders.
    """
    spec = setup.bla
    if spec is None:
        raise HallcalInputError(
            f"{dataset.source}: a BLA experiment needs a [bla] table in the setup"
        )
    dataset.require("r", "u", "y", "realization")
    _say(progress, "nonparametric BLA (indirect closed-loop method)")
    npb = _bla.nonparametric_bla(
        dataset["r"],
        dataset["u"],
        dataset["y"],
        dataset["realization"].astype(int),
        period_samples=spec.period_samples,
        transient_periods=spec.transient_periods,
        sample_time=setup.sample_time,
    )
    _say(progress, "parametric fit of G(s) with input delay")
    par = _bla.fit_parametric(
        npb,
        numerator_order=spec.numerator_order,
        denominator_order=spec.denominator_order,
        integrator=spec.integrator,
        fit_delay=spec.fit_delay,
    )
    plant = ContinuousTF(tuple(par.num), tuple(par.den), max(float(par.delay), 0.0))
    status = "ok" if (npb.status == "ok" and par.status == "ok") else f"{npb.status}/{par.status}"
    return BLAIdentification(npb, par, plant, status)


@dataclass(frozen=True)
class GainCorrection:
    """The gain correction of eq. (c_hat): the BLA is known up to a constant c.

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
        Full rotations of the data and of the simulation at c (eq. c_hat's check).
    status : str
    c_refined, c_refined_std : float or None
        c after joint refinement with theta in SEM (``solve_sem(fit_gain=True)``) and its
        standard deviation: at the SEM optimum the flux model no longer masks the loop gain.
    """

    c: float
    cost: float
    cost_unit: float
    rotations_data: int
    rotations_sim: int
    status: str
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
    """Estimate the plant gain factor c of eq. (c_hat) from the calibration run.

    The paper matches the instant of the last full rotation between the closed-loop simulation
    (with theta_0 and the plant scaled by c) and the data. In a type-1 loop tracking a ramp the
    lag of y behind r is inversely proportional to the loop gain, so that instant moves with c.
    Here the whole trajectory is matched instead of one instant: ``c = argmin mean (y_sim,c -
    y)^2`` (a bounded scalar search on log c), which uses the same information with all samples
    and is insensitive to where the last rotation falls; the number of full rotations of both is
    reported as the paper's check.
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
    opt = scipy.optimize.minimize_scalar(
        cost, bounds=(a, b), method="bounded", options={"xatol": 1e-5}
    )
    c = float(math.exp(opt.x))
    sim = simulate_loop(loop.with_plant_gain(c), flux, r)
    rot = lambda v: int(math.floor(np.max(v) / TWO_PI))  # noqa: E731
    at_edge = abs(opt.x - lo) < 1e-3 or abs(opt.x - hi) < 1e-3
    return GainCorrection(
        c=c,
        cost=float(opt.fun),
        cost_unit=cost(0.0),
        rotations_data=rot(y),
        rotations_sim=rot(sim.y) if sim.status == "ok" else -1,
        status="at-bound" if at_edge else "ok",
    )


# ------------------------------------------------------------------------------------------------
# Calibration
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Validation:
    """Angle errors of f_init and f_star against an encoder (y_ref) or the bench's truth."""

    init: AngleError
    star: AngleError
    spectrum_init: SpatialSpectrum = field(repr=False)
    spectrum_star: SpatialSpectrum = field(repr=False)
    noise_floor: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "f_init": self.init.to_dict(),
            "f_star": self.star.to_dict(),
            "noise_floor": self.noise_floor,
            "improvement_rms": self.init.rms / self.star.rms if self.star.rms > 0 else None,
        }


@dataclass(frozen=True)
class Calibration:
    """Result of :func:`calibrate` (Algorithm 1).

    Attributes
    ----------
    setup : Setup
    flux : FluxModel
        Identified g_theta*.
    lut : LUT
        Table and the f_init it corrects.
    sem : SEMResult or None
        The SEM solve (closed-loop mode).
    plant : ContinuousTF or None
        The plant model used in SEM (after the gain correction).
    gain : GainCorrection or None
    bla : BLAIdentification or None
    predicted_error : float
        Predicted RMS angle error of f_star [rad]: noise floor and the LUT uncertainty from
        cov(theta), combined in quadrature.
    adequacy : object or None
        Model-adequacy report (see :mod:`hallcal.fit.adequacy`).
    validation : Validation or None
        Errors against ``y_ref`` when the calibration data had it (validation only).
    status : str
        "ok", "not-bijective" (no usable table), "inadequate" (model refused) or "warning".
    messages : list of str
        Human-readable notes, warnings first.
    timings : dict
        Seconds per step.
    model_info : dict
        Basis description for the artifact.
    """

    setup: Setup
    flux: FluxModel
    lut: LUT
    sem: SEMResult | None
    plant: ContinuousTF | None
    gain: GainCorrection | None
    bla: BLAIdentification | None
    predicted_error: float
    adequacy: Any
    validation: Validation | None
    status: str
    messages: list[str]
    timings: dict[str, float]
    model_info: dict[str, Any]
    extra: dict[str, Any] = field(default_factory=dict)


def _closed_loop(setup: Setup, plant: ContinuousTF) -> ClosedLoop:
    if setup.controller is None:
        raise HallcalInputError("setup: closed-loop calibration needs a [controller] table")
    return ClosedLoop.from_transfer_functions(
        plant, setup.controller, setup.sample_time, setup.pole_pairs
    )


def _check_samples(dataset: Dataset, pole_pairs: int, *, revolutions: bool = True) -> None:
    """The run must cover one electrical period, and a full revolution to identify g over it."""
    y = f_init(dataset.d, pole_pairs)
    span = float(np.ptp(y))
    if span * pole_pairs < TWO_PI:
        raise HallcalInputError(
            f"{dataset.source}: the recording covers less than one electrical period "
            f"({span * pole_pairs / TWO_PI:.2f}); nothing to calibrate"
        )
    if revolutions and span < TWO_PI:
        raise HallcalInputError(
            f"{dataset.source}: the recording covers {span / TWO_PI:.2f} revolutions; the flux "
            "model is periodic over one revolution and needs at least one full revolution"
        )


def validate(lut: LUT, dataset: Dataset, *, noise_floor: float | None = None) -> Validation:
    """Errors of f_init and f_star on a dataset with ``y_ref`` (encoder or bench truth)."""
    y_ref = dataset["y_ref"]
    yi = lut.f_init(dataset.d)
    ys = yi + lut.correction(yi)
    ei, es = angle_error(yi, y_ref), angle_error(ys, y_ref)
    return Validation(
        ei,
        es,
        spatial_spectrum(yi - y_ref, y_ref),
        spatial_spectrum(ys - y_ref, y_ref),
        noise_floor,
    )


def _harmonics(setup: Setup) -> tuple[int, ...] | str:
    h = setup.model.harmonics
    return h if h == "auto" else tuple(int(v) for v in h)


def calibrate(
    dataset: Dataset,
    setup: Setup,
    *,
    bla_dataset: Dataset | None = None,
    bla: BLAIdentification | None = None,
    progress: Progress = None,
) -> Calibration:
    """Algorithm 1: from calibration data (and a BLA experiment) to the table f_star.

    Parameters
    ----------
    dataset : Dataset
        Calibration run (closed loop: r, y, d1..d3; constant speed: d1..d3).
    setup : Setup
        With ``[plant]`` (known G) or without it and with ``bla_dataset`` or ``bla``.
    bla_dataset : Dataset, optional
        Multisine experiment for step 2.
    bla : BLAIdentification, optional
        An already identified BLA.
    progress : callable, optional
        Called with a short message at each step.

    Returns
    -------
    Calibration
    """
    if setup.trajectory.kind == "constant-speed":
        return _calibrate_constant_speed(dataset, setup, progress=progress)
    timings: dict[str, float] = {}
    messages: list[str] = []
    n_m = setup.pole_pairs
    dataset.require("r", "d1", "d2", "d3")
    _check_samples(dataset, n_m)
    r = np.ascontiguousarray(dataset["r"])
    d = np.ascontiguousarray(dataset.d)
    y_clarke = f_init(d, n_m)
    y = np.ascontiguousarray(dataset["y"]) if "y" in dataset else y_clarke
    if "y" in dataset:
        mismatch = float(np.max(np.abs(y - y_clarke)))
        if mismatch > 1e-6 * max(1.0, float(np.max(np.abs(y)))) + 1e-9:
            messages.append(
                f"warning: column 'y' differs from the Clarke/atan2 f_init of d by up to "
                f"{mismatch:.3g} rad; the loop is simulated with the paper's f_init"
            )

    # Step 2: the plant
    gain = None
    if setup.plant is not None:
        plant = setup.plant
        loop = _closed_loop(setup, plant)
    else:
        t0 = time.perf_counter()
        if bla is None:
            if bla_dataset is None:
                raise HallcalInputError(
                    "setup: no [plant] table and no BLA experiment (--bla-data): the plant "
                    "model G is unknown"
                )
            bla = identify_bla(bla_dataset, setup, progress=progress)
        timings["bla"] = time.perf_counter() - t0
        if "y" not in dataset:
            raise HallcalInputError(
                f"{dataset.source}: column 'y' is missing (needed for the gain correction c)"
            )
        _say(progress, "gain correction c (eq. c_hat)")
        t0 = time.perf_counter()
        loop0 = _closed_loop(setup, bla.plant)
        harmonics = _harmonics(setup)
        start_basis = FourierBasis(tuple(range(1, n_m + 1)) if harmonics == "auto" else harmonics)
        flux0 = FluxModel(start_basis, least_squares_start(start_basis, d, y))
        gain = estimate_gain(loop0, r, y, flux0)
        plant = bla.plant.scaled(gain.c)
        loop = _closed_loop(setup, plant)
        timings["gain"] = time.perf_counter() - t0
        if gain.status != "ok":
            messages.append(f"warning: gain correction c = {gain.c:.3g} hit its search bound")

    # Step 3: SEM
    t0 = time.perf_counter()
    adequacy = None
    extra: dict[str, Any] = {}
    if setup.model.basis == "kernel":
        from hallcal.fit.kernel import solve_kernel_sem  # issue 5

        _say(progress, f"SEM with the periodic kernel basis (m = {setup.model.points})")
        kres = solve_kernel_sem(
            loop,
            r,
            d,
            points=setup.model.points,
            lengthscale=setup.model.lengthscale,
            y=y,
            max_iterations=setup.model.max_iterations,
        )
        sem = kres.sem
        flux = kres.flux
        model_info = {"basis": "kernel", **_kernel_info(kres)}
        extra["kernel"] = kres
    else:
        harmonics = _harmonics(setup)
        fit_gain = gain is not None
        if harmonics == "auto":
            _say(progress, "choosing the harmonics from the data")
            sel = _select_harmonics(loop, r, d, y, n_m, setup)
            sem, adequacy = sel.sem, getattr(sel, "adequacy", None)
            extra["selection"] = sel
            if fit_gain:
                _say(progress, "SEM with the chosen harmonics, refining the plant gain c")
                sem = solve_sem(
                    loop,
                    r,
                    d,
                    sem.flux.basis,
                    theta0=sem.flux.theta,
                    max_iterations=setup.model.max_iterations,
                    fit_gain=True,
                )
                adequacy = None
        else:
            basis = FourierBasis(harmonics)
            _say(
                progress,
                f"SEM, Fourier basis with {len(harmonics)} harmonics"
                + (", refining the plant gain c" if fit_gain else ""),
            )
            sem = solve_sem(
                loop, r, d, basis, y=y, max_iterations=setup.model.max_iterations, fit_gain=fit_gain
            )
        if fit_gain and gain is not None:
            gain = dataclasses.replace(
                gain, c_refined=gain.c * sem.gain, c_refined_std=gain.c * sem.gain_std
            )
            plant = bla.plant.scaled(gain.c_refined)
            loop = _closed_loop(setup, plant)
        flux = sem.flux
        model_info = {
            "basis": "fourier",
            "harmonics": list(flux.basis.harmonics),
            "theta": flux.theta.tolist(),
        }
    timings["sem"] = time.perf_counter() - t0
    if sem.status in ("diverged", "stalled") and sem.iterations == 0:
        messages.append(f"warning: SEM status '{sem.status}' after {sem.iterations} iterations")

    # Adequacy (issue 9)
    if adequacy is None:
        adequacy = _assess(sem, d, n_m, loop)

    # Step 4: the table
    _say(progress, "lookup table and bijectivity check")
    lut = build_lut(
        flux, n_m, points=setup.model.lut_points, projection=loop.projection, offset=loop.offset
    )
    sd = predicted_angle_error(
        flux, sem.covariance, n_m, projection=loop.projection, offset=loop.offset
    )
    floor = math.sqrt(max(sem.noise_variance, 0.0)) * math.sqrt(2 / 3) / _amplitude(flux, n_m)
    predicted = math.sqrt(floor**2 / n_m**2 + float(np.mean(sd**2)))

    status = "ok"
    if not lut.bijective:
        status = "not-bijective"
        messages.insert(
            0,
            "the identified model's map y0 -> f_init(g(y0)) is not bijective (eq. recon_biject):"
            " a lookup table would give wrong angles",
        )
    elif adequacy is not None and getattr(adequacy, "verdict", "adequate") == "inadequate":
        status = "inadequate"
        messages.insert(0, adequacy.message)
    elif adequacy is not None and getattr(adequacy, "verdict", "adequate") == "warning":
        status = "warning"
        msg = adequacy.message
        messages.insert(0, msg if msg.startswith("warning") else "warning: " + msg)

    validation = None
    if "y_ref" in dataset and lut.bijective:
        validation = validate(lut, dataset)
    return Calibration(
        setup=setup,
        flux=flux,
        lut=lut,
        sem=sem,
        plant=plant,
        gain=gain,
        bla=bla,
        predicted_error=predicted,
        adequacy=adequacy,
        validation=validation,
        status=status,
        messages=messages,
        timings=timings,
        model_info=model_info,
        extra=extra,
    )


def _amplitude(flux: FluxModel, n_m: int) -> float:
    """Fundamental amplitude of the model (electrical harmonic n_m), mean over sensors."""
    if n_m not in flux.basis.harmonics:
        y0 = TWO_PI * np.arange(1024) / 1024
        g = flux(y0)
        return float(np.mean(np.std(g, axis=0)) * math.sqrt(2))
    js, jc = flux.basis.index(n_m)
    return float(np.mean(np.hypot(flux.theta[:, js], flux.theta[:, jc])))


def _kernel_info(kres: Any) -> dict[str, Any]:
    info: dict[str, Any] = {"points": int(kres.basis.points)}
    for key in ("lengthscale", "sf", "penalty"):
        info[key] = float(getattr(kres, key))
    info["criterion"] = str(kres.criterion)
    if hasattr(kres, "weights"):
        info["weights"] = np.asarray(kres.weights).tolist()
    info["harmonics"] = list(kres.flux.basis.harmonics)
    info["theta"] = kres.flux.theta.tolist()
    return info


def _select_harmonics(loop, r, d, y, n_m, setup):
    return select_harmonics(loop, r, d, y=y, pole_pairs=n_m)


def _assess(sem, d, n_m, loop):
    return assess(sem, d, pole_pairs=n_m, projection=loop.projection, offset=loop.offset)


def _calibrate_constant_speed(dataset: Dataset, setup: Setup, *, progress: Progress) -> Calibration:
    from hallcal.fit.constant_speed import calibrate_dataset_constant_speed  # issue 8

    return calibrate_dataset_constant_speed(dataset, setup, progress=progress)


# ------------------------------------------------------------------------------------------------
# Artifact and reconstruction
# ------------------------------------------------------------------------------------------------


def artifact_from_calibration(cal: Calibration) -> dict[str, Any]:
    """The versioned JSON calibration artifact of DESIGN.md (a plain dict)."""
    sem = cal.sem
    diag: dict[str, Any] = {
        "status": cal.status,
        "messages": cal.messages,
        "bijective": bool(cal.lut.bijective),
        "min_slope": cal.lut.min_slope,
        "predicted_angle_error_rms": cal.predicted_error,
        "timings": cal.timings,
    }
    if sem is not None:
        diag.update(
            {
                "cost_initial": sem.initial_cost,
                "cost": sem.cost,
                "cost_history": sem.cost_history.tolist(),
                "iterations": sem.iterations,
                "sem_status": sem.status,
                "solve_time": sem.solve_time,
                "noise_variance": sem.noise_variance,
                "n_samples": sem.n_samples,
            }
        )
    if cal.adequacy is not None and hasattr(cal.adequacy, "to_dict"):
        diag["adequacy"] = cal.adequacy.to_dict()
    if cal.validation is not None:
        diag["validation"] = cal.validation.to_dict()
    if cal.gain is not None:
        diag["gain_correction"] = cal.gain.to_dict()
    for key, value in cal.extra.items():
        if hasattr(value, "to_dict") and key not in ("kernel", "selection"):
            diag[key] = value.to_dict()
    art: dict[str, Any] = {
        "format": "hallcal-calibration/1",
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "pole_pairs": cal.setup.pole_pairs,
        "reconstruction": {
            "method": "f_init (eq. fimp) + LUT (eq. f_final)",
            "projection": cal.lut.projection.tolist(),
            "offset": cal.lut.offset.tolist(),
        },
        "model": cal.model_info,
        "lut": cal.lut.to_dict(),
        "setup": cal.setup,
        "diagnostics": diag,
    }
    if cal.plant is not None:
        art["plant"] = {
            "num": list(cal.plant.num),
            "den": list(cal.plant.den),
            "delay": cal.plant.delay,
            "gain_correction": None if cal.gain is None else cal.gain.value,
            "source": "setup" if cal.bla is None else "bla",
        }
    return art


def lut_from_artifact(artifact: dict[str, Any]) -> LUT:
    """Rebuild the table (and its f_init) from an artifact, re-checking bijectivity."""
    rec = artifact["reconstruction"]
    t = artifact["lut"]
    return LUT.from_arrays(
        artifact["pole_pairs"], rec["projection"], rec["offset"], t["y_hat"], t["eta"]
    )


@dataclass(frozen=True)
class Reconstruction:
    """f_init and f_star over a recording, run sequentially from y = y_initial."""

    y_init: NDArray[np.float64] = field(repr=False)
    y_star: NDArray[np.float64] = field(repr=False)
    validation: Validation | None = None


def reconstruct(
    artifact: dict[str, Any], dataset: Dataset, *, y_initial: float = 0.0
) -> Reconstruction:
    """Apply a calibration to a recording (``hallcal reconstruct``)."""
    lut = lut_from_artifact(artifact)
    if not lut.bijective:
        raise HallcalInputError("artifact: its lookup table is not bijective; refusing to use it")
    yi = lut.f_init(dataset.d, y_initial=y_initial)
    ys = yi + lut.correction(yi)
    val = validate(lut, dataset) if "y_ref" in dataset else None
    return Reconstruction(yi, ys, val)
