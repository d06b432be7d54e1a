"""Independent terms of a residual stream, and a check of the noise model on the data.

For the variance bank of :mod:`imufdi_cli.maths.variance`: :class:`Winsorizer` bounds each
residual sample's deviation from its running level (outliers and steps then add about one
term), :class:`HelmertContrasts` cuts the stream into Helmert's orthonormal contrasts in
blocks (independent N(0, s^2) terms, blind to the mean), and :class:`ModelCheck` counts the
seconds in which most sensors disagree with the calibrated noise at once (motion or chip
errors a model does not cover: a budget's level does not hold there).
"""

from __future__ import annotations

import math

import numpy as np

from imufdi_cli.maths.sequential import OUTLIER_LEVEL


class Winsorizer:
    """Bounds each residual sample's deviation from a running level before the contrasts.

    ``r~_t = m_t + clip(r_t - m_t, -c sigma, c sigma)`` with ``m_t`` the exponential
    average (time constant ``tau`` samples) of the residual up to ``t - 1``. An outlier
    then enters :class:`HelmertContrasts` at most ``c`` standard deviations from the level,
    so it adds one term near the clip and little to the block's later terms (through the
    block mean); a bias step is cut the same way while the level catches up. Without a
    fault ``|r - m|`` exceeds ``c sigma`` with probability ~1e-4 at c = 4 (``m`` carries a
    little of the noise itself), so the terms stay N(0, 1) to that precision.

    Parameters
    ----------
    sigma : ndarray, shape (n,)
        Each column's noise standard deviation (SI).
    clip : float
        c, in standard deviations.
    tau : float
        Time constant of the level, samples.
    level : ndarray, shape (n,)
        The level before the first row (e.g. the calibration mean).
    """

    def __init__(self, sigma: np.ndarray, clip: float, tau: float, level: np.ndarray) -> None:
        self.bound = clip * np.asarray(sigma, float)
        self.gain = 1.0 / max(float(tau), 1.0)
        #: standard deviation of ``r - m`` for white r (m carries gain / (2 - gain) of it)
        self.deviation_sd = np.asarray(sigma, float) * math.sqrt(
            1.0 + self.gain / (2.0 - self.gain)
        )
        self.level = np.asarray(level, float).copy()
        self.clipped = np.zeros(self.level.size)  # samples cut so far, per column
        self.outliers = np.zeros(self.level.size)  # samples beyond OUTLIER_LEVEL sd
        self.samples = 0

    def push(self, r: np.ndarray) -> np.ndarray:
        """The bounded residuals (N, n) of the next rows ``r`` (N, n)."""
        from scipy.signal import lfilter  # imported when the bank runs, not on import

        r = np.asarray(r, float)
        if r.shape[0] == 0:
            return r.copy()
        decay = 1.0 - self.gain
        # y_t = gain r_t + decay y_{t-1}: the level after row t; m_t = y_{t-1}
        after, _ = lfilter([self.gain], [1.0, -decay], r, axis=0, zi=(decay * self.level)[None, :])
        level = np.concatenate([self.level[None, :], after[:-1]])
        self.level = np.asarray(after[-1], float).copy()
        deviation = r - level
        bounded = np.clip(deviation, -self.bound, self.bound)
        cut = bounded != deviation
        self.clipped += np.count_nonzero(cut, axis=0)
        self.outliers += np.count_nonzero(
            np.abs(deviation) > OUTLIER_LEVEL * self.deviation_sd, axis=0
        )
        self.samples += r.shape[0]
        return np.where(cut, level + bounded, r)  # samples within the bound unchanged

    def outlier_share(self, columns: np.ndarray | None = None) -> float:
        """Share of the samples seen (of ``columns``, a bool mask) beyond
        ``OUTLIER_LEVEL`` standard deviations of their level, less what a Gaussian puts
        there (at least 0)."""
        counts = self.outliers if columns is None else self.outliers[columns]
        total = self.samples * counts.size
        if total == 0:
            return 0.0
        return max(0.0, float(counts.sum()) / total - math.erfc(OUTLIER_LEVEL / math.sqrt(2.0)))


