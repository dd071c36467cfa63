"""``hallcal demo``: the paper's simulation study (section "Simulation results") end to end.

1. Virtual bench with the built-in defaults (11 pole pairs, Ts = 1/4000 s, G(s) with delay, C(q),
   Fourier truth with harmonics 1..11, noise variance 7.5e-6).
2. BLA experiment (random-odd multisines around a slow ramp) and the closed-loop BLA; the plant is
   then treated as unknown: calibration uses the BLA and the gain correction c_hat only.
3. Calibration run (ramp 0 -> 13 rad in 26 s), SEM, lookup table.
4. Validation on a fresh run (another noise realization and ramp) against the bench's true angle.
5. Data files, the artifact and (optionally) figures and the HTML report in ``out_dir``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hallcal import pipeline
from hallcal.io import (
    Dataset,
    default_setup,
    make_folder,
    write_artifact,
    write_dataset,
    write_json,
)
from hallcal.sim.bench import BenchRun

__all__ = ["DemoResult", "run_demo"]


@dataclass(frozen=True)
class DemoResult:
    """What the demo computed and wrote."""

    calibration: pipeline.Calibration = field(repr=False)
    validation: pipeline.Validation = field(repr=False)
    true_gain: float
    noise_floor: float
    out_dir: Path
    files: list[Path]
    elapsed: float
    runs: dict[str, BenchRun] = field(repr=False, default_factory=dict)

    def summary_lines(self) -> list[str]:
        v, cal = self.validation, self.calibration
        lines = []
        if cal.gain is not None and cal.plant is not None:
            g = cal.plant.num[-1] / cal.plant.den[-2] if len(cal.plant.den) > 1 else float("nan")
            lines.append(
                f"plant from data: gain correction c = {cal.gain.value:.4f}; identified "
                f"velocity gain {g:.4g} vs true {self.true_gain:.4g} "
                f"({100 * (g / self.true_gain - 1):+.2f} %)"
            )
        if cal.sem is not None:
            lines.append(
                f"SEM: cost {cal.sem.initial_cost:.4g} -> {cal.sem.cost:.4g}, "
                f"{cal.sem.iterations} iteration{'' if cal.sem.iterations == 1 else 's'}, "
                f"{cal.sem.solve_time:.2f} s"
            )
        lines += [
            "validation on a fresh run (against the true angle):",
            f"  f_init : RMS {1e3 * v.init.rms:8.4f} mrad   peak {1e3 * v.init.peak:8.4f} mrad",
            f"  f_star : RMS {1e3 * v.star.rms:8.4f} mrad   peak {1e3 * v.star.peak:8.4f} mrad",
            f"  noise floor : RMS {1e3 * self.noise_floor:8.4f} mrad"
            f"   (f_star / floor = {v.star.rms / self.noise_floor:.3f})",
            f"wrote {len(self.files)} files to {self.out_dir} in {self.elapsed:.1f} s",
        ]
        return lines


def _dataset(run: BenchRun, name: str) -> Dataset:
    return Dataset.from_columns(run.columns(), required=("d1", "d2", "d3"))


def run_demo(
    out_dir: str | Path,
    *,
    seed: int = 1,
    report: bool = True,
    progress: Callable[[str], None] | None = None,
) -> DemoResult:
    """Run the paper's simulation study on the built-in defaults and write everything.

    Section "Simulation results" of the paper end to end on the virtual bench: a BLA
    experiment, the calibration ramp (0 -> 13 rad in 26 s) and a fresh validation ramp, then
    Algorithm 1 with the plant treated as unknown (BLA plus gain correction, eq. (c_hat)).

    Parameters
    ----------
    out_dir : path-like
        Directory for the datasets (``.npz``), ``truth.json``, ``setup.toml``,
        ``calibration.json``, ``bla.json`` and the report; created if needed.
    seed : int, keyword-only
        Seed of the bench (truth, noise); the validation run uses ``seed + 1000``.
    report : bool, keyword-only
        Also write the figures and the HTML report.
    progress : callable, keyword-only, optional
        Called with one short message per step.

    Returns
    -------
    DemoResult
        The calibration, its validation, the noise floor [rad], the files written and the
        elapsed time [s].
    """
    t0 = time.perf_counter()
    say = progress or (lambda m: None)
    out = Path(out_dir)
    make_folder(out)
    truth_setup = default_setup()
    truth_setup = dataclasses.replace(
        truth_setup, bench=dataclasses.replace(truth_setup.bench, seed=seed)
    )
    files: list[Path] = []

    say("virtual bench: BLA experiment (random-odd multisines on a slow ramp)")
    ms = pipeline.simulate(truth_setup, experiment="multisine")
    say("virtual bench: calibration run (ramp 0 -> 13 rad in 26 s)")
    cal_run = pipeline.simulate(truth_setup, experiment="ramp")
    say("virtual bench: validation run (fresh noise, ramp 0 -> 12 rad in 24 s)")
    val_run = pipeline.simulate(
        truth_setup, experiment="ramp", seed=seed + 1000, ramp_end=12.0, duration=24.0
    )
    for name, run in (("bla", ms), ("calibration", cal_run), ("validation", val_run)):
        p = out / f"{name}.npz"
        write_dataset(p, run.columns())
        files.append(p)
    truth_path = out / "truth.json"
    write_json(truth_path, cal_run.truth_dict())
    files.append(truth_path)

    # The user's view: the plant is unknown, only the controller and the data are.
    user_setup = dataclasses.replace(truth_setup, plant=None)
    setup_path = out / "setup.toml"
    from hallcal.io import write_setup

    write_setup(setup_path, user_setup)
    files.append(setup_path)
    cal = pipeline.calibrate(
        _dataset(cal_run, "calibration"),
        user_setup,
        bla_dataset=_dataset(ms, "bla"),
        progress=say,
    )
    art = cal.to_artifact()
    art_path = out / "calibration.json"
    write_artifact(art_path, art)
    files.append(art_path)
    if cal.bla is not None:
        bla_path = out / "bla.json"
        write_json(bla_path, cal.bla.to_dict())
        files.append(bla_path)
    say("validation on the fresh run")
    val = pipeline.validate(
        cal.lut, _dataset(val_run, "validation"), noise_floor=cal_run.config.noise_floor
    )
    plant = truth_setup.plant
    assert plant is not None  # default_setup() has the paper's plant
    true_gain = plant.num[-1] / plant.den[-2]
    result_files = list(files)
    runs: dict[str, Any] = {"bla": ms, "calibration": cal_run, "validation": val_run}
    if report:
        say("figures and HTML report")
        from hallcal.output.report import write_demo_report

        result_files.append(
            write_demo_report(
                cal, val, runs=runs, out_dir=out, noise_floor=cal_run.config.noise_floor
            )
        )
    return DemoResult(
        calibration=cal,
        validation=val,
        true_gain=true_gain,
        noise_floor=cal_run.config.noise_floor,
        out_dir=out,
        files=result_files,
        elapsed=time.perf_counter() - t0,
        runs=runs,
    )
