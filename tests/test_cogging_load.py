"""Order 0 (a constant load torque): the HAC variance of a_0 (:mod:`hallcal.fit.cogging_search`,
"A constant load torque").

Under an integrating controller a load shows only in the start transient, so a_0's influence
``J_t v`` sits in a short stretch of the run. At the fit the residual there is orthogonal to it,
so the batch-means variance (and a HAC of the fitted scores themselves) understates a_0's; the
HAC variance of :func:`hac_variance` takes the residual's autocovariance from the whole run.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from hallcal.fit.cogging_search import load_test
from hallcal.fit.long_run import hac_variance
from hallcal.fit.sem import solve_sem
from hallcal.io import ModelSpec, Setup
from hallcal.pipeline.plant import closed_loop
from hallcal.sensor.flux import FourierBasis
from hallcal.sim.bench import BenchConfig, ramp_run

CHI2_1_AT_1PCT = 6.635


def _false_alarms(rho: float, draws: int, seed: int) -> tuple[float, float, float]:
    """A regression whose first parameter's regressor decays in 200 of 25 600 samples (all in
    the first of 25 batches), no effect in truth, AR(1) noise: the share of draws whose T^2
    passes chi-square(1) at 1 % with the batch-means, the white and the HAC variance."""
    rng = np.random.default_rng(seed)
    n = 25 * 1024
    t = np.arange(n)
    X = np.column_stack([np.exp(-t / 200) * np.cos(t / 40), np.ones(n), np.exp(-t / 600),
                         np.sin(6 * np.pi * t / n)])  # fmt: skip
    Ai = np.linalg.inv(X.T @ X)
    u = X @ Ai[:, 0]  # the influence of the first parameter
    batch = white = hac = 0
    for _ in range(draws):
        e = lfilter([1.0], [1.0, -rho], rng.standard_normal(n))
        b = Ai @ (X.T @ e)
        res = e - X @ b
        s = (u * res).reshape(25, -1).sum(axis=1)
        batch += b[0] ** 2 / (25 / 24 * np.sum((s - s.mean()) ** 2)) > CHI2_1_AT_1PCT
        white += b[0] ** 2 / (res @ res / (n - 4) * Ai[0, 0]) > CHI2_1_AT_1PCT
        hac += b[0] ** 2 / hac_variance(u, res, dof_used=4).variance > CHI2_1_AT_1PCT
    return batch / draws, white / draws, hac / draws


@pytest.mark.parametrize("rho", [0.0, 0.8])
def test_a_localized_influence_keeps_the_tests_level(rho):
    batch, white, hac = _false_alarms(rho, draws=150, seed=7)
    # measured on 300 draws: batch-means 0.95 (white noise) and 0.95 (AR 0.8); white 0.013 and
    # 0.36; HAC 0.013 and 0.010 (0.027 and 0.013 on these 150). Binomial sd about 0.01 at a
    # 1 % rate, hence 0.04
    assert batch > 0.5
    assert hac < 0.04
    if rho:
        assert white > 0.2  # the white variance misses the residual's correlation


def test_hac_variance_of_white_and_ar1_residuals():
    rng = np.random.default_rng(3)
    n = 20_000
    u = np.ones(n)
    lr = hac_variance(u, rng.standard_normal(n))
    # white: the lag-0 term, bandwidth near 1; within 3 % (sd of the estimate about 1 %)
    assert lr.variance == pytest.approx(n, rel=0.03) and lr.bandwidth < 3
    rho = 0.6
    e = lfilter([1.0], [1.0, -rho], rng.standard_normal(n))
    # long-run variance n / (1 - rho)^2; the Bartlett kernel at Andrews' bandwidth is biased
    # low by O(1 / S) (measured 0.9x here), hence 20 %
    assert hac_variance(u, e).variance == pytest.approx(n / (1 - rho) ** 2, rel=0.2)


def test_a0_hac_variance_is_the_white_one_on_a_white_noise_run():
    """The paper's bench (a controller without integrator) with a load of 0.003: the HAC
    variance of a_0 is near the white one and the load passes."""
    cfg = BenchConfig(cogging_terms=((0, 0.003, 0.0),))
    run = ramp_run(cfg, ramp_end=3.5, duration=7.0, seed=1)
    setup = Setup(pole_pairs=cfg.pole_pairs, sample_time=cfg.sample_time,
                  controller=cfg.controller, plant=cfg.plant, model=ModelSpec())  # fmt: skip
    loop = closed_loop(setup, cfg.plant)
    sem = solve_sem(loop, run.r, run.d, FourierBasis(tuple(range(1, 12))), y=run.y, cogging=(0,))
    result = load_test(loop, run.r, run.d, sem, alpha=1e-3)
    test, lr = result.test, result.long_run
    j = sem.layout.cogging_start
    white = float(sem.parameter_covariance[j, j])
    assert lr.white == white  # the HAC's ratio to the lag-0 term scales the white variance
    # the residual's lag-1 autocorrelation is 0.03-0.05 per channel here: HAC / white measured
    # 1.25, 1.39, 1.41 on seeds 1-3 (bandwidth 6-7 samples); the batch-means variance is
    # 160-220x the white one on these runs
    assert white < lr.variance < 1.6 * white
    # within 4 of its HAC standard deviations (measured 0.00276, 2.4 sd, on this short run)
    assert test.significant and test.amplitude == pytest.approx(0.003, abs=4 * lr.variance**0.5)
