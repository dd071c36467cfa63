"""The ``hallcal`` command line (contract in docs/design.md, "Command line").

Exit status: 0 success; 2 bad input (one line naming the file, column or key; no traceback);
3 calibration refused (model inadequate or table not bijective; use ``--force`` to write an
inadequate model anyway). Progress goes to stderr, results to stdout.
"""

from __future__ import annotations

import functools
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
from rich.console import Console

from hallcal.errors import CalibrationRefused, HallcalError, HallcalInputError

EXIT_INPUT = HallcalInputError.exit_status
EXIT_REFUSED = CalibrationRefused.exit_status

_err = Console(stderr=True, highlight=False, soft_wrap=True)
_out = Console(highlight=False, soft_wrap=True)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if text.startswith("setup:") and _setup_path[0]:
        # the numeric layers say "setup:"; the user wants the file's name
        text = _setup_path[0] + text[len("setup") :]
    return text


def _handle_errors(func: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except CalibrationRefused as exc:
            click.echo(f"hallcal: refused: {_one_line(exc)}", err=True)
            sys.exit(exc.exit_status)
        except HallcalError as exc:
            click.echo(f"hallcal: error: {_one_line(exc)}", err=True)
            sys.exit(exc.exit_status)

    return wrapper


class _Progress:
    """One line per step on stderr with the elapsed time."""

    def __init__(self, quiet: bool = False) -> None:
        self.t0 = time.perf_counter()
        self.quiet = quiet

    def __call__(self, message: str) -> None:
        if not self.quiet:
            _err.print(f"[dim]{time.perf_counter() - self.t0:6.1f} s[/dim]  {message}")


_setup_path: list[str | None] = [None]  # the setup file of this command, for error messages


def _setup(path: str | None):
    from hallcal.io import default_setup, read_setup

    _setup_path[0] = path
    return default_setup() if path is None else read_setup(path)


def _mrad(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{1e3 * x:.4f} mrad"


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="hallcal")
def cli() -> None:
    """Self-calibration of analog linear Hall sensors without an encoder.

    The method of van Meer et al., "Self-Calibrating Position Measurements: Applied to Imperfect
    Hall Sensors": closed-loop data, a BLA of the motor, simulation-error minimization of a
    flux model and a lookup-table correction f_star.
    """


# ------------------------------------------------------------------------------------------------


@cli.command()
@click.option(
    "--setup",
    "setup_path",
    type=click.Path(dir_okay=False),
    default=None,
    help="Setup TOML ([bench], [plant], [controller], [bla]); default: the paper's.",
)
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Dataset to write (.csv, .parquet, .h5, .mat, .npz).",
)
@click.option(
    "--experiment",
    type=click.Choice(["ramp", "multisine"]),
    default=None,
    help="Override [bench] experiment.",
)
@click.option("--seed", type=int, default=None, help="Noise seed of this run (truth unchanged).")
@_handle_errors
def simulate(setup_path: str | None, out: str, experiment: str | None, seed: int | None) -> None:
    """Run the virtual bench and write a dataset (truth in OUT's .truth.json sidecar)."""
    from hallcal import pipeline
    from hallcal.io import write_dataset, write_json

    setup = _setup(setup_path)
    prog = _Progress()
    kind = experiment or setup.bench.experiment
    prog(f"simulating the {kind} experiment")
    run = pipeline.simulate(setup, experiment=experiment, seed=seed)
    if run.status != "ok":
        raise HallcalInputError(
            f"{setup_path or 'setup'}: the simulated closed loop diverged (check [controller] "
            "and [plant])"
        )
    out_path = Path(out)
    write_dataset(out_path, run.columns())
    sidecar = out_path.with_suffix(".truth.json")
    write_json(sidecar, run.truth_dict())
    e = run.y - run.y0
    _out.print(f"wrote {out_path} ({run.n_samples} samples) and {sidecar}")
    _out.print(
        f"f_init error against the truth: RMS {_mrad(float((e - e.mean()).std()))}, "
        f"peak {_mrad(float(abs(e - e.mean()).max()))}; noise floor "
        f"{_mrad(run.config.noise_floor)}"
    )


@cli.command()
@click.argument("data", type=click.Path(dir_okay=False))
@click.option("--setup", "setup_path", required=True, type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="BLA JSON to write.")
@_handle_errors
def bla(data: str, setup_path: str, out: str) -> None:
    """Identify the closed-loop BLA of the plant from a multisine dataset."""
    from hallcal import pipeline
    from hallcal.io import read_dataset, write_json

    setup = _setup(setup_path)
    ds = read_dataset(data, required=("r", "u", "y", "realization"))
    res = pipeline.identify_bla(ds, setup, progress=_Progress())
    write_json(out, res.to_dict())
    p = res.plant
    _out.print(f"G(s) = {list(p.num)} / {list(p.den)} * exp(-{p.delay:.3g} s)   [{res.status}]")
    _out.print(f"wrote {out}")


@cli.command()
@click.argument("data", type=click.Path(dir_okay=False))
@click.option("--setup", "setup_path", required=True, type=click.Path(dir_okay=False))
@click.option(
    "--bla-data",
    type=click.Path(dir_okay=False),
    default=None,
    help="Multisine experiment for the BLA (when the setup has no [plant]).",
)
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="Artifact to write.")
@click.option("--force", is_flag=True, help="Write the artifact even if the model is inadequate.")
@_handle_errors
def calibrate(data: str, setup_path: str, bla_data: str | None, out: str, force: bool) -> None:
    """Calibrate: BLA (if needed), SEM, lookup table; write the JSON artifact."""
    from hallcal.api import calibrate as _calibrate

    setup = _setup(setup_path)
    cal = _calibrate(data, setup, bla_data=bla_data, progress=_Progress())
    _print_calibration(cal)
    cal.save(out, force=force or setup.model.force)
    _out.print(f"wrote {out}")


