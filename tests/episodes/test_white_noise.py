"""White noise from successive differences and the spread of its calibration estimate
(:mod:`imufdi_cli.episodes.white_noise`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from tests.episodes.helpers import SIGMA, slow_error


def test_white_sigma_leaves_out_slow_errors_the_level_sigma_carries() -> None:
    """Four co-aligned triads with white noise SIGMA and a slow error of 1.5 SIGMA on each
    sensor: the parity-residual sigma is inflated (about sqrt(1 + 1.5^2 / 2) = 1.46 x),
    on average; the successive-difference sigma is not. Its relative error is about
    sqrt(3 / (4 N (n - 3) / n)) = 1.6 % for N = 4000 (per sensor); 5 of those allowed,
    plus the 0.3 % the slow error still adds to the differences."""
    from imufdi_cli.episodes import white_sigma
    from imufdi_cli.maths.parity import residual_sigma

    rng = np.random.default_rng(21)
    H = np.tile(np.eye(3), (4, 1))
    length = 4000
    m = rng.normal(0, SIGMA, (length, 12))
    m += np.stack([slow_error(length, rng, 1.5 * SIGMA) for _ in range(12)], axis=1)
    assert float(np.mean(residual_sigma(H, m))) > 1.3 * SIGMA
    assert_allclose(white_sigma(H, m), SIGMA, rtol=5 * 0.016 + 0.003)


def test_successive_difference_dof_matches_the_moments_of_white_noise() -> None:
    """q = sum(diff(e)^2) / 2 over n white samples: E q = (n - 1), Var q = 3 n - 4
    (sigma = 1), hence nu = 2 (n - 1)^2 / (3 n - 4); checked by simulation within 4
    standard errors of the sample variance."""
    from imufdi_cli.episodes import successive_difference_dof

    n, trials = 50, 20_000
    e = np.random.default_rng(22).normal(size=(trials, n))
    q = np.sum(np.diff(e, axis=1) ** 2, axis=1) / 2
    assert q.mean() == pytest.approx(n - 1, abs=4 * math.sqrt((3 * n - 4) / trials))
    var = q.var(ddof=1)
    assert var == pytest.approx(3 * n - 4, rel=4 * math.sqrt(2 / (trials - 1)) * 1.2)
    assert successive_difference_dof(n) == pytest.approx(2 * (n - 1) ** 2 / (3 * n - 4))


@pytest.fixture(scope="module")
def white_variance_draws() -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, float]:
    """:func:`_white_variance_draws` of seed 31, read by the two tests below (each checks a
    different function against the same 800 draws; both held on each of seeds 0-19 with
    the draws shared, and these 800 calibrations are about 0.85 s of CPU)."""
    return _white_variance_draws(31)


# The two tests reading these 800 draws (about 0.85 s of CPU) are Monte Carlos with bands
# derived from the draws (docs/testing.md rule 1): under slow. The
# functions they check keep default tests in test_variance_drop.py, whose builder
# computes white_sigma_covariance, white_sigma_spread and white_variance_dof for every
# sensor and tests each against the quantile of its own calibration dof.
@pytest.mark.slow
def test_white_sigma_covariance_matches_the_spread_of_white_sigma(
    white_variance_draws: tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, float],
) -> None:
    """Six co-aligned triads with different white sigmas, 200 calibration samples:
    :func:`white_sigma_covariance` (NNLS mixing propagated) against the Monte Carlo
    covariance of :func:`white_sigma`'s squared sigmas over 800 draws. For one sensor the
    variance is more than the successive-difference 2 sigma^4 / nu (its parity residual
    carries the others' noise). Tolerances: 4 standard errors of a sample variance
    (sqrt(2 / T), times 1.2 for the estimates' excess kurtosis); the shared term B of
    sensor 0 and its consensus, which may be near zero, within 4 sqrt((A D + B^2) / T)."""
    from imufdi_cli.episodes import (
        _consensus_gain,
        successive_difference_dof,
        white_sigma_spread,
    )

    H, sigma, n_cal, draws, cov, rel = white_variance_draws
    assert_allclose(draws.var(axis=0, ddof=1), np.diag(cov), rtol=rel)
    nu = successive_difference_dof(n_cal)
    assert np.all(np.diag(cov) > 1.05 * 2 * sigma**4 / nu)
    gain, _ = _consensus_gain(H, sigma, 0)
    a_term, b_term, d_term = white_sigma_spread(cov, gain, 0)
    consensus = draws @ gain**2
    assert float(consensus.var(ddof=1)) == pytest.approx(a_term, rel=rel)
    shared = float(np.cov(consensus, draws[:, 0])[0, 1])
    assert abs(shared - b_term) <= 4 * math.sqrt((a_term * d_term + b_term**2) / len(draws))
    assert d_term == pytest.approx(float(cov[0, 0]))


def test_calibration_dof_is_the_successive_difference_dof_for_a_lone_known_consensus() -> None:
    """With the consensus variance known (A = B = 0) and sigma_k^2 estimated with
    2 sigma^4 / nu, log f^2 = log(v - c^2) - log s_k carries 2 / nu from the calibration;
    the F interval maps v through sqrt(v - c^2), which scales its error by a = v / (v -
    c^2), so nu_cal = nu a^2 (nu itself when c = 0); degenerate inputs give the default."""
    from imufdi_cli.episodes import _calibration_dof

    nu, s, c = 133.0, 0.01, 0.004
    spread = (0.0, 0.0, 2 * s**4 / nu)
    assert _calibration_dof(9 * s**2, s, 0.0, spread, 7.0) == pytest.approx(nu)
    v = 9 * s**2 + c**2
    assert _calibration_dof(v, s, c, spread, 7.0) == pytest.approx(nu * (v / (v - c**2)) ** 2)
    assert _calibration_dof(c**2 / 2, s, c, spread, 7.0) == 7.0
    assert _calibration_dof(v, s, c, (0.0, 0.0, 0.0), 7.0) == 7.0


def test_white_sigma_excess_without_identifiable_sigmas_is_one_and_outliers_raise_it() -> None:
    """The cheap checks of :func:`white_sigma_excess` (the Monte Carlo one is slow): six
    single-axis gyros on a cone (singular mixing: one common sigma) and windows of fewer
    than 4 samples give 1; on six co-aligned triads it is at least 1, near 1 for
    Gaussian noise (within 6 of its standard deviations, about 0.015 here), and ten 5-sigma
    outliers, which pass the cut once differenced, raise it."""
    from imufdi_cli.episodes import white_sigma_excess
    from imufdi_cli.simulate.presets import conical_array

    rng = np.random.default_rng(59)
    cone = conical_array().measurement_matrix("gyro")
    assert white_sigma_excess(cone, rng.normal(0, SIGMA, (200, 6))) == 1.0
    H = np.tile(np.eye(3), (6, 1))
    assert white_sigma_excess(H, rng.normal(0, SIGMA, (3, 18))) == 1.0
    m = rng.normal(0, SIGMA, (200, 18))
    clean = white_sigma_excess(H, m)
    assert 1.0 <= clean <= 1.09
    rows = np.arange(10, 200, 20)
    m[rows, np.arange(10)] += 5 * SIGMA * np.where(np.arange(10) % 2, 1.0, -1.0)
    assert white_sigma_excess(H, m) > clean


@pytest.mark.slow  # 600 calibration windows, 1.3 s
def test_white_sigma_excess_is_one_for_gaussian_noise_and_grows_with_outliers() -> None:
    """Six co-aligned triads, 200 calibration samples. Gaussian white noise: the measured
    excess is 1 up to its sampling error (mean within 4 standard errors plus the floor's
    bias, at most 0.4 sd for a near-normal estimate). Outliers of 6 sigma on 0.3 % of the
    samples, most of which pass the 4-sigma cut once differenced: the squared white sigmas
    spread more than the Gaussian propagation (fed the estimated sigmas, as the builder
    is) says; the excess finds more than 1 (beyond 4 standard errors) without overstating
    it (Gaussian x excess at most the Monte Carlo variance, within 4 standard errors of a
    sample variance, sqrt(2 / T) times 1.5 for the outliers' kurtosis)."""
    from imufdi_cli.episodes import white_sigma, white_sigma_covariance, white_sigma_excess

    rng = np.random.default_rng(47)
    H = np.tile(np.eye(3), (6, 1))
    sigma = SIGMA * np.linspace(0.8, 1.3, 18)
    trials = 300
    gaussian = np.array(
        [white_sigma_excess(H, rng.normal(0, sigma, (200, 18))) for _ in range(trials)]
    )
    sd = float(gaussian.std(ddof=1))
    assert np.all(gaussian >= 1.0)
    assert float(gaussian.mean()) <= 1.0 + 0.4 * sd + 4 * sd / math.sqrt(trials)

    draws, excess = [], []
    for _ in range(trials):
        m = rng.normal(0, sigma, (200, 18))
        m += (rng.random(m.shape) < 0.003) * 6 * sigma * rng.choice([-1.0, 1.0], m.shape)
        draws.append(white_sigma(H, m) ** 2)
        excess.append(white_sigma_excess(H, m))
    squared = np.array(draws)
    measured = float(np.mean(excess))
    assert measured > 1.0 + 4 * float(np.std(excess, ddof=1)) / math.sqrt(trials)
    predicted = np.diag(white_sigma_covariance(H, np.sqrt(squared.mean(axis=0)), 200))
    empirical = squared.var(axis=0, ddof=1)
    assert float(np.mean(empirical / predicted)) > measured
    assert float(np.mean(predicted * measured / empirical)) <= 1 + 4 * math.sqrt(2 / trials) * 1.5


@pytest.mark.slow  # with the covariance test above: 800 calibrations, about 0.85 s
def test_white_variance_dof_matches_the_spread_of_the_calibrated_residual_variance(
    white_variance_draws: tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, float],
) -> None:
    """The variance-drop monitor's calibrated white variance of sensor k's residual,
    ``v_k = s_k + sum_i g_i^2 s_i``, over 800 calibrations of six co-aligned triads with
    different sigmas: :func:`white_variance_dof` (``2 v_k^2 / (D + 2 B + A)``) against the
    Monte Carlo ``2 v_k^2 / Var(v_hat_k)`` for every sensor. Tolerance: 4 standard errors of
    a sample variance (sqrt(2 / T), times 1.2 for the estimates' excess kurtosis)."""
    from imufdi_cli.episodes import _consensus_gain
    from imufdi_cli.episodes.white_noise import white_variance_dof

    H, sigma, _, draws, cov, rel = white_variance_draws
    for k in range(18):
        gain, _ = _consensus_gain(H, sigma, k)
        v = sigma[k] ** 2 + float(np.sum(gain**2 * sigma**2))
        measured = 2 * v**2 / float((draws[:, k] + draws @ gain**2).var(ddof=1))
        assert white_variance_dof(cov, gain, k, v, 0.0) == pytest.approx(measured, rel=rel)
    # a degenerate spread gives the default
    assert white_variance_dof(np.zeros((18, 18)), gain, 0, 1.0, 7.0) == 7.0


def _white_variance_draws(
    seed: int,
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, float]:
    """800 calibrations (200 samples) of 6 co-aligned triads with unequal sigmas: H (18, 3),
    sigma (18,), n_cal, the white variances of each (800, 18), their predicted covariance
    (:func:`white_sigma_covariance`, (18, 18)) and the relative tolerance of a sample
    variance over the trials (4 standard errors, sqrt(2 / T), times 1.2 for the estimates'
    excess kurtosis)."""
    from imufdi_cli.episodes import white_sigma, white_sigma_covariance

    rng = np.random.default_rng(seed)
    H = np.tile(np.eye(3), (6, 1))
    sigma = SIGMA * np.linspace(0.8, 1.3, 18)
    n_cal, trials = 200, 800
    draws = np.array(
        [white_sigma(H, rng.normal(0, sigma, (n_cal, 18))) ** 2 for _ in range(trials)]
    )
    cov = white_sigma_covariance(H, sigma, n_cal)
    return H, sigma, n_cal, draws, cov, 4 * math.sqrt(2 / (trials - 1)) * 1.2
