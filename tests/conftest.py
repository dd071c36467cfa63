"""Shared test settings: the processes' environment (one BLAS thread, bytecode kept), a
deterministic hypothesis profile, small bench fixtures and the parallel scheduler."""

from __future__ import annotations

import os
import sys
from typing import Any

# The suite's processes (xdist workers, the hostile and fuzz children, the CLI subprocesses, Dask
# workers) inherit this environment from here: it is set before any of them starts and before
# this process loads numpy.
#
# One BLAS thread: on the 2 cores that the suite keeps busy with two processes, OpenBLAS's second
# thread only spins while it waits for work; measured under load (tests/test_bench.py 9.1 s of
# CPU with two threads against 2.6 s with one, test_misfit.py 13.1 against 4.9 s). The solver's
# passes run their BLAS at one thread already (threadpool_limits in hallcal.fit, for the same
# reason). A value set by the caller is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Bytecode: with PYTHONDONTWRITEBYTECODE each of the suite's ~300 interpreters compiles hallcal's
# sources (and pytest rewrites every test module) again, ~0.1 s per CLI command and ~2.6 s per
# xdist worker. Written to the __pycache__ folders beside the sources (ignored by git), where
# numba keeps its compiled kernels already.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False

import numpy  # noqa: E402,F401 - loaded here, under the limit set above
import pytest  # noqa: E402
import scipy.linalg  # noqa: E402,F401 - scipy's own OpenBLAS, loaded under the limit too
from hypothesis import HealthCheck, settings  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

# numpy or scipy loaded before this file (a plugin) kept its threads: limit them now as well
if os.environ["OPENBLAS_NUM_THREADS"] == "1":
    threadpool_limits(limits=1, user_api="blas")

settings.register_profile(
    "hallcal",
    derandomize=True,  # deterministic in CI
    deadline=None,  # numba compilation makes first examples slow
    max_examples=60,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "hallcal"))


# ------------------------------------------------------------------------------------------------
# tiers: `pytest -m "not slow"` for a quick local run; the README's command runs everything

#: Marker by test file: ``hostile`` (the hostile-input contract), ``arm`` (firmware under QEMU),
#: ``slow`` (whole-pipeline runs of more than a few seconds each).
_MARKERS = {
    "test_hostile.py": ("hostile", "slow"),
    "test_fuzz_setups.py": ("hostile", "slow"),
    "test_codegen_arm.py": ("arm", "slow"),
    "test_codegen_observer_arm.py": ("arm", "slow"),
    "test_fleet.py": ("slow",),
    "test_readme.py": ("slow",),
    "test_real_ringjig.py": ("slow",),
    "test_whole_recordings.py": ("slow",),
}


@pytest.fixture(scope="session")
def weak_bench() -> tuple[Any, Any, Any, Any]:
    """7 pole pairs, weak magnet variation, calibrated by SEM (harmonics 1..7) on the usual ramp:
    ``(cfg, run, sem, lut)``, simulated and solved once per session for test_absolute.py and
    test_misfit.py (read-only: frozen results). The imports are local: a session that
    needs no bench loads no solver.

    Returns
    -------
    tuple
        ``(BenchConfig, BenchRun, SEMResult, LUT)``.
    """
    from hallcal.fit.sem import solve_sem
    from hallcal.sensor.flux import FourierBasis
    from hallcal.sensor.lut import build_lut
    from hallcal.sim.bench import BenchConfig, ramp_run

    cfg = BenchConfig(pole_pairs=7, magnet_variation=0.01, seed=0)
    run = ramp_run(cfg)
    sem = solve_sem(cfg.loop(), run.r, run.d, FourierBasis(tuple(range(1, 8))), y=run.y)
    return cfg, run, sem, build_lut(sem.flux, 7)


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Any]:
    """The demo's study (``run_demo(..., report=False)``: BLA, calibration and validation runs,
    Algorithm 1; about 15 s) once per session for test_plots_report.py, test_codegen_arm.py and
    test_algorithm1.py.
    Read-only: a module writes its own outputs into a folder of its own.

    Returns
    -------
    tuple
        ``(folder, DemoResult)``: the folder holds calibration.json, validation.npz and the
        other files of the demo.
    """
    from hallcal.demo import run_demo

    out = tmp_path_factory.mktemp("demo")
    return out, run_demo(out, report=False)


# ------------------------------------------------------------------------------------------------
# parallel runs: `pytest -n auto` (pytest-xdist; the README's command)

