"""The command-line contract for hostile input, shared by the hostile suite and the setup fuzz.

Contract (README, "Exit status"; docs/design.md, "Command line"): the exit status is 0, 2 (bad
input) or 3 (refused); never a traceback or a Python warning; a failure ends with exactly one line
``hallcal: error: ...`` or ``hallcal: refused: ...`` on stderr, preceded at most by the progress
lines and the calibration's own messages; and a failed command leaves no output behind (no file
at ``--out``, no new file in an output folder, no temporary file).

:func:`run_in_process` runs the command through click's :class:`~click.testing.CliRunner` in this
process (no interpreter start-up per case); :func:`contract_violations` lists what an outcome
breaks. The test modules import this file as a plain module (``tests/`` is on ``sys.path``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

#: The one line a failure ends with (``hallcal: aborted`` after Ctrl-C, exit status 130).
ERROR_LINE = re.compile(r"^hallcal: ((error|refused): \S|aborted$)")
#: Lines a command may print on stderr before it fails: progress (elapsed seconds and a step),
#: and the calibration's messages (plant note, warnings) and export notes; a fleet's motor lines.
ALLOWED_BEFORE_ERROR = re.compile(
    r"^(\s*\d+\.\d s  \S|plant: |warning: |note: |\S+: (failed|refused): )"
)
#: A Python warning printed by the warnings module ("file.py:12: RuntimeWarning: ...").
PYTHON_WARNING = re.compile(r"\b[A-Z]\w*Warning: ")
#: Temporary files of hallcal's atomic writes (hallcal.io.files.atomic_path) and codegen's.
TEMPORARY = re.compile(r"^\..*\.tmp$|\.tmp[^/]*$")

#: Exit statuses the contract allows: success, bad input, refused (4: a fleet with a motor
#: refused or failed, 130: interrupted, for the cases that expect them).
ALLOWED_EXITS = (0, 2, 3)
#: Exit statuses after which the command's outputs stand (a fleet's summary lists its failures).
SUCCESS_EXITS = (0, 4)


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What one command did.

    Attributes
    ----------
    exit_code : int
    stdout, stderr : str
    exception : str or None
        The traceback of an exception that escaped the command (None when it exited normally).
    """

    exit_code: int
    stdout: str
    stderr: str
    exception: str | None


def run_in_process(args: Sequence[str]) -> Outcome:
    """Run ``hallcal ARGS`` through click's CliRunner in this process.

    Parameters
    ----------
    args : sequence of str
        The arguments after ``hallcal``.

    Returns
    -------
    Outcome
    """
    from click.testing import CliRunner

    from hallcal.cli import cli

    runner = CliRunner()
    result = runner.invoke(cli, list(args), prog_name="hallcal", catch_exceptions=True)
    exception = None
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        exception = "".join(traceback.format_exception(result.exception))
    return Outcome(result.exit_code, result.stdout, result.stderr, exception)


def files_under(paths: Sequence[Path]) -> set[Path]:
    """Every file at or below the given paths (those that exist)."""
    out: set[Path] = set()
    for p in paths:
        if p.is_file() or p.is_symlink():
            out.add(p)
        elif p.is_dir():
            for root, _, names in os.walk(p):
                out.update(Path(root) / n for n in names)
    return out


def file_states(paths: Sequence[Path]) -> dict[str, tuple[int, int, int]]:
    """(inode, size, mtime in ns) of every file at or below `paths`: what a command changed."""
    out: dict[str, tuple[int, int, int]] = {}
    for f in files_under(paths):
        try:
            st = f.lstat()
        except OSError:
            continue
        out[str(f)] = (st.st_ino, st.st_size, st.st_mtime_ns)
    return out


def contract_violations(
    outcome: Outcome,
    *,
    new_files: set[Path],
    expected_exits: Sequence[int] = ALLOWED_EXITS,
    changed_files: Sequence[str] = (),
) -> list[str]:
    """What `outcome` breaks of the contract (module docstring); empty when it keeps it.

    Parameters
    ----------
    outcome : Outcome
    new_files : set of Path
        Files that did not exist before the command, under its outputs and its folder.
    changed_files : sequence of str
        Files that existed before and were replaced, changed or removed by the command (a
        failed command must leave them as they were: an input, a previous complete output).
    expected_exits : sequence of int
        The exit statuses this case may end with (a subset of 0, 2, 3).

    Returns
    -------
    list of str
        One entry per violation.
    """
    problems: list[str] = []
    if outcome.exception is not None:
        last = outcome.exception.strip().splitlines()[-1]
        problems.append(f"an exception escaped: {last}")
    if outcome.exit_code not in expected_exits:
        problems.append(f"exit status {outcome.exit_code}, expected one of {list(expected_exits)}")
    err = outcome.stderr
    if "Traceback" in err:
        problems.append("a traceback on stderr")
    if PYTHON_WARNING.search(err):
        problems.append("a Python warning on stderr: " + PYTHON_WARNING.search(err).group(0))
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ERROR_LINE.match(ln)]
    temporary = sorted(str(f) for f in new_files if TEMPORARY.search(f.name))
    if temporary:
        problems.append(f"temporary files left behind: {temporary}")
    if outcome.exit_code in SUCCESS_EXITS:
        if errors:
            problems.append(f"exit {outcome.exit_code} with an error line: {errors[0]}")
        return problems
    if changed_files:
        problems.append(f"a failed command changed existing files: {sorted(changed_files)[:5]}")
    if len(errors) != 1:
        problems.append(f"{len(errors)} error lines on stderr, expected 1: {lines[-3:]}")
    elif lines[-1] != errors[0]:
        problems.append(f"the error line is not the last line of stderr: {lines[-1]!r}")
    stray = [ln for ln in lines if not ERROR_LINE.match(ln) and not ALLOWED_BEFORE_ERROR.match(ln)]
    if stray:
        problems.append(f"stray lines on stderr: {stray[:3]}")
    if new_files:
        problems.append(f"a failed command left output behind: {sorted(map(str, new_files))[:5]}")
    return problems


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(type(v))


def to_toml(d: dict[str, Any]) -> str:
    """A setup dictionary as TOML (top-level keys, then one table per sub-dictionary)."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in d.items() if not isinstance(v, dict)]
    for name, table in d.items():
        if isinstance(table, dict):
            lines += ["", f"[{name}]"]
            lines += [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def start_child(
    stash: Any,
    key: Any,
    script: Path,
    *,
    prefix: str,
    env: dict[str, str],
    log: str,
    prepare: Callable[[Path], list[str]] = lambda folder: [],
) -> None:
    """Start ``python SCRIPT FOLDER [ARGS]`` in the background: FOLDER a new temporary folder
    (ARGS what ``prepare`` writes there and returns), the child's output in FOLDER/LOG; the pair
    (FOLDER, process) is kept in the session's ``stash`` under ``key`` (the hostile driver and
    the setup fuzz, started at collection by conftest.py or by their own test)."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    args = [str(folder), *prepare(folder)]
    with open(folder / log, "w", encoding="utf-8") as out:
        proc = subprocess.Popen(
            [sys.executable, str(script), *args], env=env, stdout=out, stderr=subprocess.STDOUT
        )
    stash[key] = (folder, proc)


def stop_child(stash: Any, key: Any, *, keep: bool = False) -> None:
    """At the session's end: a child still running (its test deselected, a failure with
    ``-x``, an interrupt) is ended, and its folder removed unless ``keep``."""
    started = stash.get(key, None)
    if started is None:
        return
    folder, proc = started
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    if not keep:
        shutil.rmtree(folder, ignore_errors=True)
