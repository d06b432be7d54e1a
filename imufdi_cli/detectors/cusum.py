"""Capped CUSUM for a variance increase of standardized residual differences.

Page's CUSUM (Page, Biometrika 41, 1954; Basseville & Nikiforov, *Detection of Abrupt
Changes*, 1993, §2.2) on the log-likelihood ratio of a variance growth by a design factor
``K`` (``sigma1^2 = K sigma0^2``) of standardized Gaussian terms ``z``::

    l_t = 1/2 (1 - 1/K) min(z_t^2, c^2) - 1/2 ln K
    S_t = min(max(0, S_{t-1} + l_t), h + b)        alarm while S_t > h

The clip ``c`` bounds what one outlier can add; the cap ``h + b`` bounds how long the
statistic needs to come back under ``h`` after the variance returns to nominal (the null
drift ``E l = 1/2 (1 - 1/K) E min(z^2, c^2) - 1/2 ln K`` is negative, so the alarm ends
about ``b / |E l|`` samples after the fault).

The terms used here are a white residual minus the mean of its ``W`` previous samples
(:func:`local_mean_residual`; ``W = 1`` is the first difference), standardized by the
calibrated variance of that quantity. Consecutive z are correlated
(``-k / (W (W + 1))`` at lag k <= W; -1/2 for the first difference) and the scale is
estimated, so the textbook i.i.d. tail ``P(S > h) ~ C exp(-h)`` does not apply exactly.
:func:`cusum_threshold` therefore finds h by simulating the null process itself (the same
transform of white Gaussian noise, with each simulated channel's scale drawn with the
calibration's own estimation error), and extrapolates the simulated exceedance probability,
which decays exponentially in h, to the required per-sample level.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CusumDesign:
    """Increment of the variance CUSUM.

    Attributes
    ----------
    ratio : float
        Design variance ratio K > 1.
    clip : float
        z^2 is clipped at ``clip**2``.
    """

    ratio: float = 9.0
    clip: float = 5.0

    @property
    def gain(self) -> float:
        return 0.5 * (1.0 - 1.0 / self.ratio)

    @property
    def offset(self) -> float:
        return 0.5 * math.log(self.ratio)

    def increments(self, z: np.ndarray) -> np.ndarray:
        """``l = gain min(z^2, c^2) - offset`` (same shape as z; NaN z gives the null mean
        of a term, i.e. ``gain E min(z^2, c^2) - offset`` with z ~ N(0, 1), taken as
        ``gain - offset`` for the clip values used)."""
        z2 = np.where(np.isnan(z), 1.0, np.minimum(np.square(z), self.clip**2))
        return self.gain * z2 - self.offset  # type: ignore[no-any-return]


def local_mean_residual(
    series: np.ndarray, window: int, past: np.ndarray | None = None
) -> np.ndarray:
    """``(x_t - mean(x_{t-W}, .., x_{t-1})) / sqrt(1 + 1/W)`` per column, streaming.

    For white x of variance s^2 the result has variance s^2 and consecutive values are
    correlated ``-k / (W (W + 1))`` at lag k <= W (0 beyond); a constant offset of x drops
    out, a step of x stays in the result for W samples. ``W = 1`` is the first difference
    divided by sqrt(2).

    Parameters
    ----------
    series : ndarray, shape (N, n)
    window : int
        W >= 1.
    past : ndarray, shape (P, n), or None
        The samples before ``series`` (the last W are used); rows of the result without W
        previous samples (in ``past`` and ``series`` together) are NaN.

    Returns
    -------
    ndarray, shape (N, n)
    """
    n = series.shape[0]
    before = (
        np.zeros((0, series.shape[1])) if past is None else past[max(0, past.shape[0] - window) :]
    )
    joined = np.concatenate([before, series], axis=0)
    offset = before.shape[0]
    cumulative = np.concatenate([np.zeros((1, joined.shape[1])), np.cumsum(joined, axis=0)])
    out = np.full((n, series.shape[1]), np.nan)
    first = max(0, window - offset)  # first row of series with W previous samples
    if first < n:
        rows = np.arange(first, n) + offset  # index in joined
        means = (cumulative[rows] - cumulative[rows - window]) / window
        out[first:] = (joined[rows] - means) / math.sqrt(1.0 + 1.0 / window)
    return out


def run_cusum(
    increments: np.ndarray, state: np.ndarray, cap: float
) -> tuple[np.ndarray, np.ndarray]:
    """Capped CUSUM over a block.

    Parameters
    ----------
    increments : ndarray, shape (N, n)
        l_t per channel.
    state : ndarray, shape (n,)
        S before the block (0 at the start of a log).
    cap : float
        Upper bound ``h + b`` of S.

    Returns
    -------
    S : ndarray, shape (N, n)
    state : ndarray, shape (n,)
        S after the block.
    """
    out = np.empty_like(increments, dtype=np.float64)
    current = np.asarray(state, dtype=np.float64).copy()
    for i in range(increments.shape[0]):
        current = np.minimum(np.maximum(current + increments[i], 0.0), cap)
        out[i] = current
    return out, current


def cusum_threshold(
    level: float,
    design: CusumDesign,
    margin: float,
    calibration_dof: float,
    rng: np.random.Generator,
    chains: int = 256,
    steps: int = 16384,
    mean_window: int = 1,
) -> float:
    """Threshold h with per-sample ``P(S_t > h) = level`` for one channel under the null.

    The null process is simulated: ``z_t = local_mean_residual(e, W)_t / sqrt(1 + delta)``
    with white ``e ~ N(0, 1)`` (``W = 1``: ``(e_t - e_{t-1}) / sqrt(2 (1 + delta))``),
    ``delta ~ N(0, 2 / calibration_dof)`` drawn once per chain (the relative error of the
    calibrated variance), the CUSUM capped at ``h + margin``. The first
    1024 steps of each chain are dropped (start-up). The exceedance probability of the
    uncapped statistic decays as ``C exp(-theta h)``; it is estimated where at least 100
    samples exceed h and extrapolated (least squares in ``ln P`` over the upper half of that
    range) when ``level`` is smaller. The cap lowers the stationary tail only slightly for
    the margins used (it is applied in the simulation with h set to the estimate, and the
    estimate is refined once).

    Parameters
    ----------
    level : float
        Per-sample false-alarm probability of the channel, in (0, 0.1).
    design : CusumDesign
    margin : float
        b, the cap above h.
    calibration_dof : float
        Degrees of freedom of the calibrated variance (its relative variance is 2/dof).
    rng : numpy.random.Generator
    chains, steps : int
        Simulation size.
    mean_window : int
        W of :func:`local_mean_residual` (1: first differences).

    Returns
    -------
    float
        h.
    """
    burn = 1024
    scale = np.sqrt(
        np.maximum(1.0 + rng.normal(0.0, math.sqrt(2.0 / calibration_dof), chains), 0.05)
    )
    white = rng.standard_normal((steps + burn + mean_window, chains))
    z = local_mean_residual(white, mean_window)[mean_window:] / scale
    increments = design.increments(z)
    h = _tail_threshold(run_cusum(increments, np.zeros(chains), math.inf)[0][burn:], level)
    capped = run_cusum(increments, np.zeros(chains), h + margin)[0][burn:]
    return _tail_threshold(capped, level, cap=h + margin)


def _tail_threshold(values: np.ndarray, level: float, cap: float = math.inf) -> float:
    """h with ``P(values > h) = level`` from the empirical tail, extrapolated exponentially
    below the smallest probability it can estimate (100 exceedances)."""
    flat = np.sort(values.ravel())[::-1]
    n = flat.size
    reliable = 100
    if level * n >= reliable:
        return float(flat[int(level * n)])
    # ln P(S > h) against h, from P = 0.05 down to 100 exceedances
    counts = np.unique(np.geomspace(reliable, 0.05 * n, 24).astype(np.int64))
    heights = flat[counts]
    keep = heights < cap - 1e-9
    heights, probabilities = heights[keep], counts[keep] / n
    upper = slice(len(heights) // 2, None)
    slope, intercept = np.polyfit(heights[upper], np.log(probabilities[upper]), 1)
    if not slope < 0:
        return float(flat[reliable])
    return float((math.log(level) - intercept) / slope)
