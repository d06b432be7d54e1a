"""Whale optimization algorithm (Mirjalili & Lewis, Adv. Eng. Softw. 95:51-67, 2016).

Minimises a fitness over a box. Each iteration moves the whole population at once and
evaluates it with ONE call of a vectorised fitness (rows = candidates), so a batched
objective (e.g. :func:`imufdi_cli.detectors.mvmd.mvmd_batch`) sees the whole population.

Per whale X and dimension j, with a decreasing linearly from 2 to 0 over the iterations,
r1, r2 ~ U(0, 1), ``A = 2 a r1 - a``, ``C = 2 r2`` (eqs. 2.3-2.4), p ~ U(0, 1), l ~ U(-1, 1):

- p < 0.5 and |A| < 1, encircling the best X*:  ``X <- X* - A |C X* - X|``   (eqs. 2.1-2.2)
- p < 0.5 and |A| >= 1, search around a random whale X_r:  ``X <- X_r - A |C X_r - X|``
  (eqs. 2.7-2.8, exploration)
- p >= 0.5, spiral bubble-net:  ``X <- |X* - X| e^{b l} cos(2 pi l) + X*``    (eq. 2.5)

then positions are clipped to the bounds. Integer dimensions are searched continuously
and rounded for evaluation. Repeated candidates (same rounded position) are evaluated once
(cache), which matters because clipping and rounding make the population collapse onto the
same points late in the search.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from imufdi_cli.errors import DetectorConfigError

Fitness = Callable[[np.ndarray], np.ndarray]
"""Vectorised objective: positions (P, D) -> fitness (P,) (lower is better)."""


@dataclass
class WoaResult:
    """Outcome of :func:`woa`.

    Attributes
    ----------
    best : ndarray, shape (D,)
        Best position found (integer dimensions rounded).
    best_fitness : float
    curve : ndarray, shape (iterations + 1,)
        Best fitness after initialisation and after each iteration (non-increasing).
    n_evaluations : int
        Distinct candidates evaluated (cache hits not counted).
    n_cache_hits : int
    history : list of ndarray (P, D)
        Evaluated (rounded) population of every iteration.
    """

    best: np.ndarray
    best_fitness: float
    curve: np.ndarray
    n_evaluations: int
    n_cache_hits: int
    history: list[np.ndarray] = field(default_factory=list, repr=False)


def _key(position: np.ndarray) -> tuple[float, ...]:
    # 12 significant digits: equal after clipping/rounding, distinct otherwise
    return tuple(float(f"{v:.12g}") for v in position)


def woa(
    fitness: Fitness,
    lower: Sequence[float],
    upper: Sequence[float],
    *,
    integer: Sequence[bool] | None = None,
    population: int = 10,
    iterations: int = 10,
    rng: np.random.Generator,
    spiral_b: float = 1.0,
) -> WoaResult:
    """Minimise ``fitness`` over the box [lower, upper] with the whale optimization algorithm.

    Parameters
    ----------
    fitness : callable (P, D) -> (P,)
        Called once per iteration with the distinct, not yet evaluated candidates.
    lower, upper : sequences of D floats, lower <= upper
    integer : sequence of D bools, optional
        Dimensions rounded to integers for evaluation.
    population : int >= 2
    iterations : int >= 0
    rng : numpy.random.Generator
    spiral_b : float
        Logarithmic spiral constant b (eq. 2.5).

    Returns
    -------
    WoaResult
    """
    low = np.asarray(lower, dtype=np.float64)
    high = np.asarray(upper, dtype=np.float64)
    if low.ndim != 1 or low.shape != high.shape or low.size == 0:
        raise DetectorConfigError("WOA: lower and upper bounds must be 1-D of equal length")
    if np.any(~np.isfinite(low)) or np.any(~np.isfinite(high)) or np.any(low > high):
        raise DetectorConfigError("WOA: bounds must be finite with lower <= upper")
    if population < 2:
        raise DetectorConfigError(f"WOA: population must be >= 2, got {population}")
    if iterations < 0:
        raise DetectorConfigError(f"WOA: iterations must be >= 0, got {iterations}")
    n_dims = low.size
    is_int = np.zeros(n_dims, dtype=bool) if integer is None else np.asarray(integer, dtype=bool)
    if is_int.shape != (n_dims,):
        raise DetectorConfigError("WOA: integer mask must have one entry per dimension")

    cache: dict[tuple[float, ...], float] = {}
    hits = 0
    history: list[np.ndarray] = []

    def rounded(positions: np.ndarray) -> np.ndarray:
        out = positions.copy()
        out[:, is_int] = np.rint(out[:, is_int])
        return np.clip(out, low, high)

    def evaluate(positions: np.ndarray) -> np.ndarray:
        nonlocal hits
        candidates = rounded(positions)
        history.append(candidates)
        keys = [_key(row) for row in candidates]
        todo: dict[tuple[float, ...], int] = {}
        for row, key in enumerate(keys):
            if key in cache or key in todo:
                hits += 1
            else:
                todo[key] = row
        if todo:
            rows = np.fromiter(todo.values(), dtype=np.int64)
            values = np.asarray(fitness(candidates[rows]), dtype=np.float64).reshape(-1)
            if values.shape[0] != rows.shape[0]:
                raise DetectorConfigError("WOA: fitness must return one value per candidate")
            for key, value in zip(todo, values):
                cache[key] = float(value) if np.isfinite(value) else np.inf
        return np.array([cache[key] for key in keys])

    positions = low + (high - low) * rng.random((population, n_dims))
    scores = evaluate(positions)
    best_row = int(np.argmin(scores))
    best = rounded(positions[best_row : best_row + 1])[0]
    best_score = float(scores[best_row])
    curve = [best_score]

    for it in range(iterations):
        a = 2.0 - 2.0 * it / max(iterations, 1)  # eq. 2.3: a from 2 to 0
        r1 = rng.random((population, n_dims))
        r2 = rng.random((population, n_dims))
        A = 2.0 * a * r1 - a
        C = 2.0 * r2
        p = rng.random((population, 1))
        ell = rng.uniform(-1.0, 1.0, (population, 1))
        partners = positions[rng.integers(0, population, population)]
        encircle = best - A * np.abs(C * best - positions)  # eqs. 2.1-2.2
        explore = partners - A * np.abs(C * partners - positions)  # eqs. 2.7-2.8
        spiral = (
            np.abs(best - positions) * np.exp(spiral_b * ell) * np.cos(2.0 * np.pi * ell) + best
        )  # eq. 2.5
        shrink = np.where(np.abs(A) < 1.0, encircle, explore)
        positions = np.clip(np.where(p < 0.5, shrink, spiral), low, high)
        scores = evaluate(positions)
        row = int(np.argmin(scores))
        if scores[row] < best_score:
            best_score = float(scores[row])
            best = rounded(positions[row : row + 1])[0]
        curve.append(best_score)

    return WoaResult(
        best=best,
        best_fitness=best_score,
        curve=np.asarray(curve),
        n_evaluations=len(cache),
        n_cache_hits=hits,
        history=history,
    )


__all__ = ["Fitness", "WoaResult", "woa"]
