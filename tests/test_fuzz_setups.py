"""Fuzz: random setups through every subcommand keep the command-line contract.

Hypothesis draws setup files (random degrees, coefficients, signs, gains and delays of the plant
and the controller, so stable and unstable loops; random model orders, table sizes, pole pairs,
sample times; now and then a value out of range) and each one goes through ``simulate`` (ramp
and multisine), ``bla``, ``calibrate``, ``reconstruct``, ``export-c`` and ``report``: every command
must end with exit status 0, 2 or 3, one error line, no traceback, no warning and no partial
output (:mod:`hostile_support`). The commands run in this process (click's CliRunner), and
hallcal's RuntimeWarnings are errors here (pyproject), so a numeric warning fails too.

Downstream commands get the outputs of the upstream ones when those succeeded, else fixed inputs
(a short run of the paper's bench and its artifact with the drawn setup in it), so that every
command sees every drawn setup.

How it runs: the property runs in a child process (``python tests/test_fuzz_setups.py DIR``)
started as soon as the session's tests are collected (:func:`start_in_background`, from
conftest.py), on the core the one-at-a-time suite leaves idle; the collected test waits for it
and fails with the child's output (Hypothesis's falsifying example and the broken contract).
With ``-n auto`` (pytest-xdist) the test starts the child, and tests/conftest.py gives this module
to a worker first.
The child applies the suite's warning filter (a hallcal RuntimeWarning is an error).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Any

import pytest
from hostile_support import (
    contract_violations,
    files_under,
    run_in_process,
    start_child,
    stop_child,
    to_toml,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

#: The paper's controller C(q) and plant G(s) (docs/design.md).
PAPER_C = {"num": [2.94, -3.29, -2.10, 2.45], "den": [1, -3.45, 4.52, -2.68, 0.61]}
PAPER_G = {"num": [1.663e5], "den": [1, 632.6, 2702, 0], "delay": 1.2e-4}

#: The drawn setups on which ``calibrate`` ran the method in this process: an artifact (exit 0)
#: or a verdict's refusal (exit 3), not an input error (exit 2).
CALIBRATED: list[dict[str, Any]] = []

#: Every drawn setup runs through seven commands; 30 examples keep the module near two minutes
#: on a quiet 2-core machine while covering each branch of the strategies many times.
EXAMPLES = 30


def _rare(draw: st.DrawFn) -> bool:
    """True for about one draw in ten (an interior value: Hypothesis favours the ends)."""
    return draw(st.integers(0, 9)) == 4


def _coefficients(draw: st.DrawFn, n: int, lo: float, hi: float) -> list[float]:
    """n coefficients of random sign and magnitude 10^U(lo, hi) (some exactly zero)."""
    out = []
    for _ in range(n):
        if draw(st.integers(0, 9)) == 0:
            out.append(0.0)
            continue
        sign = draw(st.sampled_from([1.0, -1.0]))
        out.append(sign * 10.0 ** draw(st.floats(lo, hi)))
    return out


@st.composite
def controllers(draw: st.DrawFn) -> dict[str, Any]:
    """The paper's C(q), or a random one of degree 0-5 (stable or not, causal or not)."""
    if draw(st.booleans()):
        return dict(PAPER_C)
    nd = draw(st.integers(0, 5))
    den = [1.0, *_coefficients(draw, nd, -2, 0.7)]
    nn = draw(st.integers(0, nd + (1 if draw(st.integers(0, 9)) == 0 else 0)))
    num = _coefficients(draw, nn + 1, -2, 1)
    if all(v == 0 for v in num):
        num[0] = 1.0
    return {"num": num, "den": den}


