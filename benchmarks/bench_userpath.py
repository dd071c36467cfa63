"""The user's mistakes, as a user makes them: exit status, time to fail, the line.

On the README's motor (4 pole pairs, 10 kHz, ``hallcal simulate`` with the sizes of
``tests/test_readme.py``: a 1.1-revolution ramp in 8 s, 80 000 samples) the script writes the
recordings a user gets wrong (angles logged in degrees, an encoder in revolutions, a standstill,
a ``t`` column twice the sample time, constant, reversed or shuffled, a setup's sample time 10x
off, a typo'd encoder column) and runs each command in a fresh process, printing one row per
case: exit status, wall time and the line a user reads (the error line, else the last line of
the output, with the line that matters for the case under it).

``--src DIR`` runs another source tree (e.g. the code before the fixes, from ``git archive``)
on the same files, for a before/after table. The machine is shared: wall times include start-up
and the load of the moment. Run: ``python benchmarks/bench_userpath.py [--src DIR] [--keep DIR]``;
the output is committed in ``benchmarks/bench_userpath.txt``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def _files(d: Path, src: str) -> None:
    """The README motor's recordings and the mistaken copies of them."""
    from test_readme import readme_setup, small_setup  # the README's setup, small sizes

    from hallcal.io import read_dataset, write_dataset

    text = small_setup(readme_setup())
    (d / "setup.toml").write_text(text)
    (d / "pp10.toml").write_text(text.replace("pole_pairs = 4", "pole_pairs = 10"))
    (d / "st10.toml").write_text(text.replace("sample_time = 0.0001", "sample_time = 0.001"))
    (d / "m.csv").write_text("motor_id,data,setup\nm1,cal.csv,setup.toml\n")
    for args in (
        ["--out", "cal.csv"],
        ["--experiment", "multisine", "--out", "bla.csv"],
    ):
        _hallcal(d, src, "simulate", "--setup", "setup.toml", *args)
    _hallcal(d, src, "calibrate", "cal.csv", "--setup", "setup.toml", "--out", "cal.json")
    cols = {k: np.array(v) for k, v in read_dataset(d / "cal.csv", required=()).columns.items()}
    n = cols["t"].size
    rng = np.random.default_rng(0)

    def variant(name: str, **changed: np.ndarray) -> None:
        out = {**cols, **changed}
        for old, new in (("y_ref", "yref"),) if name == "typo.csv" else ():
            out[new] = out.pop(old)
        write_dataset(d / name, out)

    variant("deg.csv", **{k: np.degrees(cols[k]) for k in ("r", "y", "y_ref")})
    variant("yref_revs.csv", y_ref=cols["y_ref"] / (2 * np.pi))
    still = {h: cols[h][0] + rng.normal(0.0, np.sqrt(7.5e-6), n) for h in ("d1", "d2", "d3")}
    variant("still.csv", **still, **{k: np.zeros(n) for k in ("r", "y", "y_ref", "u")})
    variant("t2.csv", t=2 * cols["t"])
    variant("tconst.csv", t=np.zeros(n))
    variant("trev.csv", t=cols["t"][::-1].copy())
    variant("tshuf.csv", t=rng.permutation(cols["t"]))
    variant("typo.csv")


def _env(src: str) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": src}


def _hallcal(d: Path, src: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "hallcal.cli", *args], cwd=d, env=_env(src), capture_output=True,
        text=True, timeout=900,
    )  # fmt: skip


