"""The isolated sensor against the others, and the least-squares sizes' intervals
(:mod:`imufdi_cli.episodes.reference`): the calibrated bias, autocorrelated noise, the
healthy sensors' dispersion and the motion-dependent errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.episodes import Reference, fit_models, leave_one_out
from imufdi_cli.episodes.reference import _autocorrelation_factor
from tests.episodes.helpers import RATE, SIGMA, coverage_band, trace


def test_leave_one_out_on_a_co_aligned_array_is_the_mean_of_the_others() -> None:
    n = 6
    H = np.tile(np.eye(3), (2, 1))
    rng = np.random.default_rng(0)
    m = rng.normal(size=(50, n))
    residual, prediction, consensus = leave_one_out(H, m, 0.2, 1)
    # sensor 1 is the y axis of the first triad; the only other y sensor is sensor 4
    assert_allclose(prediction, m[:, 4])
    assert_allclose(residual, m[:, 1] - m[:, 4])
    assert consensus == pytest.approx(0.2)
    H16 = np.tile(np.eye(3), (16, 1))
    _, _, consensus16 = leave_one_out(H16, rng.normal(size=(5, 48)), 0.3, 0)
    assert consensus16 == pytest.approx(0.3 / math.sqrt(15))


@pytest.mark.slow
@pytest.mark.parametrize("model", ["step", "drift"])
def test_the_calibrated_bias_error_is_propagated_into_step_and_drift_intervals(
    model: str,
) -> None:
    """The calibrated bias taken out of the residual is itself estimated (from n_cal
    samples): its error is a constant offset c ~ N(0, var0 / n_cal) over the window. With
    n_cal = 200 against 250 fault samples it dominates the step's error and biases a drift
    fitted through the origin; the intervals must still cover 90 %."""
    rng = np.random.default_rng(11)
    size = {"step": np.deg2rad(0.9), "drift": np.deg2rad(10)}[model]
    trials, n_cal, covered, right = 300, 200, 0, 0
    for _ in range(trials):
        r, o, t, c = trace(model, size, rng)
        var0 = SIGMA**2 + c**2
        r = r + rng.normal(0, math.sqrt(var0 / n_cal))
        best = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250), offset_var=var0 / n_cal)[0]
        right += best.model == model
        covered += best.model == model and best.low <= size <= best.high
    assert right / trials >= 0.97
    low, high = coverage_band(right)
    assert low <= covered / right <= high


@pytest.mark.slow
def test_step_interval_covers_under_autocorrelated_noise() -> None:
    """AR(1) noise with phi = 0.5 has a long-run variance 3x its variance: a white-noise
    interval on the mean would cover only about 67 %; the Newey-West factor restores 90 %
    (up to its small-sample bias, allowed for in the lower band)."""
    rng = np.random.default_rng(12)
    phi, size, trials, covered, right = 0.5, np.deg2rad(0.9), 300, 0, 0
    for _ in range(trials):
        r, o, t, c = trace("step", size, rng, length=1200, onset=400)
        innovations = rng.normal(0, SIGMA * math.sqrt(1 - phi**2), r.size)
        ar = np.zeros(r.size)
        ar[0] = rng.normal(0, SIGMA)
        for i in range(1, r.size):
            ar[i] = phi * ar[i - 1] + innovations[i]
        r = r + ar  # coloured noise on top of the white
        var_white = 2 * SIGMA**2 + c**2
        best = fit_models(r, o, t, math.sqrt(var_white - c**2), c, onset_range=(200, 600))[0]
        right += best.model == "step"
        covered += best.model == "step" and best.low <= size <= best.high
    assert right / trials >= 0.97
    low, high = coverage_band(right)
    assert low - 0.03 <= covered / right <= high


def test_autocorrelation_factor_is_one_for_white_noise_and_the_long_run_ratio_for_ar1() -> None:
    rng = np.random.default_rng(13)
    w = np.full(20_000, 1 / 20_000)
    white = rng.normal(size=20_000)
    # sampling error about 2 sqrt(L / 3 n) = 0.03 with L = 10
    assert _autocorrelation_factor(white, w) == pytest.approx(1.0, abs=0.1)
    phi = 0.3
    ar = np.zeros(20_000)
    for i in range(1, ar.size):
        ar[i] = phi * ar[i - 1] + white[i]
    # long-run / marginal variance (1 + phi) / (1 - phi) = 1.857; the Bartlett taper at
    # L = 10 lags takes off about sum_k (k / 11) 2 phi^k = 0.09
    assert _autocorrelation_factor(ar, w) == pytest.approx(1.857 - 0.09, abs=0.15)


def _reference(rng: np.random.Generator, length: int, m: int, var: float, extra_sd: float):
    """m healthy residuals: white noise plus a random constant per sensor (bias wander the
    white-noise model does not know about) of standard deviation ``extra_sd``."""
    residuals = rng.normal(0, math.sqrt(var), (length, m)) + rng.normal(0, extra_sd, m)
    return Reference(residuals, np.full(m, var), np.zeros(m))


@pytest.mark.slow  # 600 Monte Carlo fits with and without the reference, 3 s
def test_healthy_sensors_widen_the_interval_only_when_they_spread_beyond_the_noise() -> None:
    """The same sensor-to-sensor bias spread is added to the faulty sensor's residual: the
    dispersion test must see it in the 47 others and widen the interval to keep 90 %
    coverage; with white healthy sensors it widens only at the test's 5 % level."""
    rng = np.random.default_rng(14)
    size, trials, m = np.deg2rad(0.9), 300, 47
    for extra_sd, expect_widened in ((0.0, False), (3 * SIGMA / math.sqrt(250), True)):
        covered = widened = right = 0
        for _ in range(trials):
            r, o, t, c = trace("step", size, rng)
            r = r + rng.normal(0, extra_sd)
            reference = _reference(rng, r.size, m, SIGMA**2 + c**2, extra_sd)
            fits = fit_models(r, o, t, SIGMA, c, onset_range=(50, 250), reference=reference)
            if fits[0].model != "step":
                continue
            right += 1
            plain = next(
                f for f in fit_models(r, o, t, SIGMA, c, onset_range=(50, 250)) if f.model == "step"
            )
            covered += fits[0].low <= size <= fits[0].high
            widened += fits[0].high - fits[0].low > plain.high - plain.low + 1e-15
        assert right / trials >= 0.97
        low, high = coverage_band(right)
        assert low <= covered / right <= high
        if expect_widened:
            assert widened / right >= 0.95
        else:  # binomial: 5 % of the trials, 3.5 sd above
            assert widened / right <= 0.05 + 3.5 * math.sqrt(0.05 * 0.95 / right)


