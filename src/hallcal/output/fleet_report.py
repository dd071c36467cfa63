"""The fleet page (``OUT/fleet.html`` of ``hallcal fleet``): one batch of motors at a glance.

For a quality engineer: how many motors are ok, warning, refused or failed; the distribution of
the predicted f_star error over the batch; f_init against f_star on the validation runs; the
outliers (robust z-score, see :func:`robust_outliers`); and every motor that did not succeed with
its reason. Self-contained like the calibration report (:mod:`hallcal.output.report`): inline
CSS, figures as base64 PNG, no scripts, no external references.
"""

from __future__ import annotations

import base64
import datetime as _dt
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from matplotlib.figure import Figure
from numpy.typing import ArrayLike, NDArray

from hallcal._version import __version__
from hallcal.formatting import AngleUnit, esc, number
from hallcal.io import atomic_write
from hallcal.output.plots import figure_png, log_axis
from hallcal.output.report.page import _CSS as _REPORT_CSS

__all__ = ["Outlier", "find_outliers", "render_fleet_html", "robust_outliers", "write_fleet_report"]

#: Modified z-score above which a value is an outlier (Iglewicz and Hoaglin, 1993: 3.5 flags
#: about 0.05% of a normal sample, so in a batch of 1000 well-behaved motors about 0.5 false
#: alarms, while a motor a few times worse than its peers stands out).
Z_OUTLIER = 3.5
#: Smallest excess over the batch median worth flagging: in a batch with almost no spread the
#: z-score alone would flag a motor 2% worse than the median, while the sensors' noise, and so
#: the noise floor, differs between parts by more than that (25%: a power ratio of 1.56).
MIN_EXCESS = 0.25
#: Fewest values for which a median and a MAD mean anything.
_MIN_VALUES = 5
_DPI = 110
_COLORS = {"ok": "#2e7d32", "warning": "#b26a00", "refused": "#b71c1c", "failed": "#616161"}

_CSS = (
    _REPORT_CSS
    + """
.counts span { display: inline-block; margin-right: 14px; }
table.motors td, table.motors th { padding-right: 14px; }
td.msg { max-width: 560px; }
td.nowrap { white-space: nowrap; }
"""
)


def robust_outliers(values: ArrayLike) -> tuple[NDArray[np.bool_], float | None]:
    """High outliers of positive values by the modified z-score of their logarithm.

    z_i = 0.6745 (log x_i - median) / MAD (Iglewicz and Hoaglin, 1993); x_i is an outlier when
    z_i > :data:`Z_OUTLIER` and x_i exceeds the median by more than :data:`MIN_EXCESS`. Angle
    errors are positive and skewed, their logarithm close to symmetric, and only large errors are
    a problem, so only the high side is flagged. With a MAD of zero the mean absolute deviation
    times 1.2533 stands in (the same estimator's fallback); with fewer than 5 finite values, or
    no spread at all, nothing is flagged.

    Parameters
    ----------
    values : array_like
        Positive numbers; NaN (no value) is never an outlier.

    Returns
    -------
    mask : numpy.ndarray of bool
        True where the value is a high outlier.
    threshold : float or None
        The value above which a number is an outlier (None when nothing can be flagged).
    """
    x = np.asarray(values, dtype=np.float64)
    mask = np.zeros(x.shape, dtype=bool)
    ok = np.isfinite(x) & (x > 0)
    if ok.sum() < _MIN_VALUES:
        return mask, None
    lx = np.log(x[ok])
    med = float(np.median(lx))
    scale = float(np.median(np.abs(lx - med))) / 0.6745
    if scale == 0.0:
        scale = float(np.mean(np.abs(lx - med))) * 1.2533
    if scale == 0.0:
        return mask, None
    threshold = max(med + Z_OUTLIER * scale, med + math.log1p(MIN_EXCESS))
    mask[ok] = lx > threshold
    return mask, float(math.exp(threshold))


@dataclass(frozen=True)
class Outlier:
    """One motor flagged on the fleet page.

    Attributes
    ----------
    motor_id : str
    reasons : list of str
        Why it is flagged (one line each).
    """

    motor_id: str
    reasons: list[str]


