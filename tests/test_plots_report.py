"""Figures and the HTML report: the paper's figure kinds, a self-contained report that
headless Chromium renders with every figure loaded, and ``hallcal report`` on the command line.

The demo's objects are computed once per session (conftest ``demo_run``, about 15 s);
every test then only plots or writes.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from hallcal.errors import HallcalInputError
from hallcal.io import Dataset, read_dataset, validate_artifact, write_dataset
from hallcal.output import plots
from hallcal.output.report import (
    ReportExtras,
    report_content,
    write_demo_report,
    write_report,
    write_report_from_files,
)
from hallcal.pipeline import Calibration, CalibrationStatus

CHROMIUM = "/usr/bin/chromium"
DEMO_FIGURES = ("ripple", "hall_model", "angle_error", "spectrum", "bla", "sem_cost", "lut")


@pytest.fixture(scope="module")
def demo(demo_run):
    return demo_run[1]  # conftest: one run_demo per session


@pytest.fixture(scope="module")
def demo_report(demo, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo_report")
    return write_demo_report(
        demo.calibration,
        demo.validation,
        runs=demo.runs,
        out_dir=out,
        noise_floor=demo.noise_floor,
    )


# ------------------------------------------------------------------------------------------------
# plots
# ------------------------------------------------------------------------------------------------


def _figures(demo) -> dict[str, tuple[Figure, dict[str, str]]]:
    """Each plot function on the demo's objects, with substrings its axis labels must contain."""
    cal, val = demo.calibration, demo.validation
    run_c, run_v = demo.runs["calibration"], demo.runs["validation"]
    n_m = cal.setup.pole_pairs
    yi = cal.lut.f_init(run_v.d)
    ys = yi + cal.lut.correction(yi)
    from hallcal.fit.sem import predicted_angle_error

    sd = predicted_angle_error(
        cal.flux, cal.sem.covariance, n_m, projection=cal.lut.projection, offset=cal.lut.offset
    )
    return {
        "ripple": (
            plots.plot_ripple(run_v.y0, yi, pole_pairs=n_m, y_star=ys),
            {"x": "deg", "y": "mrad"},
        ),
        "hall_model": (
            plots.plot_hall_model(
                run_c.d, cal.sem.d_sim, t=run_c.t, noise_variance=run_c.config.noise_variance
            ),
            {"x": "[s]", "y": "d1"},
        ),
        "angle_error": (
            plots.plot_angle_error(run_v.y0, yi, ys, noise_floor=demo.noise_floor),
            {"x": "deg", "y": "mrad"},
        ),
        "spectrum": (
            plots.plot_error_spectrum(val, pole_pairs=n_m, noise_floor=demo.noise_floor),
            {"x": "cycles/rev", "y": "mrad²"},
        ),
        "bla": (
            plots.plot_bla(
                cal.bla,
                true_plant=run_c.config.plant,
                corrected_plant=cal.plant,
                gain_correction=cal.gain.c,
            ),
            {"x": "Hz", "y": "deg"},
        ),
        "sem_cost": (
            plots.plot_sem_cost(cal.sem, noise_variance=run_c.config.noise_variance),
            {"x": "iteration", "y": "cost"},
        ),
        "lut": (
            plots.plot_lut(cal.lut, eta_std=sd, true_lut=None),
            {"x": "deg", "y": "rad"},
        ),
        "correction": (
            plots.plot_correction(yi, ys, pole_pairs=n_m),
            {"x": "deg", "y": "mrad"},
        ),
    }


def test_every_plot_returns_a_labelled_figure(demo):
    for name, (fig, units) in _figures(demo).items():
        assert isinstance(fig, Figure), name
        axes = fig.get_axes()
        assert axes, name
        for ax in axes:
            assert ax.get_ylabel().strip(), f"{name}: an axis without a y label"
        bottom = axes[-1]
        assert units["x"] in bottom.get_xlabel(), (name, bottom.get_xlabel())
        assert any(units["y"] in ax.get_ylabel() for ax in axes), (name, units)
        assert fig._suptitle is not None and fig._suptitle.get_text(), f"{name}: no title"
        labels = [t.get_text() for ax in axes if ax.get_legend() for t in ax.get_legend().texts]
        assert labels, f"{name}: no legend"
        assert not any("$" in t for t in labels), f"{name}: stray mathtext in {labels}"


