"""Sanity checks before the expensive steps (hallcal.pipeline.checks), each with the fix named.

The motor is the README's: 4 pole pairs at 10 kHz, G(s) = 5000 / (s^2 + 50 s) with a 150 us delay,
under a PID; the ring-jig recordings (25 pole pairs, open loop, no reference) test the check that
needs no reference.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from motor_support import SMALL_LOOP

from hallcal import pipeline
from hallcal.errors import HallcalInputError
from hallcal.io import Dataset, setup_from_dict
from hallcal.pipeline.checks import (
    UNSTABLE_MARGIN,
    CheckStatus,
    check_direction,
    check_loop,
    check_pole_pairs,
    closed_loop_poles,
    pole_pairs_from_signature,
)
from hallcal.sim.lti import ContinuousTF, DiscreteTF

RING = Path(__file__).resolve().parent / "data" / "ring-jig"

MOTOR = {
    **SMALL_LOOP,
    "model": {"harmonics": [1, 2, 3, 4]},
    "bench": {"ramp_end": 7.0, "duration": 8.0, "seed": 3},
}


@pytest.fixture(scope="module")
def run():
    """A closed-loop calibration ramp of the motor (1.1 revolutions, 80 000 samples)."""
    res = pipeline.simulate(setup_from_dict(MOTOR))
    assert res.status == "ok"
    return res.columns()


def _dataset(columns, drop=(), **replace) -> Dataset:
    cols = {k: v for k, v in columns.items() if k not in drop}
    cols.update(replace)
    return Dataset.from_columns(cols, path="run.csv")


def _ring(i: int = 1) -> Dataset:
    raw = np.loadtxt(RING / f"hall_calibration_one_rotation_{i}.txt")
    return Dataset.from_columns({f"d{h + 1}": raw[:, h] for h in range(3)}, path="ring.txt")


# ------------------------------------------------------------------------------------------------
# pole pairs


@pytest.mark.parametrize("reference", ["r", "y_ref"])
@pytest.mark.parametrize("wrong", [3, 5, 8])
def test_wrong_pole_pairs_suggest_the_right_count(run, reference, wrong):
    other = {"r": "y_ref", "y_ref": "r"}[reference]
    ds = _dataset(run, drop=(other,))
    check = check_pole_pairs(ds, wrong)
    assert check.status is CheckStatus.FAILED
    assert check.suggested == 4 and check.key == "pole_pairs"
    assert "set pole_pairs = 4" in check.text and f"pole_pairs = {wrong}" in check.text
    # the loop tracks the ramp with a constant lag: the measured ratio is 4 to within 1 %
    assert check.estimate == pytest.approx(4.0, rel=0.01)
    assert check_pole_pairs(ds, 4).status is CheckStatus.OK


def test_wrong_pole_pairs_stop_calibration_before_any_sem(run):
    """The case: pole_pairs = 5 for a 4-pole-pair motor used to run 20 s into 'not
    bijective'; now calibrate fails at once, naming the right count, before any SEM (the
    progress messages show no SEM or harmonic-selection step: the check is work, not time)."""
    setup = setup_from_dict({**MOTOR, "pole_pairs": 5})
    messages: list[str] = []
    with pytest.raises(HallcalInputError, match="set pole_pairs = 4") as exc:
        pipeline.calibrate(_dataset(run, drop=("y_ref",)), setup, progress=messages.append)
    assert exc.value.key == "pole_pairs"
    assert not any("SEM" in m or "harmonics" in m for m in messages), messages


def test_pole_pairs_from_the_magnets_signature_on_the_ring_jig():
    """No reference at all (open loop): the per-cycle amplitudes and offsets repeat every 25."""
    for i in (1, 2, 3):
        ds = _ring(i)
        sig = pole_pairs_from_signature(ds.d)
        assert sig.best == 25, i
        # F statistic: 116-269 at 25, about half at 50, at most 4 elsewhere above 5
        assert sig.f_statistic[25] > 50.0
        assert max(v for q, v in sig.f_statistic.items() if q > 5 and q % 25) < 10.0
        assert check_pole_pairs(ds, 25).status is CheckStatus.OK
        for wrong in (24, 26, 50):
            c = check_pole_pairs(ds, wrong)
            assert c.status is CheckStatus.FAILED, (i, wrong, c.text)
            assert c.suggested == 25 and "set pole_pairs = 25" in c.text


def test_pole_pairs_from_the_signature_on_a_simulated_run(run):
    """Per-magnet variations of 4 % (the bench default) are enough without a reference."""
    long = pipeline.simulate(
        setup_from_dict({**MOTOR, "bench": {**MOTOR["bench"], "ramp_end": 26.0}})
    ).columns()
    ds = _dataset(long, drop=("r", "y_ref"))  # 4.1 revolutions, 16 electrical cycles
    check = check_pole_pairs(ds, 4)
    assert check.status is CheckStatus.OK and check.method == "magnet signature"
    wrong = check_pole_pairs(ds, 5)
    assert wrong.status is CheckStatus.FAILED and wrong.suggested == 4
    # the short run has 4 complete cycles: fewer than two revolutions, nothing to test
    short = _dataset(run, drop=("r", "y_ref"))
    assert check_pole_pairs(short, 4).status is CheckStatus.SKIPPED


def test_too_little_motion_is_skipped_not_guessed(run):
    n = 5000  # 0.5 s of the ramp: 0.07 revolutions
    ds = _dataset({k: v[:n] for k, v in run.items()})
    assert check_pole_pairs(ds, 7).status is CheckStatus.SKIPPED


# ------------------------------------------------------------------------------------------------
# direction


def test_reversed_sensor_order_is_named(run):
    ds = _dataset(run, d2=run["d3"], d3=run["d2"])
    check = check_direction(ds)
    assert check.status is CheckStatus.FAILED and check.sign == -1
    assert "swap two Hall columns" in check.text
    assert check_direction(_dataset(run)).status is CheckStatus.OK
    with pytest.raises(HallcalInputError, match="runs against the"):
        pipeline.calibrate(ds, setup_from_dict(MOTOR))


# ------------------------------------------------------------------------------------------------
# loop stability


def _motor_loop():
    s = setup_from_dict(MOTOR)
    return s.controller, s.plant, s.sample_time


def test_stable_loop_passes_and_the_cancelled_integrator_is_not_unstable():
    c, p, ts = _motor_loop()
    assert check_loop(c, p, ts).status is CheckStatus.OK
    # the paper's C(q) cancels the plant's integrator with a zero at q = 1: |z| = 1 within 1e-9
    paper = setup_from_dict(
        {
            "pole_pairs": 11,
            "sample_time": 2.5e-4,
            "controller": {
                "num": [2.94, -3.29, -2.10, 2.45],
                "den": [1, -3.45, 4.52, -2.68, 0.61],
            },
            "plant": {"num": [1.663e5], "den": [1, 632.6, 2702, 0], "delay": 1.2e-4},
        }
    )
    z = closed_loop_poles(paper.controller, paper.plant, paper.sample_time)
    assert abs(np.max(np.abs(z)) - 1.0) < 1e-8
    assert check_loop(paper.controller, paper.plant, paper.sample_time).status is CheckStatus.OK
    assert 1e-8 < UNSTABLE_MARGIN


def test_unstable_loop_is_named_with_its_pole():
    c, p, ts = _motor_loop()
    flipped = DiscreteTF(tuple(-v for v in c.num), c.den)
    check = check_loop(flipped, p, ts)
    assert check.status is CheckStatus.FAILED
    assert "unstable" in check.text and "pole at z = " in check.text
    assert "sign and scaling of [controller]" in check.text
    assert check.max_abs > 1.0


def test_the_delay_is_in_the_poles():
    """A loop that is stable without the delay and unstable with a long one (exact ZOH)."""
    c, p, ts = _motor_loop()
    assert check_loop(c, ContinuousTF(p.num, p.den, 0.0), ts).status is CheckStatus.OK
    # phase margin 62 deg at 20 Hz: 8.7 ms of delay more make it unstable; 15 ms does
    long = check_loop(c, ContinuousTF(p.num, p.den, 150 * ts), ts)
    assert long.status is CheckStatus.FAILED, long.text
    assert "oscillation at" in long.text


def test_unstable_loop_is_named_before_sem(run):
    setup = setup_from_dict(
        {
            **MOTOR,
            "controller": {"num": [-9.8472, 19.6285, -9.7814], "den": [1.0, -1.962998, 0.962998]},
        }
    )
    messages: list[str] = []
    with pytest.raises(
        HallcalInputError, match="closed loop of .controller. and .plant. is unstable"
    ):
        pipeline.calibrate(_dataset(run), setup, progress=messages.append)
    assert not any("SEM" in m or "harmonics" in m for m in messages), messages
    with pytest.raises(HallcalInputError, match="is unstable: pole at z"):
        pipeline.simulate(setup)


def test_checks_are_typed():
    c, p, ts = _motor_loop()
    check = check_loop(c, p, ts)
    assert isinstance(check.status, CheckStatus) and check.status.success
    assert dataclasses.is_dataclass(check)
    assert not CheckStatus.FAILED.success


# ------------------------------------------------------------------------------------------------
# the recording's own checks: t against sample_time, angle units, standstill


def _synthetic(n_m: int, *, n: int = 4000, revolutions: float = 1.5, still: bool = False):
    """Ideal Hall signals of a rotor turning ``revolutions`` (or standing), sigma 2.7e-3."""
    rng = np.random.default_rng(n_m)
    y0 = np.zeros(n) if still else np.linspace(0.0, 2 * np.pi * revolutions, n)
    d = {
        f"d{h}": np.cos(n_m * y0 - 2 * np.pi * (h - 1) / 3) + rng.normal(0, 2.7e-3, n)
        for h in (1, 2, 3)
    }
    return {"t": 1e-4 * np.arange(n), "r": y0.copy(), "y": y0.copy(), "y_ref": y0.copy(), **d}


@pytest.mark.parametrize("n_m", [1, 2, 4, 11, 25])
def test_degrees_are_told_from_rad_at_every_pole_pair_count(n_m):
    from hallcal.pipeline.checks import CheckStatus, check_angle_units

    cols = _synthetic(n_m)
    assert check_angle_units(Dataset.from_columns(cols), n_m).status is CheckStatus.OK
    for which in (("r",), ("y_ref",), ("r", "y", "y_ref")):
        bad = dict(cols, **{k: np.degrees(cols[k]) for k in which})
        c = check_angle_units(Dataset.from_columns(bad), n_m)
        assert c.status is CheckStatus.FAILED and c.key == which[0]
        assert c.message.startswith(f"{which[0]} looks like degrees"), c.message
    # electrical degrees (x n_m) are named as such
    if n_m >= 2:
        bad = dict(cols, r=np.degrees(cols["r"]) * n_m)
        c = check_angle_units(Dataset.from_columns(bad), n_m)
        assert c.message.startswith("r looks like electrical degrees"), c.message


def test_a_wrong_pole_pair_count_is_not_taken_for_a_unit():
    """Setup 5 on a 4-pole-pair rotor: ratio 1.25, the pole-pair check's business."""
    from hallcal.pipeline.checks import CheckStatus, check_angle_units

    assert check_angle_units(Dataset.from_columns(_synthetic(4)), 5).status is CheckStatus.OK


