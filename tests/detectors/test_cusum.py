"""Capped variance CUSUM (imufdi_cli.detectors.cusum)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.detectors.cusum import (
    CusumDesign,
    _TopValues,
    cusum_threshold,
    local_mean_residual,
    run_cusum,
)


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


def test_local_mean_residual_matches_its_definition_across_blocks():
    rng = np.random.default_rng(4)
    x = rng.normal(0.0, 1.0, (200, 2)) + np.array([5.0, -3.0])  # offsets drop out
    for window in (1, 8):
        direct = np.full_like(x, np.nan)
        for t in range(window, 200):
            direct[t] = (x[t] - x[t - window : t].mean(axis=0)) / math.sqrt(1.0 + 1.0 / window)
        whole = local_mean_residual(x, window)
        assert_allclose(whole, direct, equal_nan=True)
        parts = [local_mean_residual(x[:3], window), local_mean_residual(x[3:50], window, x[:3])]
        parts.append(local_mean_residual(x[50:], window, x[:50]))
        assert_allclose(np.vstack(parts), direct, equal_nan=True)
    # W = 1: the first difference over sqrt(2)
    assert_allclose(local_mean_residual(x, 1)[1:], np.diff(x, axis=0) / math.sqrt(2.0))


def test_local_mean_residual_of_white_noise_has_unit_variance_and_small_correlation():
    """Var = 1 and lag-k correlation -k / (W (W + 1)) (k <= W); tolerances 5 standard
    errors of a sample variance / correlation of n = 200000 values (sqrt(2/n), 1/sqrt(n))."""
    n, window = 200_000, 8
    z = local_mean_residual(np.random.default_rng(5).standard_normal((n, 1)), window)[window:, 0]
    assert abs(z.var() - 1.0) <= 5 * math.sqrt(2.0 / n)
    for lag in (1, 4, 8, 9):
        expected = -lag / (window * (window + 1)) if lag <= window else 0.0
        assert abs(np.corrcoef(z[:-lag], z[lag:])[0, 1] - expected) <= 5 / math.sqrt(n)


@pytest.mark.slow
@pytest.mark.parametrize(("level", "window"), [(1e-3, 1), (1e-4, 1), (1e-4, 8)])
def test_threshold_gives_the_level_on_an_independent_null_simulation(level, window):
    """h from one seeded simulation; the exceedance rate of an independent simulation of
    the same null (white noise minus the mean of its W previous samples, computed here by
    a convolution; calibration error negligible) must match the level. Tolerance from the
    spread over independent chains (alarms cluster, so the binomial variance of single
    samples would be too small): 4 standard errors of the mean over 256 chains, plus the
    extrapolation's own error, bounded at 35 %."""
    design = CusumDesign(ratio=9.0, clip=5.0)
    margin = 15.0
    h = cusum_threshold(level, design, margin, 1e12, np.random.default_rng(1), mean_window=window)
    chains, steps = 256, 40000
    white = np.random.default_rng(2).standard_normal((steps + window, chains))
    kernel = np.concatenate([[1.0], np.full(window, -1.0 / window)])
    z = np.stack(
        [np.convolve(white[:, c], kernel, mode="valid") for c in range(chains)], axis=1
    ) / math.sqrt(1.0 + 1.0 / window)
    s, _ = run_cusum(design.increments(z), np.zeros(chains), h + margin)
    per_chain = (s[1024:] > h).mean(axis=0)
    mean = per_chain.mean()
    standard_error = per_chain.std(ddof=1) / math.sqrt(chains)
    assert abs(mean - level) <= 4 * standard_error + 0.35 * level


def test_calibration_error_raises_the_threshold():
    """Paired (same draws): a calibrated variance of 100 dof gives a higher h than an exact
    one. A smaller simulation than the detectors' (64 chains of 4096 steps, 1/13 of the
    samples) keeps the test quick; over seeds 0-19 its ratio was 1.11-1.4 (mean 1.25)."""
    design = CusumDesign()
    size = {"chains": 64, "steps": 4096}
    exact = cusum_threshold(1e-4, design, 15.0, 1e12, np.random.default_rng(3), **size)
    estimated = cusum_threshold(1e-4, design, 15.0, 100.0, np.random.default_rng(3), **size)
    assert estimated > exact


#: Thresholds computed by the implementation before its speed-up (index arrays, a Python
#: step per sample, a full sort, two full runs):
#: level, ratio, clip, margin, dof, seed, chains, steps, W, h. The first is cnn-map's input
#: test on a wearable12 log (seed 0, alpha 0.01); the fifth drifts upwards (the cap acts).
STORED_THRESHOLDS = [
    (2.7791289747827936e-05, 9.0, 5.0, 16.354196105591633, 132.0354088144793, [0, 0x1C5],
     256, 16384, 8, 11.673540537347879),
    (1e-4, 9.0, 5.0, 15.0, 1e12, 3, 64, 4096, 1, 11.09612732418254),
    (1e-4, 9.0, 5.0, 15.0, 100.0, 3, 64, 4096, 1, 15.023554275898421),
    (1e-3, 4.0, 3.0, 5.0, 50.0, 7, 64, 4096, 1, 129.82002401972613),
    (1e-4, 9.0, 5.0, 15.0, 1e12, 1, 64, 4096, 8, 7.3111767764265005),
    (1e-6, 9.0, 5.0, 2.0, 40.0, 11, 32, 2048, 3, 27.531483656654345),
]  # fmt: skip


