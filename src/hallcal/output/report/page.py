"""The report as one self-contained HTML page (:func:`render_html`): the accuracy and
calibration tables, the figures as base64 PNG, the setup."""

from __future__ import annotations

import base64
import datetime as _dt
import math
import re

import numpy as np

from hallcal._version import __version__
from hallcal.formatting import AngleUnit, esc, number, ranges, tf_text
from hallcal.io import (
    setup_to_toml,
)
from hallcal.output.report.content import ReportContent
from hallcal.output.report.figures import ReportFigure

_DPI = 120


# ------------------------------------------------------------------------------------------------
# HTML
# ------------------------------------------------------------------------------------------------

_CSS = """
:root { --blue: #1f77b4; --red: #d62728; --grey: #6b6b6b; --line: #d9d9d9; }
* { box-sizing: border-box; }
body { margin: 0; background: #f6f6f4; color: #1b1b1b;
       font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif; }
main { max-width: 1000px; margin: 0 auto; padding: 24px 28px 48px; background: #fff; }
h1 { font-size: 26px; margin: 0 0 4px; }
h2 { font-size: 19px; margin: 32px 0 10px; padding-bottom: 4px; border-bottom: 1px solid
     var(--line); }
.meta { color: var(--grey); font-size: 13px; margin: 0 0 14px; }
.status { display: inline-block; padding: 3px 10px; border-radius: 4px; font-weight: 600;
          color: #fff; }
.status-ok { background: #2e7d32; } .status-warning { background: #b26a00; }
.status-bad { background: #b71c1c; } .status-unknown { background: #616161; }
.notes { border-left: 4px solid #b26a00; background: #fff8e6; padding: 8px 14px; margin: 12px 0; }
.notes p { margin: 4px 0; }
table { border-collapse: collapse; margin: 8px 0 12px; font-size: 14px; }
th, td { border-bottom: 1px solid var(--line); padding: 5px 12px 5px 0; text-align: left;
         vertical-align: top; }
th { font-weight: 600; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.init td:first-child { color: var(--blue); font-weight: 600; }
tr.star td:first-child { color: var(--red); font-weight: 600; }
.kv th { width: 230px; color: #333; }
figure { margin: 22px 0; }
figure img { display: block; width: 100%; height: auto; border: 1px solid var(--line); }
figcaption { font-size: 13.5px; color: #333; margin-top: 6px; }
pre { background: #f3f3f3; padding: 10px 14px; overflow-x: auto; font-size: 13px; }
footer { color: var(--grey); font-size: 12px; margin-top: 36px; }
"""


def _prose(x: object) -> str:
    """A message as HTML: escaped, with its `command` spans set as code (not raw backticks)."""
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", esc(x))


def _status_class(status: str) -> str:
    if status == "ok":
        return "status-ok"
    if status in ("warning",):
        return "status-warning"
    if status in ("not_bijective", "inadequate"):
        return "status-bad"
    return "status-unknown"


def _kv(rows: list[tuple[str, str]]) -> str:
    body = "".join(f"<tr><th>{esc(k)}</th><td>{v}</td></tr>" for k, v in rows)
    return f'<table class="kv">{body}</table>'


def _accuracy_table(c: ReportContent) -> str:
    v = c.validation
    parts = []
    if v is not None:
        ri = v.init.rms / v.star.rms if v.star.rms > 0 else math.nan
        pi = v.init.peak / v.star.peak if v.star.peak > 0 else math.nan
        parts.append(
            "<table><tr><th></th><th>RMS</th><th>peak</th></tr>"
            f'<tr class="init"><td>f_init (before)</td><td class="num">{c.angle(v.init.rms)}</td>'
            f'<td class="num">{c.angle(v.init.peak)}</td></tr>'
            f'<tr class="star"><td>f_star (after)</td><td class="num">{c.angle(v.star.rms)}</td>'
            f'<td class="num">{c.angle(v.star.peak)}</td></tr>'
            f'<tr><td>improvement</td><td class="num">×{number(ri, ".3g")}</td>'
            f'<td class="num">×{number(pi, ".3g")}</td></tr>'
            "</table>"
            f'<p class="meta">Against the reference angle y_ref of {esc(c.validation_source)}; '
            "RMS and peak about the mean error (a constant offset of the angle origin is not a "
            "reconstruction error).</p>"
        )
    elif c.validation_traces is not None and c.validation_traces.y_ref is not None:
        vt = c.validation_traces
        e = vt.y_init - vt.y_ref
        e = e - e.mean()
        parts.append(
            f"<p>f_init against y_ref of {esc(c.validation_source)}: RMS "
            f"{c.angle(float(np.sqrt(np.mean(e**2))))}, peak {c.angle(float(np.max(np.abs(e))))}; "
            "no f_star (table not bijective).</p>"
        )
    else:
        parts.append("<p><b>Errors against an encoder: unavailable</b> (no y_ref column).</p>")
        sl = c.straight_line
        if sl is not None:
            where = (
                f"the held-out constant-speed samples {sl.start}..{sl.stop} "
                f"({sl.revolutions:.2f} revolutions the calibration did not use)"
                if sl.held_out
                else f"the calibration samples {sl.start}..{sl.stop} (no held-out samples left)"
            )
            ratio = sl.init_rms / sl.star_rms if sl.star_rms > 0 else math.nan
            parts.append(
                "<table><tr><th>straight-line check</th><th>RMS from the best line</th></tr>"
                f'<tr class="init"><td>f_init</td><td class="num">{c.angle(sl.init_rms)}</td>'
                "</tr>"
                f'<tr class="star"><td>f_star</td><td class="num">{c.angle(sl.star_rms)}</td>'
                "</tr>"
                f'<tr><td>improvement</td><td class="num">×{number(ratio, ".3g")}</td></tr>'
                "</table>"
                f'<p class="meta">At constant speed the true angle is a straight line in the '
                f"sample index, so on {esc(where)} the residual of the best line bounds the "
                "error from above (the rig's own speed ripple is included).</p>"
            )
        cv = c.calibration
        if cv.y_star is not None:
            corr = cv.y_star - cv.y_init
            parts.append(
                "<p>Correction f_star − f_init along the calibration recording (no encoder "
                f"needed): RMS about the mean {c.angle(float(np.std(corr)))}, peak "
                f"{c.angle(float(np.max(np.abs(corr))))}.</p>"
            )
    rows = [
        (
            "noise floor (RMS)",
            f"{c.angle(c.noise_floor)} <span class='meta'>({esc(c.noise_floor_source)})</span>",
        ),
        (
            "predicted f_star error (RMS)",
            f"{c.angle(c.predicted_error)} <span class='meta'>"
            + (
                "(the noise floor: what the Hall noise alone leaves; the rig's motion is not "
                "in it)</span>"
                if c.constant_speed is not None
                else "(noise floor and the table's uncertainty from cov(θ))</span>"
            ),
        ),
    ]
    return "".join(parts) + _kv(rows)


