"""The cogging search is skipped when one fit of the model uses up the harmonic search's work
budget (:func:`hallcal.pipeline.closed_loop._cogging_unaffordable`; the unseen zoo motor 178:
p = 1155 flux parameters on 100 000 samples, ``benchmarks/bench_bigmotor.txt``).

The paper's bench (11 pole pairs, a short ramp) stands in for the big motor: the harmonic
search is given a work budget of one Gauss-Newton iteration, so that its first fit reaches it as
178's did (the default budget is 6e11 N p^2; the bench's fit costs about 1e8 per iteration).
"""

from __future__ import annotations

import dataclasses
import functools

import pytest

import hallcal.fit.order as order
import hallcal.pipeline.closed_loop as closed_loop
from hallcal import pipeline
from hallcal.io import Dataset, ModelSpec, default_setup
from hallcal.messages import MessageCode, Severity


@functools.cache
def _bench() -> tuple:
    s = default_setup()
    bench = dataclasses.replace(s.bench, seed=21, ramp_end=7.0, duration=12.0)
    s = dataclasses.replace(s, bench=bench, model=ModelSpec(harmonics="auto"))
    return s, Dataset.from_columns(pipeline.simulate(s, experiment="ramp").columns())


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


@pytest.mark.parametrize("cogging", ["auto", (22,)])
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