@pytest.mark.parametrize("case", STORED_THRESHOLDS)
def test_threshold_is_the_one_computed_before_the_speed_up(case):
    """Same draws, same arithmetic order: an empirical quantile (level x samples >= 100)
    is an order statistic of identical values and must match exactly (the draws are numpy's
    Generator stream, the same on every machine, and the path only adds, squares, divides,
    takes square roots, minima and maxima: IEEE-754 operations, correctly rounded on every
    CPU and SIMD level, in the same order; unchanged across numpy's AVX-512, AVX2 and SSE4.2
    loops and numpy 2.0 to 2.4); an extrapolated one goes through a LAPACK least-squares
    fit and a logarithm, whose last bits differ between BLAS kernels, SIMD levels and
    builds (by up to 5.2e-16 of h, measured), so it must match to 1e-12 relative."""
    level, ratio, clip, margin, dof, seed, chains, steps, window, stored = case
    h = cusum_threshold(
        level,
        CusumDesign(ratio=ratio, clip=clip),
        margin,
        dof,
        np.random.default_rng(seed),
        chains=chains,
        steps=steps,
        mean_window=window,
    )
    if level * chains * steps >= 100:
        assert h == stored
    else:
        assert h == pytest.approx(stored, rel=1e-12, abs=0.0)


def test_run_cusum_is_bit_identical_to_the_step_by_step_recursion():
    """Exact equality with ``min(max(S + l, 0), cap)`` one sample at a time (float64, and
    float32 increments added to the float64 state), a NaN carried on, capped and uncapped."""
    rng = np.random.default_rng(6)
    increments = rng.normal(-0.3, 1.5, (2000, 5))
    increments[100:110, 2] = np.nan
    for values in (increments, increments.astype(np.float32)):
        for cap, start in ((6.0, np.full(5, 1.0)), (math.inf, np.zeros(5))):
            s = start.copy()
            expected = np.empty(values.shape)
            for i in range(values.shape[0]):
                s = np.minimum(np.maximum(s + values[i], 0.0), cap)
                expected[i] = s
            path, state = run_cusum(values, start, cap)
            np.testing.assert_array_equal(path, expected)
            np.testing.assert_array_equal(state, expected[-1])
    path, state = run_cusum(np.zeros((0, 3)), np.ones(3), 2.0)
    assert path.shape == (0, 3)
    np.testing.assert_array_equal(state, np.ones(3))


@pytest.mark.parametrize("columns", [3, 80])  # below and above the row-loop switch
def test_local_mean_residual_is_bit_identical_to_its_cumulative_sum_form(columns):
    """Exact equality with the cumulative-sum expression it has always computed (float64
    and float32 input, with and without past samples)."""

    def reference(series, window, past=None):
        before = np.zeros((0, series.shape[1])) if past is None else past[-window:]
        joined = np.concatenate([before, series], axis=0)
        offset = before.shape[0]
        cumulative = np.concatenate([np.zeros((1, joined.shape[1])), np.cumsum(joined, axis=0)])
        out = np.full(series.shape, np.nan)
        first = max(0, window - offset)
        if first < series.shape[0]:
            rows = np.arange(first, series.shape[0]) + offset
            means = (cumulative[rows] - cumulative[rows - window]) / window
            out[first:] = (joined[rows] - means) / math.sqrt(1.0 + 1.0 / window)
        return out

    x = np.random.default_rng(7).normal(3.0, 1.0, (600, columns))
    for series in (x, x.astype(np.float32)):
        for window in (1, 8, 13):
            np.testing.assert_array_equal(
                local_mean_residual(series, window), reference(series, window)
            )
            for past in (series[:4], series[:300]):
                np.testing.assert_array_equal(
                    local_mean_residual(series[300:], window, past),
                    reference(series[300:], window, past),
                )
        np.testing.assert_array_equal(local_mean_residual(series[:5], 8), reference(series[:5], 8))


@pytest.mark.parametrize("positive_share", [0.5, 0.01])  # enough positives, and too few
def test_top_values_are_the_order_statistics_of_a_full_sort(positive_share):
    rng = np.random.default_rng(8)
    values = np.where(rng.random((3000, 7)) < positive_share, rng.exponential(1.0, (3000, 7)), 0.0)
    descending = np.sort(values.ravel())[::-1]
    for level in (1e-4, 0.02, 0.09):
        top = _TopValues(values, level)
        assert top.n == values.size
        np.testing.assert_array_equal(top.descending, descending[: top.descending.size])
        assert top.descending.size > max(int(level * values.size), int(0.05 * values.size))
