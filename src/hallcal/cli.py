"""The ``hallcal`` command line (contract in docs/design.md, "Command line").

Exit status: 0 success; 2 bad input (one line naming the file, column or key; no traceback),
also an output that would overwrite an input and a failed write (a full disk, a file-size limit:
nothing partial is left); 3 refused (calibration: model inadequate or table not bijective, use
``--force`` to write an inadequate model anyway; BLA: the fitted plant model is unstable); 4
(``hallcal fleet`` only) at least one motor refused or failed, the others calibrated (their rows
in ``summary.csv`` say why); 130 interrupted (Ctrl-C: one line ``hallcal: aborted``, the outputs
as they were before). Progress and notes go to stderr, results to stdout.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import math
import os
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import click

from hallcal._constants import DEFAULT_C_PREFIX, DEFAULT_FAULT_AFTER, DEFAULT_TOLERANCE
from hallcal.errors import CalibrationRefused, HallcalError, HallcalInputError
from hallcal.formatting import AngleUnit, one_line, ranges, tf_text
from hallcal.limits import MAX_POLE_PAIRS
from hallcal.messages import Message, MessageCode

EXIT_INPUT = HallcalInputError.exit_status
#: Exit status after Ctrl-C (SIGINT): 128 + 2, the shells' convention.
EXIT_ABORTED = 130


class _Stream:
    """Plain lines on stdout or stderr through :func:`click.echo`.

    Progress and results are one line each, so rich (40 ms to import, and it would read
    ``[plant]`` in a message as markup) is not used here; styles are dropped when the stream
    is not a terminal.
    """

    def __init__(self, *, err: bool) -> None:
        self.err = err

    def print(self, message: object = "") -> None:
        click.echo(str(message), err=self.err)


_err = _Stream(err=True)
_out = _Stream(err=False)

#: ``ctx.obj`` of the commands that :func:`main` runs: the process is the command's own, not an
#: in-process caller's (click's CliRunner, the test suite's hostile and fuzz workers).
_OWN_PROCESS = "hallcal: the command's own process"


@contextlib.contextmanager
def _imports() -> Iterator[None]:
    """Around a command's heavy imports (NumPy, SciPy, numba, hallcal's computing modules).

    In the command's own process (:data:`_OWN_PROCESS`) their objects live as long as it does:
    the cycle collector is paused over them, they are frozen after (``gc.freeze``: its passes
    skip them), and it makes no full pass for the rest of the command (the young generations'
    passes go on and free the command's own cycles; the command is one computation of seconds,
    not a long run like ``fleet``, which keeps the collector as it is). The full passes over
    numba's heap (one in the imports, one in numba's start-up at the first kernel) and the young
    ones over the imports cost about 0.1 s of CPU per ``hallcal calibrate``. An in-process
    caller keeps its collector as it is: a freeze would keep its garbage for good.
    """
    ctx = click.get_current_context(silent=True)
    if ctx is None or ctx.obj != _OWN_PROCESS or not gc.isenabled():
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        young, middle, _ = gc.get_threshold()
        gc.set_threshold(young, middle, _NO_FULL_PASS)
        gc.enable()


#: Third threshold of the cycle collector (:func:`gc.set_threshold`) that it never reaches.
_NO_FULL_PASS = 2**30


#: Seeds of the random generators: non-negative and within 64 bits with room for the demo's
#: validation run (seed + 1000), so that they fit the artifact's JSON.
_SEED = click.IntRange(0, 2**62)
UNITS = tuple(u.value for u in AngleUnit)
_EXITS = "0 success, 2 bad input (one line naming the file, column or key)"
_EXITS_REFUSED = _EXITS + ", 3 refused"


def _one_line(exc: BaseException | str) -> str:
    text = one_line(exc)
    ctx = click.get_current_context(silent=True)
    path = None if ctx is None else ctx.meta.get("hallcal.setup_path")
    if text.startswith("setup:") and path:
        # the numeric layers say "setup:"; the user wants the file's name
        text = path + text[len("setup") :]
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
        except MemoryError:  # a step the budgets do not cover: one line, not a traceback
            click.echo(
                "hallcal: error: out of memory: the input is too large for the memory this "
                "process may use (a shorter recording, or a smaller model)",
                err=True,
            )
            sys.exit(EXIT_INPUT)
        except OSError as exc:  # one the writers did not see (no space for a folder)
            from hallcal.io.files import WRITE_ERRNOS

            if exc.errno not in WRITE_ERRNOS:
                raise
            where = exc.filename if exc.filename is not None else "output"
            click.echo(f"hallcal: error: {where}: {_one_line(exc.strerror or exc)}", err=True)
            sys.exit(EXIT_INPUT)

    return wrapper


def _guard(
    outputs: list[str | Path],
    inputs: list[str | None],
    *,
    folders: tuple[str | Path, ...] = (),
) -> None:
    """Refuse, before any work, an output that is an input or another output (exit 2)."""
    from hallcal.io import check_outputs

    check_outputs(outputs, inputs, folders=folders)


class _Progress:
    """One line per step on stderr with the elapsed time."""

    def __init__(self, quiet: bool = False) -> None:
        self.t0 = time.perf_counter()
        self.quiet = quiet

    def __call__(self, message: str) -> None:
        if not self.quiet:
            elapsed = click.style(f"{time.perf_counter() - self.t0:6.1f} s", dim=True)
            _err.print(f"{elapsed}  {message}")


def _setup(path: str | None):
    from hallcal.io import default_setup, read_setup

    ctx = click.get_current_context(silent=True)
    if ctx is not None:  # the setup file of this command, for error messages
        ctx.meta["hallcal.setup_path"] = path
    return default_setup() if path is None else read_setup(path)


def _output_dir(path: str) -> Path:
    """Check, before any work, that the output folder of report, export-c or demo can be written.

    A missing folder is created and removed again (with any missing parents): the command
    creates it only when it has something to write, so a failure leaves nothing behind.
    """
    from hallcal.io import check_outputs

    out = Path(path)
    check_outputs([], folders=[out])  # a name longer than the file system allows
    if out.exists():
        if not out.is_dir():
            raise HallcalInputError(f"{out}: exists and is not a directory")
        if not os.access(out, os.W_OK | os.X_OK):
            raise HallcalInputError(f"{out}: the directory is not writable")
        return out
    missing = []
    p = out
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    try:
        out.mkdir(parents=True)
    except OSError as exc:
        why = exc.strerror or exc
        raise HallcalInputError(f"{out}: cannot create the directory ({why})") from None
    for m in missing:  # innermost first
        m.rmdir()
    return out


def _output_file(path: str, *, dataset: bool = False) -> Path:
    """Check an output file's folder (and a dataset's extension) before any work is done."""
    from hallcal.io import check_outputs

    out = Path(path)
    check_outputs([out])  # a folder in the way, a name longer than the file system allows
    if dataset:
        from hallcal.io import DATASET_EXTENSIONS

        if out.suffix.lower() not in DATASET_EXTENSIONS:
            shown = f"'{out.suffix}'" if out.suffix else "(none)"
            raise HallcalInputError(
                f"{out}: unknown dataset extension {shown} (expected one of "
                f"{', '.join(DATASET_EXTENSIONS)})"
            )
    if not out.parent.is_dir():
        raise HallcalInputError(f"{out}: directory '{out.parent}' does not exist")
    if not os.access(out.parent, os.W_OK | os.X_OK):
        raise HallcalInputError(f"{out}: the directory '{out.parent}' is not writable")
    return out


class _Aborted(Exception):
    """Ctrl-C during a command (exit status 130)."""


class _Group(click.Group):
    """The command group, with click's own usage errors in hallcal's one-line form.

    ``hallcal calibrate`` without ``--out`` prints ``hallcal: error: Missing option '--out'
    (see 'hallcal calibrate --help')`` and exits with status 2, like every other input error.
    """

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:  # before click turns it into Abort with a blank line
            raise _Aborted from None

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except click.ClickException as exc:
            ctx = getattr(exc, "ctx", None)
            hint = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
            message = _one_line(exc.format_message())
            if type(exc).__name__ == "NoArgsIsHelpError":  # its message is the whole help
                message = "no command given"
            click.echo(f"hallcal: error: {message}{hint}", err=True)
            sys.exit(exc.exit_code)
        except (click.exceptions.Abort, KeyboardInterrupt):
            click.echo("hallcal: aborted", err=True)
            sys.exit(EXIT_ABORTED)
        except Exception as exc:
            if not _interrupted(exc):
                raise
            click.echo("hallcal: aborted", err=True)
            sys.exit(EXIT_ABORTED)
        sys.exit(rv if isinstance(rv, int) else 0)


def _interrupted(exc: BaseException) -> bool:
    """Whether `exc` came from Ctrl-C: numba's compiled loops hand a KeyboardInterrupt back as
    the cause of a SystemError ("returned a result with an exception set")."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt | _Aborted):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def _plural(count: int, word: str) -> str:
    return f"{count} {word}" + ("" if count == 1 else "s")


