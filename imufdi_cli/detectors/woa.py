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


class WoaSearch:
    """The whale optimization search of :func:`woa` as a sequence of requests.

    :meth:`ask` gives the candidates whose fitness the search needs next (distinct and not
    yet evaluated: they may be none when the whole population was seen before) and
    :meth:`tell` takes their values; repeat until :attr:`done`, then :meth:`result`.
    :func:`woa` is this loop with one fitness; a caller driving several searches at once
    can evaluate all their requests together (e.g. in one batched MVMD call). The
    positions, random draws and cache are those of :func:`woa`, in the same order, so a
    search gives the same result however it is driven.

    Parameters
    ----------
    See :func:`woa` (without ``fitness``).
    """

    def __init__(
        self,
        lower: Sequence[float],
        upper: Sequence[float],
        *,
        integer: Sequence[bool] | None = None,
        population: int = 10,
        iterations: int = 10,
        rng: np.random.Generator,
        spiral_b: float = 1.0,
    ) -> None:
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
        is_int = (
            np.zeros(n_dims, dtype=bool) if integer is None else np.asarray(integer, dtype=bool)
        )
        if is_int.shape != (n_dims,):
            raise DetectorConfigError("WOA: integer mask must have one entry per dimension")
        self.low, self.high, self.is_int = low, high, is_int
        self.population, self.iterations = population, iterations
        self.rng, self.spiral_b = rng, spiral_b
        self.cache: dict[tuple[float, ...], float] = {}
        self.hits = 0
        self.history: list[np.ndarray] = []
        self.iteration = -1  # -1: the initial population is being evaluated
        self.best = np.empty(0)
        self.best_score = np.inf
        self.curve: list[float] = []
        self.done = False
        self.positions = low + (high - low) * rng.random((population, n_dims))
        self._request(self.positions)

    def _rounded(self, positions: np.ndarray) -> np.ndarray:
        out = positions.copy()
        out[:, self.is_int] = np.rint(out[:, self.is_int])
        return np.clip(out, self.low, self.high)

    def _request(self, positions: np.ndarray) -> None:
        """Round the population and list its candidates not evaluated yet."""
        candidates = self._rounded(positions)
        self.history.append(candidates)
        self.keys = [_key(row) for row in candidates]
        todo: dict[tuple[float, ...], int] = {}
        for row, key in enumerate(self.keys):
            if key in self.cache or key in todo:
                self.hits += 1
            else:
                todo[key] = row
        self.todo = todo
        self.pending = candidates[np.fromiter(todo.values(), dtype=np.int64, count=len(todo))]

    def ask(self) -> np.ndarray:
        """Candidates (R, D) to evaluate next, integer dimensions rounded (R may be 0)."""
        if self.done:
            raise DetectorConfigError("WOA: the search is over")
        return self.pending

    def tell(self, values: np.ndarray) -> None:
        """Fitness (R,) of the candidates of the latest :meth:`ask`; moves the population."""
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if values.shape[0] != self.pending.shape[0]:
            raise DetectorConfigError("WOA: fitness must return one value per candidate")
        for key, value in zip(self.todo, values):
            self.cache[key] = float(value) if np.isfinite(value) else np.inf
        scores = np.array([self.cache[key] for key in self.keys])
        positions = self.positions
        if self.iteration < 0:
            best_row = int(np.argmin(scores))
            self.best = self._rounded(positions[best_row : best_row + 1])[0]
            self.best_score = float(scores[best_row])
        else:
            row = int(np.argmin(scores))
            if scores[row] < self.best_score:
                self.best_score = float(scores[row])
                self.best = self._rounded(positions[row : row + 1])[0]
        self.curve.append(self.best_score)
        self.iteration += 1
        if self.iteration >= self.iterations:
            self.done = True
            return
        self.positions = self._move(self.iteration)
        self._request(self.positions)

    def _move(self, it: int) -> np.ndarray:
        """The population after iteration ``it`` (eqs. 2.1-2.8), clipped to the box."""
        rng, population, best, positions = self.rng, self.population, self.best, self.positions
        n_dims = self.low.size
        a = 2.0 - 2.0 * it / max(self.iterations, 1)  # eq. 2.3: a from 2 to 0
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
            np.abs(best - positions) * np.exp(self.spiral_b * ell) * np.cos(2.0 * np.pi * ell)
            + best
        )  # eq. 2.5
        shrink = np.where(np.abs(A) < 1.0, encircle, explore)
        return np.clip(np.where(p < 0.5, shrink, spiral), self.low, self.high)

    def result(self) -> WoaResult:
        """The outcome once :attr:`done`."""
        if not self.done:
            raise DetectorConfigError("WOA: the search is not over")
        return WoaResult(
            best=self.best,
            best_fitness=self.best_score,
            curve=np.asarray(self.curve),
            n_evaluations=len(self.cache),
            n_cache_hits=self.hits,
            history=self.history,
        )


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
        Called once per iteration with the distinct, not yet evaluated candidates (not
        called when there are none).
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
    search = WoaSearch(
        lower,
        upper,
        integer=integer,
        population=population,
        iterations=iterations,
        rng=rng,
        spiral_b=spiral_b,
    )
    while not search.done:
        candidates = search.ask()
        search.tell(fitness(candidates) if candidates.shape[0] else np.empty(0))
    return search.result()


__all__ = ["Fitness", "WoaResult", "WoaSearch", "woa"]
