"""Whale optimization algorithm."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.detectors.woa import WoaSearch, woa
from imufdi_cli.errors import DetectorConfigError


def sphere(points: np.ndarray) -> np.ndarray:
    return ((points - np.array([3.0, -1.5])) ** 2).sum(axis=1)


def test_finds_minimum_of_shifted_sphere():
    result = woa(
        sphere, [-10, -10], [10, 10], population=20, iterations=60, rng=np.random.default_rng(1)
    )
    assert_allclose(result.best, [3.0, -1.5], atol=1e-2)
    assert result.best_fitness < 1e-4
    assert result.curve.shape == (61,)
    assert np.all(np.diff(result.curve) <= 0)


def test_one_call_per_iteration_and_cache_on_integer_grid():
    calls = []

    def fitness(points: np.ndarray) -> np.ndarray:
        calls.append(len(points))
        return (points[:, 0] - 2) ** 2 + (points[:, 1] - 100.0) ** 2 / 1e4

    result = woa(
        fitness,
        [1, 50],
        [6, 500],
        integer=[True, False],
        population=8,
        iterations=10,
        rng=np.random.default_rng(0),
    )
    assert len(calls) <= 11  # at most one batched call per iteration (+ initial)
    assert result.best[0] == 2.0
    assert result.best[0] == np.rint(result.best[0])
    assert result.n_evaluations == sum(calls)
    assert result.n_evaluations + result.n_cache_hits == 8 * 11


def test_seeded_runs_are_reproducible():
    a = woa(sphere, [-5, -5], [5, 5], population=6, iterations=5, rng=np.random.default_rng(7))
    b = woa(sphere, [-5, -5], [5, 5], population=6, iterations=5, rng=np.random.default_rng(7))
    assert_allclose(a.best, b.best)
    assert_allclose(a.curve, b.curve)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"population": 1}, "population must be >= 2"),
        ({"iterations": -1}, "iterations"),
    ],
)
def test_bad_settings_raise(kwargs, match):
    with pytest.raises(DetectorConfigError, match=match):
        woa(sphere, [0, 0], [1, 1], rng=np.random.default_rng(0), **kwargs)


def test_bad_bounds_raise():
    with pytest.raises(DetectorConfigError, match="lower <= upper"):
        woa(sphere, [1, 0], [0, 1], rng=np.random.default_rng(0))


def test_ask_tell_gives_the_same_search_as_woa():
    # WoaSearch driven by hand (as tune_signals drives several at once) draws and caches
    # exactly as woa(): same history, curve, best and counts
    def fitness(points: np.ndarray) -> np.ndarray:
        return (points[:, 0] - 3) ** 2 + (points[:, 1] - 0.4) ** 2

    bounds = ([1, 0.0], [6, 1.0])
    kwargs = {"integer": [True, False], "population": 6, "iterations": 7}
    plain = woa(fitness, *bounds, rng=np.random.default_rng(3), **kwargs)
    search = WoaSearch(*bounds, rng=np.random.default_rng(3), **kwargs)
    asked = 0
    while not search.done:
        candidates = search.ask()
        asked += candidates.shape[0]
        search.tell(fitness(candidates))
    result = search.result()
    assert_array_equal(result.curve, plain.curve)
    assert_array_equal(result.best, plain.best)
    assert (result.n_evaluations, result.n_cache_hits) == (plain.n_evaluations, plain.n_cache_hits)
    assert asked == plain.n_evaluations
    for a, b in zip(result.history, plain.history, strict=True):
        assert_array_equal(a, b)
    with pytest.raises(DetectorConfigError, match="over"):
        search.ask()


def test_tell_needs_one_value_per_candidate_and_result_waits_for_the_end():
    search = WoaSearch([0.0], [1.0], population=3, iterations=2, rng=np.random.default_rng(0))
    with pytest.raises(DetectorConfigError, match="not over"):
        search.result()
    with pytest.raises(DetectorConfigError, match="one value per candidate"):
        search.tell(np.zeros(search.ask().shape[0] + 1))
