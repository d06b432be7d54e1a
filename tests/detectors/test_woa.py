"""Whale optimization algorithm."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.detectors.woa import woa
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