def _calibration_rows(c: ReportContent) -> list[tuple[str, str]]:
    rows: list[tuple[str, str]] = []
    rows.append(
        ("status", f'<span class="status {_status_class(c.status)}">{esc(c.status)}</span>')
    )
    sem = c.sem
    if sem is not None:
        n = int(sem.n_samples)
        s2 = c.true_noise_variance if c.true_noise_variance is not None else sem.noise_variance
        level = 3 * n * float(s2) if s2 is not None else math.nan
        rows += [
            (
                "SEM cost before → after",
                f"{number(sem.initial_cost)} → {number(sem.cost)} "
                f"<span class='meta'>(noise level 3Nσ² = {number(level)}, N = {n})</span>",
            ),
            ("SEM iterations", f"{int(sem.iterations)} ({esc(sem.status)})"),
            ("SEM solve time", f"{number(sem.solve_time, '.2f')} s"),
            (
                "noise variance σ² (from residual)",
                f"{number(sem.noise_variance, '.4g')} (Hall signal unit)² per channel",
            ),
        ]
    if c.gain_correction is not None:
        text = number(c.gain_correction, ".5g")
        g = c.gain_details or {}
        if g.get("c_refined") is not None:
            std = g.get("c_refined_std")
            if std is not None:
                text += f" ± {number(std, '.2g')}"
            text += (
                " <span class='meta'>(refined jointly with θ in SEM; the gain-correction estimate "
                f"was {number(g.get('c'), '.5g')})</span>"
            )
        rows.append(("gain correction ĉ", text))
    if c.plant is not None:
        plant = tf_text(c.plant.num, c.plant.den, c.plant.delay, page=True)
        rows.append(("plant model used in SEM", f"<code>{esc(plant)}</code>"))
    lut = c.lut
    rows.append(
        (
            "lookup table",
            f"{lut.points} points; bijective: <b>{'yes' if lut.bijective else 'NO'}</b> "
            f"(min slope of y0 → ŷ: {number(lut.min_slope, '.3g')})",
        )
    )
    rows += _model_rows(c)
    if c.timings:
        rows.append(
            ("time per step", esc(", ".join(f"{k} {v:.2f} s" for k, v in c.timings.items())))
        )
    return rows