def test_plots_mark_what_the_paper_marks(demo):
    figs = _figures(demo)
    n_m = demo.calibration.setup.pole_pairs
    # spectrum: the pole-pair harmonic is marked
    ax = figs["spectrum"][0].get_axes()[0]
    assert any(np.allclose(line.get_xdata(), n_m) for line in ax.get_lines())
    # f_init blue, f_star red, as in the paper
    ax = figs["angle_error"][0].get_axes()[0]
    colors = {line.get_label().split(":")[0]: line.get_color() for line in ax.get_lines()}
    assert colors["f_init"] == plots.INIT_COLOR and colors["f_star"] == plots.STAR_COLOR
    # SEM cost on a log axis with the noise level 3 N sigma^2
    ax = figs["sem_cost"][0].get_axes()[0]
    assert ax.get_yscale() == "log"
    n = demo.calibration.sem.n_samples
    level = 3 * n * demo.runs["calibration"].config.noise_variance
    assert any(np.allclose(line.get_ydata(), level) for line in ax.get_lines())
    # BLA: magnitude in dB over a log frequency axis, phase below
    mag, ph = figs["bla"][0].get_axes()
    assert mag.get_xscale() == "log" and "dB" in mag.get_ylabel() and "deg" in ph.get_ylabel()


def test_plots_without_optional_inputs(demo):
    cal = demo.calibration
    run_v = demo.runs["validation"]
    yi = cal.lut.f_init(run_v.d)
    fig = plots.plot_angle_error(run_v.y0, yi)
    assert len(fig.get_axes()[0].get_lines()) == 1
    fig = plots.plot_lut(cal.lut)
    assert len(fig.get_axes()) == 1
    fig = plots.plot_hall_model(run_v.d, run_v.d, sensor=3)
    assert "sample" in fig.get_axes()[0].get_xlabel()
    fig = plots.plot_sem_cost(cal.sem)
    assert "estimated" in " ".join(t.get_text() for t in fig.get_axes()[0].get_legend().texts)
    with pytest.raises(ValueError, match="shape"):
        plots.plot_hall_model(run_v.d, run_v.d[:, :2])


# ------------------------------------------------------------------------------------------------
# the HTML report
# ------------------------------------------------------------------------------------------------


def test_demo_report_has_every_figure_and_the_summary(demo, demo_report):
    text = demo_report.read_text(encoding="utf-8")
    for key in DEMO_FIGURES:
        assert f'id="fig-{key}"' in text, key
        assert (demo_report.parent / "figures" / f"{key}.png").stat().st_size > 10_000, key
    assert text.count('<img src="data:image/png;base64,') == len(DEMO_FIGURES)
    v, cal = demo.validation, demo.calibration
    for x in (v.init.rms, v.init.peak, v.star.rms, v.star.peak, demo.noise_floor):
        assert f"{1e3 * x:.3f} mrad" in text
    assert f"{1e3 * cal.predicted_error:.3f} mrad" in text
    assert f"{cal.sem.initial_cost:.4g} → {cal.sem.cost:.4g}" in text
    assert f"{cal.sem.iterations} ({cal.sem.status})" in text
    assert f"{cal.sem.solve_time:.2f} s" in text
    assert "bijective: <b>yes</b>" in text
    gain = cal.gain.value if hasattr(cal.gain, "value") else cal.gain.c
    assert f"{gain:.5g}" in text
    if cal.adequacy is not None and hasattr(cal.adequacy, "verdict"):
        assert f"<b>{cal.adequacy.verdict}</b>" in text
    assert "pole_pairs = 11" in text  # the setup, as TOML
    # written atomically: no temporary files left behind
    leftovers = [p.name for p in demo_report.parent.rglob("*.tmp")]
    assert not leftovers