def _epilog(*examples: str, exits: str = _EXITS) -> str:
    """A command's help epilog: examples and the exit statuses (``\\b`` keeps the layout)."""
    lines = "\n".join(f"  {e}" for e in examples)
    return f"\b\nExamples:\n{lines}\n\n\b\nExit status: {exits}."


_units_option = click.option(
    "--units",
    type=click.Choice(UNITS),
    default=AngleUnit.MRAD.value,
    show_default=True,
    callback=lambda _ctx, _param, value: AngleUnit(value),
    help="Angle errors in mechanical mrad, rad or deg, or in electrical degrees (mechanical x "
    "pole pairs).",
)


_FILE = click.Path(dir_okay=False)
_FOLDER = click.Path(file_okay=False)
#: The positional arguments of a recording and of a calibration artifact.
_data_argument = click.argument("data", type=_FILE)
_artifact_argument = click.argument("artifact", type=_FILE)


def _setup_option(help: str, *, required: bool = False) -> Callable[..., Any]:
    """The ``--setup`` option (a setup TOML file, parameter ``setup_path``)."""
    return click.option("--setup", "setup_path", required=required, type=_FILE, help=help)


def _out_option(help: str, *, folder: bool = False, **kwargs: Any) -> Callable[..., Any]:
    """The ``--out`` option: a file (default) or a folder, required unless a default is given."""
    kwargs.setdefault("required", "default" not in kwargs)
    return click.option("--out", type=_FOLDER if folder else _FILE, help=help, **kwargs)


def _notes(messages: tuple[Message, ...] | list[Message]) -> None:
    """Notes and warnings on stderr, once each, as :meth:`Message.line` renders them."""
    for line in dict.fromkeys(m.line() for m in messages):
        _err.print(line)