def _model_rows(c: ReportContent) -> list[tuple[str, str]]:
    """The flux model and its adequacy (or the constant-speed check that stands in for it)."""
    out: list[tuple[str, str]] = []
    info = c.model_info
    if info:
        basis = info.get("basis", "?")
        desc = esc(basis)
        if "harmonics" in info and basis == "fourier":
            desc += f", mechanical harmonics {esc(ranges(info['harmonics']))}"
        elif "points" in info:
            desc += f", {esc(info['points'])} points"
        out.append(("flux model", desc))
    if c.adequacy is not None:
        verdict = c.adequacy.get("verdict", "–")
        msg = str(c.adequacy.get("message", "") or "")
        if msg.lower().startswith(str(verdict).lower()):
            msg = msg[len(str(verdict)) :].lstrip(" :,-")
        out.append(("model adequacy", f"<b>{esc(verdict)}</b>" + (f": {esc(msg)}" if msg else "")))
    elif c.constant_speed is not None:
        cs = c.constant_speed
        motion = cs.get("motion_rms")
        floor = cs.get("angle_noise_floor")
        ratio = (
            f" ({number(motion / floor, '.3g')} × the noise floor)"
            if isinstance(motion, int | float) and isinstance(floor, int | float) and floor > 0
            else ""
        )
        warnings = [str(w) for w in cs.get("warnings", [])]
        out.append(
            (
                "model adequacy (constant speed)",
                f"<b>{esc(cs.get('status', '–'))}</b>: rotor motion off the straight line "
                f"{c.angle(motion)} RMS{ratio}; "
                f"{number(100 * float(cs.get('downweighted_fraction', 0.0)), '.3g')} % of the "
                "samples down-weighted as outliers"
                + (f"; {esc('; '.join(warnings))}" if warnings else ""),
            )
        )
        out.append(
            (
                "constant-speed segment",
                f"samples {esc(cs.get('start'))}..{esc(cs.get('stop'))}, "
                f"{number(cs.get('revolutions'), '.3g')} revolutions, Hall noise "
                f"{number(cs.get('noise_std'), '.3g')} per channel",
            )
        )
    else:
        out.append(("model adequacy", "<span class='meta'>not assessed</span>"))
    return out


#: Which firmware path to use (docs/firmware.md, "Which path"; numbers from the benchmarks:
#: bench_cycles.txt, bench_observer.txt, bench_observer_c.txt; Cortex-M4F, taken branch 1 + 2).
_WHICH_PATH = (
    "<p><b>Lean table</b> (<code>hallcal export-c</code>): at most 275-312 Cortex-M4F cycles "
    "per sample (update + read), 2-4 kB of tables; at the noise floor while temperature, "
    "mounting and sensors stay as calibrated (4.2x the floor 60 K warmer), no detection of a "
    "failed sensor or a remount beyond range checks. <b>Observer</b> (<code>hallcal export-c "
    "--observer</code>, <code>reconstruct --observer</code>): at most 661 cycles "
    "(median 545, 593 on healthy samples), about 53 kB of tables for 11 pole pairs; at the floor "
    "as calibrated, again 2 s after a 60 K change and through servo motion to 4e4 rad/s^2, a "
    "failed channel excluded within 16 samples without a slip, a remount flagged <i>stale</i> "
    "within 0.1 revolution, and the only "
    "path on a folding map. Use the table when the budget is tight and the motor stays as "
    "calibrated; the observer when it does not or when a wrong angle must be detected.</p>"
)


def render_html(content: ReportContent, images: list[tuple[ReportFigure, bytes]]) -> str:
    """The report as one self-contained HTML page (figures as base64 PNG, no scripts, no URLs).

    Parameters
    ----------
    content : ReportContent
    images : list of (ReportFigure, bytes)
        Each figure with its PNG.

    Returns
    -------
    str
    """
    c = content
    created = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    src = "; ".join(f"{k}: {v}" for k, v in c.sources.items()) or "in memory"
    out = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{esc(c.title)}</title><style>{_CSS}</style></head><body><main>",
        f"<h1>{esc(c.title)}</h1>",
        f'<p class="meta">{c.pole_pairs} pole pairs · '
        + (
            "time in samples (sample_time = 1)"
            if c.setup.sample_time == 1.0
            else f"sample time {number(c.setup.sample_time, '.4g')} s"
        )
        + " · angle errors in "
        + AngleUnit.parse(c.angle_units).description
        + f" · inputs: {esc(src)} · created {created} · hallcal {esc(__version__)}</p>",
        f'<p><span class="status {_status_class(c.status)}">status: {esc(c.status)}</span></p>',
    ]
    if c.messages or c.notes:
        out.append('<div class="notes">')
        out += [f"<p>{_prose(m)}</p>" for m in (*c.messages, *c.notes)]
        out.append("</div>")
    out.append("<h2>Accuracy</h2>")
    out.append(_accuracy_table(c))
    out.append("<h2>Calibration</h2>")
    out.append(_kv(_calibration_rows(c)))
    out.append("<h2>Figures</h2>")
    for i, (fig, png) in enumerate(images, start=1):
        w, h = fig.figure.get_size_inches() * _DPI
        b64 = base64.b64encode(png).decode("ascii")
        out.append(
            f'<figure id="fig-{esc(fig.key)}"><img src="data:image/png;base64,{b64}" '
            f'alt="{esc(fig.title)}" width="{int(round(w))}" height="{int(round(h))}">'
            f"<figcaption><b>Figure {i}. {esc(fig.title)}.</b> {esc(fig.caption)}"
            "</figcaption></figure>"
        )
    out.append("<h2>Firmware: which path</h2>")
    out.append(_WHICH_PATH)
    out.append("<h2>Setup</h2>")
    out.append(f"<pre>{esc(setup_to_toml(c.setup))}</pre>")
    out.append(
        "<footer>hallcal implements van Meer et al., “Self-Calibrating Position Measurements: "
        "Applied to Imperfect Hall Sensors”. Figures are also written as PNG files next to this "
        "report.</footer>"
    )
    out.append("</main></body></html>")
    return "\n".join(out) + "\n"