def _column(rows: Sequence[Mapping[str, Any]], key: str) -> NDArray[np.float64]:
    return np.array(
        [np.nan if r.get(key) is None else float(r[key]) for r in rows], dtype=np.float64
    )


def find_outliers(rows: Sequence[Mapping[str, Any]]) -> list[Outlier]:
    """Motors that succeeded but stand out from the batch.

    Flags: a predicted error or an f_star RMS (validation) that is a high outlier
    (:func:`robust_outliers`), and f_star no better than f_init on the validation run.

    Parameters
    ----------
    rows : sequence of mapping
        Summary rows (``hallcal.fleet.SUMMARY_COLUMNS``).

    Returns
    -------
    list of Outlier
        In the order of `rows`.
    """
    good = [r for r in rows if r.get("status") in ("ok", "warning")]
    reasons: dict[str, list[str]] = {r["motor_id"]: [] for r in good}

    def mrad(x: float | None) -> str:
        return AngleUnit.MRAD.text(x, page=True)

    for key, what in (("predicted_error", "predicted error"), ("f_star_rms", "f_star RMS")):
        vals = _column(good, key)
        mask, thr = robust_outliers(vals)
        med = float(np.nanmedian(vals)) if np.isfinite(vals).any() else math.nan
        for r, v, m in zip(good, vals, mask, strict=True):
            if m and thr is not None:
                reasons[r["motor_id"]].append(
                    f"{what} {mrad(v)} (batch median {mrad(med)}, outlier above {mrad(thr)})"
                )
    for r in good:
        fi, fs = r.get("f_init_rms"), r.get("f_star_rms")
        if fi is not None and fs is not None and fs >= fi:
            reasons[r["motor_id"]].append(
                f"f_star RMS {mrad(fs)} is not better than f_init {mrad(fi)}"
            )
    return [Outlier(r["motor_id"], reasons[r["motor_id"]]) for r in good if reasons[r["motor_id"]]]


def _log_scale(values: NDArray[np.float64]) -> bool:
    """A log axis when the values span more than a factor 3, else a linear one."""
    return float(values.max()) > 3.0 * float(values.min())


def _bins(values: NDArray[np.float64], n: int = 24) -> NDArray[np.float64]:
    lo, hi = float(values.min()), float(values.max())
    if _log_scale(values):
        return np.geomspace(lo / 1.05, hi * 1.05, n)
    pad = max(0.05 * (hi - lo), 0.01 * hi)
    return np.linspace(lo - pad, hi + pad, n)


def _figure_predicted(rows: Sequence[Mapping[str, Any]]) -> Figure | None:
    good = [r for r in rows if r.get("status") in ("ok", "warning")]
    vals = _column(good, "predicted_error")
    vals = vals[np.isfinite(vals) & (vals > 0)]
    if vals.size == 0:
        return None
    mrad = AngleUnit.MRAD.convert(vals)
    fig = Figure(figsize=(8.0, 3.4), layout="constrained")
    ax = fig.add_subplot()
    ax.hist(mrad, bins=_bins(mrad), color="#1f77b4", edgecolor="white")
    if _log_scale(mrad):
        ax.set_xscale("log")
        log_axis(ax.xaxis, float(mrad.min()), float(mrad.max()))
    ax.axvline(float(np.median(mrad)), color="black", ls="--", lw=1, label="median")
    _, thr = robust_outliers(vals)
    if thr is not None:
        thr_mrad = AngleUnit.MRAD.convert(thr)
        ax.axvline(thr_mrad, color="#d62728", ls=":", lw=1.2, label="outlier threshold")
    ax.set_xlabel("predicted f_star error, RMS [mrad]")
    ax.set_ylabel("motors")
    ax.legend(frameon=False)
    return fig


