"""Capped variance CUSUM (imufdi_cli.detectors.cusum)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.detectors.cusum import CusumDesign, cusum_threshold, run_cusum


def test_increment_is_the_variance_log_likelihood_ratio():
    design = CusumDesign(ratio=4.0, clip=5.0)
    z = np.array([0.0, 1.0, 2.0, 10.0, np.nan])
    # ln N(z; 0, K) / N(z; 0, 1) = 1/2 (1 - 1/K) z^2 - 1/2 ln K, z^2 clipped at 25
    expected = 0.5 * 0.75 * np.array([0.0, 1.0, 4.0, 25.0, 1.0]) - 0.5 * math.log(4.0)
    assert_allclose(design.increments(z), expected)


def test_run_cusum_is_the_capped_page_recursion_across_blocks():
    rng = np.random.default_rng(0)
    increments = rng.normal(-0.2, 2.0, (300, 3))
    cap = 6.0
    direct = np.zeros_like(increments)
    s = np.zeros(3)
    for i, row in enumerate(increments):
        s = np.clip(s + row, 0.0, cap)
        direct[i] = s
    first, state = run_cusum(increments[:117], np.zeros(3), cap)
    second, _ = run_cusum(increments[117:], state, cap)
    assert_allclose(np.vstack([first, second]), direct)
    assert direct.max() == cap and direct.min() == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("level", [1e-3, 1e-4])
def test_threshold_gives_the_level_on_an_independent_null_simulation(level):
    """h from one seeded simulation; the exceedance rate of an independent simulation of
    the same null (differences of white noise, calibration error negligible) must match
    the level. Tolerance from the spread over independent chains (alarms cluster, so the
    binomial variance of single samples would be too small): 4 standard errors of the
    mean over 256 chains, plus the extrapolation's own error, bounded at 35 %."""
    design = CusumDesign(ratio=9.0, clip=5.0)
    margin = 15.0
    h = cusum_threshold(level, design, margin, 1e12, np.random.default_rng(1))
    chains, steps = 256, 40000
    white = np.random.default_rng(2).standard_normal((steps + 1, chains))
    z = np.diff(white, axis=0) / math.sqrt(2.0)
    s, _ = run_cusum(design.increments(z), np.zeros(chains), h + margin)
    per_chain = (s[1024:] > h).mean(axis=0)
    mean = per_chain.mean()
    standard_error = per_chain.std(ddof=1) / math.sqrt(chains)
    assert abs(mean - level) <= 4 * standard_error + 0.35 * level


def test_calibration_error_raises_the_threshold():
    design = CusumDesign()
    exact = cusum_threshold(1e-4, design, 15.0, 1e12, np.random.default_rng(3))
    estimated = cusum_threshold(1e-4, design, 15.0, 100.0, np.random.default_rng(3))
    assert estimated > exact
