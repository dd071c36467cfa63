"""The table's constant offset: its predicted sd (white, batch-means, HAC) against the actual one.

The predicted table error (:mod:`hallcal.fit._table_error`) takes cov(theta) as the larger of
the white ``sigma^2 (J^T J)^-1`` and the batch-means covariance. The table's constant offset is
the linear functional ``c^T theta``, ``c = mean_y0 d eta / d theta`` (the mean of
:func:`hallcal.fit.sem.angle_error_gradient` over the revolution). This measures its sd three
ways at the final fit: white ``c^T C_w c``, batch-means ``c^T C_b c``, and the HAC variance of
:func:`hallcal.fit.cogging_search.hac_variance` with the influence ``u_t = J_t A^-1 c`` (two
model simulations along ``A^-1 c``), as :func:`hallcal.fit.cogging_search.load_test` does for
a_0: ``sigma^2 c^T A^-1 c`` times the long-run / lag-0 ratio of ``sum_t u_t^T e_t``. Each is
compared with the table's actual offset (f_star's mean error on the validation run) as a
z-score; the question was whether the HAC sd brings the RMS of z near 1 where today's exceeds it.

Rows: zoo motors (``bench_zoo.run_motor``, oracle floor; ``179:0-9`` its calibration noise
draws), the paper bench with cogging 0.003 at 132 and a random torque disturbance 2e-3, plant
given (``bench_cogging.py``'s row), and the paper bench itself, over bench seeds. Columns (over
the floor): ``star`` f_star's RMS error about zero, ``off`` its mean (the table's offset);
the offset's sd: ``white``, ``batch`` (batch-means, when the run has enough batches), ``andr``
the HAC at Andrews' AR(1) bandwidth ``S``, ``hac`` the HAC at N / 12 the calibration uses
(:mod:`hallcal.fit.offset_variance`); ``z_now`` = off / max(white, batch), ``z_new`` = off /
max(white, batch, hac); ``pred0`` the predicted error without the HAC (``pred`` minus the
excess in quadrature), ``pred`` with it, ``a/p0`` and ``a/p`` star over each; then the HAC /
white sd ratio at fixed Bartlett bandwidths.

Run ``nice python benchmarks/bench_offset_hac.py [--zoo 179:0-9 183 ...] [--cogging 1-6]
[--paper 1-6]``; the output is committed beside it.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys

import numpy as np

import hallcal.pipeline as hp
import hallcal.pipeline.closed_loop as cl
from hallcal.fit._table_error import MIN_BATCHES
from hallcal.fit.gauss_newton import simulate_model
from hallcal.fit.long_run import INFLUENCE_STEP, _lagged_products, hac_variance
from hallcal.fit.offset_variance import offset_excess
from hallcal.fit.sem import angle_error_gradient

_CAP: dict = {}
#: Fixed Bartlett bandwidths [samples] at which the long-run / white sd ratio is printed.
SPAN = (30, 100, 300, 1000, 3000)
_build_lut = cl.build_lut


def _capturing_build_lut(*args, **kwargs):
    f = sys._getframe(1).f_locals
    if all(k in f for k in ("loop", "s", "fit")):
        _CAP.update(loop=f["loop"], r=f["s"].r, d=f["s"].d, sem=f["fit"].sem)
    return _build_lut(*args, **kwargs)


cl.build_lut = _capturing_build_lut


def offset_sds(step: float = INFLUENCE_STEP) -> dict:
    """Offset sd's [rad] at the captured final fit: white, batch, HAC with Andrews' bandwidth,
    HAC at N / 12 (the calibration's, :func:`hallcal.fit.offset_variance.offset_long_run`), the
    excess the calibration added, and the HAC / white sd ratio at the fixed bandwidths SPAN."""
    loop, r, d, sem = _CAP["loop"], _CAP["r"], _CAP["d"], _CAP["sem"]
    G = angle_error_gradient(sem.flux, loop.pole_pairs, projection=loop.projection,
                             offset=loop.offset)  # fmt: skip
    c = G.mean(axis=0)
    p = c.size
    out = {"white": math.sqrt(max(float(c @ sem.covariance @ c), 0.0)), "batch": math.nan}
    if sem.batch_covariance is not None and sem.batches >= MIN_BATCHES:
        Cb = np.asarray(sem.batch_covariance)[:p, :p]
        out["batch"] = math.sqrt(max(float(c @ Cb @ c), 0.0))
    hac = offset_excess(loop, r, d, sem)
    lr = hac.long_run
    out["excess"], out["hac"] = hac.excess, math.sqrt(lr.variance) if lr else math.nan
    cov, layout = sem.parameter_covariance, sem.layout
    v = cov[:, :p] @ c / sem.noise_variance  # A^-1 c
    wv = float(c @ cov[:p, :p] @ c)  # sigma^2 c^T A^-1 c
    x = layout.pack(sem.flux.theta, math.log(sem.gain) if layout.fit_gain else 0.0, sem.cogging,
                    sem.drift)  # fmt: skip
    h = step * math.sqrt(wv) / max(float(c @ v[:p]), 1e-300)
    u = (simulate_model(loop, layout, x + h * v, r).d
         - simulate_model(loop, layout, x - h * v, r).d) / (2.0 * h)  # fmt: skip
    e = np.asarray(d, dtype=np.float64) - sem.d_sim
    a = hac_variance(u, e, dof_used=layout.size)  # Andrews' AR(1) plug-in bandwidth
    out["andrews"], out["S"] = math.sqrt(wv * a.variance / a.white), a.bandwidth
    ee = e - e.mean(axis=0)
    lags = min(max(SPAN), len(e) // 12)
    gam = _lagged_products(ee, ee, lags)
    cu = _lagged_products(u, u, lags)
    ell = np.arange(-lags, lags + 1)
    w0 = float(np.einsum("hg,hg->", gam[lags], cu[lags]))
    out["span"] = [
        math.sqrt(max(float(np.einsum("l,lhg,lhg->", np.clip(1 - np.abs(ell) / S, 0, None), gam,
                                      cu)) / w0, 0.0))
        for S in SPAN
    ]  # fmt: skip
    return out


def zoo_row(seed: int, k: int) -> str:
    from bench_zoo import run_motor

    cap = {}
    calibrate = hp.calibrate

    def keep(*a, **kw):
        cap["cal"] = calibrate(*a, **kw)
        return cap["cal"]

    hp.calibrate = keep
    try:
        row = run_motor(seed, noise=k)
    finally:
        hp.calibrate = calibrate
    floor = cap["cal"].predicted_error / row["pred"]
    sd = _applied(offset_sds(), cap["cal"].adequacy)
    return _line(f"zoo {seed} k={k}", row["off"], row["star"], row["pred"], sd, floor,
                 row["status"])  # fmt: skip


def _applied(sd: dict, adequacy) -> dict:
    """The excess as the calibration applied it: none where the motion bias is predicted."""
    if adequacy is not None and (
        adequacy.motion_bias > 0 or not adequacy.ratio > adequacy.thresholds["warn_ratio"]
    ):
        sd["excess"] = 0.0
    sd["ratio"] = adequacy.ratio if adequacy is not None else math.nan
    return sd


def cogging_row(seed: int, *, amp: float = 0.003, td: float = 2e-3) -> str:
    import bench_cogging as bc

    import hallcal
    from hallcal.io import Dataset, setup_from_dict
    from hallcal.pipeline import simulate, validate
    from hallcal.pipeline.simulate import bench_config

    bc.SEED = seed
    order = 132
    sim = setup_from_dict(bc._setup(amp, order, td, plant=True))
    cfg = bench_config(sim)
    run = simulate(sim, experiment="ramp")
    val = simulate(sim, experiment="ramp", seed=seed + 100, ramp_end=12.0, duration=24.0)
    cal = hallcal.calibrate(run.columns(with_encoder=False), bc._setup(amp, order, td, plant=True))
    v = validate(cal.lut, Dataset.from_columns(val.columns(), path="validation"))
    floor = cfg.noise_floor
    name = f"cog132 Td s={seed}" if amp else f"paper s={seed}"
    sd = _applied(offset_sds(), cal.computed.adequacy)
    return _line(name, v.star.mean / floor, v.star.rms / floor, cal.predicted_error / floor, sd,
                 floor, cal.status.value)  # fmt: skip


def _line(name, off, star, pred, sd, floor, status) -> str:
    w, b, a, hc = (sd[k] / floor for k in ("white", "batch", "andrews", "hac"))
    now = max(w, b if math.isfinite(b) else 0.0)
    new = max(now, hc)
    before = math.sqrt(max(pred**2 - (sd["excess"] / floor) ** 2, 0.0))
    return (f"{name:>15} {status:>8} {star:6.3f} {off:+6.3f} | {w:5.3f} {b:5.3f} {a:5.3f} "
            f"{sd['S']:5.1f} {hc:5.3f} | {off / now:+6.2f} {off / new:+6.2f} | {before:6.3f} "
            f"{pred:6.3f} {star / before:5.2f} {star / pred:5.2f} {sd['ratio']:5.2f} | "
            + " ".join(f"{x:4.2f}" for x in sd["span"]))  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--zoo", nargs="*", default=[])  # "179:0-9" or "183"
    ap.add_argument("--cogging", default="")  # "1-6"
    ap.add_argument("--paper", default="")  # "1-6": the paper's bench (no cogging, no T_d)
    a = ap.parse_args()
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(), flush=True)
    print(f"{'case':>15} {'status':>8} {'star':>6} {'off':>6} | {'white':>5} {'batch':>5} "
          f"{'andr':>5} {'S':>5} {'hac':>5} | {'z_now':>6} {'z_new':>6} | {'pred0':>6} "
          f"{'pred':>6} {'a/p0':>5} {'a/p':>5} {'cost':>5} | HAC/white sd at S = "
          + " ".join(str(S) for S in SPAN))  # fmt: skip
    for spec in a.zoo:
        seed, _, ks = spec.partition(":")
        lo, _, hi = (ks or "0").partition("-")
        for k in range(int(lo), int(hi or lo) + 1):
            print(zoo_row(int(seed), k), flush=True)
    if a.cogging:
        lo, _, hi = a.cogging.partition("-")
        for s in range(int(lo), int(hi or lo) + 1):
            print(cogging_row(s), flush=True)
    if a.paper:
        lo, _, hi = a.paper.partition("-")
        for s in range(int(lo), int(hi or lo) + 1):
            print(cogging_row(s, amp=0.0, td=0.0), flush=True)
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(), flush=True)


if __name__ == "__main__":
    main()