@pytest.mark.slow
def test_motion_errors_are_fitted_out_of_step_intervals() -> None:
    """A step of 0.9 deg/s on a sensor whose residual carries c^T omega(t) (its scale and
    misalignment errors under a 3-axis swing, c ~ N(0, 1e-3) per axis, tens of deg/s of
    motion: errors of several SIGMA), as do the 5 healthy sensors with their own c.
    Without the motion columns the healthy sensors' spread widens the interval by a
    quasi-likelihood factor that is wrong for this sensor; with them every motion error
    drops out and the interval covers 90 % (binomial band)."""
    rng = np.random.default_rng(25)
    size, trials, covered, right, length, onset = np.deg2rad(0.9), 200, 0, 0, 600, 200
    t = np.arange(length) / RATE
    for _ in range(trials):
        phase = rng.uniform(0, 2 * np.pi, 3)
        omega = np.deg2rad([60, 40, 50]) * np.sin(
            2 * np.pi * np.array([0.5, 0.35, 0.25]) * t[:, None] + phase
        )
        c = SIGMA / math.sqrt(5)
        motion = omega + rng.normal(0, c, omega.shape)
        r = rng.normal(0, math.hypot(SIGMA, c), length) + omega @ rng.normal(0, 1e-3, 3)
        r[onset:] += size
        healthy = rng.normal(0, math.hypot(SIGMA, c), (length, 5))
        healthy += omega @ rng.normal(0, 1e-3, (3, 5))
        variance = np.full(5, SIGMA**2 + c**2)
        reference = Reference(healthy, variance, np.zeros(5), motion)
        best = fit_models(
            r, np.zeros(length), t, SIGMA, c, onset_range=(50, 350), reference=reference
        )[0]
        right += best.model == "step"
        covered += best.model == "step" and best.low <= size <= best.high
    assert right / trials >= 0.97
    low, high = coverage_band(right)
    assert low <= covered / right <= high


