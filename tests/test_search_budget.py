"""The cogging search is skipped when one fit of the model uses up the harmonic search's work
budget (:func:`hallcal.pipeline.closed_loop._cogging_unaffordable`; the unseen zoo motor 178:
p = 1155 flux parameters on 100 000 samples, ``benchmarks/bench_bigmotor.txt``).

A small motor stands in for the big one (4 pole pairs, every magnet's shape its own, band
1..20, 24 000 samples: its first fit needs 2 iterations, ``tests/test_order.py``): the harmonic
search is given a work budget of one Gauss-Newton iteration, so that its first fit reaches it as
178's did (the default budget is 6e11 N p^2; this fit costs about 4e8 per iteration).
"""

from __future__ import annotations

import dataclasses
import functools

import pytest

import hallcal.fit.order as order
import hallcal.pipeline.closed_loop as closed_loop
from hallcal import pipeline
from hallcal.io import Dataset, ModelSpec, Setup
from hallcal.messages import MessageCode, Severity
from hallcal.sim.bench import BenchConfig, ramp_run


@functools.cache
def _bench() -> tuple[Setup, Dataset]:
    cfg = BenchConfig(pole_pairs=4, electrical_harmonics=((3, 0.10), (5, 0.04)),
                      shape_variation=0.03, shape_harmonics=4, seed=5)  # fmt: skip
    run = ramp_run(cfg, ramp_end=19.0, duration=6.0, seed=5)
    setup = Setup(pole_pairs=4, sample_time=cfg.sample_time, controller=cfg.controller,
                  plant=cfg.plant, model=ModelSpec(harmonics="auto"))  # fmt: skip
    return setup, Dataset.from_columns(run.columns())


def _skip_notes(cal: pipeline.Calibration) -> list:
    return [m for m in cal.messages if m.code is MessageCode.COGGING and "not searched" in m.text]


def test_a_model_over_the_work_budget_in_one_fit_skips_the_cogging_search(monkeypatch):
    setup, data = _bench()
    # one iteration's work: the search's first fit stops at the budget (status WORK_BUDGET)
    monkeypatch.setattr(order, "select_harmonics",
                        functools.partial(order.select_harmonics, work_budget=1.0))  # fmt: skip

    def no_search(*args, **kwargs):
        raise AssertionError("the cogging search ran")

    monkeypatch.setattr(closed_loop, "select_cogging", no_search)
    cal = pipeline.calibrate(data, setup)
    assert cal.selection is not None and cal.selection.status == "work_budget"
    [note] = _skip_notes(cal)
    assert note.severity is Severity.WARNING  # a skipped step: at best a warning
    assert "harmonic search's work budget" in note.text and "cogging = [orders]" in note.text
    assert cal.status is pipeline.CalibrationStatus.WARNING
    assert cal.cogging is None and cal.cogging_selection is None
    # the first fit was cut at one iteration: it is finished to convergence all the same
    assert cal.sem.status == "converged" and cal.sem.iterations >= 1


@pytest.mark.parametrize("cogging", ["auto", (8,)])
def test_the_search_or_the_given_orders_run_within_the_budget_or_when_given(monkeypatch, cogging):
    """The default budget: the search runs as before; given orders are fitted jointly even
    when the budget is used up (the rule skips a search, not a model the user asked for)."""
    setup, data = _bench()
    setup = dataclasses.replace(setup, model=ModelSpec(harmonics="auto", cogging=cogging))
    if cogging != "auto":
        monkeypatch.setattr(order, "select_harmonics",
                            functools.partial(order.select_harmonics, work_budget=1.0))  # fmt: skip
    cal = pipeline.calibrate(data, setup)
    assert _skip_notes(cal) == []
    assert cal.cogging_selection is not None
    assert cal.cogging_selection.status == ("given" if cogging != "auto" else "none")
