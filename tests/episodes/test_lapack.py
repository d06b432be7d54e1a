"""episodes.lapack: numpy's LAPACK gufuncs called directly give numpy.linalg's floats to the
bit, and numpy.linalg's errors."""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli.episodes import lapack


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("shape", [(201, 4), (201, 5), (76, 4), (12, 3), (5, 5)])
def test_svd_reduced_is_numpys(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(20261123)
    for _ in range(20):
        a = rng.normal(size=shape) * rng.uniform(1e-3, 1e3, size=shape[1])
        expected = np.linalg.svd(a, full_matrices=False)
        got = lapack.svd_reduced(a)
        assert all(_same(x, y) for x, y in zip(got, expected))


def test_svd_reduced_raises_as_numpy() -> None:
    a = np.ones((6, 3))
    a[2, 1] = np.nan
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.svd(a, full_matrices=False)
    with pytest.raises(np.linalg.LinAlgError):
        lapack.svd_reduced(a)


@pytest.mark.parametrize("p", [1, 2, 3])
def test_solve_and_det_are_numpys(p: int) -> None:
    rng = np.random.default_rng(17)
    for _ in range(50):
        X = rng.normal(size=(150, p)) * rng.uniform(1e-4, 1e4)
        gram = X.T @ X
        assert _same(lapack.solve(gram, X.T), np.linalg.solve(gram, X.T))
        assert lapack.det(gram) == float(np.linalg.det(gram))


def test_solve_raises_as_numpy() -> None:
    singular = np.array([[1.0, 2.0], [2.0, 4.0]])
    b = np.ones((2, 3))
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.solve(singular, b)
    with pytest.raises(np.linalg.LinAlgError):
        lapack.solve(singular, b)