@click.group(
    cls=_Group,
    context_settings={"help_option_names": ["-h", "--help"]},
    epilog=_epilog(
        "hallcal demo --out hallcal-demo",
        "hallcal inspect run.csv --setup setup.toml",
        "hallcal calibrate cal.csv --setup setup.toml --bla-data bla.csv --out cal.json",
        exits=_EXITS_REFUSED + " (the result must not be used)",
    ),
)
@click.version_option(package_name="hallcal")
def cli() -> None:
    """Self-calibration of analog linear Hall sensors without an encoder.

    The method of van Meer et al., "Self-Calibrating Position Measurements: Applied to Imperfect
    Hall Sensors": closed-loop data, a BLA of the motor, simulation-error minimization of a
    flux model and a lookup-table correction f_star. The setup file's keys are documented in
    docs/setup-reference.md.

    Exit status: 0 success; 2 bad input (one line naming the file, column or key); 3 refused;
    4 (fleet) at least one motor refused or failed; 130 interrupted (Ctrl-C).
    """


# ------------------------------------------------------------------------------------------------


@cli.command(
    epilog=_epilog(
        "hallcal simulate --setup setup.toml --out cal.csv",
        "hallcal simulate --setup setup.toml --experiment multisine --out bla.csv",
        "hallcal simulate --setup setup.toml --seed 2 --out run.csv   # a fresh validation run",
    )
)
@_setup_option("Setup TOML ([bench], [plant], [controller], [bla]); default: the paper's.")
@_out_option("Dataset to write (.csv, .parquet, .h5, .mat, .npz).")
@click.option(
    "--experiment",
    type=click.Choice(["ramp", "multisine"]),
    default=None,
    help="Override [bench] experiment: the calibration ramp or the BLA multisines of [bla].",
)
@click.option(
    "--seed",
    type=_SEED,
    default=None,
    help="Noise seed of this run (the motor's truth stays that of [bench] seed).",
)
@_handle_errors
def simulate(setup_path: str | None, out: str, experiment: str | None, seed: int | None) -> None:
    """Run the virtual bench and write a dataset (truth in OUT's .truth.json sidecar).

    The simulated motor is the setup's [plant] with the [bench] sensor imperfections; the
    recording has the encoder column y_ref (the true angle), so it can serve as a validation run.
    """
    with _imports():
        from hallcal import pipeline
        from hallcal.io import output_set, write_dataset, write_json

    setup = _setup(setup_path)
    _output_file(out, dataset=True)
    _output_file(str(Path(out).with_suffix(".truth.json")))  # the sidecar: both or neither
    _guard([out, Path(out).with_suffix(".truth.json")], [setup_path])
    prog = _Progress()
    kind = experiment or setup.bench.experiment
    if setup.controller is None:
        default = "the setup has no [controller]: the virtual bench uses the paper's C(q)"
        _err.print(Message.note(MessageCode.DEFAULT_USED, default).line())
    prog(f"simulating the {kind} experiment")
    run = pipeline.simulate(setup, experiment=experiment, seed=seed)
    if run.status != "ok":
        raise HallcalInputError(
            f"{setup_path or 'setup'}: the simulated closed loop diverged (check [controller] "
            "and [plant])"
        )
    out_path = Path(out)
    sidecar = out_path.with_suffix(".truth.json")
    with output_set():
        write_dataset(out_path, run.columns())
        write_json(sidecar, run.truth_dict())
    e = run.y - run.y0
    mrad = AngleUnit.MRAD.text
    _out.print(f"wrote {out_path} ({run.n_samples} samples) and {sidecar}")
    _out.print(
        f"f_init error against the truth: RMS {mrad(float((e - e.mean()).std()))}, "
        f"peak {mrad(float(abs(e - e.mean()).max()))}; noise floor "
        f"{mrad(run.config.noise_floor)}"
    )


@cli.command(
    epilog=_epilog(
        "hallcal inspect run.csv",
        "hallcal inspect ring.txt --pole-pairs 25",
        "hallcal inspect cal.csv --setup setup.toml",
    )
)
@_data_argument
@_setup_option(
    "Setup TOML: its pole_pairs, sample_time and [trajectory] are checked against the data."
)
@click.option(
    "--pole-pairs",
    type=click.IntRange(1, MAX_POLE_PAIRS),
    default=None,
    help="Pole pairs to check (default: the setup's, else the count the data suggest).",
)
@_handle_errors
def inspect(data: str, setup_path: str | None, pole_pairs: int | None) -> None:
    """Look at a recording before calibrating it.

    Samples, sample time, revolutions and direction, the pole-pair count the data show (from the
    reference r or an encoder y_ref, else from the magnets' signature), the sensors' electrical
    spacing, amplitudes and offsets, ADC clipping, the constant-speed window and the [trajectory]
    start/stop to use for an open-loop calibration.
    """
    with _imports():
        from hallcal.io import read_dataset
        from hallcal.limits import check_command_samples
        from hallcal.pipeline.inspect import inspect_recording

    setup = None if setup_path is None else _setup(setup_path)
    ds = read_dataset(data, required=("d1", "d2", "d3"))
    try:
        check_command_samples(ds.n_samples, "inspect")
    except ValueError as exc:
        raise HallcalInputError(f"{data}: {exc}") from None
    found = inspect_recording(ds, setup=setup, pole_pairs=pole_pairs)
    for line in found.lines():
        (_err if isinstance(line, Message) else _out).print(str(line))
    toml = found.trajectory_toml()
    if toml is not None and "r" not in ds:
        _out.print("setup lines for a constant-speed calibration:")
        _out.print(toml)
    if found.pole_pairs_given:  # a wrong count: the report above used the data's; exit 2
        found.pole_pair_check.raise_if_failed(ds.source)


