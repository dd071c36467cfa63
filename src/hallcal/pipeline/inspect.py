"""Look at a recording before calibrating it (``hallcal inspect``).

What a motor-control engineer wants to know about a log before spending a calibration on it:
how long it is, how far and how fast the rotor turned, whether the pole-pair count and the sensor
order fit the data (:mod:`hallcal.pipeline.checks`), where the constant-speed part is
(:func:`hallcal.fit.constant_speed.find_constant_speed`) and what ``[trajectory] start``/``stop``
to write for an open-loop calibration, plus the sensors' electrical spacing, amplitudes and
offsets and whether an ADC clipped. No printing: :class:`Inspection` holds the numbers and
:meth:`Inspection.lines` the text.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.fit.constant_speed import (
    SensorGeometry,
    SpeedSegment,
    estimate_sensor_geometry,
    find_constant_speed,
)
from hallcal.io.dataset import Dataset
from hallcal.io.setup import Setup
from hallcal.messages import Message, MessageCode
from hallcal.pipeline.checks import (
    Check,
    CheckStatus,
    DirectionCheck,
    PolePairCheck,
    check_direction,
    check_hall_motion,
    check_pole_pairs,
    check_recording,
    pole_pairs_from_signature,
    raise_if_failed,
    unwrapped_electrical_angle,
)

__all__ = ["Inspection", "inspect_recording"]

#: Revolutions used for calibration when the constant-speed window is long enough to keep some for
#: a check on unseen data (the recording guide: two revolutions, better more).
CAL_REVOLUTIONS = 2.0

#: Samples per electrical cycle below which the recording guide's advice (20-60) is not met.
MIN_SAMPLES_PER_CYCLE = 20

#: Share of samples at a channel's extreme value above which the ADC is taken to clip (a clean
#: sinusoid touches its extremes in well under 0.1 % of the samples at 20+ samples per cycle).
CLIP_FRACTION = 0.01


@dataclass(frozen=True)
class Inspection:
    """What :func:`inspect_recording` found.

    Attributes
    ----------
    source : str
        The file.
    samples : int
    columns : tuple of str
    sample_time : float or None
        From the setup, else from the ``t`` column; None when unknown.
    pole_pairs : int or None
        The count used below: the setup's / the option's, else the one the data suggest.
    pole_pairs_given : bool
        Whether ``pole_pairs`` came from the user.
    pole_pair_check : PolePairCheck
    direction : DirectionCheck
    geometry : SensorGeometry
        Electrical spacing, amplitudes and offsets of the sensors.
    electrical_cycles : float
        Net electrical cycles of the Hall signals (signed).
    segment : SpeedSegment or None
        The longest constant-speed part (None without a pole-pair count).
    trajectory : tuple of (int, int) or None
        Suggested ``[trajectory] start, stop`` for a constant-speed calibration.
    held_out : tuple of (int, int) or None
        The rest of the window, for checking the calibration on unseen samples.
    messages : tuple of Message
        Warnings and notes.
    reference : tuple of float or None
        First and last value of the reference ``r`` [rad] (closed-loop recordings).
    motion : Check or None
        Whether the Hall signals move (:func:`~hallcal.pipeline.checks.check_hall_motion`);
        FAILED for a standstill recording, whose rotation, spacing and window are not read.
    counted_with : int or None
        The pole-pair count used for revolutions and the window: the given one, or the data's
        when the given one is wrong.
    realizations : int
        Realizations of a multisine BLA experiment (column ``realization``), else 0.
    """

    source: str
    samples: int
    columns: tuple[str, ...]
    sample_time: float | None
    pole_pairs: int | None
    pole_pairs_given: bool
    pole_pair_check: PolePairCheck
    direction: DirectionCheck
    geometry: SensorGeometry = field(repr=False)
    electrical_cycles: float
    segment: SpeedSegment | None
    trajectory: tuple[int, int] | None
    held_out: tuple[int, int] | None
    messages: tuple[Message, ...] = ()
    reference: tuple[float, float] | None = None
    motion: Check | None = None
    counted_with: int | None = None
    realizations: int = 0

    @property
    def standstill(self) -> bool:
        """The Hall signals are noise around a fixed point: the rotor did not turn."""
        return self.motion is not None and self.motion.status is CheckStatus.FAILED

    @property
    def revolutions(self) -> float | None:
        """Net mechanical revolutions (signed), when the pole pairs are known."""
        n = self.counted_with if self.counted_with is not None else self.pole_pairs
        return None if not n or self.standstill else self.electrical_cycles / n

    def trajectory_toml(self) -> str | None:
        """The ``[trajectory]`` table to paste into the setup for a constant-speed calibration."""
        if self.trajectory is None:
            return None
        start, stop = self.trajectory
        return f'[trajectory]\nkind = "constant-speed"\nstart = {start}\nstop = {stop}'

    def lines(self) -> list[str | Message]:
        """The report of ``hallcal inspect``, one line per item: a finding (str) or a
        warning or note for the user (:class:`~hallcal.messages.Message`)."""
        out: list[str | Message] = [
            f"{self.source}: {self.samples} samples, columns {', '.join(self.columns)}"
        ]
        if self.sample_time is not None:
            out.append(
                f"sample time {self.sample_time:.6g} s ({1.0 / self.sample_time:.6g} Hz), "
                f"duration {self.samples * self.sample_time:.4g} s"
            )
        else:
            out.append("sample time unknown (no t column, no setup): times are in samples")
        if self.pole_pairs_given:
            text = self.pole_pair_check.text.removeprefix("pole pairs: ")
            status = self.pole_pair_check.status
            head = "WRONG" if status is CheckStatus.FAILED else status.value
            line = f"pole pairs: {self.pole_pairs} (given, {head}): {text}"
            if self.counted_with is not None and self.counted_with != self.pole_pairs:
                line += f"; the lines below count with the data's {self.counted_with}"
            out.append(line)
        elif self.pole_pairs is not None:
            out.append(
                f"pole pairs: the data suggest {self.pole_pairs} ({self.pole_pair_check.method}); "
                "give --pole-pairs or --setup to check a count"
            )
        else:
            out.append(f"pole pairs: unknown ({self.pole_pair_check.message})")
        if self.standstill:
            assert self.motion is not None
            out.append(f"rotation: none: {self.motion.message}")
            out.append(
                "a standstill recording: nothing to calibrate (at power-up it serves "
                "`hallcal reconstruct --absolute`)"
            )
            out.extend(self.messages)
            return out
        cyc = self.electrical_cycles
        revs = self.revolutions
        turn = f"{abs(cyc):.1f} electrical cycles"
        if revs is not None:
            turn += f" = {abs(revs):.2f} revolutions"
            if self.counted_with is not None and self.counted_with != self.pole_pairs:
                turn += f" (at the data's {self.counted_with} pole pairs)"
        sense = (
            "in the sensor order d1 -> d2 -> d3"
            if cyc > 0
            else "against the sensor order (d3 -> d2 -> d1)"
        )
        out.append(f"rotation: {turn}, {sense}")
        direction = self.direction
        if direction.status is CheckStatus.WARNING:
            out.append(direction.to_message())
        elif direction.status is not CheckStatus.SKIPPED:
            out.append(direction.text)
        g = self.geometry
        spacing = ", ".join(f"{v:.0f}" for v in g.spacing_deg)
        out.append(
            f"sensors: electrical spacing {spacing} deg (nominal 120, 120, 120); amplitudes "
            f"{', '.join(f'{a:.4g}' for a in g.amplitudes)}; offsets "
            f"{', '.join(f'{o:.4g}' for o in g.offsets)}"
        )
        seg = self.segment
        if self.reference is not None:
            r0, r1 = self.reference
            out.append(
                f"reference r: {r0:.4g} -> {r1:.4g} rad ({(r1 - r0) / TWO_PI:.2f} revolutions)"
                + (
                    f", {abs(r1 - r0) / TWO_PI / (self.samples * self.sample_time):.4g} rev/s "
                    "on average"
                    if self.sample_time is not None
                    else ""
                )
            )
        elif seg is None:
            out.append("constant-speed window: not searched (pole pairs unknown)")
        elif not seg.ok:
            out.append("constant-speed window: none found (speed never steady for two cycles)")
        else:
            speed = abs(seg.speed) / TWO_PI  # revolutions per sample
            if self.sample_time is not None:
                rate = f"{speed / self.sample_time:.4g} rev/s"
            else:
                rate = f"{1000 * speed:.4g} rev per 1000 samples"
            out.append(
                f"constant-speed window: samples {seg.start}..{seg.stop} ({seg.revolutions:.2f} "
                f"revolutions at {rate}, {seg.samples_per_cycle} samples per electrical cycle)"
            )
        if self.realizations:
            out.append(
                f"multisine BLA experiment (column realization: {self.realizations} "
                "realizations): identify the plant from it with `hallcal bla`, and give it to "
                "`hallcal calibrate --bla-data`; it is not a calibration run"
            )
        elif "r" in self.columns:
            out.append(
                "closed-loop recording (column r): calibrate it with the default "
                '[trajectory] kind = "closed-loop"'
            )
        elif self.trajectory is not None:
            start, stop = self.trajectory
            text = f"suggested for an open-loop calibration: start = {start}, stop = {stop}"
            if self.held_out is not None:
                text += (
                    f" ({CAL_REVOLUTIONS:g} revolutions; samples {self.held_out[0]}.."
                    f"{self.held_out[1]} stay unseen for checking the result)"
                )
            out.append(text)
        out.extend(self.messages)
        return out


def _sample_time(dataset: Dataset, setup: Setup | None) -> float | None:
    if setup is not None and setup.sample_time != 1.0:
        return float(setup.sample_time)
    if "t" in dataset and dataset.n_samples > 1:
        dt = np.diff(np.asarray(dataset["t"], dtype=np.float64))
        step = float(np.median(dt))
        if step > 0.0 and np.all(np.abs(dt - step) <= 0.01 * step):
            return step
    return None


def _suggest_pole_pairs(dataset: Dataset) -> int | None:
    """The count the data suggest without a given one: reference slope, else the signature."""
    check = check_pole_pairs(dataset, 1)
    if check.method in ("reference r", "encoder y_ref") and math.isfinite(check.estimate):
        n = int(round(check.estimate))
        return n if n >= 1 and abs(check.estimate - n) <= 0.15 else None
    return pole_pairs_from_signature(np.asarray(dataset.d)).best


def _clipping(dataset: Dataset) -> list[Message]:
    out = []
    for h in (1, 2, 3):
        x = np.asarray(dataset[f"d{h}"], dtype=np.float64)
        for which, value in (("minimum", x.min()), ("maximum", x.max())):
            share = float(np.mean(x == value))
            if share > CLIP_FRACTION:
                out.append(
                    Message.warning(
                        MessageCode.CLIPPING,
                        f"d{h} sits at its {which} {value:.6g} in {100 * share:.1f} % of the "
                        "samples: the ADC or the sensor clips; lower the gain or move the sensor",
                    )
                )
    return out


def inspect_recording(
    dataset: Dataset, *, setup: Setup | None = None, pole_pairs: int | None = None
) -> Inspection:
    """Look at a recording: samples, rotation, pole pairs, sensors, constant-speed window.

    Parameters
    ----------
    dataset : Dataset
        Columns d1, d2, d3; ``r`` or ``y_ref`` are used as the mechanical reference if present,
        ``t`` for the sample time.
    setup : Setup, optional
        Its ``pole_pairs`` and ``sample_time`` are used, and a constant-speed ``[trajectory]``
        is compared with the window found.
    pole_pairs : int, optional
        Overrides the setup's.

    Returns
    -------
    Inspection

    Raises
    ------
    HallcalInputError
        Missing Hall columns, too few samples, a ``t`` column that disagrees with the setup's
        ``sample_time`` or angle columns in degrees
        (:func:`~hallcal.pipeline.checks.check_recording`). A wrong given pole-pair count is
        not raised here: the report uses the data's count and says so, and
        :attr:`Inspection.pole_pair_check` fails (``hallcal inspect`` then exits 2).
    """
    dataset.require("d1", "d2", "d3")
    d = np.asarray(dataset.d, dtype=np.float64)
    if d.shape[0] < 16:
        raise HallcalInputError(f"{dataset.source}: {d.shape[0]} samples are too few to inspect")
    given = pole_pairs if pole_pairs is not None else (None if setup is None else setup.pole_pairs)
    sample_time = None if setup is None else setup.sample_time
    raise_if_failed(
        check_recording(dataset, pole_pairs=given or 1, sample_time=sample_time), dataset.source
    )
    realizations = int(np.unique(dataset["realization"]).size) if "realization" in dataset else 0
    reference = None if "r" not in dataset else (float(dataset["r"][0]), float(dataset["r"][-1]))
    motion = check_hall_motion(dataset)
    if motion.status is CheckStatus.FAILED:  # noise around a fixed point: nothing turned
        skipped = PolePairCheck(
            CheckStatus.SKIPPED,
            "pole pairs not checked: the rotor stood still",
            pole_pairs=given or 0,
        )
        return Inspection(
            source=dataset.source,
            samples=dataset.n_samples,
            columns=tuple(dataset.names),
            sample_time=_sample_time(dataset, setup),
            pole_pairs=given,
            pole_pairs_given=given is not None,
            pole_pair_check=skipped,
            direction=DirectionCheck(CheckStatus.SKIPPED, "direction not checked (standstill)"),
            geometry=estimate_sensor_geometry(d, given),
            electrical_cycles=0.0,
            segment=None,
            trajectory=None,
            held_out=None,
            messages=tuple(_clipping(dataset)),
            reference=reference,
            motion=motion,
            realizations=realizations,
        )
    n = given if given is not None else _suggest_pole_pairs(dataset)
    check = check_pole_pairs(dataset, n if n is not None else 1)
    if given is not None and check.status is CheckStatus.FAILED and check.suggested:
        n = check.suggested  # the lines below count with the data's pole pairs, not the wrong one
    messages = _clipping(dataset)
    geometry = estimate_sensor_geometry(d, n)
    if geometry.message:
        messages.append(
            Message.note(MessageCode.SENSOR_GEOMETRY, f"sensor geometry: {geometry.message}")
        )
    psi = unwrapped_electrical_angle(dataset)
    cycles = float(psi[-1] - psi[0]) / TWO_PI
    segment = trajectory = held_out = None
    if n is not None and abs(cycles) >= 2.0:
        segment = find_constant_speed(d, n, geometry=geometry)
        if segment.ok and "r" not in dataset:  # open loop: the window is what gets calibrated
            if segment.revolutions >= CAL_REVOLUTIONS + 1.0:
                start, mid, stop = segment.split(CAL_REVOLUTIONS)
                trajectory, held_out = (start, mid), (mid, stop)
            else:
                trajectory = (segment.start, segment.stop)
            if segment.samples_per_cycle < MIN_SAMPLES_PER_CYCLE:
                messages.append(
                    Message.warning(
                        MessageCode.TRAJECTORY_WINDOW,
                        f"{segment.samples_per_cycle} samples per electrical cycle in the "
                        f"constant-speed window; aim for {MIN_SAMPLES_PER_CYCLE}-60 (turn slower "
                        "or sample faster; docs/recording-guide.md)",
                    )
                )
            if segment.revolutions < CAL_REVOLUTIONS:
                messages.append(
                    Message.warning(
                        MessageCode.TRAJECTORY_WINDOW,
                        f"the constant-speed window holds {segment.revolutions:.2f} revolutions; "
                        f"an open-loop calibration needs at least {CAL_REVOLUTIONS:g}",
                    )
                )
    if setup is not None and setup.trajectory.kind == "constant-speed" and segment is not None:
        t = setup.trajectory
        stop = dataset.n_samples if t.stop is None else t.stop
        if segment.ok and (t.start < segment.start or stop > segment.stop):
            messages.append(
                Message.warning(
                    MessageCode.TRAJECTORY_WINDOW,
                    f"the setup's trajectory.start..stop = {t.start}..{stop} reaches outside "
                    f"the constant-speed window {segment.start}..{segment.stop}",
                )
            )
    return Inspection(
        source=dataset.source,
        samples=dataset.n_samples,
        columns=tuple(dataset.names),
        sample_time=_sample_time(dataset, setup),
        pole_pairs=given if given is not None else n,
        pole_pairs_given=given is not None,
        pole_pair_check=check,
        direction=check_direction(dataset),
        geometry=geometry,
        electrical_cycles=cycles,
        segment=segment,
        trajectory=trajectory,
        held_out=held_out,
        messages=tuple(messages),
        reference=reference,
        motion=motion,
        counted_with=n,
        realizations=realizations,
    )
