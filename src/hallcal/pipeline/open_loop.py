"""Algorithm 1 on an open-loop constant-speed run (``[trajectory] kind = "constant-speed"``).

The numeric part is :func:`hallcal.fit.constant_speed.calibrate_constant_speed` (the flux model
and the straight-line angle y0 = a + b k by variable projection, the sensor geometry from raw
data); this module takes the dataset and the setup, checks the options and returns a
:class:`~hallcal.pipeline.calibration.Calibration`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from hallcal.errors import HallcalInputError
from hallcal.fit.constant_speed import (
    ConstantSpeedStatus,
    calibrate_constant_speed,
    default_harmonics,
    find_constant_speed,
    speed_deviation,
)
from hallcal.fit.held_out import held_out_choice, held_out_error
from hallcal.io.dataset import Dataset
from hallcal.io.setup import Setup
from hallcal.messages import Message, MessageCode
from hallcal.pipeline.calibration import Calibration, Diagnostics, computed_calibration, validate
from hallcal.pipeline.checks import CheckStatus, check_pole_pairs, check_recording, raise_if_failed
from hallcal.pipeline.observe import FOLDING_NOTE, calibrated_noise, observer_section
from hallcal.pipeline.powerup import drift_message, power_up_analysis
from hallcal.pipeline.progress import Progress, say
from hallcal.pipeline.verdict import decide
from hallcal.sensor.flux import FourierBasis
from hallcal.sensor.observer import observer_model

__all__ = ["calibrate_open_loop"]


def _segment(dataset: Dataset, setup: Setup) -> tuple[int, int]:
    """``[trajectory] start``/``stop`` checked against the recording (``stop`` None: the end)."""
    n = dataset.n_samples
    traj = setup.trajectory
    start = int(traj.start)
    stop = n if traj.stop is None else int(traj.stop)
    if not 0 <= start < stop <= n:
        raise HallcalInputError(
            f"setup: trajectory.start..stop = {start}..{stop} is outside {dataset.source} "
            f"({n} samples)",
            key="trajectory.stop",
        )
    return start, stop


def _harmonics(setup: Setup) -> tuple[int, ...]:
    n = setup.pole_pairs
    if setup.model.basis != "fourier":
        raise HallcalInputError(
            f'setup: model.basis = "{setup.model.basis}" is not available with trajectory.kind = '
            '"constant-speed"; use "fourier"',
            key="model.basis",
        )
    h = setup.model.harmonics
    harmonics = default_harmonics(n) if h == "auto" else tuple(int(v) for v in h)
    if n not in harmonics:
        raise HallcalInputError(
            f"setup: model.harmonics must contain the pole-pair harmonic {n} (pole_pairs)",
            key="model.harmonics",
        )
    return harmonics


def _speed_warning(d: np.ndarray, start: int, stop: int, pole_pairs: int) -> Message | None:
    """A warning when f_init's speed is not constant over the chosen samples."""
    deviation = speed_deviation(d[start:stop], pole_pairs)
    if deviation <= 0.1:
        return None
    seg = find_constant_speed(d, pole_pairs)
    hint = f"; the constant-speed part looks like {seg.start}..{seg.stop}" if seg.ok else ""
    return Message.warning(
        MessageCode.SPEED_VARIES,
        f"f_init's speed varies by {100 * deviation:.0f}% within trajectory.start.."
        f"stop = {start}..{stop} (averaged over electrical cycles){hint}",
    )


