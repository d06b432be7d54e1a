"""Shared helpers of the simulate tests."""

from __future__ import annotations

import math

from scipy import stats

DEG = math.pi / 180.0


def sigma_interval(sigma: float, n: int, p: float = 1e-6) -> tuple[float, float]:
    """Interval of the sample std of n N(0, sigma^2) values at two-sided level p (chi^2)."""
    low = sigma * math.sqrt(stats.chi2.ppf(p / 2, n) / n)
    high = sigma * math.sqrt(stats.chi2.ppf(1 - p / 2, n) / n)
    return low, high


def binomial_interval(prob: float, n: int, p: float = 1e-6) -> tuple[float, float]:
    """Interval of a binomial proportion (n trials, probability prob) at two-sided level p."""
    return stats.binom.ppf(p / 2, n, prob) / n, stats.binom.ppf(1 - p / 2, n, prob) / n