def _pole_list(poles: tuple[complex, ...]) -> str:
    if not poles:
        return "-"
    out = []
    for p in poles:
        if abs(p.imag) < 1e-9 * max(abs(p), 1.0):
            out.append(f"{p.real:.4g}")
        elif p.imag > 0:
            out.append(f"{p.real:.4g}±{p.imag:.3g}j")
    return ", ".join(out)


@cli.command(
    epilog=_epilog(
        "hallcal bla bla.csv --setup setup.toml --out bla.json   # also writes bla.png",
        exits=_EXITS_REFUSED + " (the fitted plant model is unstable; bla.json and bla.png are "
        "written for inspection)",
    )
)
@_data_argument
@_setup_option(
    "Setup TOML with [bla] (period, periods, model orders) and sample_time.", required=True
)
@_out_option("BLA JSON to write; its Bode plot goes next to it with the suffix .png.")
@_handle_errors
def bla(data: str, setup_path: str, out: str) -> None:
    """Identify the closed-loop BLA of the plant from a multisine dataset.

    Prints the model order chosen (or checked), the fitted G(s) with its poles and the fit's
    cost against the BLA's variance, and writes the Bode plot (BLA, its standard deviations and
    the fit). An unstable fit is refused with the [bla] setting to change.
    """
    with _imports():
        from hallcal import pipeline
        from hallcal.io import output_set, read_dataset, write_json

    setup = _setup(setup_path)
    _output_file(out)
    _guard([out, Path(out).with_suffix(".png")], [data, setup_path])
    ds = read_dataset(data, required=("r", "u", "y", "realization"))
    res = pipeline.identify_bla(ds, setup, progress=_Progress())
    out_path = Path(out)
    png = out_path.with_suffix(".png")
    with output_set():  # the JSON and its Bode plot: both or neither
        write_json(out_path, res.to_dict())
        _write_bla_plot(res, png)
    npb, par = res.nonparametric, res.parametric
    _out.print(
        f"BLA of {data}: {_plural(npb.realizations, 'realization')} x "
        f"{_plural(npb.periods, 'steady-state period')}, {npb.freq.size} lines from "
        f"{npb.freq.min():.4g} to {npb.freq.max():.4g} Hz"
    )
    sel = res.selection
    if sel is not None:
        _out.print("model orders tried (cost: weighted output error, about the number of lines")
        _out.print(f"for a model that explains the BLA within its variance, here {sel.lines}):")
        _out.print("  denominator order  parameters  cost        criterion   poles [rad/s]")
        given = setup.bla.denominator_order if setup.bla is not None else "auto"
        for c in sel.candidates:
            mark = "  unstable" if not c.stable else ""
            if sel.chosen is c:
                mark += "  <- chosen" if given == "auto" else "  <- the data's choice"
            if given != "auto" and c.denominator_order == given:
                mark += "  <- [bla] denominator_order"
            _out.print(
                f"  {c.denominator_order:<17d}  {c.parameters:<10d}  {c.cost:<10.4g}  "
                f"{c.criterion:<10.4g}  {_pole_list(c.poles)}{mark}"
            )
    p = res.plant
    _out.print(tf_text(p.num, p.den, p.delay))
    if res.check is not None:
        _out.print(f"poles (besides the integrator): {_pole_list(res.check.poles)} rad/s")
    _out.print(f"fit cost {par.cost:.4g} for {par.freq.size} lines; status {res.status}")
    _notes(res.messages)
    _out.print(f"wrote {out_path} and {png} (Bode plot with the standard deviations)")
    if not res.status.success:
        raise CalibrationRefused(f"{data}: {res.refusal}")


def _write_bla_plot(res: Any, path: Path) -> None:
    from hallcal.io.files import atomic_write
    from hallcal.output.plots import figure_png, plot_bla

    with atomic_write(path, "wb") as f:
        f.write(figure_png(plot_bla(res), dpi=110))


@cli.command(
    epilog=_epilog(
        "hallcal calibrate cal.csv --setup setup.toml --bla-data bla.csv --out cal.json",
        "hallcal calibrate ring.csv --setup ring.toml --out cal.json --units electrical-deg",
        exits=_EXITS_REFUSED + " (model inadequate or table not bijective; nothing written "
        "unless --force)",
    )
)
@_data_argument
@_setup_option("Setup TOML (docs/setup-reference.md).", required=True)
@click.option(
    "--bla-data",
    type=_FILE,
    default=None,
    help="Multisine experiment for the BLA of the plant; wins over the setup's [plant].",
)
@_out_option("Artifact to write.")
@click.option("--force", is_flag=True, help="Write the artifact even if the model is inadequate.")
@_units_option
@_handle_errors
def calibrate(
    data: str, setup_path: str, bla_data: str | None, out: str, force: bool, units: AngleUnit
) -> None:
    """Calibrate: checks, plant (BLA if given), SEM, lookup table; write the JSON artifact.

    Before the expensive steps the pole-pair count, the direction of rotation and the stability
    of the loop of [controller] and the plant are checked; each failure names the fix.
    """
    with _imports():
        from hallcal.api import calibrate as _calibrate

    setup = _setup(setup_path)
    _output_file(out)
    _guard([out], [data, setup_path, bla_data])
    cal = _calibrate(data, setup, bla_data=bla_data, progress=_Progress())
    _print_calibration(cal, units)
    cal.save(out, force=force or setup.model.force)
    _out.print(f"wrote {out}")