class HelmertContrasts:
    """Independent, mean-free terms of a residual stream: Helmert contrasts in blocks.

    The rows are cut into consecutive blocks of ``block`` samples aligned on the sample
    count (so the terms do not depend on how the stream is split into calls). Within a
    block, sample ``j = 1 .. B-1`` (0-based) gives the term::

        z_j = (x_j - mean(x_0 .. x_{j-1})) sqrt(j / (j + 1))

    and sample 0 gives none (NaN). These are the orthonormal contrasts of the block
    (Helmert's transformation): for white noise of variance s^2 and any mean constant over
    the block they are independent N(0, s^2), ``(B - 1) / B`` of the samples' information
    about the variance; a bias, a bias step between blocks and a slow drift drop out. A
    step inside a block leaves at most ``B - 1`` terms of that block, whose squares sum to
    at most ``B/4`` of the step squared; with B = 4 at most two large terms.
    Causal: each term is known when its sample arrives.

    Parameters
    ----------
    columns : int
    block : int
        B >= 2.
    """

    def __init__(self, columns: int, block: int = 4) -> None:
        if block < 2:
            raise ValueError(f"block must be >= 2, got {block}")
        self.block = int(block)
        self.open = np.zeros((0, columns))  # the open block's samples so far (< B rows)

    def terms_per_sample(self) -> float:
        return (self.block - 1) / self.block

    def push(self, x: np.ndarray) -> np.ndarray:
        """Terms (N, columns) for the next rows ``x`` (N, columns); NaN where a sample
        starts a block."""
        x = np.asarray(x, float)
        columns = x.shape[1]
        carried = self.open.shape[0]
        joined = np.concatenate([self.open, x]) if carried else x
        total = joined.shape[0]
        full = -(-total // self.block) * self.block
        grid = np.zeros((full, columns))
        grid[:total] = joined
        grid = grid.reshape(-1, self.block, columns)
        before = np.cumsum(grid, axis=1)[:, :-1]  # sums of x_0 .. x_{j-1}, j = 1 .. B-1
        j = np.arange(1, self.block, dtype=float)[None, :, None]
        terms = np.full_like(grid, np.nan)
        terms[:, 1:] = (grid[:, 1:] - before / j) * np.sqrt(j / (j + 1.0))
        out = terms.reshape(full, columns)[carried:total]
        rest = total % self.block
        self.open = joined[total - rest :].copy() if rest else np.zeros((0, columns))
        return out


class ModelCheck:
    """Whether the calibrated noise still describes the data, one window at a time.

    The rows pushed are squared evidence relative to what the calibrated noise predicts
    (1 in expectation without a fault), one column per sensor. Over every window of
    ``window`` rows (aligned on the row count) the mean of each column is taken and the
    window is *flagged* when the median column exceeds ``ratio``: most sensors disagree with
    the noise model at once, which one faulty sensor cannot cause (motion the model does
    not cover, chip errors, a noise that changes with orientation). ``flagged`` and
    ``windows`` count them; a detector under a budget warns when the flagged time is not
    negligible (its level then does not hold there).
    """

    def __init__(self, columns: int, window: int, ratio: float = 2.0) -> None:
        self.window = max(1, int(window))
        self.ratio = float(ratio)
        self.sums = np.zeros(columns)
        self.counts = np.zeros(columns)
        self.rows = 0
        self.windows = 0
        self.flagged = 0
        self.worst = 0.0  # largest median ratio of a window

    def push(self, squares: np.ndarray) -> None:
        """Rows (N, columns) of relative squares (NaN: no term)."""
        squares = np.asarray(squares, float)
        position = 0
        while position < squares.shape[0]:
            room = self.window - self.rows % self.window
            part = squares[position : position + room]
            present = ~np.isnan(part)
            self.sums += np.where(present, part, 0.0).sum(axis=0)
            self.counts += present.sum(axis=0)
            self.rows += part.shape[0]
            position += part.shape[0]
            if self.rows % self.window == 0:
                self._close()

    def _close(self) -> None:
        counted = self.counts > 0
        if counted.any():
            median = float(np.median(self.sums[counted] / self.counts[counted]))
            self.windows += 1
            self.flagged += median > self.ratio
            self.worst = max(self.worst, median)
        self.sums[:] = 0.0
        self.counts[:] = 0.0

    def share(self) -> float:
        """Share of the complete windows that were flagged."""
        return self.flagged / self.windows if self.windows else 0.0
