"""Streaming moving sums across consecutive blocks (pca-parity, noise-glr, cnn-map)."""

from __future__ import annotations

import numpy as np


class MovingWindow:
    """Streaming moving sums over the last ``length`` rows, across consecutive blocks.

    ``push(values)`` returns, for every new row, the sum of the rows of the window ending at
    it and the number of rows in that window (fewer than ``length`` at the start of the log).
    """

    def __init__(self, length: int, width: int) -> None:
        if length < 1:
            raise ValueError("window length must be >= 1")
        self.length = length
        self.tail = np.zeros((0, width))
        self.seen = 0

    def push(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Moving sums (N, width) and window counts (N,) for a block of rows (N, width)."""
        values = np.asarray(values, dtype=np.float64)
        n_new = values.shape[0]
        joined = np.concatenate([self.tail, values], axis=0)
        cumulative = np.concatenate([np.zeros((1, joined.shape[1])), np.cumsum(joined, axis=0)])
        end = np.arange(self.tail.shape[0], joined.shape[0]) + 1  # exclusive end in joined
        start = np.maximum(end - self.length, 0)
        sums = cumulative[end] - cumulative[start]
        counts = np.minimum(self.seen + np.arange(1, n_new + 1), self.length)
        self.seen += n_new
        keep = self.length - 1
        self.tail = joined[max(joined.shape[0] - keep, 0) :] if keep > 0 else joined[:0]
        return sums, counts