def _print_calibration(cal, units: AngleUnit = AngleUnit.MRAD) -> None:
    n_m = cal.pole_pairs
    sem = cal.sem
    _notes(cal.messages)
    info = cal.model_info
    if info.get("basis") == "fourier":
        _out.print(f"model: Fourier basis, mechanical harmonics {ranges(info['harmonics'])}")
    elif info.get("basis") == "kernel":
        _out.print(
            f"model: periodic kernel basis, {info.get('points')} points, "
            f"lengthscale {info.get('lengthscale', float('nan')):.3g} rad"
        )
    if cal.gain is not None:
        g = cal.gain
        refined = (
            ""
            if g.c_refined is None or not math.isfinite(g.c_refined_std or math.nan)
            else f", refined with the flux model: {g.c_refined:.4f} ± {g.c_refined_std:.4f}"
        )
        _out.print(f"gain correction of the BLA (the paper's c-hat): c = {g.c:.4f}{refined}")
    if sem is not None:
        _out.print(
            f"SEM cost {sem.initial_cost:.6g} -> {sem.cost:.6g} in "
            f"{_plural(int(sem.iterations), 'iteration')} ({sem.status}), {sem.solve_time:.2f} s; "
            f"noise variance {sem.noise_variance:.3g} (Hall signal unit)²"
        )
    cs = cal.constant_speed
    if cs is not None:
        _out.print(
            f"constant-speed fit: {cs.revolutions:.2f} revolutions, rotor motion off the straight "
            f"line {units.text(cs.motion_rms, n_m)} RMS"
        )
    _out.print(
        f"predicted f_star error: RMS {units.text(cal.predicted_error, n_m)} "
        f"(noise floor {units.text(cal.noise_floor, n_m)})"
    )
    if cal.adequacy is not None:
        _out.print(f"model adequacy: {cal.adequacy.verdict}")
    _out.print(f"lookup table: {cal.lut.points} points, bijective: {cal.lut.bijective}")
    if cal.identifiability is not None:
        _out.print(cal.identifiability.message)
    _print_validation(cal.validation, units, n_m)


def _print_validation(v, units: AngleUnit, n_m: int) -> None:
    """One line: f_init and f_star against the recording's y_ref, when it has one."""
    if v is not None:
        _out.print(
            f"against y_ref: f_init RMS {units.text(v.init.rms, n_m)} peak "
            f"{units.text(v.init.peak, n_m)}; f_star RMS {units.text(v.star.rms, n_m)} "
            f"peak {units.text(v.star.peak, n_m)}"
        )


@cli.command(
    epilog=_epilog(
        "hallcal reconstruct cal.json run.csv --out angles.csv",
        "hallcal reconstruct cal.json powerup.csv --absolute --out angles.csv",
        "hallcal reconstruct cal.json run.csv --observer --out angles.csv",
        exits=_EXITS + ", 3 the signals do not fit the calibration's model (ring remounted, "
        "sensors swapped or rewired, sensors drifted), or the artifact has no table (kept for "
        "the observer only: use --observer)",
    )
)
@_artifact_argument
@_data_argument
@_out_option("Table to write: columns y_init and y_star [rad, mechanical], one row per sample.")
@click.option(
    "--absolute",
    is_flag=True,
    help="The recording starts at power-up anywhere (no homing): identify the pole pair from "
    "the magnets' signatures; angles in the calibration's frame.",
)
@click.option(
    "--observer",
    is_flag=True,
    help="Also run the model-based observer: columns y_obs [rad] (tracking maximum-likelihood "
    "angle with gain/offset adaptation), misfit (about 1 when the model fits) and state (ok, "
    "adapting, stale, degraded, fault).",
)
@_units_option
@_handle_errors
def reconstruct(
    artifact: str, data: str, out: str, absolute: bool, observer: bool, units: AngleUnit
) -> None:
    """Apply a calibration to a recording: columns y_init and y_star.

    f_init and f_star run over the recording from y = 0 before the first sample (the frame of
    the calibration run), or, with --absolute, from the pole pair identified at power-up. With
    an encoder column y_ref both are compared with it. The signals are first tested against
    the calibration's flux model (its calibrated noise): when no pole pair fits, it refuses
    (exit 3) and names swapped or rewired sensors when another order of d1..d3 fits.
    --observer adds the model-based observer's y_obs, misfit and state (docs/firmware.md says
    when to use which).
    """
    with _imports():
        from hallcal.api import load
        from hallcal.io import write_dataset

    if absolute and observer:
        raise HallcalInputError("--absolute and --observer cannot be combined")
    _output_file(out, dataset=True)
    _guard([out], [artifact, data])
    cal = load(artifact)
    rec = cal.reconstruct(data, absolute=absolute, observer=observer)
    if rec.signals is not None:
        rec.signals.raise_if_failed()  # exit 3: the signals do not fit this calibration
        if rec.signals.warning is not None:
            _err.print(rec.signals.warning.line())
    write_dataset(out, rec.columns)
    _out.print(f"wrote {out} ({len(rec)} samples)")
    _notes(rec.messages)
    if rec.identification is not None:
        report = cal.identifiability
        travel = report.lock_travel if report is not None else 0.0
        _print_identification(rec.identification, cal.pole_pairs, lock_travel=travel)
    _print_validation(rec.validation, units, cal.pole_pairs)
    if rec.observer is not None:
        _print_observer(rec, units, cal.pole_pairs)


