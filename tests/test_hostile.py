"""The standing adversarial suite: hostile files, setups, artifacts, paths and options.

Every case of :mod:`hostile_cases` (about 960, each class the issues "Hostile input" and 29 list;
:mod:`hostile_safety` for output safety) runs through the command line and must keep the contract
of :mod:`hostile_support`: exit status 0, 2 or 3 as the case expects (2 for a bad input, and a
corrupt or truncated file said to be one; 4 for a fleet with a failed motor, 130 after Ctrl-C),
exactly one error line, never a traceback or a warning, never output left behind by a failure
and no existing file changed by it (an input, the previous outputs);
export-c's C must compile with no symbol or macro beyond those of a valid export; a report must
escape the artifact's texts. Each case must stay within 2 GB; how long a case takes is not
asserted (timings belong in ``benchmarks/``).

How they run: interpreter start-up costs about a second per command, so the cases run in two
worker processes (:mod:`hostile_worker`) that call the command line in-process, one case after
the other. They start as soon as the session's tests are collected (a driver process, see
:func:`start_in_background`): the suite runs its other tests one at a time, and the workers use
the core that leaves idle. The workers run under an address-space limit (``RLIMIT_AS`` =
2 GiB: a case that allocates more fails with MemoryError) and a watchdog ends a worker whose
case hangs (over 120 s, far above any case's run time even on a loaded machine: the case fails
as a hang; the worker restarts with the next one). A sample of cases per
subcommand also runs as a real ``python -m hallcal.cli`` subprocess under the same limits. With
``-k``, only the selected cases are built and run. With ``-n auto`` (pytest-xdist) the ``hostile``
fixture starts the driver, and tests/conftest.py gives this module to a worker first.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import resource
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hostile_cases import (
    ADC_SCALE,
    BASE_SETUP,
    BLA_TABLE,
    Base,
    Case,
    all_cases,
)
from hostile_support import (
    Outcome,
    contract_violations,
    files_under,
    run_in_process,
    start_child,
    stop_child,
    to_toml,
)

from hallcal.io import read_dataset

HERE = Path(__file__).resolve().parent
WORKER = HERE / "hostile_worker.py"
#: The watchdog of one case [s]: it stops a hung case, it does not time a slow one (the old
#: 30 s per-case bound was a speed assertion; the whole suite took 18 min under load).
WATCHDOG_SECONDS = 120.0
#: The memory bound of one case.
CASE_BYTES = 2 * 2**30
#: Two workers: the machine has two cores.
WORKERS = 2
#: Exit status of a worker ended by its watchdog (hostile_worker.WATCHDOG_EXIT).
WATCHDOG_EXIT = 86

CASES = all_cases()
CC = shutil.which("gcc") or shutil.which("cc")


def _limits() -> None:
    """In the child: the address-space limit of one case (its whole worker, in fact)."""
    resource.setrlimit(resource.RLIMIT_AS, (CASE_BYTES, CASE_BYTES))


def _env() -> dict[str, str]:
    env = dict(os.environ)
    # one thread per library: thread stacks and BLAS buffers would count against RLIMIT_AS
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[name] = "1"
    # pyarrow's jemalloc reserves a gigabyte of address space up front: RLIMIT_AS would count the
    # reservation as memory; the system allocator reserves only what it uses
    env["ARROW_DEFAULT_MEMORY_POOL"] = "system"
    env["MPLBACKEND"] = "Agg"
    env["HOSTILE_CASE_SECONDS"] = str(WATCHDOG_SECONDS)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(HERE.parent / "src"), str(HERE), env.get("PYTHONPATH", "")]
    )
    return env


def _build_base(d: Path) -> Base:
    """The valid inputs: the paper's bench, 1.5 s (6000 samples), its artifact, a multisine."""
    setup_text = to_toml(BASE_SETUP)
    bla_text = to_toml({**BASE_SETUP, "bla": BLA_TABLE})
    (d / "s.toml").write_text(setup_text)
    (d / "b.toml").write_text(bla_text)
    for args in (
        ["simulate", "--setup", "s.toml", "--out", "cal.npz"],
        ["simulate", "--setup", "b.toml", "--experiment", "multisine", "--out", "ms.npz"],
        ["calibrate", "cal.npz", "--setup", "s.toml", "--out", "a.json"],
        ["export-c", *ADC_SCALE, "a.json", "--out", "fw"],
    ):
        cwd = os.getcwd()
        os.chdir(d)
        try:
            outcome = run_in_process(args)
        finally:
            os.chdir(cwd)
        assert outcome.exit_code == 0, (args, outcome.stderr, outcome.exception)
    return _load_base(d)


