"""The ``[bench]`` table of the setup file: the virtual bench's knobs, declared once.

:class:`BenchSpec` is what a setup says about the virtual bench;
:class:`~hallcal.sim.bench.BenchConfig` is a :class:`BenchSpec` plus the loop (pole pairs, sample
time, plant, controller) and the knobs that only code sets. Each field's
:func:`~hallcal.settings.setting` declares the key's type, range, default, unit and meaning for
the parser (:mod:`hallcal.io.setup`) and the reference (``docs/setup-reference.md``). Kept apart
from :mod:`hallcal.sim.bench` so that reading a setup does not import the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from hallcal.limits import MAX_ABS_VALUE, MAX_BENCH_ELECTRICAL_HARMONICS
from hallcal.settings import setting

__all__ = ["BenchSpec"]

_ZEROS = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class BenchSpec:
    """The virtual motor of ``hallcal simulate`` (``[bench]``); defaults are the paper's.

    Every attribute is a setup key; its type, unit, accepted values and meaning are declared on
    the field (:func:`hallcal.settings.settings_of` lists them, ``docs/setup-reference.md``
    renders them). The sensor model they parametrize is in :mod:`hallcal.sim.bench`.
    """

    experiment: Literal["ramp", "multisine"] = setting(
        "ramp",
        kind="choice",
        choices=("ramp", "multisine"),
        accepts='`"ramp"`, `"multisine"` (needs `[bla]`)',
        doc="What `hallcal simulate` runs unless `--experiment` says otherwise.",
    )
    seed: int = setting(
        0,
        kind="integer",
        minimum=0,
        doc="Seed of the motor's imperfections and of the noise (`--seed` changes the noise only).",
    )
    noise_variance: float = setting(
        7.5e-6,
        kind="number",
        minimum=0.0,
        unit="Hall unit²",
        doc="Variance of the white noise on each Hall channel.",
    )
    ramp_end: float = setting(
        13.0, kind="number", unit="rad", doc="End of the calibration ramp 0 -> `ramp_end`."
    )
    duration: float = setting(
        26.0, kind="number", positive=True, unit="s", doc="Duration of the calibration ramp."
    )
    amplitude: float = setting(
        1.0,
        kind="number",
        positive=True,
        limit=MAX_ABS_VALUE,
        unit="Hall unit",
        doc="Amplitude A of the Hall signals.",
    )
    magnet_variation: float = setting(
        0.04,
        kind="number",
        minimum=0.0,
        doc="Relative size of the per-magnet flux differences (mechanical harmonics 1 .. n_m - 1).",
    )
    pole_modulation: float = setting(
        0.0,
        kind="number",
        minimum=0.0,
        doc="Relative per-pole amplitude differences (sidebands k n_m ± 1..3).",
    )
    shape_variation: float = setting(
        0.0,
        kind="number",
        minimum=0.0,
        doc="Per-magnet shape variation s: every pole pair's flux waveform gets its own smooth "
        "random deformation of RMS s A (mechanical harmonics 1 .. `shape_harmonics` n_m, every "
        "sideband); s = 0.02 adds about 1.4 mrad RMS to f_init's error with 11 pole pairs, "
        "0.075 about 5.4 mrad.",
    )
    shape_harmonics: int = setting(
        5,
        kind="integer",
        minimum=1,
        doc="Electrical bandwidth K of that deformation (its highest electrical harmonic).",
    )
    misalignment_deg: tuple[float, float, float] = setting(
        _ZEROS,
        kind="numbers",
        length=3,
        unit="electrical degrees",
        doc="Added to each sensor's nominal 0/120/240 degrees.",
    )
    gain_mismatch: tuple[float, float, float] = setting(
        _ZEROS,
        kind="numbers",
        length=3,
        accepts="each > -1",
        doc="Relative gain error of each sensor (gain 1 + g).",
    )
    offset: tuple[float, float, float] = setting(
        _ZEROS,
        kind="numbers",
        length=3,
        limit=MAX_ABS_VALUE,
        unit="Hall unit",
        doc="Offset of each sensor.",
    )
    electrical_harmonics: tuple[tuple[int, float], ...] = setting(
        (),
        kind="custom",
        limit=MAX_BENCH_ELECTRICAL_HARMONICS,
        type_text="list of [integer, number] pairs",
        accepts="harmonic ≥ 2, each once",
        doc="Electrical harmonics of the flux with their relative amplitudes, e.g. "
        "`[[3, 0.05], [5, 0.02]]` (trapezoidal flux).",
    )
    torque_disturbance: float = setting(
        0.0,
        kind="number",
        minimum=0.0,
        unit="unit of u",
        doc="Standard deviation of a random low-frequency torque at the plant input.",
    )
    cogging: float = setting(
        0.0,
        kind="number",
        minimum=0.0,
        unit="unit of u",
        doc="Amplitude of a cogging torque at the plant input.",
    )
    cogging_periods: int = setting(
        0,
        kind="integer",
        minimum=0,
        doc="Cogging periods per revolution; 0 means 6 n_m.",
    )

    def __post_init__(self) -> None:
        for name in ("misalignment_deg", "gain_mismatch", "offset"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        pairs = tuple((int(h), float(a)) for h, a in self.electrical_harmonics)
        object.__setattr__(self, "electrical_harmonics", pairs)
