"""One zoo motor over several calibration noise seeds: is an act/pred outside [0.67, 1.5] the tail
of one run's scatter or a bias of the prediction?

``bench_zoo.py`` calibrates each motor once. A row outside the calibrated band can be a run in
the tail of its own scatter (the verdict's upper quantile,
:func:`hallcal.fit.adequacy.error_spread`, is meant to cover it) or a prediction that is wrong
for that kind of motor. This script keeps the motor and its validation run and redraws only
the calibration run's noise (seed ``motor + 20000 k``, k = 0 the zoo's own row), optionally
with the cogging search off.

Columns as ``bench_zoo.py`` (``k`` the noise draw, ``cog`` the cogging setting).

Found (``bench_zoo_noise.txt``): the lead's unseen zoo seeds 170-199 (``bench_zoo.py --seeds
170 .. 199 --jobs 2``) had two rows outside the band, none "ok" above 1.3x the floor and no table
worse than f_init written: 177 (``shape``, 10 pole pairs) over-predicted (act/pred 0.46: the
white covariance's 2.99x against the batch-means' 1.76x and 1.37x measured, the known
pessimism of the white one where the loop hides directions, :mod:`hallcal.fit._table_error`)
and 179 (``adc12``, 14 pole pairs, a 12-bit ADC, noise floor 0.02 mrad) under-predicted, a
warning at 3.05x the floor predicted 1.80x (act/pred 1.69, upper quantile 3.01x). Motor 179
over ten noise draws, cogging ``"auto"``: act/pred 0.92-1.27 on eight, 1.69 and 1.73 on two
(draws 0 and 4), f_star above its 95 % upper quantile on three (0, 4 and 8: 3.05/3.01, 3.04/2.96,
1.47/1.46), mean act/pred 1.19. Two causes:

- The cogging search takes orders the motor does not have (order 28 = 2 n_m on draw 4, 0 and
  28 on draw 8; order 0 on four more draws), and the noise that made them significant is then
  fitted: the table moves along its constant offset and the electrical harmonic 2 n_m beyond
  what the covariance of the chosen model says (draw 4: offset 2.24x the floor against a
  standard deviation of 1.11x, harmonic 28 1.71x against 0.92x). With ``cogging = "none"`` draw
  4 is at 1.36x predicted 1.40x, draw 8 at 1.06x predicted 1.07x; over the ten draws act/pred
  0.92-1.27 on nine, mean 1.08. Elsewhere in the zoo it is not seen: the rows of classes
  other than ``cogload`` where the search took an order have act/pred mean 1.10, but the drift
  motors among them (whose drift the model lacks) are at 1.09 without one too; the other five
  (``bench_zoo.txt`` 11, 19; unseen 183, 193, 194) are at 0.72-1.23, mean 1.02.
  Fixed since by the search's sideband check (:mod:`hallcal.fit.cogging_search`, step 4:
  the torque at 28 stood in for the flux harmonics among its sidebands 28 +- h that the sparse
  harmonic selection had left out; with them in the basis its T^2 on draw 4 fell from 103 to
  6.8): with ``"auto"`` no order k > 0 is taken on any of the ten draws, draw 4 is at 1.36x
  (predicted 1.40x), draw 8 at 1.06x (1.07x), act/pred 0.92-1.27 on nine (order 0 alone is
  then still taken on four draws, 3, 5, 7 and 9, the table within 0.06x the floor of "none";
  since order 0 is decided with the HAC variance, :mod:`hallcal.fit.cogging_search`, "Order
  0's variance", no draw takes it and every row is the "none" row).
- Draw 0 (the zoo's row; no cogging chosen) is the tail of the table's offset: 2.47x the floor
  against a standard deviation of 1.30x (batch means; 0.60x white), the electrical harmonics
  n_m and 2 n_m about 2x theirs; the same draw with all 70 harmonics: offset 5.48x against
  2.58x. Without the 12-bit quantizer the same seed's table is 0.96x the floor against 1.06x
  predicted (another noise realization, so no proof that quantization is the cause). Over the
  ten draws with ``cogging = "none"`` the offset's z-scores (error over the standard deviation
  of the covariance the prediction uses) have RMS 1.20 (chi-square 14.4 on 10 degrees of
  freedom: no evidence of an understated variance); draw 0 is a 1.9-sigma offset with n_m and
  2 n_m near 2 sigma at once, the tail its upper quantile (3.01x, 95 %) stands for, reached.

177 over four noise draws: act/pred 0.46-0.61 on all four (white 2.95-2.99x, batch means
1.56-2.04x, actual 1.37-1.80x): the white covariance's pessimism on this slow ramp is
systematic; the prediction takes the larger covariance on purpose (the batch-means one misses
the offset's and the slow warps' bias on the zoo's slow ramps, :mod:`hallcal.fit._table_error`).

Not fixed: counting the selected cogging orders' table change as possible bias (as
:func:`hallcal.fit.adequacy.motion_bias` does for unmodelled motion) would also inflate every
motor whose cogging is real (``cogload``); it needs its own measurement on the zoo.

Run: ``nice python benchmarks/bench_zoo_noise.py --motor 179 --draws 10 [--cogging none]
[--jobs 2] [--out benchmarks/bench_zoo_noise.txt]``.
"""

from __future__ import annotations

import argparse
import functools
import os

from bench_support import run_rows
from bench_zoo import CALIBRATED, _line, run_motor


def _draw(k: int, *, motor: int, cogging: str) -> dict:
    """Motor ``motor`` calibrated on noise draw k."""
    return {**run_motor(motor, noise=k, cogging=cogging), "k": k, "cog": cogging}


def _row(r: dict) -> str:
    return f"k={r['k']:<2d} cog={r['cog']:<5} {_line(r)}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--motor", type=int, default=179)
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--cogging", default="auto", choices=("auto", "none"))
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    lines = [
        f"bench_zoo_noise: zoo motor {args.motor}, calibration noise draws 0..{args.draws - 1} "
        f"(seed motor + 20000 k), cogging {args.cogging}; errors RMS about zero over the ORACLE "
        "floor",
        f"load average at start {os.getloadavg()[0]:.1f} (2 cores)",
        "",
    ]
    print("\n".join(lines), flush=True)
    run = functools.partial(_draw, motor=args.motor, cogging=args.cogging)
    rows = run_rows(run, list(range(args.draws)), args.jobs, _row, lines)
    used = [r for r in rows if r["status"] in ("ok", "warning")]
    ratios = sorted(r["star"] / r["pred"] for r in used)
    outside = [r["k"] for r in used if not CALIBRATED[0] <= r["star"] / r["pred"] <= CALIBRATED[1]]
    beyond = [r["k"] for r in used if r["star"] > r["upper"]]
    tail = [
        "",
        f"{len(used)} of {len(rows)} draws calibrated; act/pred "
        + ", ".join(f"{v:.2f}" for v in ratios),
        f"outside [{CALIBRATED[0]}, {CALIBRATED[1]}]: {outside}; f_star above its upper quantile: "
        f"{beyond}",
        f"load average at end {os.getloadavg()[0]:.1f}",
    ]
    print("\n".join(tail))
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write("\n".join(lines + tail) + "\n")


if __name__ == "__main__":
    main()
