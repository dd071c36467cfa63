"""Shared test settings: deterministic hypothesis profile and small bench fixtures."""

from __future__ import annotations

import os
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

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
    Algorithm 1; about 15 s) once per session for test_plots_report.py and test_codegen_arm.py.
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


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        for name in _MARKERS.get(item.path.name, ()):
            item.add_marker(getattr(pytest.mark, name))


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
    for them and check what they found."""
    if session.config.option.collectonly:
        return
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