@st.composite
def plants(draw: st.DrawFn, sample_time: float) -> dict[str, Any]:
    """The paper's G(s), or a random one: order 1-4, an integrator or not, a gain of random
    sign and size, as many zeros as poles now and then (feedthrough), a delay of 0-3 samples
    (sometimes a whole number of samples, rarely far above the limit)."""
    if draw(st.integers(0, 2)) == 1:
        return dict(PAPER_G)
    order = draw(st.integers(1, 4))
    integrator = draw(st.booleans())
    den = [1.0, *(abs(c) for c in _coefficients(draw, order, 0, 3.5))]
    if integrator:
        den[-1] = 0.0
    nz = draw(st.integers(0, order))
    gain = draw(st.sampled_from([1.0, -1.0])) * 10.0 ** draw(st.floats(-2, 7))
    num = [gain] if nz == 0 else [gain, *(abs(c) for c in _coefficients(draw, nz, 0, 3))]
    kind = draw(st.integers(0, 9))
    if kind == 3:
        delay = 0.0
    elif kind == 4:
        delay = float(draw(st.integers(1, 3))) * sample_time
    elif kind == 5:
        delay = 1000.0 * sample_time  # above the limit of 64 samples
    else:
        delay = draw(st.floats(0.0, 3.0)) * sample_time
    return {"num": num, "den": den, "delay": delay}


@st.composite
def setups(draw: st.DrawFn) -> dict[str, Any]:
    """A setup dictionary in the TOML layout (mostly valid, sometimes not).

    A third of them run the paper's loop (its C(q), G(s) and sample time) with the rest drawn:
    random loops are mostly unstable or not formed, so without these no drawn setup would
    reach the SEM (``calibrate`` on the fixed inputs stops at their sample times)."""
    if _rare(draw):
        pole_pairs = draw(st.sampled_from([0, 257, 10**6, -3]))
    else:
        pole_pairs = draw(st.integers(1, 16))
    paper_loop = draw(st.integers(0, 2)) == 0
    if paper_loop:
        sample_time = 2.5e-4
    elif _rare(draw):
        sample_time = draw(st.sampled_from([1.0, 1e-9, 10.0]))
    else:
        sample_time = draw(st.sampled_from([2.5e-4, 1e-4, 1e-3, 5e-5]))
    setup: dict[str, Any] = {"pole_pairs": pole_pairs, "sample_time": sample_time}
    kind = "constant-speed" if not paper_loop and _rare(draw) else "closed-loop"
    if paper_loop:
        setup["controller"], setup["plant"] = dict(PAPER_C), dict(PAPER_G)
    else:
        if kind == "closed-loop" or draw(st.booleans()):
            setup["controller"] = draw(controllers())
        if not _rare(draw):
            setup["plant"] = draw(plants(sample_time))
    model: dict[str, Any] = {}
    if _rare(draw):
        model["basis"] = "kernel"
        model["points"] = draw(st.integers(8, 64))
    else:
        if draw(st.booleans()):
            model["harmonics"] = "auto"
        else:
            top = max(3 * (pole_pairs if 0 < pole_pairs <= 16 else 11), 2)
            model["harmonics"] = draw(
                st.lists(st.integers(1, top), min_size=1, max_size=12, unique=True)
            )
    model["max_iterations"] = draw(st.integers(1, 4))
    model["lut_points"] = draw(st.sampled_from([16, 64, 1024, 4096]))
    setup["model"] = model
    trajectory: dict[str, Any] = {"kind": kind}
    if kind == "constant-speed":
        trajectory["start"] = draw(st.integers(0, 100))
    setup["trajectory"] = trajectory
    # 1.5-4 s (the paper's loop settles in about 0.5 s), at most 16 000 samples at these sample
    # times: the loop runs, the SEM iterates, and every command stays short
    duration = draw(st.floats(1.5, 4.0)) if sample_time >= 1e-4 else draw(st.floats(0.1, 0.8))
    setup["bench"] = {
        "duration": duration if sample_time < 1.0 else 2000.0 * sample_time,
        "ramp_end": draw(st.sampled_from([7.0, 13.0, -7.0, 9.0])) if not _rare(draw) else 0.0,
        "seed": draw(st.integers(0, 2**31)),
        "noise_variance": draw(st.sampled_from([7.5e-6, 0.0, 1e-2])),
    }
    if draw(st.integers(0, 2)) == 1:
        nyquist = 0.5 / sample_time
        setup["bla"] = {
            "period_samples": draw(st.sampled_from([64, 256, 512])),
            "periods": draw(st.integers(2, 3)),
            "transient_periods": 1,
            "realizations": draw(st.integers(2, 3)),
            "band": [0.001 * nyquist, 0.8 * nyquist],
            "numerator_order": draw(st.integers(0, 1)),
            "denominator_order": draw(st.integers(1, 3)),
        }
    return setup


