"""The pieces of a span's walk through :class:`~imufdi_cli.maths.sequential.bank.CusumBank`:
the references applied ahead of the sub-chunks (:class:`_Feed`), the ring of recent rows
kept for onsets (:class:`_History`), a sub-chunk's transformed evidence (:class:`_Chunk`)
and the running sums and minima carried from one sub-chunk to the next (:class:`_Running`,
:class:`_Walk`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from imufdi_cli.maths.sequential.bank import _Reference


class _Feed:
    """The references applied to a span's rows ahead of its sub-chunks: in pieces that end
    on the references' sub-block boundaries while they learn (so that each sub-block's
    sums are those of one pass), as the sub-chunks need them."""

    def __init__(
        self,
        reference: _Reference,
        z: np.ndarray,
        x: np.ndarray | None,
        factors: np.ndarray,
        samples: int,
        *,
        frozen: bool,
    ) -> None:
        self.reference, self.z, self.x, self.factors = reference, z, x, factors
        self.samples, self.frozen = samples, frozen
        self.zr = np.empty_like(z)
        self.variance = np.empty(z.shape[0])
        self.marks: list[tuple[int, tuple[np.ndarray, ...]]] = []
        self.done = 0

    def _apply(self, hi: int) -> None:
        lo = self.done
        rows = slice(lo, hi)
        x = None if self.x is None else self.x[rows]
        _, _, marks = self.reference.apply(
            self.z[rows],
            x,
            self.factors[rows],
            self.frozen,
            self.samples + lo,
            out=self.zr[rows],
            variance=self.variance[rows],
        )
        self.marks.extend((lo + start, snap) for start, snap in marks)
        self.done = hi

    def rows(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """z' and s^2 of rows ``lo:hi`` of the span."""
        if hi > self.done:
            end = hi
            if not self.frozen:  # up to a sub-block boundary (or the span's end)
                stride = self.reference.stride
                end = min(self.z.shape[0], hi + (-(self.samples + hi) % stride))
            self._apply(end)
        return self.zr[lo:hi], self.variance[lo:hi]

    def reference_variance(self, lo: int, hi: int) -> np.ndarray:
        """(hi - lo, n): the references' variance ``w`` each of rows ``lo:hi`` of the span
        was standardized by (it moves at the sub-block boundaries the feed has passed)."""
        starts = np.array([start for start, _ in self.marks])
        table = np.stack([snap[1] for _, snap in self.marks])
        return table[np.searchsorted(starts, np.arange(lo, hi), side="right") - 1]

    def rewind(self, row: int) -> None:
        """The references as they were on the span's row ``row`` (an episode opens there)."""
        value = self.marks[0][1]
        for start, snap in self.marks:
            if start <= row:
                value = snap
        self.reference.restore(value)


class _History:
    """The last ``length`` rows of u, z'/s^2 and 1/s^2 (N, n), kept in a ring."""

    def __init__(self, length: int, n: int) -> None:
        self.length = max(0, length)
        self.u = np.zeros((self.length, n))
        self.q = np.zeros((self.length, n))
        self.w = np.zeros(self.length)
        self.filled = 0
        self.end = 0  # where the next row goes

    def add(self, u: np.ndarray, q: np.ndarray, w: np.ndarray) -> None:
        if self.length == 0:
            return
        rows = u.shape[0]
        if rows >= self.length:
            u, q, w = u[-self.length :], q[-self.length :], w[-self.length :]
            rows = self.length
        first = min(rows, self.length - self.end)
        for target, source in ((self.u, u), (self.q, q), (self.w, w)):
            target[self.end : self.end + first] = source[:first]
            target[: rows - first] = source[first:]
        self.end = (self.end + rows) % self.length
        self.filled = min(self.length, self.filled + rows)

    def _order(self, values: np.ndarray, count: int) -> np.ndarray:
        """The last ``count`` rows of ``values`` (a ring), oldest first."""
        count = min(count, self.filled)
        start = (self.end - count) % self.length if self.length else 0
        if start + count <= self.length:
            return values[start : start + count]
        return np.concatenate([values[start:], values[: start + count - self.length]])

    def last_inverse(self) -> np.ndarray:
        return self._order(self.w, self.filled)

    def last_column(self, sensor: int) -> np.ndarray:
        return self._order(self.u[:, sensor], self.filled)

    def last_q(self, count: int) -> np.ndarray:
        return self._order(self.q, count)


