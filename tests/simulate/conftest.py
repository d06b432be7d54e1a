"""Shared helpers of the simulate tests."""

from __future__ import annotations

import math

from imufdi_cli.maths.quantiles import chi2

DEG = math.pi / 180.0


def sigma_interval(sigma: float, n: int, p: float = 1e-6) -> tuple[float, float]:
    """Interval of the sample std of n N(0, sigma^2) values at two-sided level p (chi^2).

    (``imufdi_cli.maths.quantiles.chi2``: scipy.stats' floats, tests/test_quantiles.py, without
    importing scipy.stats in every process that runs a simulate test.)"""
    low = sigma * math.sqrt(chi2.ppf(p / 2, n) / n)
    high = sigma * math.sqrt(chi2.ppf(1 - p / 2, n) / n)
    return low, high


def binomial_interval(prob: float, n: int, p: float = 1e-6) -> tuple[float, float]:
    """Interval of a binomial proportion (n trials, probability prob) at two-sided level p
    (scipy.stats imported here: a test calling this asks for the ``scipy_stats`` fixture,
    so that it runs on the worker that imports it, tests/conftest.py)."""
    from scipy import stats

    return stats.binom.ppf(p / 2, n, prob) / n, stats.binom.ppf(1 - p / 2, n, prob) / n
