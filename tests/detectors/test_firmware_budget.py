"""The firmware voters' null models under a false-alarm budget (detectors.firmware_budget)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lfilter

from imufdi_cli.detectors.firmware_budget import (
    _MEAN_NORM,
    ap_episode_rate,
    ap_limit_scale,
    difference_noise,
    imu_noise,
    lundberg_exponent,
    px4_null_rate,
    weighted_chi2_sf,
)
from imufdi_cli.detectors.px4_selector import accumulate_excess


def test_the_weighted_chi_square_tail_is_exact_and_keeps_its_precision(scipy_stats) -> None:
    t = np.array([1e-3, 0.1, 1.0, 10.0, 60.0])
    np.testing.assert_allclose(
        weighted_chi2_sf(t, np.ones(3)), scipy_stats.chi2.sf(t, 3), rtol=1e-10
    )
    # unequal weights against 4 million draws (binomial sd below 0.1 % of each value here)
    a = np.array([1.0, 0.25, 2.0])
    u = np.random.default_rng(0).standard_normal((4_000_000, 3))
    s = (u**2 * a).sum(axis=1)
    for level in (0.1, 1.0, 5.0):
        assert weighted_chi2_sf(level, a) == pytest.approx(np.mean(s > level), rel=0.01)
    assert weighted_chi2_sf(200.0, a) < 1e-20  # a tail far beyond any simulation


def test_noise_from_differences_ignores_smooth_motion_and_splits_the_imus() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(20_000) / 100.0
    sigma = np.array([0.01, 0.02, 0.03, 0.015])
    # a slow common motion (its sample differences, <= 6e-4, are small against the noise)
    x = rng.standard_normal((t.size, 4, 3)) * sigma[:, None] + 0.3 * np.sin(0.2 * t)[:, None, None]
    variance, dof = difference_noise(x)
    np.testing.assert_allclose(np.sqrt(variance), np.repeat(sigma[:, None], 3, axis=1), rtol=0.03)
    assert dof > 10_000
    deviation = x - x.mean(axis=1, keepdims=True)
    dev_variance, _ = difference_noise(deviation)
    np.testing.assert_allclose(np.sqrt(imu_noise(dev_variance)), variance**0.5, rtol=0.05)


def _ap_simulated_rate(variance: np.ndarray, limit: float, hold: int, rng) -> float:  # type: ignore[no-untyped-def]
    """Starts of runs of ``hold`` failures per sample, white Gaussian differences."""
    n = 2_000_000
    d = np.sqrt((rng.standard_normal((n, 3)) ** 2 * variance).sum(axis=1))
    fail = d > limit
    run = np.zeros(n, dtype=np.int64)
    count = 0
    for i in range(n):  # the plain loop: a run of `hold` failures starts an episode
        count = count + 1 if fail[i] else 0
        run[i] = count
    return float(np.count_nonzero(run == hold)) / n


def test_the_ap_run_model_matches_a_simulation() -> None:
    variance = np.array([1.0, 0.5, 2.0])
    rng = np.random.default_rng(2)
    for limit, hold in ((1.5, 3), (0.9, 12)):
        model = ap_episode_rate(
            1.0, variance[None, :], np.ones(3), np.array([limit]), hold, math.inf
        )
        simulated = _ap_simulated_rate(variance, limit, hold, rng)
        # at least ~2000 runs in 2 million samples: binomial sd below 2.5 %
        assert model == pytest.approx(simulated, rel=0.08)


def test_the_ap_scale_meets_the_rate_on_the_falling_side() -> None:
    variance = np.full((3, 3), 1e-4)
    limits = np.full(3, 0.1)
    for hold, per_sample in ((1, 1e-6), (1001, 1e-8)):
        scale = ap_limit_scale(variance, np.ones(3), limits, hold, per_sample, 300.0)
        rate = ap_episode_rate(scale, variance, np.ones(3), limits, hold, 300.0)
        assert rate == pytest.approx(per_sample, rel=0.01)
        # the failure probability is below the peak h / (h + 1) of (1 - p) p^h
        p = float(weighted_chi2_sf((scale * 0.1) ** 2, np.full(3, 1e-4)))
        assert p < hold / (hold + 1.0)


def test_the_lundberg_exponent_is_the_perrons_root_and_converged() -> None:
    c = 0.05
    mean = math.sqrt(c / (2 - c)) * _MEAN_NORM
    theta = lundberg_exponent(1.2 * mean, c)
    assert 0.3 < theta < 0.36
    # the slope of log P(E > u) of a long simulation of the recursion (H 20 to 60)
    rng = np.random.default_rng(3)
    noise = rng.standard_normal((20_000, 128, 3))
    d = lfilter([c], [1.0, -(1.0 - c)], noise, axis=0)[1000:]
    energy = accumulate_excess(np.linalg.norm(d, axis=2) - 1.2 * mean, np.zeros(128))
    levels = np.array([0.2, 0.35, 0.5]) * 1.2 * mean * 100.0
    tail = np.array([np.mean(energy > u) for u in levels])
    slope = -np.polyfit(levels, np.log(tail), 1)[0]
    assert slope == pytest.approx(theta, rel=0.12)


@pytest.mark.parametrize(
    ("factor", "hold", "samples"),
    [(1.3, 30.0, 8_000), pytest.param(1.2, 60.0, 32_768, marks=pytest.mark.slow)],
)
def test_the_px4_null_rate_matches_a_direct_simulation(
    factor: float, hold: float, samples: int
) -> None:
    """The upcrossings of H rho by the firmware recursion on white noise: a direct count
    (256 chains; about 110 and 110-130 upcrossings) against the model's
    ``C exp(-theta* H rho)``: within 50 % (the count's Poisson error is ~10 %, the
    prefactor, a median over levels of a short simulation, scatters by ~20 %; in the
    threshold that is a fraction of a percent, the rate falling a decade per 2 % of rho)."""
    c = 0.05
    mean = math.sqrt(c / (2 - c)) * _MEAN_NORM
    rho = factor * mean
    rng = np.random.default_rng(4)
    noise = rng.standard_normal((samples + 600, 256, 3))
    d = lfilter([c], [1.0, -(1.0 - c)], noise, axis=0)[600:]
    energy = accumulate_excess(np.linalg.norm(d, axis=2) - rho, np.zeros(256))
    above = energy > hold * rho
    direct = np.count_nonzero(above[1:] & ~above[:-1]) / above.size
    model = float(px4_null_rate(rho, hold, c, 0))
    assert model == pytest.approx(direct, rel=0.5)
    assert float(px4_null_rate(0.9 * mean, hold, c, 0)) == 1.0  # below the mean: always