def _print_observer(rec, units: AngleUnit, n_m: int) -> None:
    """Two lines: the observer's states and first exclusion; y_obs against y_ref."""
    obs = rec.observer
    counts = Counter(obs.state.tolist())
    shares = ", ".join(f"{name} {c / len(obs):.1%}" for name, c in sorted(counts.items()))
    excl = (
        f"; channel d{obs.excluded + 1} excluded from sample {obs.first_exclusion}"
        if obs.excluded >= 0
        else ""
    )
    _out.print(f"observer: {shares}; final misfit {obs.misfit[-1]:.2f}{excl}")
    if rec.observer_error is not None:
        e = rec.observer_error
        _out.print(
            f"against y_ref: y_obs RMS {units.text(e.rms, n_m)} peak {units.text(e.peak, n_m)}"
        )


@cli.command(
    epilog=_epilog(
        "hallcal plan cal.json --revolutions 3",
        "hallcal plan cal.json --revolutions 2 --speeds 0.5,1,2,4,8",
        exits=_EXITS + ", 3 no candidate speed reaches the target",
    )
)
@_artifact_argument
@click.option(
    "--revolutions",
    type=float,
    default=2.0,
    show_default=True,
    help="Length of the planned calibration ramp [mechanical revolutions].",
)
@click.option(
    "--speeds",
    default=None,
    help="Comma-separated candidate ramp speeds [rad/s]; default: 13 speeds spaced by sqrt(2) "
    "up to the fastest the flux model's band allows.",
)
@click.option(
    "--target",
    type=float,
    default=1.1,
    show_default=True,
    help="Acceptable predicted f_star error relative to the noise floor.",
)
@_handle_errors
def plan(artifact: str, revolutions: float, speeds: str | None, target: float) -> None:
    """How fast to ramp the next closed-loop calibration run of this motor type.

    From a calibration of the same motor type (its loop, flux map, cogging and noise), predicts
    the RMS error of f_star that a ramp at each speed would give (Fisher information of the SEM
    problem). A slow ramp on a fast position loop puts the sensor error where the loop's
    integral action hides it; the same revolutions at a higher speed determine the table.
    """
    with _imports():
        from hallcal.api import load
        from hallcal.pipeline.plan import plan_next_ramp

    grid = None
    if speeds is not None:
        try:
            grid = [float(v) for v in speeds.split(",") if v.strip()]
        except ValueError:
            raise HallcalInputError(
                f"--speeds: expected comma-separated numbers [rad/s], got {speeds!r}"
            ) from None
    cal = load(artifact)
    result = plan_next_ramp(cal.result, revolutions=revolutions, speeds=grid, target=target)
    floor = result.predictions[0].floor if result.predictions else math.nan
    _out.print(f"noise floor {AngleUnit.MRAD.text(floor)}; ramp over {revolutions:g} revolutions")
    _out.print(f"{'speed [rad/s]':>14} {'samples':>9} {'f_star [mrad]':>14} {'x floor':>8}")
    for p in result.predictions:
        mark = (
            "  <- slowest within target"
            if p is result.recommended and result.status.success
            else ""
        )
        _out.print(f"{p.speed:14.4g} {p.samples:9d} {1e3 * p.predicted:14.4g} {p.ratio:8.3f}{mark}")
    if not result.status.success:
        raise CalibrationRefused(f"plan: {result.message}")
    _out.print(result.message)


def _print_identification(ident, pole_pairs: int, *, lock_travel: float = 0.0) -> None:
    """One line: which pole pair the recording started in, and how certain that is (with
    ``lock_travel`` > 0 the calibration's lock waits for that many electrical revolutions)."""
    where = f"pole pair offset {ident.offset} of {pole_pairs}"
    if ident.status.success:
        _out.print(
            f"{where}: identified after {ident.lock_sample + 1} samples "
            f"(posterior {ident.posterior:.6f}, margin {ident.margin:.1f} sigma)"
        )
        return
    why = (
        f"this motor's lock waits for {lock_travel:g} electrical revolution"
        f"{'' if lock_travel == 1 else 's'} of motion (at rest a sensor's drift since calibration "
        "would mimic another pole pair): turn the rotor that far"
        if lock_travel > 0.0
        else "the rotor stood at a weak position: move it, or record longer"
    )
    warning = Message.warning(
        MessageCode.POWERUP,
        f"{where} is the most likely one but not certain after all {ident.samples} samples "
        f"(posterior {ident.posterior:.3f}); {why}",
    )
    _err.print(warning.line())


