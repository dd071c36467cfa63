"""The observer's C (``hallcal export-c --observer``) on a Cortex-M4F under QEMU, against Python.

Skipped only when the ARM toolchain is absent (``.ci/run`` installs it, and sets
``HALLCAL_REQUIRE_TOOLS`` so that a skip fails there). A small bench (4 pole pairs, the bench's
truth harmonics) calibrated through the API, its observer exported and compiled with the strict
flags for the M4F (``tests/arm_harness.py``), then run bare metal:

* on a validation run with a channel stuck at its zero-field level half way: y_obs within
  1e-5 rad of :func:`hallcal.sensor.observer.run_observer` on the same float32 inputs, the
  same state at every sample (the acceptance of issue 26);
* on the adversarial set of ``firmware_support.observer_adversarial`` (glitches at every phase
  of the adaptation's cycle, stuck, rail, clipped and non-finite channels, random readings,
  swapped wires, the start's node search): the worst Cortex-M4 cycles of ``update`` + ``read``
  per sample, counted from QEMU's instruction trace with the harness's M4 timing table (a taken
  branch 1 + 2 cycles, no wait states): deterministic, no wall clock.
"""

from __future__ import annotations

import tomllib

import arm_harness as ah
import numpy as np
import pytest
from cli_support import PAPER_LOOP_TOML
from firmware_support import observer_adversarial

from hallcal.output.codegen.c_observer import export_observer_c
from hallcal.pipeline.observe import run_on
from hallcal.sim.bench import BenchConfig, simulate_run

MISSING = ah.toolchain()
pytestmark = pytest.mark.skipif(
    MISSING is not None, reason=f"ARM toolchain incomplete ({MISSING} not found)"
)

BENCH = BenchConfig(pole_pairs=4, seed=3)
SETUP = (
    """\
pole_pairs = 4
sample_time = 2.5e-4
"""
    + PAPER_LOOP_TOML
    + """\
[model]
basis = "fourier"
harmonics = [1, 2, 3, 4]
"""
)


@pytest.fixture(scope="module")
def observer_m4f(tmp_path_factory):
    """The calibration, its observer built for the Cortex-M4F, and a validation run."""
    import hallcal

    n = 24000
    cal = hallcal.calibrate(
        simulate_run(BENCH, 8.0 * np.arange(n) / n, seed=21).columns(), tomllib.loads(SETUP)
    )
    out = tmp_path_factory.mktemp("obs_arm")
    res = export_observer_c(cal.to_artifact(), out / "gen")
    b = ah.build(out / "gen", out / "work", target="m4f", fixed=False, prefix="hallcal_obs")
    val = simulate_run(BENCH, 5.0 * np.arange(n) / n, seed=22)
    return cal, res, b, val


def test_m4f_observer_agrees_with_python_within_1e_5_rad(observer_m4f):
    cal, _, b, val = observer_m4f
    d = val.d[:8000].astype(np.float32)
    d[4000:, 1] = np.float32(cal.flux.theta[1, 0])  # stuck at its zero-field level
    raw = ah.run(b, d)
    py = run_on(cal, d.astype(np.float64))
    # the acceptance bound; float32 against float64 (measured below 1e-6)
    assert np.max(np.abs(ah.angles(b, raw) - py.y_obs)) < 1e-5
    assert np.array_equal(raw[:, 2] & 0xFF, py.state_code)
    assert py.state[-1] == "degraded" and py.excluded == 1


def test_m4f_observer_worst_case_cycles_update_and_read(observer_m4f):
    """Worst case over the adversarial set, ``update`` + ``read``: at most 600 Cortex-M4
    cycles, issue 26's budget (measured 590 on this bench, a disconnection's sample with the
    adaptation's row 0, and 593 on the paper bench, benchmarks/bench_observer_c.txt, an
    outlier's fits without one channel with the angle's wrap; 602 / 598 before the Gauss-Newton
    step's bound was tested before its division (none when bounded), the measure's CYCLE / den
    moved to row 0, the wrap and the chosen fit's bound laid out inline and the readmission put
    under the outlier fits' test, where it never applies; 613 / 599
    before the adaptation waited one sample after an exclusion (the exclusion's resets no longer
    share a sample with a part: this bench's worst was that sample), the table's floor was taken
    by a biased truncation and the adaptation's parts rebalanced (row 0 87 -> 69, the back
    substitution 78 -> 61 at most); 686 / 661 before the fits without a channel recomputed
    their channel terms instead
    of keeping the sums' terms live (spilled on every sample), the state's per-sample fields were
    moved within the FPU's load offsets, the finite test was made in the FPU, the slope taken
    from the value's Horner sums and a dozen branches turned into conditional moves or one test;
    662 / 660 before the tracker followed the acceleration (+6 median: one more state and gain;
    without it the observer said `stale` on any servo motion from 1e4 rad/s^2 and lost the angle
    at 1e5), the bounded update was spread over two parts and the back substitution over two
    (the worst healthy sample 654 -> 625, an outlier explained by a common gain plus the update
    704 -> 656) and `read` took the state and the excluded channel from the flags word (-5);
    672 / 671 before
    the blame ring was reset at an exclusion instead of checked against a start sample, the
    window's cap chosen where the fit is made, the fits' range test made one integer compare,
    the common-gain test given one product less and ``read`` copying field by field; 705 / 697
    before the block layout hints, the chosen channel's values carried through the choice and the
    measure's division moved to the next part; 725 / 721 before the fits without one channel
    were chosen by their unbounded chi2 (no bound per fit); 831 / 820
    before the table of cubic coefficients, the one-comparison clamps and the exclusion moved to
    the next sample; 984 before the per-channel values were kept in registers and the adaptation's
    parts written out straight-line; 4282 per normal sample and 28112 at an exclusion before the
    linearized step and the spread adaptation). The issue's budget of 600 was met on the paper
    bench, not on this one (2 over: an outlier's sample); now on both: the per-sample path
    without the adaptation's part costs about 430 with the read, the adaptation's part 52-87
    and its dispatch about 20, an outlier's tests about 150 (docs/firmware.md)."""
    cal, res, b, val = observer_m4f
    adv = observer_adversarial(val.d[:6000], cal.flux.theta[:, 0])
    cyc = ah.model_cycles(ah.trace_calls(b, adv, read=True), ah.CycleModel())
    assert len(cyc) == len(adv)  # every call traced
    assert cyc.max() <= 600  # measured 590: margin 10 for GCC's block layout (+-2-6 per change)
    assert ah.undefined_symbols(b.obj) == []  # no library function, no libgcc helper
    # every table: the cubics, THRINV, OFF, ONE, Q and the per-channel BLO, BHI, C0, W0, GROSS
    tables = res.table_points * 12 * 4 + 2 * (2 * 256 + 1) * 4 + 8 * 2 + 5 * 4 + 6 * 4 + 5 * 12
    assert res.table_bytes == tables
