"""Cogging identified jointly with the flux: the acceptance table, end to end.

Paper bench (11 pole pairs, ramp 0 -> 13 rad in 26 s, noise variance 7.5e-6) with a cogging
torque ``A sin(k y0)`` at the plant input (plant input units), alone and with a random torque
disturbance on top (std 2e-3, 5 Hz low-pass), calibrated through :func:`hallcal.calibrate` with
``[model] cogging = "auto"`` and ``harmonics = "auto"``, once with the plant given (``[plant]``)
and once with the plant from a closed-loop BLA experiment (no ``[plant]``; the gain is refined
jointly). Each calibration is validated on a fresh run (other noise seed, ramp 0 -> 12 rad in
24 s) against the bench's true angle. Then the bench without cogging, "auto" against "none", and
a trapezoidal flux with cogging, "auto" against "none" (unmodelled, the cogging motion leaks into
the flux harmonics at its sidebands: the case where the predicted error must include the bias).

Columns: f_star's RMS error about zero / noise floor (the table's constant offset included, as
``validate`` measures it since it measures about zero; before that the file showed the RMS about
the mean); the offset (f_star's mean error) / noise floor, so that (f*/floor)^2 = 1 + offset^2
when the rest is at the floor; the identified orders; the amplitude error and the phase error of
the bench's order; the predicted f_star error over the actual one; the status; the wall time and
the CPU time of the calibration (BLA identification included; the CPU time is the work, the wall
time also the machine's load).

Run: ``python benchmarks/bench_cogging.py``; the output is committed beside it.
"""

from __future__ import annotations

import math
import subprocess
import time

import hallcal
from hallcal.io import Dataset, setup_from_dict
from hallcal.io.setup import default_setup
from hallcal.pipeline import simulate, validate
from hallcal.pipeline.simulate import bench_config

SEED = 21


def _setup(
    amp: float, order: int, disturbance: float, *, plant: bool, cogging="auto", extra=None
) -> dict:
    s = default_setup().to_dict()
    s["model"]["harmonics"] = "auto"
    s["model"]["cogging"] = cogging
    s["bench"].update(seed=SEED, cogging=amp, cogging_periods=order, torque_disturbance=disturbance)
    s["bench"].update(extra or {})
    if not plant:
        s.pop("plant")
    return s


def _case(
    amp: float, order: int, disturbance: float, *, plant: bool, cogging="auto", extra=None
) -> str:
    sim = setup_from_dict(_setup(amp, order, disturbance, plant=True, extra=extra))
    cfg = bench_config(sim)
    run = simulate(sim, experiment="ramp")
    val = simulate(sim, experiment="ramp", seed=SEED + 100, ramp_end=12.0, duration=24.0)
    bla = None if plant else simulate(sim, experiment="multisine").columns(with_encoder=False)
    setup = _setup(amp, order, disturbance, plant=plant, cogging=cogging, extra=extra)
    t0, c0 = time.perf_counter(), time.process_time()
    cal = hallcal.calibrate(run.columns(with_encoder=False), setup, bla_data=bla)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    v = validate(cal.lut, Dataset.from_columns(val.columns(), path="validation"))
    floor = cfg.noise_floor
    orders = cal.cogging.orders if cal.cogging is not None else ()
    amp_err = phase_err = "-"
    if cal.cogging is not None and order in orders:
        i = orders.index(order)
        amp_err = f"{100 * (cal.cogging.amplitude[i] / amp - 1):+.2f}%"
        phase_err = f"{math.degrees(cal.cogging.phase[i]) - 90.0:+.2f}"  # truth: sin = 90 deg
    return (
        f"{amp:>7g} {order:>4d} {disturbance:>6g} {'plant' if plant else 'BLA':>6} "
        f"{cogging if isinstance(cogging, str) else str(cogging):>6} "
        f"{v.star.rms / floor:>8.3f} {v.star.mean / floor:>+7.3f} "
        f"{str(list(orders)):>8} {amp_err:>9} {phase_err:>8} "
        f"{cal.predicted_error / v.star.rms:>10.3f} {cal.status.value:>8} {wall:>7.1f} {cpu:>6.1f}"
    )


def _uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def main() -> None:
    print(f"uptime: {_uptime()}")
    print(
        f"{'A':>7} {'k':>4} {'T_d':>6} {'plant':>6} {'cog':>6} {'f*/floor':>8} {'offset':>7} "
        f"{'orders':>8} "
        f"{'A err':>9} {'phase':>8} {'pred/act':>10} {'status':>8} {'time s':>7} {'cpu s':>6}"
    )
    for plant in (True, False):
        for amp, order in ((0.003, 132), (0.008, 66)):
            for disturbance in (0.0, 2e-3):
                print(_case(amp, order, disturbance, plant=plant), flush=True)
    for cogging in ("auto", "none"):
        print(_case(0.0, 66, 0.0, plant=True, cogging=cogging), flush=True)
    print(
        "trapezoidal flux (3rd electrical harmonic 10 %, 5th 4 %) with cogging 0.01 at 66/rev: "
        "unmodelled, the motion leaks into flux sidebands"
    )
    trapezoid = {"electrical_harmonics": [[3, 0.1], [5, 0.04]]}
    for cogging in ("auto", "none"):
        print(_case(0.01, 66, 0.0, plant=True, cogging=cogging, extra=trapezoid), flush=True)
    print(f"uptime: {_uptime()}")


if __name__ == "__main__":
    main()