@cli.command(
    "export-c",
    epilog=_epilog(
        "hallcal export-c cal.json --out firmware/",
        "hallcal export-c cal.json --out firmware/ --adc-scale 4096 --no-fixed-point",
    ),
)
@_artifact_argument
@_out_option("Folder for the C files.", folder=True)
@click.option("--no-fixed-point", is_flag=True, help="Only the float variant.")
@click.option(
    "--adc-scale",
    type=float,
    default=None,
    help="ADC counts per unit of the calibration's Hall signals (the fixed-point variant's "
    "input). Default: the fixed-point pair only when the artifact is in counts; the float pair "
    "needs no scale.",
)
@click.option(
    "--max-speed",
    type=float,
    default=None,
    help="Largest mechanical speed [rad/s] for the step rule (default: 22.5 electrical "
    "degrees per sample).",
)
@click.option(
    "--table-points",
    type=int,
    default=None,
    help="Intervals of the correction table, pole pairs x 2^k (default: from the error budget).",
)
@click.option(
    "--tolerance",
    type=float,
    default=DEFAULT_TOLERANCE,
    show_default=True,
    help="Relative widening of the calibrated amplitude windows.",
)
@click.option(
    "--fault-after",
    type=int,
    default=DEFAULT_FAULT_AFTER,
    show_default=True,
    help="Rejected samples in a row before the fault flag.",
)
@click.option("--prefix", default=DEFAULT_C_PREFIX, show_default=True, help="C name prefix.")
@click.option(
    "--observer",
    is_flag=True,
    help="Write the model-based observer instead (<prefix>_obs.h/.c, float; "
    "docs/firmware.md): also for a calibration kept for the observer only.",
)
@click.option(
    "--no-powerup",
    is_flag=True,
    help="No pole-pair identification at power-up in the float variant (saves its tables; "
    "the angle then comes from set_angle after init, as in the fixed-point variant).",
)
@_handle_errors
def export_c(
    artifact: str,
    out: str,
    no_fixed_point: bool,
    adc_scale: float | None,
    max_speed: float | None,
    table_points: int | None,
    tolerance: float,
    fault_after: int,
    prefix: str,
    no_powerup: bool,
    observer: bool,
) -> None:
    """Generate lean C99 sources of f_star (float and fixed point) for firmware.

    The API, the plausibility checks and the error bounds: docs/firmware.md.
    """
    with _imports():
        from hallcal.api import export_c as _export
        from hallcal.io import read_artifact
        from hallcal.pipeline.calibration import require_table

    if observer:
        from hallcal.output.codegen.c_observer import export_observer_c

        _guard([Path(out) / f"{prefix}_obs.{x}" for x in ("h", "c")], [artifact])
        art = read_artifact(artifact)
        res_obs = export_observer_c(art, _output_dir(out), prefix=f"{prefix}_obs", source=artifact)
        for p in res_obs.paths:
            _echo(f"wrote {p}")
        _echo(f"observer tables: {res_obs.table_points} points per revolution, "
              f"{res_obs.table_bytes} bytes")  # fmt: skip
        return
    names = [f"{prefix}.h", f"{prefix}.c"]
    names += [] if no_fixed_point else [f"{prefix}_q.h", f"{prefix}_q.c"]
    _guard([Path(out) / n for n in names], [artifact])
    art = read_artifact(artifact)  # its sha256 is the file's, as sha256sum prints it
    require_table(art, artifact)
    out_dir = _output_dir(out)
    res = _export(
        art,
        out_dir,
        fixed_point=False if no_fixed_point else None,
        source=artifact,
        adc_scale=adc_scale,
        max_speed=max_speed,
        table_points=table_points,
        tolerance=tolerance,
        fault_after=fault_after,
        prefix=prefix,
        powerup=not no_powerup,
    )
    for m in res.messages:
        _echo(Message.note(MessageCode.C_EXPORT, m).line(), err=True)
    for p in res.paths:
        _echo(f"wrote {p}")
    bounds = f"float {res.float_bound:.2g} rad"
    if res.fixed_bound is not None:
        bounds += f", fixed point {res.fixed_bound:.2g} rad"
    _echo(
        f"table {res.table_points} intervals ({res.table_bytes} bytes), "
        f"{res.table_error:.2g} rad from the calibration's; stated bounds: {bounds}"
    )


def _echo(text: str, *, err: bool = False) -> None:
    """One line to stdout or stderr, whatever characters the stream's encoding lacks (a file
    name in an ASCII locale) written as escapes rather than failing."""
    stream = sys.stderr if err else sys.stdout
    encoding = getattr(stream, "encoding", None) or "ascii"
    click.echo(text.encode(encoding, "backslashreplace").decode(encoding), err=err)


@cli.command(
    epilog=_epilog(
        "hallcal report cal.json cal.csv --validation run.csv --out report/",
        "hallcal report cal.json ring.csv --out report/ --units electrical-deg",
    )
)
@_artifact_argument
@_data_argument
@click.option(
    "--validation",
    "validation",
    type=_FILE,
    default=None,
    help="A fresh run with y_ref to validate on.",
)
@_out_option("Folder for the report.", folder=True)
@_units_option
@_handle_errors
def report(artifact: str, data: str, validation: str | None, out: str, units: AngleUnit) -> None:
    """Figures and an HTML report of a calibration (docs/report.md).

    DATA is the calibration recording; a bla.json next to the artifact is plotted when the
    plant came from a BLA.
    """
    with _imports():
        from hallcal.output.report import write_report_from_files

    _output_dir(out)
    _guard(
        [Path(out) / "report.html"],
        [artifact, data, validation],
        folders=(Path(out) / "figures",),
    )
    path = write_report_from_files(
        artifact, data, validation=validation, out_dir=out, progress=_Progress(), units=units
    )
    _out.print(f"wrote {path}")


