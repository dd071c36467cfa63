"""The calibration report: figures and a self-contained HTML page (``hallcal report``, ``demo``).

Compute first, plot separately: :func:`report_content` (from the calibration artifact and its
recording, plus what an in-memory calibration has: :class:`ReportExtras`) gathers everything the
report shows into a :class:`ReportContent`;
:func:`make_figures` turns it into figures with :mod:`hallcal.output.plots`; :func:`write_report`
writes the PNG files and one HTML file with the figures embedded as base64 PNG, inline CSS, no
scripts and no external references, so it opens in a browser without network access.

The report follows the paper's results sections (van Meer et al., Figs. 2 and 4-8) and adds
the diagnostics of each step of Algorithm 1: the BLA, the SEM cost, and the lookup table with its
uncertainty band. Errors against an encoder are only
shown when a recording has the ``y_ref`` column (validation only, never used by calibration);
without one the report says so and shows what needs no encoder: the model fit, the table, the
cost and the correction f_star - f_init. For an open-loop (constant-speed) calibration the
straight-line check stands in for the encoder: f_init and f_star against their best straight line
on the constant-speed samples the calibration did not use. Angle errors are in mechanical mrad or
another :class:`hallcal.formatting.AngleUnit` (``angle_units="electrical-deg"``: electrical
degrees).

The modules: :mod:`~hallcal.output.report.content` (:class:`ReportContent` and its builder),
:mod:`~hallcal.output.report.figures`, :mod:`~hallcal.output.report.page` (the HTML) and
:mod:`~hallcal.output.report.write` (the files, the CLI's and the demo's entry points).
"""

from __future__ import annotations

from hallcal.output.report.content import ReportContent, ReportExtras, report_content
from hallcal.output.report.figures import ReportFigure, make_figures
from hallcal.output.report.page import render_html
from hallcal.output.report.write import (
    FIGURE_DIR,
    REPORT_NAME,
    write_calibration_report,
    write_demo_report,
    write_report,
    write_report_from_files,
)

__all__ = [
    "FIGURE_DIR",
    "REPORT_NAME",
    "ReportContent",
    "ReportExtras",
    "ReportFigure",
    "make_figures",
    "render_html",
    "report_content",
    "write_calibration_report",
    "write_demo_report",
    "write_report",
    "write_report_from_files",
]