def _load_base(d: Path) -> Base:
    """The valid inputs :func:`_build_base` wrote into `d`, read back."""
    columns = {k: np.array(v) for k, v in read_dataset(d / "cal.npz").columns.items()}
    ms = read_dataset(d / "ms.npz", required=("r", "u", "y", "realization"))
    multisine = {k: np.array(v) for k, v in ms.columns.items()}
    artifact = json.loads((d / "a.json").read_text())
    return Base(d, (d / "s.toml").read_text(), (d / "b.toml").read_text(), columns, multisine,
                artifact)  # fmt: skip


def _run_workers(cases: list[dict[str, Any]], d: Path) -> dict[str, dict[str, Any]]:
    """Run the cases in WORKERS processes; a case that kills its worker is recorded as such."""
    shares = [cases[i::WORKERS] for i in range(WORKERS)]
    jobs = []
    for i, share in enumerate(shares):
        manifest = d / f"cases-{i}.json"
        manifest.write_text(json.dumps(share))
        jobs.append((manifest, d / f"results-{i}.jsonl", {c["id"] for c in share}))
    results: dict[str, dict[str, Any]] = {}
    pending = list(jobs)
    while pending:
        procs = [
            (
                job,
                subprocess.Popen(
                    [sys.executable, str(WORKER), str(job[0]), str(job[1])],
                    env=_env(),
                    preexec_fn=_limits,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                    text=True,
                ),
            )
            for job in pending
        ]
        pending = []
        for job, proc in procs:
            _, stderr = proc.communicate()
            manifest, out, ids = job
            lines = [json.loads(x) for x in out.read_text().splitlines() if x.strip()]
            finished = {x["id"] for x in lines if "exit_code" in x}
            started = [x["id"] for x in lines if x.get("started")]
            for x in lines:
                if "exit_code" in x:
                    results[x["id"]] = x
            if proc.returncode != 0:
                crashed = [i for i in started if i not in finished]
                if not crashed:  # the worker died outside a case: that is the suite's failure
                    raise AssertionError(f"hostile worker failed: {stderr[-3000:]}")
                why = "hang" if proc.returncode == WATCHDOG_EXIT else "crash"
                for case_id in crashed:
                    record = {"id": case_id, "exit_code": None, "killed": why}
                    record["stderr"] = stderr[-3000:]
                    results[case_id] = record
                    with open(out, "a", encoding="utf-8") as f:
                        f.write(json.dumps(record) + "\n")
                if ids - set(results):
                    pending.append(job)
    return results