def _figure_validation(rows: Sequence[Mapping[str, Any]]) -> Figure | None:
    val = [r for r in rows if r.get("f_init_rms") is not None and r.get("f_star_rms") is not None]
    if not val:
        return None
    fi = AngleUnit.MRAD.convert(_column(val, "f_init_rms"))
    fs = AngleUnit.MRAD.convert(_column(val, "f_star_rms"))
    fig = Figure(figsize=(9.0, 3.8), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2, width_ratios=(1.0, 1.3))
    colors = [_COLORS.get(str(r.get("status")), "#1f77b4") for r in val]
    ax1.scatter(fi, fs, s=16, c=colors, zorder=3)
    lo = float(min(fi.min(), fs.min())) / 1.5
    hi = float(max(fi.max(), fs.max())) * 1.5
    ax1.plot([lo, hi], [lo, hi], color="grey", lw=1, ls="--", label="f_star = f_init")
    ax1.set_xscale("log")
    ax1.set_yscale("log")
    log_axis(ax1.xaxis, lo, hi)
    log_axis(ax1.yaxis, lo, hi)
    ax1.set_xlim(lo, hi)
    ax1.set_ylim(lo, hi)
    ax1.set_xlabel("f_init RMS [mrad]")
    ax1.set_ylabel("f_star RMS [mrad]")
    ax1.legend(frameon=False, loc="upper left")
    both = np.concatenate([fi, fs])
    bins = _bins(both[both > 0], 30)
    ax2.hist(fi, bins=bins, color="#1f77b4", alpha=0.75, label="f_init")
    ax2.hist(fs, bins=bins, color="#d62728", alpha=0.75, label="f_star")
    if _log_scale(both[both > 0]):
        ax2.set_xscale("log")
        log_axis(ax2.xaxis, float(both[both > 0].min()), float(both.max()))
    ax2.set_xlabel("RMS angle error on the validation run [mrad]")
    ax2.set_ylabel("motors")
    ax2.legend(frameon=False)
    return fig


def _img(fig: Figure, title: str, caption: str) -> str:
    w, h = fig.get_size_inches() * _DPI
    b64 = base64.b64encode(figure_png(fig, dpi=_DPI)).decode("ascii")
    return (
        f'<figure><img src="data:image/png;base64,{b64}" alt="{esc(title)}" '
        f'width="{int(round(w))}" height="{int(round(h))}"><figcaption><b>{esc(title)}.</b> '
        f"{esc(caption)}</figcaption></figure>"
    )


def render_fleet_html(rows: Sequence[Mapping[str, Any]], *, source: str = "") -> str:
    """The fleet page as one self-contained HTML document.

    Parameters
    ----------
    rows : sequence of mapping
        Summary rows (``hallcal.fleet.SUMMARY_COLUMNS``), in manifest order.
    source : str
        Where the batch came from (the manifest), shown at the top.

    Returns
    -------
    str
    """
    out = _head(rows, source)
    out += _without_artifact(rows)
    out += _outlier_section(rows)
    out += _distributions(rows)
    out.append("<h2>All motors</h2>")
    out.append(
        _motor_table(
            rows,
            (
                "motor_id",
                "status",
                "predicted_error",
                "f_init_rms",
                "f_star_rms",
                "model",
                "seconds",
                "message",
            ),
        )
    )
    out.append(
        "<footer>hallcal implements van Meer et al., “Self-Calibrating Position Measurements: "
        "Applied to Imperfect Hall Sensors”. The same figures are in summary.parquet and "
        "summary.csv next to this page (angles in rad there).</footer>"
    )
    out.append("</main></body></html>")
    return "\n".join(out) + "\n"


def _head(rows: Sequence[Mapping[str, Any]], source: str) -> list[str]:
    """The page's head, title, origin and the number of motors per status."""
    counts = {s: 0 for s in _COLORS}
    for r in rows:
        counts[str(r["status"])] = counts.get(str(r["status"]), 0) + 1
    reused = sum(1 for r in rows if r.get("reused"))
    created = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    return [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>hallcal fleet: {len(rows)} motors</title><style>{_CSS}</style></head>",
        "<body><main>",
        f"<h1>Fleet calibration: {len(rows)} motors</h1>",
        f'<p class="meta">manifest: {esc(source or "in memory")} · created {created} · '
        f"hallcal {esc(__version__)}"
        + (f" · {reused} results reused from an earlier run" if reused else "")
        + "</p>",
        '<p class="counts">'
        + "".join(
            f'<span><span class="status" style="background:{_COLORS[s]}">{s}</span> '
            f"{counts.get(s, 0)}</span>"
            for s in _COLORS
        )
        + "</p>",
    ]