@cli.command(epilog=_epilog("hallcal demo --out hallcal-demo", "hallcal demo --no-report"))
@_out_option(
    "Folder for data, artifact, figures and report.",
    folder=True,
    default="hallcal-demo",
    show_default=True,
)
@click.option(
    "--seed", type=_SEED, default=1, show_default=True, help="Seed of the simulated motor."
)
@click.option("--no-report", is_flag=True, help="Skip figures and the HTML report.")
@_handle_errors
def demo(out: str, seed: int, no_report: bool) -> None:
    """The paper's simulation study end to end on the built-in defaults."""
    from hallcal.demo import run_demo
    from hallcal.io import output_set

    _output_dir(out)
    with output_set():  # every file of the demo, or none (Ctrl-C, a full disk)
        res = run_demo(out, seed=seed, report=not no_report, progress=_Progress())
    for line in res.summary_lines():
        _out.print(line)


@cli.command(
    epilog=_epilog(
        "hallcal fleet manifest.csv --out batch/",
        "hallcal fleet manifest.csv --out batch/ --export-c --scheduler sequential",
        exits=_EXITS + " (the manifest or an option), 4 at least one motor refused or failed "
        "(see summary.csv); success is every motor ok or warning",
    )
)
@click.argument("manifest", type=_FILE)
@_out_option(
    "Output folder: <motor_id>/ per motor, summary.csv, summary.parquet, fleet.html.", folder=True
)
@click.option(
    "--scheduler",
    default=None,
    metavar="ADDRESS",
    help="Address of an existing Dask scheduler (tcp://host:8786); default: a local cluster "
    "with one worker per core. 'sequential': no Dask, one motor after the other.",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    help="Workers of the local cluster (default: one per core).",
)
@click.option(
    "--export-c", is_flag=True, help="Also write each motor's C99 sources (<motor_id>/c/)."
)
@click.option(
    "--adc-scale",
    type=float,
    default=None,
    help="ADC counts per Hall signal unit, for the fixed-point C export (default: the "
    "fixed-point pair only for artifacts in counts; the float pair always).",
)
@click.option("--recompute", is_flag=True, help="Recalibrate motors whose results are up to date.")
@click.option("--no-report", is_flag=True, help="Skip fleet.html.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@_handle_errors
def fleet(
    manifest: str,
    out: str,
    scheduler: str | None,
    workers: int | None,
    export_c: bool,
    adc_scale: float | None,
    recompute: bool,
    no_report: bool,
    quiet: bool,
) -> None:
    """Calibrate many motors on Dask, listed in MANIFEST (CSV or Parquet).

    MANIFEST columns: motor_id, data, setup, and optional bla_data and validation (an empty cell
    is none); relative paths are relative to MANIFEST. Each motor gets a row in summary.csv and
    summary.parquet with its status (ok, warning, refused, failed) and a one-line reason; a bad
    file or a crashed worker stops only its motor. A rerun skips motors whose results are up to
    date (same input contents, setup and hallcal version).
    """
    from rich.console import Console  # the progress bar only: imported by this command alone
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from hallcal.fleet import EXIT_INCOMPLETE, all_succeeded, run_fleet, summary_counts

    if workers is not None and scheduler is not None:
        raise HallcalInputError("--workers applies to the local cluster, not to --scheduler")
    counts = {"ok": 0, "warning": 0, "refused": 0, "failed": 0}
    bar = Progress(
        TextColumn("calibrating"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[counts]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True, highlight=False, soft_wrap=True),
        disable=quiet,
    )
    task_id = None

    def progress(row, done: int, total: int) -> None:
        nonlocal task_id
        if task_id is None:  # the batch starts: its checks passed, its folder is locked
            bar.start()
            task_id = bar.add_task("fleet", total=total, counts="")
        if row is None:
            return
        counts[row["status"]] = counts.get(row["status"], 0) + 1
        if row["status"] in ("refused", "failed"):
            line = f"{row['motor_id']}: {row['status']}: {row['message']}"
            bar.console.print(line, markup=False)  # messages hold [plant], [model]...
        text = " ".join(f"{k} {v}" for k, v in counts.items() if v)
        bar.update(task_id, completed=done, counts=text)

    try:
        table = run_fleet(
            manifest,
            out,
            scheduler=scheduler,
            workers=workers,
            export_c=export_c,
            adc_scale=adc_scale,
            recompute=recompute,
            report=not no_report,
            progress=progress,
        )
    finally:
        if task_id is not None:
            bar.stop()
    c = summary_counts(table)
    reused = sum(table.column("reused").to_pylist())
    _out.print(
        f"{table.num_rows} motors: {c['ok']} ok, {c['warning']} warning, {c['refused']} "
        f"refused, {c['failed']} failed"
        + (f" ({reused} up to date from an earlier run)" if reused else "")
    )
    out_dir = Path(out)
    written = ["summary.csv", "summary.parquet"] + ([] if no_report else ["fleet.html"])
    _out.print("wrote " + ", ".join(str(out_dir / w) for w in written))
    if not all_succeeded(table):
        sys.exit(EXIT_INCOMPLETE)


def main() -> None:
    """Console entry point."""
    try:
        cli(prog_name="hallcal", obj=_OWN_PROCESS)
    except KeyboardInterrupt:  # between click's handlers (start-up, the last lines)
        sys.stderr.write("hallcal: aborted\n")
        sys.exit(EXIT_ABORTED)
    finally:
        # The process ends with the command: move every object left to the cycle collector's
        # permanent generation, so that the interpreter's final collections skip them (the
        # import-time objects of numba, NumPy and SciPy, most of the heap). That pass cost
        # 0.35 s of CPU per `hallcal calibrate` on the 2-core machine; all is freed at exit.
        gc.freeze()


if __name__ == "__main__":  # pragma: no cover
    main()