def calibrate_open_loop(
    dataset: Dataset, setup: Setup, *, progress: Progress = None
) -> Calibration:
    """Calibrate from a constant-speed run; see :func:`calibrate_constant_speed`.

    Uses ``[trajectory] start``/``stop``, ``pole_pairs``, the ``[model]`` harmonics (``"auto"``:
    :func:`~hallcal.fit.constant_speed.default_harmonics`), ``lut_points`` and
    ``max_iterations``; ``sample_time`` is not needed (time in samples). Only the columns d1,
    d2, d3 are required; ``y_ref``, when present, is used for validation only.

    Parameters
    ----------
    dataset : Dataset
        The constant-speed run (d1, d2, d3; optional ``y_ref``).
    setup : Setup
        With ``[trajectory] kind = "constant-speed"``.
    progress : callable, keyword-only, optional
        Called with a short message at each step.

    Returns
    -------
    Calibration
        Status, refusal, flux model, table, messages and (with ``y_ref``) validation.

    Raises
    ------
    HallcalInputError
        Naming the file, column or setup key at fault.
    """
    dataset.require("d1", "d2", "d3")
    d = np.ascontiguousarray(dataset.d)
    n = int(setup.pole_pairs)
    start, stop = _segment(dataset, setup)
    harmonics = _harmonics(setup)
    raise_if_failed(
        check_recording(dataset, pole_pairs=n, sample_time=setup.sample_time),
        dataset.source,
    )
    pole_pairs = check_pole_pairs(dataset, n)
    pole_pairs.raise_if_failed(dataset.source)
    warning = _speed_warning(d, start, stop, n)
    messages: list[Message] = [] if warning is None else [warning]
    if pole_pairs.status is CheckStatus.WARNING:
        messages.append(pole_pairs.to_message())
    unused = [f"[{t}]" for t in ("controller", "plant") if getattr(setup, t) is not None]
    if setup.model.cogging not in ("auto", "none"):
        unused.append("[model] cogging")
    if unused:
        messages.append(
            Message.note(
                MessageCode.UNUSED_INPUT,
                f"{' and '.join(unused)} {'is' if len(unused) == 1 else 'are'} not used by a "
                'constant-speed calibration (trajectory.kind = "constant-speed")',
            )
        )
    say(
        progress,
        f"constant-speed calibration on samples {start}..{stop} ({len(harmonics)} harmonics)",
    )
    t0 = time.perf_counter()
    fit: dict[str, Any] = {
        "start": start,
        "stop": stop,
        "max_iterations": setup.model.max_iterations,
        "lut_points": setup.model.lut_points,
    }
    try:
        res = calibrate_constant_speed(d, n, FourierBasis(harmonics), **fit)
        if setup.model.harmonics == "auto":
            held = held_out_choice(d, n, speed=res.b, **fit)
            if held is not None and held.harmonics != harmonics:
                harmonics = held.harmonics
                res = calibrate_constant_speed(d, n, FourierBasis(harmonics), **fit)
        else:
            held = held_out_error(d, n, harmonics, speed=res.b, **fit)
    except ValueError as exc:
        raise HallcalInputError(f"{dataset.source}: {exc}") from None
    timings = {"constant_speed": time.perf_counter() - t0}
    predicted = res.angle_noise_floor if held is None else held.predicted(res)
    if held is None:
        messages.append(
            Message.warning(
                MessageCode.SPEED_FIT,
                f"the segment holds {res.revolutions:.2f} revolutions, too few to hold one out "
                "and check the table on it: the predicted error is the noise floor alone (1.5 "
                "revolutions or more give a checked prediction)",
            )
        )
    messages.extend(Message.warning(MessageCode.SPEED_FIT, w) for w in res.warnings)
    if res.status is ConstantSpeedStatus.NOT_CONVERGED:
        messages.append(
            Message.warning(MessageCode.SPEED_FIT, "the speed estimate did not converge")
        )
    var = calibrated_noise(res.model, n, d, max(res.noise_std, 1e-300) ** 2, start=start, stop=stop)
    injectivity = observer_model(res.model, n, var).injectivity
    if not res.lut.bijective and injectivity.injective:
        folding = FOLDING_NOTE.format(sep=injectivity.separation)
        messages.insert(0, Message.note(MessageCode.FOLDING, folding))
    verdict = decide(
        bijective=res.lut.bijective, predicted=predicted,
        floor=res.angle_noise_floor, correction_rms=float(np.sqrt(np.mean(res.lut.eta**2))),
        checks_passed=res.status.success and not messages, min_slope=res.lut.min_slope,
    )  # fmt: skip
    status, refusal = verdict.status, verdict.refusal
    messages[:0] = verdict.leading  # the reason for a warning first, as in the closed loop
    if held is not None and verdict.leading:
        messages.insert(
            len(verdict.leading),
            Message.note(
                MessageCode.SPEED_FIT,
                "the prediction is the table's error on held-out revolutions against the "
                "straight-line angle, so the rotor's own departure from constant speed counts "
                "in it (on a stepper jig it can dominate): the table may be better than "
                "predicted, never claimed at the floor",
            ),
        )
    say(progress, "power-up identifiability of the pole pair")
    t0 = time.perf_counter()
    identifiability = power_up_analysis(res.model, res.lut, d, start=start, stop=stop)
    timings["identifiability"] = time.perf_counter() - t0
    messages.extend(m for m in [drift_message(identifiability)] if m is not None)
    validation = None
    if "y_ref" in dataset and res.lut.bijective:
        validation = validate(
            res.lut, dataset, noise_floor=res.angle_noise_floor, remove_mean=True
        )  # the spin fixes no frame: the table's offset is arbitrary
    return computed_calibration(
        setup,
        res.model,
        res.lut,
        status,
        predicted,
        res.angle_noise_floor,
        refusal=refusal,
        messages=tuple(messages),
        timings=timings,
        model_info={
            "basis": "fourier",
            "harmonics": list(harmonics),
            "theta": res.model.theta.tolist(),
        },
        identifiability=identifiability,
        observer=observer_section(injectivity, var),
        computed=Diagnostics(validation=validation, constant_speed=res),
    )