CASES: list[tuple[str, list[str], str | None]] = [
    # (case, command: "hallcal ..." or "python -c ...", a stdout line to show under it)
    ("1 degrees: calibrate", ["calibrate", "deg.csv", "--setup", "setup.toml", "--out", "x.json"],
     None),
    ("1 degrees: inspect", ["inspect", "deg.csv", "--setup", "setup.toml"], None),
    ("1 degrees: reconstruct", ["reconstruct", "cal.json", "deg.csv", "--out", "a.csv"], None),
    ("1 y_ref in revolutions", ["calibrate", "yref_revs.csv", "--setup", "setup.toml", "--out",
                                "x.json"], None),
    ("2 export-c, no scale", ["export-c", "cal.json", "--out", "fw/"], None),
    ("2 cal.export_c('fw/')", ["-c", "import hallcal; r = hallcal.load('cal.json')"
                               ".export_c('fw/'); print([p.name for p in r.paths])"], None),
    ("2 fleet --export-c", ["fleet", "m.csv", "--out", "batch", "--export-c", "--scheduler",
                            "sequential", "--quiet", "--no-report"], None),
    ("4 inspect standstill", ["inspect", "still.csv", "--setup", "setup.toml"], "rotation"),
    ("4 inspect pole_pairs 10", ["inspect", "cal.csv", "--setup", "pp10.toml"], "rotation"),
    ("4 inspect multisine", ["inspect", "bla.csv", "--setup", "setup.toml"], None),
    ("5 t twice", ["calibrate", "t2.csv", "--setup", "setup.toml", "--out", "x.json"], None),
    ("5 t constant", ["calibrate", "tconst.csv", "--setup", "setup.toml", "--out", "x.json"], None),
    ("5 t reversed", ["calibrate", "trev.csv", "--setup", "setup.toml", "--out", "x.json"], None),
    ("5 t shuffled", ["calibrate", "tshuf.csv", "--setup", "setup.toml", "--out", "x.json"], None),
    ("5 sample_time 10x: calibrate", ["calibrate", "cal.csv", "--setup", "st10.toml", "--out",
                                      "x.json"], None),
    ("5 sample_time 10x: bla", ["bla", "bla.csv", "--setup", "st10.toml", "--out", "b.json"],
     "G(s)"),
    ("5 sample_time 10x: inspect", ["inspect", "cal.csv", "--setup", "st10.toml"], "sample time"),
    ("6 column yref", ["calibrate", "typo.csv", "--setup", "setup.toml", "--out", "x.json"], None),
    ("8 plan", ["plan", "cal.json", "--revolutions", "2"], None),
    ("8 plan --speeds", ["plan", "cal.json", "--revolutions", "2", "--speeds", "0.25,0.5,1,2"],
     None),
    ("9 print(cal.status)", ["-c", "import hallcal; print(hallcal.load('cal.json').status)"],
     None),
]  # fmt: skip


def _row(d: Path, src: str, name: str, args: list[str], show: str | None) -> list[str]:
    for p in ("fw", "batch"):
        shutil.rmtree(d / p, ignore_errors=True)
    cmd = (
        [sys.executable, *args] if args[0] == "-c" else [sys.executable, "-m", "hallcal.cli", *args]
    )
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=d, env=_env(src), capture_output=True, text=True, timeout=900)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        progress = ("  ", " s  ")  # the progress lines ("   1.2 s  step") are not the message
        lines = [ln for ln in res.stderr.splitlines() if not (ln.startswith(progress[0])
                                                                and progress[1] in ln)]  # fmt: skip
        line = lines[-1] if lines else ""
    else:
        line = res.stdout.strip().splitlines()[-1] if res.stdout.strip() else ""
    out = [f"{name:<30} exit {res.returncode}  {wall:5.1f} s  {line}"]
    if show is not None:
        out += [f"{'':<30}   {ln}" for ln in res.stdout.splitlines() if ln.startswith(show)]
    if name.startswith("2 fleet"):
        summary = d / "batch" / "summary.csv"
        if summary.is_file():
            row = summary.read_text().splitlines()[-1]
            out.append(f"{'':<30}   summary.csv: {row[:160]}")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--src", default=str(ROOT / "src"), help="source tree to run")
    parser.add_argument("--keep", default=None, help="keep the files in this folder")
    a = parser.parse_args()
    d = Path(a.keep or tempfile.mkdtemp(prefix="bench-userpath-"))
    d.mkdir(parents=True, exist_ok=True)
    _files(d, str(ROOT / "src"))  # the same inputs for any --src
    _hallcal(d, a.src, "calibrate", "cal.csv", "--setup", "setup.toml", "--out", "warm.json")
    print(f"source tree: {a.src}; load average {os.getloadavg()[0]:.1f}")
    for name, args, show in CASES:
        for line in _row(d, a.src, name, args, show):
            print(line, flush=True)
    print(f"load average {os.getloadavg()[0]:.1f}")
    if a.keep is None:
        shutil.rmtree(d, ignore_errors=True)


if __name__ == "__main__":
    main()
