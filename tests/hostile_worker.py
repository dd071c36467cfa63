"""Run hostile command-line cases in one process, under the suite's resource limits.

Usage: ``python hostile_worker.py CASES.json RESULTS.jsonl``. CASES.json is a list of
``{"id", "args", "cwd", "watch"}``; for each case the worker changes to ``cwd``, runs ``hallcal
ARGS`` in this process (click's CliRunner, :func:`hostile_support.run_in_process`) and appends one
JSON line to RESULTS.jsonl: exit status, stdout and stderr (trimmed), an escaped exception, the
files that appeared under ``watch`` (the case folder and its outputs) and the process's peak
resident memory. Cases already in RESULTS.jsonl are skipped, so the parent can
restart the worker after a case killed it.

The parent (tests/test_hostile.py) starts the worker with an address-space limit (RLIMIT_AS), so a
case that tries to allocate more fails with MemoryError (an escaped exception, a violation), and a
watchdog thread here ends the process when one case hangs (runs longer than a generous limit,
HOSTILE_CASE_SECONDS): the parent then reports that case as a hang and restarts the worker with
the remaining cases.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hostile_support import file_states, files_under, run_in_process  # noqa: E402


@contextlib.contextmanager
def _fault(fault: dict | None) -> Iterator[None]:
    """A case's injected fault, in this process, for the duration of the case.

    ``{"fsize": n}``: a file-size limit of n bytes (RLIMIT_FSIZE: writes past it fail with
    EFBIG; Python ignores SIGXFSZ); ``{"at_write": k, "errno": e}``: the k-th temporary file of
    hallcal's writers fails to open with errno e (ENOSPC, EACCES, EROFS...);
    ``{"at_write": k, "interrupt": true}``: Ctrl-C (KeyboardInterrupt) there instead.
    """
    if not fault:
        yield
        return
    from hallcal.io import files

    saved_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    # where hallcal's writers create their temporary files (before output sets: tempfile.mkstemp)
    owner, name = (files, "_create_temporary")
    if not hasattr(files, name):
        owner, name = (files.tempfile, "mkstemp")
    original = getattr(owner, name)
    count = [0]

    def create(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        count[0] += 1
        if count[0] == fault.get("at_write"):
            if fault.get("interrupt"):
                raise KeyboardInterrupt
            code = int(fault["errno"])
            raise OSError(code, os.strerror(code))
        return original(*args, **kwargs)

    if "fsize" in fault:
        resource.setrlimit(resource.RLIMIT_FSIZE, (int(fault["fsize"]), saved_limit[1]))
    if "at_write" in fault:
        setattr(owner, name, create)
    try:
        yield
    finally:
        setattr(owner, name, original)
        resource.setrlimit(resource.RLIMIT_FSIZE, saved_limit)


#: Exit status of the worker when the watchdog ends it (the parent looks for it).
WATCHDOG_EXIT = 86


def _watchdog(state: dict[str, float | str | None], limit: float) -> None:
    while True:
        time.sleep(0.5)
        started = state.get("started")
        if isinstance(started, float) and time.monotonic() - started > limit:
            sys.stderr.write(f"hostile-worker: case {state.get('id')} ran over {limit:.0f} s\n")
            sys.stderr.flush()
            os._exit(WATCHDOG_EXIT)


def _vm_mb() -> float | None:
    """The process's current address-space size (what RLIMIT_AS limits), in MB."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def main() -> None:
    cases_path, results_path = Path(sys.argv[1]), Path(sys.argv[2])
    limit = float(os.environ.get("HOSTILE_CASE_SECONDS", "120"))
    cases = json.loads(cases_path.read_text())
    done: set[str] = set()
    if results_path.exists():
        for line in results_path.read_text().splitlines():
            if line.strip():
                done.add(json.loads(line)["id"])
    state: dict[str, float | str | None] = {"started": None, "id": None}
    threading.Thread(target=_watchdog, args=(state, limit), daemon=True).start()
    with open(results_path, "a", encoding="utf-8") as out:
        for case in cases:
            if case["id"] in done:
                continue
            # mark the case as started before running it: a watchdog exit or a crash then
            # leaves this line without a result, and the parent knows which case it was
            out.write(json.dumps({"id": case["id"], "started": True}) + "\n")
            out.flush()
            os.chdir(case["cwd"])
            watch = [Path(case["cwd"]) / w for w in case["watch"]]
            before = files_under(watch)
            states = file_states(watch)
            state["id"] = case["id"]
            state["started"] = time.monotonic()
            with _fault(case.get("fault")):
                outcome = run_in_process(case["args"])
            state["started"] = None
            new = sorted(str(p) for p in files_under(watch) - before)
            after = file_states(watch)
            changed = sorted(f for f, st in states.items() if after.get(f) != st)
            result = {
                "id": case["id"],
                "exit_code": outcome.exit_code,
                "stdout": outcome.stdout[-4000:],
                "stderr": outcome.stderr[-8000:],
                "exception": outcome.exception,
                "new_files": new,
                "changed_files": changed,
                "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                "vm_mb": _vm_mb(),
            }
            out.write(json.dumps(result) + "\n")
            out.flush()


if __name__ == "__main__":
    main()