def test_a_reference_that_stands_still_is_not_taken_for_a_unit():
    """r constant while the rotor turns (found by tests/test_fuzz_setups.py: ramp_end = 0 with a
    constant-speed trajectory): slope 0 is no unit, and no math domain error."""
    from hallcal.pipeline.checks import CheckStatus, check_angle_units

    cols = dict(_synthetic(4), r=np.zeros(_synthetic(4)["r"].size))
    assert check_angle_units(Dataset.from_columns(cols), 4).status is CheckStatus.OK


def test_standstill_is_not_motion():
    from hallcal.pipeline.checks import CheckStatus, check_angle_units, check_hall_motion

    ds = Dataset.from_columns(_synthetic(4, still=True))
    assert check_hall_motion(ds).status is CheckStatus.FAILED
    assert check_angle_units(ds, 4).status is CheckStatus.SKIPPED
    assert check_hall_motion(Dataset.from_columns(_synthetic(4))).status is CheckStatus.OK


@pytest.mark.parametrize(
    ("t", "sample_time", "key", "text"),
    [
        (2e-4 * np.arange(100), 1e-4, "sample_time", "the t column steps 0.0002 s"),
        (1e-1 * np.arange(100), 1e-4, "sample_time", "(or t is in ms: log it in s)"),
        (np.zeros(100), 1e-4, "t", "the t column is constant"),
        (1e-4 * np.arange(100)[::-1], 1e-4, "t", "decreases at every row"),
        (1e-4 * np.r_[0:50, 49, 51:100], 1e-4, "t", "steps back or stands still at 1 of 99"),
    ],
)
def test_sample_time_against_t(t, sample_time, key, text):
    from hallcal.pipeline.checks import CheckStatus, check_sample_time

    c = check_sample_time(Dataset.from_columns({"t": t}), sample_time)
    assert c.status is CheckStatus.FAILED and c.key == key and text in c.text, c.text
    ok = check_sample_time(Dataset.from_columns({"t": 1e-4 * np.arange(100)}), 1e-4)
    assert ok.status is CheckStatus.OK
    # 1.0 is the setup's "rate unknown": only the order is checked
    assert check_sample_time(Dataset.from_columns({"t": 0.37 * np.arange(9)}), 1.0).status.success