def test_correlation_of_the_leave_two_out_residuals_of_co_aligned_triads() -> None:
    """16 co-aligned triads, sensor 0 (an x gyro) isolated: the 15 other x residuals, each
    against the mean of the 14 x gyros other than itself and sensor 0, correlate with -1/14;
    the 16 y (and z) residuals, each against the mean of the other 15, with -1/15. So
    tr R^2 = 15 + 15 * 14 / 14^2 + 2 (16 + 16 * 15 / 15^2) = 50.21 and the Satterthwaite
    dof m^2 / tr R^2 = 44 = 47 - 3, the rank of the residuals."""
    from imufdi_cli.episodes.reference import correlation_sq, leave_two_out

    H = np.tile(np.eye(3), (16, 1))
    found = leave_two_out(H, np.full(48, SIGMA), 0, None, None)
    assert found is not None
    A = found[0]
    expected = 15 + 15 * 14 / 14**2 + 2 * (16 + 16 * 15 / 15**2)
    assert correlation_sq(A, np.full(48, SIGMA)) == pytest.approx(expected, rel=1e-12)
    assert 47**2 / expected == pytest.approx(44.0, abs=1e-3)
    # uncorrelated residuals: tr R^2 = m
    assert correlation_sq(np.eye(5), np.full(5, 2.0)) == pytest.approx(5.0)


def test_successive_variance_is_von_neumanns_estimate() -> None:
    from imufdi_cli.episodes.reference import Reference, successive_variance

    x = np.array([[0.0, 1.0], [1.0, 1.0], [3.0, 1.0]])
    # differences (1, 2) and (0, 0): (1 + 4) / (2 * 2)
    assert_allclose(successive_variance(x), [1.25, 0.0])
    assert_allclose(Reference(x, np.ones(2), np.zeros(2)).white_variance, [1.25, 0.0])


@pytest.mark.slow  # 1500 windows of 48 gyros and 300 calibrations, about 4 s
def test_the_healthy_sensors_test_holds_its_level_with_outliers_and_calibrated_sigmas() -> None:
    """paper-table4's noise: 16 co-aligned triads, white sigma 0.15 deg/s and outliers of
    +-1 deg/s on 0.1 % of the samples (4.4 % of the variance), sigmas calibrated from 200
    samples (residual_sigma leaves the outliers out), the reference residuals of a builder,
    no fault anywhere. The healthy sensors' test must widen a step's interval in 5 % of the
    windows (its level): 1500 windows, Binomial(1500, 0.05), 3.5 sd allowed. Against the
    calibrated sigmas and chi-square(47) it widened 9-10 % (diagnostic episodes of seeds
    100-159: 9.5 %)."""
    from imufdi_cli.episodes import EpisodeBuilder
    from imufdi_cli.episodes.reference import _dispersion
    from imufdi_cli.maths.parity import residual_sigma

    rng = np.random.default_rng(31)
    H = np.tile(np.eye(3), (16, 1))
    truth = np.deg2rad([10.0, 10.0, 10.0]) @ H.T

    def noise(rows: int) -> np.ndarray:
        out = rng.normal(0, SIGMA, (rows, 48))
        hit = rng.random((rows, 48)) < 0.001
        out[hit] += np.deg2rad(1.0) * rng.choice([-1.0, 1.0], int(hit.sum()))
        return truth + out

    trials, widened, length, n = 1500, 0, 400, 250
    w = np.full(n, 1 / n)  # a step's estimate over the last n samples
    for trial in range(trials):
        if trial % 5 == 0:  # a new calibration every 5 windows (its errors count)
            cal = noise(200)
            builder = EpisodeBuilder(
                "x",
                "gyro",
                H,
                [str(i) for i in range(48)],
                residual_sigma(H, cal),
                RATE,
                calibration_mean=cal.mean(axis=0),
                calibration_samples=200,
            )
        k = int(rng.integers(48))
        reference = builder._reference(k, noise(length))
        assert reference is not None
        _, wide = _dispersion(w, reference, SIGMA**2, 1 / 200, 0.9)
        widened += wide is not None
    assert abs(widened / trials - 0.05) <= 3.5 * math.sqrt(0.05 * 0.95 / trials)