@dataclass
class _Chunk:
    """A sub-chunk of a span: u of (1), z'/s^2, 1/s^2 of its rows and the designs run."""

    u: np.ndarray
    q: np.ndarray
    inverse: np.ndarray
    ran: list[bool]


class _Running:
    """A cumulative sum (and its running minimum) carried across sub-chunks: the same
    floats as one ``cumsum`` (``minimum.accumulate``) over all their rows."""

    def __init__(self, total: np.ndarray, minimum: float) -> None:
        self.total = total
        self.low = minimum
        self.rows = 0

    def sum(self, values: np.ndarray) -> np.ndarray:
        """The running sum over the next rows ``values`` (M, k)."""
        out = values.copy()
        if self.rows:
            out[0] = self.total + out[0]
        np.cumsum(out, axis=0, out=out)
        self.total = out[-1].copy()
        self.rows += values.shape[0]
        return out

    def minimum(self, cumulative: np.ndarray) -> np.ndarray:
        """``min(minimum so far, running minimum of cumulative)`` per row (1-D)."""
        low = np.minimum(np.minimum.accumulate(cumulative), self.low)
        self.low = float(low[-1])
        return low


@dataclass
class _Walk:
    """The carried state of a span's CUSUMs after its last row: every hypothesis'
    statistic ``state`` (2 D, n), the running minimum of its cumulative sum (None: the
    design did not run on the last sub-chunk, its statistic is 0), the running sums of u
    and 1/s^2, and the rows walked."""

    state: np.ndarray
    low: list[np.ndarray | None]
    w1: np.ndarray
    w2: float = 0.0
    rows: int = 0

    @classmethod
    def start(cls, state: np.ndarray) -> _Walk:
        flat = np.array(state, dtype=float).reshape(-1, state.shape[-1])
        return cls(flat, [None] * flat.shape[0], np.zeros(flat.shape[1]))

    def copy(self) -> _Walk:
        return _Walk(self.state.copy(), list(self.low), self.w1.copy(), self.w2, self.rows)

    def carried_sum(self, u: np.ndarray) -> np.ndarray:
        """The span's cumulative sum of u over the next rows (M, n)."""
        w1 = u.copy()
        if self.rows:
            w1[0] = self.w1 + w1[0]
        np.cumsum(w1, axis=0, out=w1)
        return w1

    def carried_drift(self, inverse: np.ndarray) -> np.ndarray:
        """The span's cumulative sum of 1/s^2 over the next rows (M,)."""
        w2 = inverse.copy()
        if self.rows:
            w2[0] = self.w2 + w2[0]
        np.cumsum(w2, out=w2)
        return w2

    def minimum(self, k: int, factor: float, half: float) -> np.ndarray:
        """What hypothesis k's running minimum starts the next rows from: ``-S_0`` at the
        span's start, the carried minimum, or (its design idle on the last sub-chunk, its
        statistic 0 there) its cumulative sum on the last row."""
        if self.rows == 0:
            return -self.state[k]
        low = self.low[k]
        if low is not None:
            return low
        return self.w1 * factor - self.w2 * half

    def keep(self, k: int, last: np.ndarray, minimum: np.ndarray) -> None:
        self.state[k] = last
        self.low[k] = minimum

    def rest(self, k: int) -> None:
        self.state[k] = 0.0
        self.low[k] = None

    def advance(self, w1: np.ndarray, w2: float, rows: int) -> None:
        self.w1 = w1.copy()
        self.w2 = w2
        self.rows += rows
