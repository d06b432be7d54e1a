"""What lets ``imufdi calibrate`` stream a log of any length in bounded memory.

The calibration is made in passes over the log's blocks (:mod:`imufdi_cli.calibrate.run`):
each stage keeps sums, not samples. Three things need more than sums and are kept on
disk, not in memory:

- the 10th percentile of the static-detection spread (:class:`Spool` of the values and
  :func:`percentile`, an exact selection by radix passes over the file: the same value as
  ``np.percentile`` of all of them);
- the rows of the spread, usability and accelerometer consensus that the static intervals
  are cut from (:class:`Spool`, read back in order);
- the per-row statistic and motion energy of the jitter level fit, whose root is found by
  evaluating the exceedance rate over the spooled rows (:func:`spool_chunks`).

:class:`MovingStd` is the centred moving standard deviation of
:func:`imufdi_cli.calibrate.static.find_static`, streamed; :func:`with_neighbours` hands
each block its rows' predecessor and successor (central differences, the jitter's
backward difference).
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from typing import IO, Any

import numpy as np

#: Rows read from a spool at a time.
SPOOL_CHUNK = 1 << 16
#: Values collected in memory by :func:`order_statistics` once a radix level holds no more
#: (a 16-bit radix level of a spool of N values holds about N / 65536 of them).
SELECT_LIMIT = 1 << 16


class Spool:
    """Rows of a fixed dtype and shape appended to an anonymous temporary file (removed
    when closed or collected): memory stays at one chunk whatever the number of rows."""

    def __init__(self, dtype: Any, shape: tuple[int, ...] = ()) -> None:
        self.dtype = np.dtype(dtype)
        self.shape = tuple(shape)
        self.row_bytes = self.dtype.itemsize * int(np.prod(self.shape, dtype=np.int64))
        self.rows = 0
        self._file: IO[bytes] = tempfile.TemporaryFile(prefix="imufdi-calibrate-")

    def __len__(self) -> int:
        return self.rows

    def append(self, values: np.ndarray) -> None:
        values = np.ascontiguousarray(values, dtype=self.dtype)
        if values.shape[1:] != self.shape:
            raise ValueError(f"spool of rows {self.shape} given {values.shape[1:]}")
        self._file.seek(0, 2)
        self._file.write(values.tobytes())
        self.rows += int(values.shape[0])

    def read(self, start: int, stop: int) -> np.ndarray:
        """Rows ``start:stop`` (clipped to the spool)."""
        start, stop = max(0, start), min(stop, self.rows)
        if stop <= start:
            return np.zeros((0, *self.shape), self.dtype)
        self._file.seek(start * self.row_bytes)
        raw = self._file.read((stop - start) * self.row_bytes)
        return np.frombuffer(raw, self.dtype).reshape(-1, *self.shape)

    def chunks(self, size: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """``(first row, rows)`` in order, ``size`` rows at a time (default
        :data:`SPOOL_CHUNK`)."""
        size = size or SPOOL_CHUNK
        for start in range(0, self.rows, size):
            yield start, self.read(start, start + size)

    def close(self) -> None:
        self._file.close()


def spool_chunks(
    spools: tuple[Spool, ...], size: int | None = None
) -> Iterator[tuple[np.ndarray, ...]]:
    """The same rows of several spools of one length, chunk by chunk (default
    :data:`SPOOL_CHUNK` rows)."""
    size = size or SPOOL_CHUNK
    rows = len(spools[0])
    for start in range(0, rows, size):
        yield tuple(s.read(start, start + size) for s in spools)


def _keys(values: np.ndarray) -> np.ndarray:
    """uint64 keys in the order of the float64 ``values`` (NaN excluded by the caller):
    the IEEE bits with the sign bit flipped for positives and all bits for negatives; -0.0
    and 0.0 are one key."""
    bits = (np.asarray(values, np.float64) + 0.0).view(np.uint64)
    negative = (bits >> np.uint64(63)).astype(bool)
    return np.where(negative, ~bits, bits | np.uint64(1 << 63))


def order_statistics(spool: Spool, ranks: list[int]) -> list[float]:
    """The values of the given 0-based ranks in the sorted values of a float64 spool, exactly
    (radix selection on the order-preserving keys, 16 bits per pass; once a level holds at
    most :data:`SELECT_LIMIT` values they are collected and partitioned)."""
    out = []
    for rank in ranks:
        if not 0 <= rank < len(spool):
            raise IndexError(f"rank {rank} of {len(spool)} values")
        prefix, bits, below = 0, 0, 0
        while True:
            if bits == 64:  # every key bit fixed: the value itself
                out.append(float(_from_key(np.uint64(prefix))))
                break

            def members(chunk: np.ndarray, prefix: int = prefix, bits: int = bits) -> np.ndarray:
                keys = _keys(chunk)
                if bits == 0:
                    return keys
                return keys[(keys >> np.uint64(64 - bits)) == np.uint64(prefix)]

            count = sum(int(members(c).size) for _, c in spool.chunks())
            if count <= SELECT_LIMIT:
                keys = np.concatenate([members(c) for _, c in spool.chunks()])
                out.append(float(_from_key(np.partition(keys, rank - below)[rank - below])))
                break
            shift = np.uint64(48 - bits)
            counts = np.zeros(1 << 16, np.int64)
            for _, c in spool.chunks():
                digits = ((members(c) >> shift) & np.uint64(0xFFFF)).astype(np.int64)
                counts += np.bincount(digits, minlength=1 << 16)
            cumulative = np.cumsum(counts)
            digit = int(np.searchsorted(cumulative, rank - below, side="right"))
            below += int(cumulative[digit - 1]) if digit else 0
            prefix = (prefix << 16) | digit
            bits += 16
    return out


def _from_key(key: np.uint64) -> np.float64:
    key = np.uint64(key)
    bits = key & ~np.uint64(1 << 63) if key >> np.uint64(63) else ~key
    return np.array([bits], np.uint64).view(np.float64)[0]


def percentile(spool: Spool, q: float) -> float:
    """``np.percentile(values, q)`` (its default linear method) of a float64 spool's
    values, from their two order statistics: the virtual index, weight and interpolation
    of numpy's ``_quantile``/``_lerp``, so the result is the one numpy gives for the
    values in memory."""
    n = len(spool)
    if n == 0:
        raise ValueError("percentile of no values")
    quantile = np.true_divide(np.float64(q), 100)
    virtual = np.float64(n - 1) * quantile  # numpy's "linear" method
    previous = np.floor(virtual)
    low = int(previous)
    if virtual >= n - 1:  # numpy takes the largest value for both neighbours
        low = n - 1
    low = max(low, 0)
    high = min(low + 1, n - 1)
    gamma = virtual - previous
    found = order_statistics(spool, [low] if low == high else [low, high])
    a, b = np.float64(found[0]), np.float64(found[-1])
    diff = b - a
    value = b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma
    return float(value)


class MovingStd:
    """The centred moving standard deviation of :func:`~imufdi_cli.calibrate.static._moving_std`
    over a stream of (k, 3) rows: each row's window is ``[i - w // 2, i - w // 2 + w)``,
    moved inside ``[0, n)`` at the ends (n: every row, known at :meth:`finish`), the
    variances of the three columns summed under the root.

    :meth:`feed` returns the values of the rows whose window is complete, in order;
    :meth:`finish` the rest. Memory: about one window plus one block of rows.
    """

    def __init__(self, w: int) -> None:
        self.w = int(w)
        self.h = self.w // 2
        self.buffer = np.zeros((0, 3))
        self.start = 0  # global index of buffer[0]
        self.done = 0  # rows whose value was returned
        self.seen = 0

    def _values(self, rows: np.ndarray, n: int | None) -> np.ndarray:
        """Values of the global ``rows`` from the buffer (their windows lie in it)."""
        w = self.w if n is None else max(2, min(self.w, n))
        high_lo = (n - w) if n is not None else None
        lo = rows - w // 2
        lo = np.maximum(lo, 0)
        if high_lo is not None:
            lo = np.minimum(lo, high_lo)
        buf = self.buffer
        c1 = np.concatenate([np.zeros((1, 3)), np.cumsum(buf, axis=0)])
        c2 = np.concatenate([np.zeros((1, 3)), np.cumsum(buf * buf, axis=0)])
        at = lo - self.start
        mean = (c1[at + w] - c1[at]) / w
        var = (c2[at + w] - c2[at]) / w - mean * mean
        return np.sqrt(np.maximum(var, 0.0).sum(axis=1))

    def feed(self, rows: np.ndarray) -> np.ndarray:
        self.buffer = np.concatenate([self.buffer, np.asarray(rows, float)])
        self.seen += int(rows.shape[0])
        # row i is complete once its window [max(i - h, 0), ... + w) has been seen
        last = self.seen - self.w + self.h  # the last complete row (i - h + w <= seen)
        if self.seen < self.w:
            return np.zeros(0)
        ready = np.arange(self.done, last + 1)
        out = self._values(ready, None) if ready.size else np.zeros(0)
        self.done = last + 1
        keep_from = max(self.done - self.w, 0)  # the end rows' windows reach back to n - w
        self.buffer = self.buffer[keep_from - self.start :]
        self.start = keep_from
        return out

    def finish(self) -> np.ndarray:
        n = self.seen
        ready = np.arange(self.done, n)
        out = self._values(ready, n) if ready.size else np.zeros(0)
        self.done = n
        return out


def with_neighbours(
    blocks: Iterator[tuple[int, dict[str, np.ndarray]]],
) -> Iterator[
    tuple[int, dict[str, np.ndarray], dict[str, np.ndarray] | None, dict[str, np.ndarray] | None]
]:
    """``(first row, fields, last row before, first row after)`` for each block of
    per-row ``fields`` (dicts of arrays of one length): the neighbour rows (1-row dicts)
    are None at the ends of the stream. One block is held back."""
    held: tuple[int, dict[str, np.ndarray]] | None = None
    before: dict[str, np.ndarray] | None = None
    for start, fields in blocks:
        if not len(next(iter(fields.values()))):
            continue
        if held is not None:
            after = {k: v[:1] for k, v in fields.items()}
            yield held[0], held[1], before, after
            before = {k: v[-1:] for k, v in held[1].items()}
        held = (start, fields)
    if held is not None:
        yield held[0], held[1], before, None