def test_report_is_self_contained(demo_report):
    text = demo_report.read_text(encoding="utf-8")
    assert not re.search(r"https?://", text, flags=re.IGNORECASE)
    assert "<script" not in text.lower()
    assert "<link" not in text.lower() and "@import" not in text
    # every src is an embedded image
    assert all(s.startswith("data:image/png;base64,") for s in re.findall(r'src="([^"]*)"', text))


def _chromium(args: list[str], profile: Path) -> subprocess.CompletedProcess:
    cmd = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
        *args,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


_PROBE = """<script>
window.addEventListener("load", function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  document.body.setAttribute("data-images", String(imgs.length));
  document.body.setAttribute("data-loaded", String(ok));
});
</script>"""


@pytest.mark.skipif(
    not Path(CHROMIUM).exists(),
    reason=f"{CHROMIUM} not installed (Debian: apt-get install chromium); .ci/run installs it",
)
def test_report_renders_in_headless_chromium(demo_report, tmp_path):
    import matplotlib.image

    # 1. every <img> decoded: a copy of the report with a tiny probe script, DOM dumped after load
    probe = tmp_path / "probe.html"
    probe.write_text(
        demo_report.read_text(encoding="utf-8").replace("</body>", _PROBE + "</body>"),
        encoding="utf-8",
    )
    res = _chromium(
        ["--virtual-time-budget=10000", "--dump-dom", probe.as_uri()], tmp_path / "profile1"
    )
    assert res.returncode == 0, res.stderr[-2000:]
    m = re.search(r'data-images="(\d+)" data-loaded="(\d+)"', res.stdout)
    assert m, "the probe did not run: " + res.stdout[:500]
    assert int(m.group(1)) == len(DEMO_FIGURES)
    assert m.group(1) == m.group(2), f"only {m.group(2)} of {m.group(1)} images loaded"

    # 2. a screenshot of the report itself (kept in the test's tmp dir), not blank
    shot = tmp_path / "report.png"
    res = _chromium(
        [f"--screenshot={shot}", "--window-size=1200,3000", demo_report.as_uri()],
        tmp_path / "profile2",
    )
    assert res.returncode == 0 and shot.exists(), res.stderr[-2000:]
    img = matplotlib.image.imread(shot)
    assert img.shape[0] == 3000 and img.shape[1] == 1200
    rgb = img[..., :3]
    # Figures are in the screenshot: plenty of non-white pixels, and the paper's colours
    assert np.mean(rgb.min(axis=-1) < 0.9) > 0.05
    blue = (rgb[..., 2] > 0.55) & (rgb[..., 0] < 0.3)
    red = (rgb[..., 0] > 0.7) & (rgb[..., 1] < 0.3) & (rgb[..., 2] < 0.3)
    assert blue.sum() > 1000 and red.sum() > 1000


def test_report_degrades_without_sem_or_a_bijective_table(demo, tmp_path):
    cal = demo.calibration
    data = Dataset.from_columns(demo.runs["calibration"].columns())
    # e.g. a constant-speed calibration: no SEM, no BLA, no plant
    art = cal.to_artifact()
    solver = ("cost_initial", "cost", "cost_history", "iterations", "sem_status", "solve_time")
    solver += ("noise_variance", "n_samples", "adequacy", "gain_correction")
    diag = {k: v for k, v in art["diagnostics"].items() if k not in solver}
    bare = {**{k: v for k, v in art.items() if k != "plant"}, "diagnostics": diag}
    content = report_content(bare, data, extras=ReportExtras())
    text = write_report(content, tmp_path / "bare").read_text()
    for key in ("ripple", "hall_model", "angle_error", "spectrum", "lut"):
        assert f'id="fig-{key}"' in text, key
    for key in ("bla", "sem_cost"):
        assert f'id="fig-{key}"' not in text, key
    assert "calibration recording" in text  # validated in-sample on its y_ref, and says so
    # a table that is not bijective (1 + d eta / d y_hat = 1 + 10 cos < 0 in places: the map
    # y0 -> y_hat folds): f_star is undefined, f_init is still shown
    y_hat = np.asarray(art["lut"]["y_hat"])
    lut = {"y_hat": y_hat.tolist(), "eta": (0.5 * np.sin(20.0 * y_hat)).tolist()}
    diag = {**art["diagnostics"], "status": CalibrationStatus.NOT_BIJECTIVE.value}
    folded = validate_artifact({**art, "lut": lut, "diagnostics": diag}, bijective=False)
    assert not folded.lut().bijective
    with pytest.raises(HallcalInputError, match="not bijective"):  # never by default
        validate_artifact({**art, "lut": lut})
    content = report_content(Calibration(folded, cal.computed), data)  # its SEM and BLA
    text = write_report(content, tmp_path / "broken").read_text()
    assert "bijective: <b>NO</b>" in text and "status-bad" in text
    assert 'id="fig-angle_error"' in text and 'id="fig-spectrum"' not in text
    assert "f_star is undefined" in text