@functools.cache
def _macros(path: Path | None) -> frozenset[str]:
    """Names of the macros defined at the end of preprocessing `path` (None: stdint.h alone).

    Cached: the compiler's and <stdint.h>'s own macros (``path`` None) are the same for every
    generated file; each case's files have paths of their own, so those are preprocessed once.
    """
    source = ["-x", "c", str(path)] if path is not None else ["-x", "c", "-"]
    res = subprocess.run(
        [CC, "-std=c99", "-dM", "-E", *source],
        input="#include <stdint.h>\n" if path is None else None,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return frozenset(
        ln.split()[1].split("(")[0] for ln in res.stdout.splitlines() if ln.startswith("#")
    )


#: :func:`_c_symbols` of the files compiled so far, by :func:`_c_key` (see there).
_COMPILED: dict[str, tuple[bool, str, set[str], set[str]]] = {}


def _c_key(path: Path) -> str:
    """What a compile of `path` depends on: its name, its bytes and those of the headers beside it
    (its ``#include "..."``). Many cases export the base artifact unchanged, into folders of
    their own: their files are compiled once (the same bytes compile to the same symbols)."""
    digest = hashlib.sha256(path.name.encode() + b"\0" + path.read_bytes())
    for h in sorted(path.parent.glob("*.h")):
        digest.update(b"\0" + h.name.encode() + b"\0" + h.read_bytes())
    return digest.hexdigest()


def _c_symbols(path: Path) -> tuple[bool, str, set[str], set[str]]:
    """Compile one generated file with gcc -std=c99 (trigraphs on, as ISO C99 has them); a file
    compiled before (:func:`_c_key`) is not compiled again.

    Returns (compiled, compiler output, global symbols it defines, macros it defines beyond the
    compiler's and <stdint.h>'s).
    """
    key = _c_key(path)
    if key in _COMPILED:
        _, _, symbols, macros = _COMPILED[key]
        return True, "", set(symbols), set(macros)
    result = _compile_c(path)
    if result[0]:  # a failure is compiled again: its message names its own file
        _COMPILED[key] = result
    return result


def _compile_c(path: Path) -> tuple[bool, str, set[str], set[str]]:
    """:func:`_c_symbols` without the cache."""
    obj = path.parent / (path.name + ".o")
    res = subprocess.run(
        [CC, "-std=c99", "-c", "-o", str(obj), "-x", "c", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    if res.returncode != 0:
        return False, res.stderr[-2000:], set(), set()
    nm = subprocess.run(["nm", "-g", "--defined-only", str(obj)], capture_output=True, text=True)
    obj.unlink()
    symbols = {ln.split()[-1] for ln in nm.stdout.splitlines() if ln.strip()}
    return True, "", symbols, _macros(path) - _macros(None)


def _c_api(folder: Path) -> tuple[set[str], set[str]]:
    """Symbols and macros of the valid export (the API)."""
    symbols: set[str] = set()
    macros: set[str] = set()
    for p in sorted(folder.iterdir()):
        ok, err, s, m = _c_symbols(p)
        assert ok, err
        symbols |= s
        macros |= m
    return symbols, macros


def _selected(items: list[pytest.Item]) -> list[Case]:
    """The cases this session runs (``-k`` selects some: only those are built and run)."""
    chosen = {
        item.callspec.params.get("case").id
        for item in items
        if hasattr(item, "callspec") and isinstance(item.callspec.params.get("case"), Case)
    }
    chosen |= {
        item.callspec.params["case_id"]
        for item in items
        if hasattr(item, "callspec") and "case_id" in item.callspec.params
    }
    return [c for c in CASES if c.id in chosen]


def run_cases(d: Path, ids: list[str]) -> None:
    """Build the base and the cases ``ids`` in `d`, run them in the workers, and write the
    results and the manifest to ``d/results.json``: the work of the ``hostile`` fixture, done by
    a driver process (``python tests/test_hostile.py DIR IDS.json``) that
    :func:`start_in_background` starts when the session's tests are known."""
    base = _build_base(d)
    by_id = {c.id: c for c in CASES}
    manifest = []
    for case_id in ids:
        case = by_id[case_id]
        folder = d / "cases" / re.sub(r"[^A-Za-z0-9_.-]", "_", case.id)
        folder.mkdir(parents=True)
        args = case.build(folder, base)
        manifest.append(
            {"id": case.id, "args": args, "cwd": str(folder), "watch": ["."], "fault": case.fault}
        )
    results = _run_workers(manifest, d)
    (d / "results.json").write_text(json.dumps({"results": results, "manifest": manifest}))


#: The driver process of this session's cases and its folder (:func:`start_in_background`).
_DRIVER = pytest.StashKey[tuple[Path, subprocess.Popen]]()


def start_in_background(session: pytest.Session) -> None:
    """Start this session's hostile cases in a driver process (called by conftest.py once the
    tests are collected).

    The suite runs its tests one at a time, on one of the machine's two cores; the cases' two
    workers run beside them from the start instead of after the modules before this one (the
    same cases, limits and checks: only when they run changes). The ``hostile`` fixture waits
    for the driver and reads its results.
    """
    ids = [c.id for c in _selected(session.items)]
    if not ids or _DRIVER in session.config.stash:
        return

    def prepare(d: Path) -> list[str]:
        (d / "ids.json").write_text(json.dumps(ids))
        return [str(d / "ids.json")]

    start_child(
        session.config.stash,
        _DRIVER,
        Path(__file__).resolve(),
        prefix="hallcal-hostile-",
        env=_env(),
        log="driver.log",
        prepare=prepare,
    )


def stop_background(session: pytest.Session) -> None:
    """At the session's end: a driver still running (its tests deselected by a failure with
    ``-x``, or interrupted) is ended, and its folder removed unless ``HOSTILE_KEEP``."""
    stop_child(session.config.stash, _DRIVER, keep=bool(os.environ.get("HOSTILE_KEEP")))


@pytest.fixture(scope="module")
def hostile(request: pytest.FixtureRequest) -> dict[str, Any]:
    """Every selected case's inputs built and run (by the driver started at collection), and
    the results by case id."""
    start_in_background(request.session)  # started at collection already: nothing to do
    d, proc = request.config.stash[_DRIVER]
    proc.wait()
    log = (d / "driver.log").read_text(errors="replace")
    assert proc.returncode == 0, f"the hostile driver failed ({proc.returncode}): {log[-3000:]}"
    done = json.loads((d / "results.json").read_text())
    manifest = done["manifest"]
    if os.environ.get("HOSTILE_KEEP"):  # for debugging: keep the folders and say where
        print(f"hostile: {len(manifest)} cases; results kept in {d}")
    return {
        "results": done["results"],
        "folders": {m["id"]: Path(m["cwd"]) for m in manifest},
        "args": {m["id"]: m["args"] for m in manifest},
        "base": _load_base(d),
        "api": _c_api(d / "fw") if CC else (set(), set()),
    }


def _param(case: Case) -> Any:
    marks = [pytest.mark.xfail(strict=True, reason=case.xfail)] if case.xfail else []
    return pytest.param(case, id=case.id, marks=marks)


@pytest.mark.parametrize("case", [_param(c) for c in CASES])
def test_hostile_case(case: Case, hostile: dict[str, Any]) -> None:
    r = hostile["results"][case.id]
    folder = hostile["folders"][case.id]
    assert "killed" not in r, f"{r['killed']} (>{WATCHDOG_SECONDS:.0f} s or 2 GB?): {r['stderr']}"
    assert r["maxrss_mb"] * 2**20 <= CASE_BYTES, f"resident memory {r['maxrss_mb']:.0f} MB"
    outcome = Outcome(r["exit_code"], r["stdout"], r["stderr"], r["exception"])
    new = {Path(p) for p in r["new_files"]}
    problems = contract_violations(
        outcome, new_files=new, expected_exits=case.expect, changed_files=r["changed_files"]
    )
    if case.message and outcome.exit_code != 0:
        last = outcome.stderr.strip().splitlines()[-1] if outcome.stderr.strip() else ""
        if not re.search(case.message, last):
            problems.append(f"the error line does not match {case.message!r}: {last!r}")
    if case.c_dir and outcome.exit_code == 0:
        problems += _c_problems(folder / case.c_dir, hostile["api"])
    if case.html_dir and outcome.exit_code == 0:
        text = (folder / case.html_dir / "report.html").read_text(encoding="utf-8")
        for raw in ("<script>alert('hallcal')", "<img src=x"):  # the artifact's texts
            if raw in text:
                problems.append(f"the report contains the artifact's raw markup {raw!r}")
    args = " ".join(map(repr, hostile["args"][case.id]))
    assert not problems, (
        f"hallcal {args}  (in {folder})\n  "
        + "\n  ".join(problems)
        + f"\n--- stderr ---\n{outcome.stderr[-2000:]}\n{outcome.exception or ''}"
    )


def _c_problems(folder: Path, api: tuple[set[str], set[str]]) -> list[str]:
    if CC is None:
        return ["no C compiler (gcc or cc) to check the generated C"]
    symbols, macros = api
    problems = []
    files = sorted(p for p in folder.iterdir() if p.suffix in (".c", ".h"))
    if not files:
        return [f"export-c wrote no C files into {folder}"]
    for p in files:
        ok, err, s, m = _c_symbols(p)
        if not ok:
            problems.append(f"{p.name} does not compile with -std=c99: {err}")
            continue
        if s - symbols:
            problems.append(f"{p.name} defines symbols beyond the API: {sorted(s - symbols)}")
        if m - macros:
            problems.append(f"{p.name} defines macros beyond the API: {sorted(m - macros)}")
    return problems


#: One hostile case per subcommand, run as a real process: the console script's own start-up,
#: imports, output streams and exit status, under the same limits (RLIMIT_AS and the watchdog).
SUBPROCESS_SAMPLES = (
    "data-hall-data-random-d1-h5-calibrate",
    "setup-delay-1e6-simulate",
    "ms-truncated-bla",
    "artifact-projection-zero-reconstruct",
    "artifact-deep-nesting-report",
    "option-export-c-no-fixed-point",
    "option-demo-seed-negative",
    "option-no-arguments",
)
_BY_ID = {c.id: c for c in CASES}


@pytest.mark.parametrize("case_id", SUBPROCESS_SAMPLES)
def test_hostile_case_in_a_subprocess(
    case_id: str, hostile: dict[str, Any], tmp_path: Path
) -> None:
    case = _BY_ID[case_id]
    args = case.build(tmp_path, hostile["base"])
    before = files_under([tmp_path])
    res = subprocess.run(
        [sys.executable, "-m", "hallcal.cli", *args],
        cwd=tmp_path,
        env=_env(),
        preexec_fn=_limits,
        capture_output=True,
        text=True,
        timeout=WATCHDOG_SECONDS + 30,  # a watchdog (+ interpreter start-up), not a speed bound
    )
    outcome = Outcome(res.returncode, res.stdout, res.stderr, None)
    new = files_under([tmp_path]) - before
    problems = contract_violations(
        outcome, new_files=new if res.returncode else set(), expected_exits=case.expect
    )
    if case.message and res.returncode:
        if not re.search(case.message, res.stderr.strip().splitlines()[-1]):
            problems.append(f"the error line does not match {case.message!r}")
    if case.c_dir and res.returncode == 0:
        problems += _c_problems(tmp_path / case.c_dir, hostile["api"])
    assert not problems, "\n".join(problems) + "\n" + res.stderr[-2000:]


def test_the_suite_covers_every_class_and_subcommand() -> None:
    """At least 300 cases; every reader, every subcommand and every class of the contract."""
    assert len(CASES) >= 300
    ids = " ".join(c.id for c in CASES)
    for reader in ("-csv-", "-parquet-", "-h5-", "-hdf5-", "-mat-", "-npz-"):
        assert f"data-trunchalf{reader}" in ids and f"data-scaled-tiny{reader}" in ids
    commands = ("simulate", "calibrate", "bla", "reconstruct", "report", "export-c", "demo")
    for command in (*commands, "inspect"):
        assert any(c.id.endswith(f"-{command}") or f"option-{command}-" in c.id for c in CASES), (
            command
        )
    for cls in (
        "data-trunc1-mat",  # MAT truncated to 1 byte
        "data-trunc100-mat",
        "data-header-garbage-h5",  # HDF5 with a corrupt header
        "data-npz-raw-member",
        "data-npz-pickled-object",
        "data-hall-data-random-d1-h5",  # corrupted HDF5 read as data
        "data-hall-data-random-d1-mat",
        "data-scaled-tiny-npz",  # 1e-300
        "setup-delay-1e6",
        "setup-harmonics-5000",
        "setup-harmonics-1e9",
        "setup-kernel-points-1e6",
        "artifact-deep-nesting",
        "artifact-offset-1e999",
        "artifact-pole-pairs-10e400",
        "artifact-pole-pairs-1e6",
        "artifact-projection-zero",
        "artifact-projection-rank1",
        "option-export-c-out-non-ascii",
        "option-export-c-no-fixed-point",
        "option-export-c-adc-scale-1e30",
        "option-export-c-path-splice",
        "option-export-c-path-trigraph",
        # outputs that are inputs, output sets under faults, the fleet's edges
        "safety-out-symlink-calibrate",
        "safety-out-png-collides-bla",
        "safety-efbig-export-c",
        "safety-enospc-export-c",
        "safety-ctrl-c-report",
        "safety-name-255-reconstruct",
        "safety-standstill-reconstruct",
        "safety-surrogate-report",
        "safety-empty-objects-report",
        "safety-revolutions-1e6-plan",
        "safety-dev-zero-fleet",
        "safety-locked-fleet",
    ):
        assert cls in ids, cls


if __name__ == "__main__":  # the driver of start_in_background
    run_cases(Path(sys.argv[1]), json.loads(Path(sys.argv[2]).read_text()))