def _ranges(values: list[int]) -> str:
    """[1, 2, 3, 5, 33] -> '1..3, 5, 33'."""
    out, v = [], sorted(int(x) for x in values)
    i = 0
    while i < len(v):
        j = i
        while j + 1 < len(v) and v[j + 1] == v[j] + 1:
            j += 1
        out.append(f"{v[i]}..{v[j]}" if j > i + 1 else ", ".join(map(str, v[i : j + 1])))
        i = j + 1
    return ", ".join(out)


def _print_calibration(cal) -> None:
    sem = cal.sem
    for m in cal.messages:
        _err.print(m)
    info = cal.model_info
    if info.get("basis") == "fourier":
        _out.print(f"model: Fourier basis, mechanical harmonics {_ranges(info['harmonics'])}")
    elif info.get("basis") == "kernel":
        _out.print(
            f"model: periodic kernel basis, {info.get('points')} points, "
            f"lengthscale {info.get('lengthscale', float('nan')):.3g} rad"
        )
    if cal.gain is not None:
        g = cal.gain
        refined = (
            ""
            if g.c_refined is None
            else (f", refined with theta: {g.c_refined:.4f} +- {g.c_refined_std:.4f}")
        )
        _out.print(f"gain correction c_hat (eq. c_hat) = {g.c:.4f}{refined}")
    if sem is not None:
        _out.print(
            f"cost {sem.initial_cost:.6g} -> {sem.cost:.6g} in {sem.iterations} iterations "
            f"({sem.status}), {sem.solve_time:.2f} s; noise variance {sem.noise_variance:.3g}"
        )
    _out.print(f"predicted f_star error: RMS {_mrad(cal.predicted_error)}")
    if cal.adequacy is not None:
        _out.print(f"model adequacy: {cal.adequacy.verdict}")
    _out.print(f"lookup table: {cal.lut.points} points, bijective: {cal.lut.bijective}")
    _print_validation(cal.validation)


def _print_validation(v) -> None:
    """One line: f_init and f_star against the recording's y_ref, when it has one."""
    if v is not None:
        _out.print(
            f"against y_ref: f_init RMS {_mrad(v.init.rms)} peak {_mrad(v.init.peak)}; "
            f"f_star RMS {_mrad(v.star.rms)} peak {_mrad(v.star.peak)}"
        )


@cli.command()
@click.argument("artifact", type=click.Path(dir_okay=False))
@click.argument("data", type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False))
@_handle_errors
def reconstruct(artifact: str, data: str, out: str) -> None:
    """Apply a calibration to a recording: columns y_init and y_star."""
    from hallcal.api import load
    from hallcal.io import write_dataset

    cal = load(artifact)
    rec = cal.reconstruct(data)
    write_dataset(out, rec.columns)
    _out.print(f"wrote {out} ({len(rec)} samples)")
    _print_validation(rec.validation)


@cli.command("export-c")
@click.argument("artifact", type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(file_okay=False))
@click.option("--no-fixed-point", is_flag=True, help="Only the float variant.")
@click.option(
    "--adc-scale",
    type=float,
    default=1.0,
    show_default=True,
    help="ADC counts per unit of the calibration's Hall signals (fixed point input).",
)
@_handle_errors
def export_c(artifact: str, out: str, no_fixed_point: bool, adc_scale: float) -> None:
    """Generate C99 sources of f_star (float and fixed point) for firmware."""
    from hallcal.io import read_artifact
    from hallcal.output.codegen import export_c as _export

    art = read_artifact(artifact)
    res = _export(art, out, fixed_point=not no_fixed_point, source=artifact, adc_scale=adc_scale)
    for m in res.messages:
        _err.print(f"note: {m}")
    for p in res.paths:
        _out.print(f"wrote {p}")
    _out.print(
        f"table {res.table_bytes} bytes (float); stated error bounds: float "
        f"{res.float_bound:.2g} rad, fixed point {res.fixed_bound:.2g} rad"
    )


@cli.command()
@click.argument("artifact", type=click.Path(dir_okay=False))
@click.argument("data", type=click.Path(dir_okay=False))
@click.option(
    "--validation",
    "validation",
    type=click.Path(dir_okay=False),
    default=None,
    help="A fresh run with y_ref to validate on.",
)
@click.option("--out", required=True, type=click.Path(file_okay=False))
@_handle_errors
def report(artifact: str, data: str, validation: str | None, out: str) -> None:
    """Figures and an HTML report of a calibration."""
    from hallcal.output.report import write_report_from_files

    path = write_report_from_files(
        artifact, data, validation=validation, out_dir=out, progress=_Progress()
    )
    _out.print(f"wrote {path}")


@cli.command()
@click.option(
    "--out",
    default="hallcal-demo",
    type=click.Path(file_okay=False),
    show_default=True,
    help="Folder for data, artifact, figures and report.",
)
@click.option("--seed", type=int, default=1, show_default=True)
@click.option("--no-report", is_flag=True, help="Skip figures and the HTML report.")
@_handle_errors
def demo(out: str, seed: int, no_report: bool) -> None:
    """The paper's simulation study end to end on the built-in defaults."""
    from hallcal.demo import run_demo

    res = run_demo(out, seed=seed, report=not no_report, progress=_Progress())
    for line in res.summary_lines():
        _out.print(line)


def main() -> None:
    """Console entry point."""
    cli(prog_name="hallcal")


if __name__ == "__main__":  # pragma: no cover
    main()