#: The modules that share a session fixture of this file, by the fixture: they run in one
#: worker, so the fixture is computed once (checked at collection: :func:`_check_groups`).
_SHARED = {
    "demo_run": ("test_algorithm1.py", "test_codegen_arm.py", "test_plots_report.py"),
    "weak_bench": ("test_absolute.py", "test_misfit.py"),
}
_GROUP = {module: fixture for fixture, modules in _SHARED.items() for module in modules}


def _group(nodeid: str) -> str:
    """The unit of work of a parallel run: the test's module (its module fixtures and caches are
    computed once), or the session fixture it shares with other modules (:data:`_SHARED`)."""
    module = nodeid.split("::", 1)[0].rsplit("/", 1)[-1]
    return _GROUP.get(module, module)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """With ``-n``: whole groups (:func:`_group`) to a worker, in the order collected
    (:func:`pytest_collection_modifyitems`: the longest work first), not xdist's order by number
    of tests, which would start the one-test setup fuzz last. An explicit ``--dist`` other
    than ``load`` (the default of ``-n``) is xdist's own."""
    if config.getvalue("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ByGroup(LoadScopeScheduling):  # type: ignore[misc]
        def _split_scope(self, nodeid: str) -> str:
            return _group(nodeid)

    config.option.loadscopereorder = False
    return ByGroup(config, log)


def _worker(config: pytest.Config) -> bool:
    """True in an xdist worker."""
    return hasattr(config, "workerinput")


def _check_groups(items: list[pytest.Item]) -> None:
    """A module that uses a session fixture is in :data:`_SHARED` (else each worker would
    compute the fixture again)."""
    for item in items:
        for name in getattr(item, "fixturenames", ()):
            if name in _SHARED and item.path.name not in _SHARED[name]:
                raise pytest.UsageError(
                    f"{item.path.name} uses the session fixture {name}: add it to "
                    "_SHARED in tests/conftest.py"
                )


def _rank(item: pytest.Item) -> int:
    """0 for the modules with background work (the hostile cases and the setup fuzz: minutes
    in child processes), 1 for the slow ones, 2 for the others."""
    if hasattr(getattr(item, "module", None), "start_in_background"):
        return 0
    return 1 if "slow" in _MARKERS.get(item.path.name, ()) else 2


@pytest.hookimpl(tryfirst=True)  # the order of the items is the order the workers get them
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        for name in _MARKERS.get(item.path.name, ()):
            item.add_marker(getattr(pytest.mark, name))
    if not _worker(config):
        return
    # in an xdist worker: each group (_group) ranked by its longest work, so that the two
    # workers end near together; within a rank, the order collected
    _check_groups(items)
    rank: dict[str, int] = {}
    for item in items:
        g = _group(item.nodeid)
        rank[g] = min(rank.get(g, 2), _rank(item))
    first = {g: i for i, g in enumerate(dict.fromkeys(_group(item.nodeid) for item in items))}
    items.sort(key=lambda item: (rank[_group(item.nodeid)], first[_group(item.nodeid)]))


def _background_modules(session: pytest.Session) -> list[Any]:
    """The test modules of this session that run their work in the background: those that
    define ``start_in_background`` and ``stop_background`` (tests/test_hostile.py,
    tests/test_fuzz_setups.py)."""
    modules: list[Any] = []
    for item in session.items:
        module = getattr(item, "module", None)
        if hasattr(module, "start_in_background") and module not in modules:
            modules.append(module)
    return modules


def pytest_collection_finish(session: pytest.Session) -> None:
    """The hostile cases and the setup fuzz start in the background as soon as the tests are
    known: their processes use the core the one-at-a-time suite leaves idle; their tests wait
    for them and check what they found. In an xdist worker (``-n``) their tests start them:
    every worker collects every test, and their modules are given out first."""
    if session.config.option.collectonly or _worker(session.config):
        return  # in an xdist worker, the tests start their work: their groups run first
    for module in _background_modules(session):
        module.start_in_background(session)


def pytest_sessionfinish(session: pytest.Session) -> None:
    for module in _background_modules(session):
        module.stop_background(session)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]):  # type: ignore[no-untyped-def]
    """On CI (``HALLCAL_REQUIRE_TOOLS=1``, set by .ci/run) a skip is a failure.

    The ARM toolchain, QEMU and chromium are installed by .ci/run; a test that skips there
    because one is missing would be a check that cannot fail.
    """
    outcome = yield
    report = outcome.get_result()
    if (
        os.environ.get("HALLCAL_REQUIRE_TOOLS")
        and report.skipped
        and not hasattr(report, "wasxfail")
    ):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = (
            f"skipped where every tool must be present (HALLCAL_REQUIRE_TOOLS): {reason}"
        )