def make_fixed_inputs(d: Path) -> dict[str, Path]:
    """A short run of the paper's bench (1.5 s: 1.1 revolutions) and its artifact, in `d`."""
    setup = {
        "pole_pairs": 11,
        "sample_time": 2.5e-4,
        "controller": PAPER_C,
        "plant": PAPER_G,
        "model": {"harmonics": list(range(1, 12)), "max_iterations": 3},
        "bench": {"ramp_end": 7.0, "duration": 1.5, "seed": 5},
    }
    (d / "s.toml").write_text(to_toml(setup))
    for args in (
        ["simulate", "--setup", str(d / "s.toml"), "--out", str(d / "cal.npz")],
        ["calibrate", str(d / "cal.npz"), "--setup", str(d / "s.toml"), "--out", str(d / "a.json")],
    ):
        outcome = run_in_process(args)
        assert outcome.exit_code == 0, outcome.stderr + (outcome.exception or "")
    return {"data": d / "cal.npz", "artifact": d / "a.json"}


def _run(
    args: list[str], outputs: list[Path], folder: Path, *, inspection: tuple[Path, ...] = ()
) -> int:
    """Run one command; assert the contract; return its exit status. ``inspection``: the files
    a refusal (exit 3) writes on purpose (``bla``'s JSON and Bode plot, its ``--help``)."""
    before = files_under([folder, *outputs])
    outcome = run_in_process(args)
    new = files_under([folder, *outputs]) - before
    if outcome.exit_code == 3:
        new -= set(inspection)
    problems = contract_violations(outcome, new_files=new if outcome.exit_code else set())
    assert not problems, (
        f"hallcal {' '.join(args)}\n  "
        + "\n  ".join(problems)
        + f"\n--- stderr ---\n{outcome.stderr[-3000:]}\n{outcome.exception or ''}"
    )
    return outcome.exit_code


def _artifact_with_setup(base: Path, setup: dict[str, Any], dest: Path) -> None:
    """The fixed artifact with the drawn setup (and its pole pairs) in it."""
    art = json.loads(base.read_text(encoding="utf-8"))  # raw JSON: the drawn setup may be invalid
    art["setup"] = json.loads(json.dumps(setup, allow_nan=True))
    if isinstance(setup.get("pole_pairs"), int):
        art["pole_pairs"] = setup["pole_pairs"]
        # the power-up analysis is of the fixed motor's pole pairs: not of this one
        art.pop("identifiability", None)
    dest.write_text(json.dumps(art, allow_nan=True))


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    derandomize=True,
)
@given(setup=setups())
def test_random_setups_keep_the_contract_in_every_subcommand(
    setup: dict[str, Any], fixed_inputs: dict[str, Path]
) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        w = Path(tmp)
        s = w / "s.toml"
        s.write_text(to_toml(setup))
        sim = _run(["simulate", "--setup", str(s), "--out", str(w / "cal.npz")], [], w)
        data = w / "cal.npz" if sim == 0 else fixed_inputs["data"]
        bla_args: list[str] = []
        if "bla" in setup:
            ms = w / "ms.npz"
            code = _run(
                ["simulate", "--setup", str(s), "--experiment", "multisine", "--out", str(ms)],
                [],
                w,
            )
            if code == 0:
                _run(
                    ["bla", str(ms), "--setup", str(s), "--out", str(w / "bla.json")],
                    [],
                    w,
                    inspection=(w / "bla.json", w / "bla.png"),
                )
                bla_args = ["--bla-data", str(ms)]
        cal = _run(
            ["calibrate", str(data), "--setup", str(s), *bla_args, "--out", str(w / "c.json")],
            [],
            w,
        )
        artifact = w / "c.json"
        if cal in (0, 3):
            CALIBRATED.append(setup)
        if cal != 0:
            _artifact_with_setup(fixed_inputs["artifact"], setup, artifact)
        _run(["reconstruct", str(artifact), str(data), "--out", str(w / "rec.csv")], [], w)
        # the bench's Hall signals have amplitude 1: 2048 counts per unit (a 12-bit ADC)
        _run(
            ["export-c", "--adc-scale", "2048", str(artifact), "--out", str(w / "fw")],
            [w / "fw"],
            w,
        )
        _run(["report", str(artifact), str(data), "--out", str(w / "rep")], [w / "rep"], w)
        shutil.rmtree(w / "rep", ignore_errors=True)


