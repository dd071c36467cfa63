"""SEM (problem/state_eq) and the table (f_final) on the virtual bench: the acceptance bounds.

Each case calibrates on one run and validates on a fresh run (other noise realization, other
ramp) against the bench's true angle. The bound "within 10% of the noise floor" is the acceptance;
the noise floor is sigma sqrt(2/3) / (A n_m) (docs/design.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from hallcal.fit.sem import predicted_angle_error, solve_sem
from hallcal.sensor.flux import FluxModel, FourierBasis, sinusoidal_theta
from hallcal.sensor.lut import LUT, NotBijectiveError, StarReconstructor, build_lut
from hallcal.sensor.metrics import angle_error, spatial_spectrum
from hallcal.sim.bench import BenchConfig, ramp_run

CASES = {
    "paper": (BenchConfig(seed=21), tuple(range(1, 12))),
    "7pp-3rd-harmonic": (
        BenchConfig(
            pole_pairs=7,
            electrical_harmonics=((3, 0.08),),
            misalignment_deg=(0.0, 3.0, 0.0),
            noise_variance=2e-5,
            seed=22,
        ),
        tuple(range(1, 22)),
    ),
}


@pytest.fixture(scope="module", params=list(CASES))
def calibrated(request):
    cfg, harmonics = CASES[request.param]
    run = ramp_run(cfg)
    val = ramp_run(cfg, ramp_end=12.0, duration=24.0, seed=cfg.seed + 100)
    res = solve_sem(cfg.loop(), run.r, run.d, FourierBasis(harmonics), y=run.y)
    lut = build_lut(res.flux, cfg.pole_pairs)
    return cfg, run, val, res, lut


def test_reaches_noise_floor_on_fresh_run(calibrated):
    cfg, run, val, res, lut = calibrated
    assert res.status == "converged"
    assert lut.bijective
    e_init = angle_error(lut.f_init(val.d), val.y0)
    e_star = angle_error(lut.f_star(val.d), val.y0)
    assert e_init.rms > 5 * cfg.noise_floor  # there was something to calibrate
    assert e_star.rms < 1.10 * cfg.noise_floor


def test_final_cost_is_at_noise_level(calibrated):
    """J(theta*) ~ 3 N sigma^2: the relative std of a chi-square with 3N dof is sqrt(2/(3N))
    (0.4% here); 3% leaves room for the p fitted parameters and the start transient."""
    cfg, run, _, res, _ = calibrated
    expected = 3 * run.n_samples * cfg.noise_variance
    assert res.cost == pytest.approx(expected, rel=0.03)
    assert res.noise_variance == pytest.approx(cfg.noise_variance, rel=0.03)
    assert np.all(np.diff(res.cost_history) <= 0)  # LM only accepts descending steps


def test_parameter_errors_match_covariance(calibrated):
    """theta* - theta_true is consistent with sigma^2 (J^T J)^-1: the mean squared standardized
    error of p parameters is chi-square / p, whose std is sqrt(2/p) (~0.17 for p = 69); [0.3, 3]
    is a wide but sharp band (a wrong covariance is typically off by orders of magnitude)."""
    cfg, run, _, res, _ = calibrated
    truth = run.truth
    # express the truth in the model's basis (same harmonic set up to the constant term)
    y = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    th_true = np.linalg.lstsq(res.flux.basis.evaluate(y), truth(y), rcond=None)[0].T
    err = (res.flux.theta - th_true).ravel()
    sd = np.sqrt(np.diag(res.covariance))
    z2 = np.mean((err / sd) ** 2)
    assert 0.3 < z2 < 3.0


def test_predicted_error_matches_validation(calibrated):
    """The covariance predicts the table's residual error: total f_star error^2 ~ floor^2 +
    mean var(eta); checked within 10% like the acceptance bound."""
    cfg, _, val, res, lut = calibrated
    sd = predicted_angle_error(
        res.flux, res.covariance, cfg.pole_pairs, projection=lut.projection, offset=lut.offset
    )
    predicted = np.sqrt(cfg.noise_floor**2 + np.mean(sd**2))
    observed = angle_error(lut.f_star(val.d), val.y0).rms
    assert observed == pytest.approx(predicted, rel=0.10)


def test_streaming_f_star_equals_whole_array(calibrated):
    *_, val, _, lut = calibrated
    rec = StarReconstructor(lut)
    n = 3000
    stream = np.array([rec.update(*row) for row in val.d[:n]])
    np.testing.assert_allclose(stream, lut.f_star(val.d[:n]), atol=1e-12)


def test_spectrum_shows_ripple_removed(calibrated):
    cfg, _, val, _, lut = calibrated
    s_init = spatial_spectrum(lut.f_init(val.d) - val.y0, val.y0)
    s_star = spatial_spectrum(lut.f_star(val.d) - val.y0, val.y0)
    # the dominant ripple line of f_init is gone (down to the white-noise level per line)
    k = int(np.argmax(s_init.power))
    assert s_star.power[k] < 0.01 * s_init.power[k]
    # Parseval: the cumulative PSD ends at the error variance (whole revolutions only, so
    # the two differ by the sampling of the segment: 10%)
    e = lut.f_star(val.d) - val.y0
    assert s_star.cumulative[-1] == pytest.approx(np.var(e), rel=0.10)


def test_non_bijective_table_refuses_to_correct():
    """A model whose flux folds back (huge 2nd electrical harmonic) gives no table."""
    basis = FourierBasis((11, 22))
    th = sinusoidal_theta(basis, 11)
    js, jc = basis.index(22)
    th[0, jc] = 1.5  # sensor 1 dominated by the 2nd electrical harmonic
    lut = build_lut(FluxModel(basis, th), 11)
    assert not lut.bijective and lut.min_slope <= 0
    with pytest.raises(NotBijectiveError):
        lut.f_star(np.ones((3, 3)))
    with pytest.raises(NotBijectiveError):
        StarReconstructor(lut)
    again = LUT.from_arrays(11, lut.projection, lut.offset, lut.y_hat, lut.eta)
    assert not again.bijective


def test_table_resolution_is_far_below_noise_floor():
    """4096 points: interpolation error of the table < 1% of the paper's noise floor."""
    cfg = BenchConfig(seed=4)
    truth = cfg.truth()
    fine = build_lut(truth, 11, points=1 << 16)
    lut = build_lut(truth, 11)
    y = np.linspace(0, 2 * np.pi, 100_003)
    diff = lut.correction(y) - fine.correction(y)
    assert np.max(np.abs(diff)) < 0.01 * cfg.noise_floor


def test_covariance_source_is_checked():
    """A misspelled source of the covariance is an error, not a silent default."""
    with pytest.raises(ValueError, match="covariance must be one of"):
        solve_sem(None, np.zeros(4), np.zeros((4, 3)), FourierBasis((1,)), covariance="exactly")