def _without_artifact(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    bad = [r for r in rows if r.get("status") in ("refused", "failed")]
    out = ["<h2>Motors without a usable calibration</h2>"]
    if bad:
        out.append(_motor_table(bad, ("motor_id", "status", "message")))
    else:
        out.append("<p>None: every motor has an artifact.</p>")
    return out


def _outlier_section(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    outliers = find_outliers(rows)
    out = [
        "<h2>Outliers</h2>",
        f"<p>Motors with an artifact whose predicted error or f_star RMS is far above the "
        f"batch's (modified z-score of the logarithm above {Z_OUTLIER}), or whose f_star is no "
        "better than f_init on the validation run.</p>",
    ]
    if outliers:
        body = "".join(
            f"<tr><td>{esc(o.motor_id)}</td><td class=msg>{'<br>'.join(map(esc, o.reasons))}"
            "</td></tr>"
            for o in outliers
        )
        out.append(f'<table class="motors"><tr><th>motor</th><th>why</th></tr>{body}</table>')
    else:
        out.append("<p>None.</p>")
    return out


def _distributions(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """The figures: predicted errors, and f_init against f_star on the validation runs."""
    out = ["<h2>Distributions</h2>"]
    fig = _figure_predicted(rows)
    if fig is not None:
        out.append(
            _img(
                fig,
                "Predicted f_star error over the batch",
                "The RMS angle error each calibration predicts for its f_star (noise floor and "
                "the table's uncertainty from cov(θ)), motors with an artifact. Dashed: median; "
                "dotted: the outlier threshold.",
            )
        )
    else:
        out.append("<p>No motor has a predicted error.</p>")
    fig = _figure_validation(rows)
    if fig is not None:
        out.append(
            _img(
                fig,
                "f_init against f_star on the validation runs",
                "Left: each motor's RMS error before (f_init) and after (f_star) calibration on "
                "its validation run; below the dashed diagonal the calibration helped. Right: the "
                "two distributions over the batch.",
            )
        )
    else:
        out.append("<p>No validation runs in the manifest: f_init and f_star not measured.</p>")
    return out


_HEADINGS = {
    "motor_id": "motor",
    "status": "status",
    "message": "message",
    "predicted_error": "predicted",
    "f_init_rms": "f_init RMS",
    "f_star_rms": "f_star RMS",
    "model": "model",
    "seconds": "seconds",
}


def _motor_table(rows: Sequence[Mapping[str, Any]], keys: Sequence[str]) -> str:
    head = "".join(f"<th>{_HEADINGS.get(k, k)}</th>" for k in keys)
    body = []
    for r in rows:
        cells = []
        for k in keys:
            v = r.get(k)
            if k in ("predicted_error", "f_init_rms", "f_star_rms"):
                cells.append(f'<td class="num">{AngleUnit.MRAD.text(v, page=True)}</td>')
            elif k == "seconds":
                cells.append(f'<td class="num">{number(v, ".1f")}</td>')
            elif k == "status":
                color = _COLORS.get(str(v), "#616161")
                style = f"color:{color};font-weight:600"
                cells.append(f'<td><span style="{style}">{esc(v)}</span></td>')
            elif k == "message":
                cells.append(f'<td class="msg">{esc(v or "")}</td>')
            else:
                cells.append(f'<td class="nowrap">{esc("" if v is None else v)}</td>')
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f'<table class="motors"><tr>{head}</tr>{"".join(body)}</table>'


def write_fleet_report(
    table: pa.Table | Sequence[Mapping[str, Any]],
    path: str | os.PathLike[str],
    *,
    source: str = "",
) -> Path:
    """Write the fleet page atomically.

    Parameters
    ----------
    table : pyarrow.Table or sequence of mapping
        The summary (``hallcal.fleet.run_fleet``'s result) or its rows.
    path : path-like
        The HTML file to write.
    source : str
        The manifest, shown at the top.

    Returns
    -------
    pathlib.Path
    """
    rows = table.to_pylist() if isinstance(table, pa.Table) else list(table)
    text = render_fleet_html(rows, source=source)
    p = Path(path)
    with atomic_write(p, "w") as f:
        f.write(text)
    return p