# The property is run by a child process; pytest collects the test below, which waits for it.
test_random_setups_keep_the_contract_in_every_subcommand.__test__ = False  # type: ignore[attr-defined]

HERE = Path(__file__).resolve().parent
#: The child process running the property (:func:`start_in_background`) and its folder.
_CHILD = pytest.StashKey[tuple[Path, subprocess.Popen]]()
#: Commands each drawn setup runs at least (simulate, calibrate, reconstruct, export-c, report).
COMMANDS_PER_SETUP = 5


def _selected(session: pytest.Session) -> bool:
    return any(
        item.path.name == "test_fuzz_setups.py"
        and item.name == "test_every_subcommand_keeps_the_contract_on_random_setups"
        for item in session.items
    )


def start_in_background(session: pytest.Session) -> None:
    """Start the property in a child process when this session runs its test (called by
    conftest.py once the tests are collected, and by the test itself)."""
    if not _selected(session) or _CHILD in session.config.stash:
        return
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(HERE.parent / "src"), env.get("PYTHONPATH", "")])
    env.setdefault("MPLBACKEND", "Agg")
    start_child(session.config.stash, _CHILD, Path(__file__).resolve(), prefix="hallcal-fuzz-",
                env=env, log="child.log")  # fmt: skip


def stop_background(session: pytest.Session) -> None:
    """At the session's end: a child still running is ended and its folder removed."""
    stop_child(session.config.stash, _CHILD)


def test_every_subcommand_keeps_the_contract_on_random_setups(request: pytest.FixtureRequest):
    """:func:`test_random_setups_keep_the_contract_in_every_subcommand` on its derandomized
    examples, in the child process; every command it ran kept the contract."""
    start_in_background(request.session)  # started at collection already: nothing to do
    d, proc = request.config.stash[_CHILD]
    proc.wait()
    log = (d / "child.log").read_text(encoding="utf-8", errors="replace")
    assert proc.returncode == 0, f"the fuzz failed in its child process:\n{log[-8000:]}"
    ran = int(log.rsplit("fuzz: commands run: ", 1)[1].split(";")[0])
    assert ran >= COMMANDS_PER_SETUP * EXAMPLES, log[-2000:]  # the examples did run
    # a third of the draws run the paper's loop: that none of 30 reaches the method has
    # probability (2/3)^30 = 5e-6, unless calibrate stops them all at its input checks
    calibrated = int(log.rsplit("calibrated: ", 1)[1].split()[0])
    assert calibrated >= 1, log[-2000:]


def _child(d: Path) -> None:
    """The child: the property on its examples, with the suite's warning filter (pyproject:
    ``error::RuntimeWarning:hallcal.*``); prints how many commands it ran."""
    global _run
    warnings.filterwarnings("error", category=RuntimeWarning, module="hallcal.*")
    count = [0]
    run_one = _run

    def counted(
        args: list[str], outputs: list[Path], folder: Path, *, inspection: tuple[Path, ...] = ()
    ) -> int:
        count[0] += 1
        return run_one(args, outputs, folder, inspection=inspection)

    _run = counted
    test_random_setups_keep_the_contract_in_every_subcommand(fixed_inputs=make_fixed_inputs(d))
    print(f"fuzz: commands run: {count[0]}; calibrated: {len(CALIBRATED)}")  # exit 0 or 3


if __name__ == "__main__":  # the child of start_in_background
    _child(Path(sys.argv[1]))
