"""The angle units and text helpers shared by the CLI, the report and the fleet page."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hallcal.errors import HallcalInputError
from hallcal.formatting import (
    MISSING,
    AngleUnit,
    esc,
    finite,
    number,
    one_line,
    polynomial_text,
    ranges,
    tf_text,
)

# angle errors as they occur (up to a few rad) and beyond; finite only
_ANGLES = st.floats(min_value=-10.0, max_value=10.0, allow_nan=False)


def test_the_cli_offers_every_unit_and_keeps_its_spellings():
    from hallcal.cli import UNITS

    assert set(UNITS) == {u.value for u in AngleUnit}
    assert {"mrad", "electrical-deg"} <= set(UNITS)  # the spellings of earlier releases


@given(x=_ANGLES, n_m=st.integers(min_value=1, max_value=256))
def test_the_text_is_what_the_cli_and_the_report_wrote_before(x, n_m):
    # the formulas the CLI (4 decimals, "-") and the report (3 decimals, en dash) used
    assert AngleUnit.MRAD.text(x, n_m) == f"{1e3 * x:.4f} mrad"
    assert AngleUnit.ELECTRICAL_DEG.text(x, n_m) == f"{math.degrees(x) * n_m:.4f} electrical deg"
    assert AngleUnit.MRAD.text(x, n_m, page=True) == f"{1e3 * x:.3f} mrad"
    assert (
        AngleUnit.ELECTRICAL_DEG.text(x, n_m, page=True)
        == f"{math.degrees(x) * n_m:.3f} electrical deg"
    )


@pytest.mark.parametrize("x", [None, math.nan, math.inf])
def test_a_missing_angle_is_a_dash(x):
    assert AngleUnit.MRAD.text(x) == "-"
    assert AngleUnit.DEG.text(x, page=True) == MISSING


def test_conversion_of_arrays_and_the_mechanical_units():
    x = np.array([0.0, 0.001, -np.pi])
    np.testing.assert_array_equal(AngleUnit.MRAD.convert(x), 1e3 * x)
    np.testing.assert_array_equal(AngleUnit.DEG.convert(x), np.degrees(x))
    np.testing.assert_array_equal(AngleUnit.ELECTRICAL_DEG.convert(x, 4), np.degrees(x) * 4)
    assert AngleUnit.RAD.text(0.0012345) == "0.0012345 rad"
    assert AngleUnit.DEG.text(math.pi / 180) == "1.0000 deg"
    assert AngleUnit.MRAD.description == "mechanical mrad"
    assert AngleUnit.ELECTRICAL_DEG.description == "electrical degrees"


@pytest.mark.parametrize("name", ["degs", "electrical_deg", "", "MRAD"])
def test_an_unknown_unit_is_an_error_naming_the_valid_ones(name):
    with pytest.raises(HallcalInputError) as info:
        AngleUnit.parse(name)
    for u in AngleUnit:
        assert repr(u.value) in str(info.value)


def test_the_report_refuses_an_unknown_unit_before_any_work(tmp_path):
    from hallcal.output.report import write_calibration_report

    # no calibration and no data: the unit is checked first, so neither is touched
    with pytest.raises(HallcalInputError, match="'electrical-deg'"):
        write_calibration_report(None, None, tmp_path / "rep", units="degs")  # type: ignore[arg-type]
    assert not (tmp_path / "rep").exists()


def test_numbers_ranges_and_messages():
    assert finite("1.5") == 1.5 and finite(math.inf) is None and finite(None) is None
    assert number(None) == MISSING
    assert number("x") == MISSING
    assert number(math.nan, ".1f") == MISSING
    assert number(2.25, ".1f") == "2.2"
    assert ranges([33, 1, 2, 3, 5]) == "1..3, 5, 33"
    assert ranges([1, 2, 4, 5, 6], to="-", sep=",") == "1,2,4-6"
    assert one_line("a\n  b\tc ") == "a b c"
    assert esc('<a href="x">') == "&lt;a href=&quot;x&quot;&gt;"


def test_transfer_function_text_on_the_terminal_and_the_page():
    assert polynomial_text([1.0, 632.6, 2702.0, 0.0]) == "s^3 + 632.6 s^2 + 2702 s"
    assert polynomial_text([0.0]) == "0"
    num, den = (1.5e4,), (1.0, -2.0, 0.0)
    assert tf_text(num, den, 5e-4) == "G(s) = 1.5e+04 / (s^2 - 2 s), input delay 0.5 ms"
    assert tf_text(num, den, 0.0) == "G(s) = 1.5e+04 / (s^2 - 2 s)"
    assert tf_text(num, den, 5e-4, page=True) == "(1.5e+04) / (s^2 - 2 s) · exp(-0.0005 s)"


def test_the_cli_names_the_setup_file_of_the_running_command_only():
    """The numeric layers say "setup:"; the CLI puts the file of this command there (kept on
    the click context, not in a module-level global that outlives the command)."""
    import click
    import click.testing

    from hallcal import cli

    @click.command()
    def command() -> None:
        click.get_current_context().meta["hallcal.setup_path"] = "motor.toml"
        click.echo(cli._one_line(HallcalInputError("setup: [plant] and\n  [controller]: x")))

    runner = click.testing.CliRunner()
    assert runner.invoke(command).output == "motor.toml: [plant] and [controller]: x\n"
    # outside a command (or after it) nothing is remembered
    assert cli._one_line(HallcalInputError("setup: y")) == "setup: y"
