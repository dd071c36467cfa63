"""The virtual bench driven by a setup file (``hallcal simulate``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.io.setup import Setup
from hallcal.limits import MAX_SAMPLES, check_command_samples
from hallcal.pipeline.boundary import numeric_errors
from hallcal.pipeline.checks import check_loop

if TYPE_CHECKING:
    from hallcal.sim.bench import BenchConfig, BenchRun

# The bench (and scipy.signal, which it uses) is imported when a run is simulated, so that
# importing the pipeline for a calibration does not pay for it.

__all__ = ["bench_config", "simulate"]


def bench_config(setup: Setup) -> BenchConfig:
    """The virtual bench described by a setup (``[bench]`` knobs, plant and controller).

    Parameters
    ----------
    setup : Setup
        With a ``[plant]`` table (the true G(s)); without ``[controller]`` the paper's C(q).

    Returns
    -------
    BenchConfig

    Raises
    ------
    HallcalInputError
        When the setup has no ``[plant]`` (the bench needs the true G(s)).
    """
    from hallcal.sim.bench import PAPER_CONTROLLER, BenchConfig

    b = setup.bench
    if setup.plant is None:
        raise HallcalInputError(
            "setup: the virtual bench needs a [plant] table (the true G(s) of the simulated motor)",
            source="setup",
            key="plant",
        )
    return BenchConfig.from_spec(
        b,
        pole_pairs=setup.pole_pairs,
        sample_time=setup.sample_time,
        plant=setup.plant,
        controller=setup.controller or PAPER_CONTROLLER,
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

    Returns
    -------
    BenchRun

    Raises
    ------
    HallcalInputError
        No ``[plant]``, a ramp of fewer than 2 or more than :data:`~hallcal.limits.MAX_SAMPLES`
        samples, a plant and controller the loop cannot use (named), or whose closed loop is
        unstable (the pole named, :func:`~hallcal.pipeline.checks.check_loop`).
    """
    from hallcal.sim.bench import simulate_run

    with numeric_errors("setup", "plant"):
        cfg = bench_config(setup)
        check_loop(cfg.controller, cfg.plant, setup.sample_time).raise_if_failed("setup")
    kind = experiment or setup.bench.experiment
    if kind == "ramp":
        b = setup.bench
        end = b.ramp_end if ramp_end is None else ramp_end
        dur = b.duration if duration is None else duration
        samples = dur / setup.sample_time
        if not 2 <= samples <= MAX_SAMPLES:
            raise HallcalInputError(
                f"setup: key 'bench.duration' is {samples:.4g} samples ({dur:g} s at sample_time "
                f"{setup.sample_time:g} s), outside 2 .. {MAX_SAMPLES} samples (the limit)",
                source="setup",
                key="bench.duration",
            )
        try:
            check_command_samples(samples, "simulate", hint="a shorter duration")
        except ValueError as exc:
            raise HallcalInputError(
                f"setup: key 'bench.duration': {exc}", source="setup", key="bench.duration"
            ) from None
        n = int(round(samples))
        r = end * np.arange(n) / n
        with numeric_errors("setup", "plant"):
            return simulate_run(cfg, r, seed=seed)
    if kind == "multisine":
        spec = setup.bla
        if spec is None:
            raise HallcalInputError(
                "setup: the multisine experiment needs a [bla] table", source="setup", key="bla"
            )
        from hallcal.identify.excitation import multisine_experiment

        with numeric_errors("setup", "bla"):
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
        with numeric_errors("setup", "plant"):
            return simulate_run(cfg, exp.r, seed=seed, realization=exp.realization)
    raise HallcalInputError(
        f"setup: unknown experiment '{kind}'", source="setup", key="bench.experiment"
    )