@pytest.mark.slow  # 1000 Monte Carlo fits with the motion columns, about 7 s
def test_step_interval_with_five_healthy_sensors_and_a_motion_inflated_calibration() -> None:
    """conical6's case: 6 single-axis gyros, so 5 healthy residuals that span only 2
    dimensions (the healthy sensors' Q has d = m^2 / tr R^2, about 2 degrees of freedom),
    motion errors in every residual (fitted out by the motion columns), and a calibrated
    sigma that holds the motion errors of a calibration window spanning the start of the
    motion: its variance is 1.87 times the white one here (conical6's calibration
    windows, seeds 100-129: 1.56 on average, 0.99-2.30). The calibrated offset is the
    calibration mean of the residual; once M (relative to its calibration mean) holds the
    motion errors, what is left of its error is the mean of n_cal white samples, white /
    n_cal, not level / n_cal (with which the interval covered 96.3 % here, and 94.6 % of
    352 diagnostic conical6 steps). The interval must cover 90 % (binomial band, 3.5 sd:
    0.867-0.933 on 1000 trials)."""
    from imufdi_cli.episodes.reference import correlation_sq

    rng = np.random.default_rng(41)
    size, length, onset, n_cal, m, trials = np.deg2rad(0.9), 600, 200, 200, 5, 1000
    t = np.arange(length) / RATE
    white = SIGMA**2 * (1 + 1 / 3)  # the sensor and a consensus of three others
    level = 1.87 * white
    basis = rng.normal(size=(2, m))
    basis /= np.linalg.norm(basis, axis=0)  # each healthy residual has the white variance
    tr_r2 = correlation_sq(basis, np.ones(2))
    assert 1.5 <= m * m / tr_r2 <= 2.0  # about 2 degrees of freedom, as on conical6
    frequencies = np.array([0.5, 0.35, 0.25])
    covered = right = 0
    for _ in range(trials):
        phase = rng.uniform(0, 2 * np.pi, 3)
        omega = np.deg2rad([60, 40, 50]) * np.sin(2 * np.pi * frequencies * t[:, None] + phase)
        motion = omega + rng.normal(0, SIGMA / 2, omega.shape)
        r = rng.normal(0, math.sqrt(white), length) + omega @ rng.normal(0, 1e-3, 3)
        r += rng.normal(0, math.sqrt(white / n_cal))  # the calibrated offset's error
        r[onset:] += size
        healthy = rng.normal(0, math.sqrt(white), (length, 2)) @ basis
        healthy += rng.normal(0, math.sqrt(white / n_cal), 2) @ basis
        healthy += omega @ rng.normal(0, 1e-3, (3, m))
        reference = Reference(healthy, np.full(m, level), np.full(m, level / n_cal), motion, tr_r2)
        best = fit_models(
            r,
            np.zeros(length),
            t,
            math.sqrt(0.75 * level),
            math.sqrt(0.25 * level),
            onset_range=(50, 350),
            offset_var=level / n_cal,
            reference=reference,
        )[0]
        right += best.model == "step"
        covered += best.model == "step" and best.low <= size <= best.high
    assert right / trials >= 0.97
    low, high = coverage_band(right)
    assert low <= covered / right <= high