# ------------------------------------------------------------------------------------------------
# from files and on the command line
# ------------------------------------------------------------------------------------------------


def test_report_without_encoder_says_so(demo, tmp_path):
    ds = read_dataset(demo.out_dir / "calibration.npz")
    cols = {k: v for k, v in ds.columns.items() if k != "y_ref"}
    data = tmp_path / "no_encoder.npz"
    write_dataset(data, cols)
    messages: list[str] = []
    path = write_report_from_files(
        demo.out_dir / "calibration.json", data, out_dir=tmp_path / "rep", progress=messages.append
    )
    text = path.read_text(encoding="utf-8")
    assert "Errors against an encoder: unavailable" in text
    for key in ("hall_model", "correction", "bla", "sem_cost", "lut"):
        assert f'id="fig-{key}"' in text, key
    for key in ("ripple", "angle_error", "spectrum"):
        assert f'id="fig-{key}"' not in text, key
    assert "band from cov(θ)" in text  # the covariance was recomputed from the files
    assert messages, "no progress reported"
    assert not re.search(r"https?://", text, flags=re.IGNORECASE)


def test_report_rejects_validation_data_without_encoder(demo, tmp_path):
    ds = read_dataset(demo.out_dir / "validation.npz")
    bad = tmp_path / "val.npz"
    write_dataset(bad, {k: v for k, v in ds.columns.items() if k != "y_ref"})
    with pytest.raises(HallcalInputError, match=r"val\.npz.*y_ref"):
        write_report_from_files(
            demo.out_dir / "calibration.json",
            demo.out_dir / "calibration.npz",
            validation=bad,
            out_dir=tmp_path / "rep",
        )


def _hallcal(*args: str) -> subprocess.CompletedProcess:
    exe = shutil.which("hallcal")
    cmd = [exe] if exe else [sys.executable, "-m", "hallcal.cli"]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=300)


def test_cli_report_writes_the_html(demo, tmp_path):
    out = tmp_path / "report"
    d = demo.out_dir
    res = _hallcal(
        "report",
        str(d / "calibration.json"),
        str(d / "calibration.npz"),
        "--validation",
        str(d / "validation.npz"),
        "--out",
        str(out),
    )
    assert res.returncode == 0, res.stderr
    html = out / "report.html"
    assert str(html) in res.stdout
    text = html.read_text(encoding="utf-8")
    for key in DEMO_FIGURES:  # bla.json next to the artifact is picked up
        assert f'id="fig-{key}"' in text, key
    v = demo.validation
    assert f"{1e3 * v.star.rms:.3f} mrad" in text  # the same fresh run, the same table


def test_cli_report_missing_artifact_exits_2(tmp_path):
    missing = tmp_path / "nope.json"
    res = _hallcal("report", str(missing), str(tmp_path / "data.npz"), "--out", str(tmp_path))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert "nope.json" in lines[0] and "Traceback" not in res.stderr
