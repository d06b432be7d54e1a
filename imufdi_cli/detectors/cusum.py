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

This is the per-sample test's CUSUM (a level per sample, correlated local-mean terms: the
health detector's variance checks and cnn-map's input test at ``alpha``). Under a
false-alarm budget every variance CUSUM (noise-glr, cnn-map's input test) is the bank of
:mod:`imufdi_cli.maths.variance` instead, on independent Helmert contrasts, with thresholds
from the Brook-Evans run lengths of its exact increments rather than a simulation.
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

    def increments(self, z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``l = gain min(z^2, c^2) - offset`` (same shape as z; NaN z gives the null mean
        of a term, i.e. ``gain E min(z^2, c^2) - offset`` with z ~ N(0, 1), taken as
        ``gain - offset`` for the clip values used).

        ``out`` (float64, z's shape; may be z itself) receives the result in place of a
        new array, with the same values.
        """
        nan = np.isnan(z)
        z2 = np.square(z, out=out)
        np.minimum(z2, self.clip**2, out=z2)
        if nan.any():
            np.copyto(z2, 1.0, where=nan)
        z2 *= self.gain
        z2 -= self.offset
        return z2


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
    n, columns = series.shape
    before = np.zeros((0, columns)) if past is None else past[max(0, past.shape[0] - window) :]
    offset = before.shape[0]
    # the dtype the arithmetic has always run in: float64 zeros (no past) promote float32
    dtype = np.result_type(before, series)
    joined = series if offset == 0 and series.dtype == dtype else np.concatenate([before, series])
    out = np.empty((n, columns), dtype=np.float64)
    first = min(n, max(0, window - offset))  # first row of series with W previous samples
    out[:first] = np.nan
    if first == n:
        return out
    # cumulative[k] = sum of joined[:k] (sequential sums in dtype, as numpy's cumsum)
    cumulative = np.empty((joined.shape[0] + 1, columns), dtype=np.float64)
    cumulative[0] = 0.0
    if dtype != np.float64:
        cumulative[1:] = np.cumsum(joined, axis=0)
    elif columns < 64:
        np.cumsum(joined, axis=0, out=cumulative[1:])
    else:  # the same sums row by row: numpy's cumsum down a C-ordered axis 0 is slower
        previous = cumulative[0]
        for row, total in zip(joined, cumulative[1:]):
            np.add(previous, row, out=total)
            previous = total
    lo, hi = first + offset, n + offset  # rows of joined with W previous samples
    result = out[first:]
    np.subtract(cumulative[lo:hi], cumulative[lo - window : hi - window], out=result)
    result /= window  # the mean of the W previous samples
    np.subtract(joined[lo:hi], result, out=result)
    result /= math.sqrt(1.0 + 1.0 / window)
    return out


def run_cusum(
    increments: np.ndarray, state: np.ndarray, cap: float
) -> tuple[np.ndarray, np.ndarray]:
    """Capped CUSUM over a block.

    One pass over time, numpy across the channels (the recursion is sequential in time and
    independent across channels), every step written in place into the output.

    Parameters
    ----------
    increments : ndarray, shape (N, n)
        l_t per channel.
    state : ndarray, shape (n,)
        S before the block (0 at the start of a log).
    cap : float
        Upper bound ``h + b`` of S (``inf``: uncapped).

    Returns
    -------
    S : ndarray, shape (N, n)
    state : ndarray, shape (n,)
        S after the block.
    """
    out = np.empty_like(increments, dtype=np.float64)
    current = np.asarray(state, dtype=np.float64).copy()
    _page_recursion(increments, current, cap, out)
    if out.shape[0]:
        current = out[-1].copy()
    return out, current


def _page_recursion(increments: np.ndarray, start: np.ndarray, cap: float, out: np.ndarray) -> None:
    """``out[t] = min(max(out[t-1] + increments[t], 0), cap)`` from ``out[-1] = start``, in
    place (the minimum is skipped for an infinite cap: it changes nothing)."""
    previous = start
    capped = not math.isinf(cap)
    for step, row in zip(increments, out):
        np.add(previous, step, out=row)
        np.maximum(row, 0.0, out=row)
        if capped:
            np.minimum(row, cap, out=row)
        previous = row


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

    The capped run is not simulated again from the start: a chain whose uncapped statistic
    never exceeds ``h + margin`` has the same capped path (the minimum never acts), and the
    others are rerun from the first step any of them exceeds it. The threshold is the same,
    bit for bit, as two full runs.

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
    increments = local_mean_residual(white, mean_window)[mean_window:]
    increments /= scale  # z
    design.increments(increments, out=increments)
    path = white[mean_window:]  # white is not read again: its memory holds S
    _page_recursion(increments, np.zeros(chains), math.inf, path)
    top = _TopValues(path[burn:], level)
    h = _tail_threshold(top, level)
    cap = h + margin
    over = path > cap
    hit = np.flatnonzero(over.any(axis=0))  # chains the cap would change
    if hit.size:
        since = int(over[:, hit].argmax(axis=0).min())
        start = path[since - 1, hit] if since > 0 else np.zeros(hit.size)
        rerun = np.empty((path.shape[0] - since, hit.size))
        _page_recursion(increments[since:, hit], start, cap, rerun)
        path[since:, hit] = rerun
        top = _TopValues(path[burn:], level)
    return _tail_threshold(top, level, cap=cap)


class _TopValues:
    """The largest values of a sample, in decreasing order, as far as the tail estimates of
    :func:`_tail_threshold` reads them at ``level`` (the ``level`` and 5 % quantiles).

    A partial sort: the values read are the order statistics of the full sort, exactly.
    """

    def __init__(self, values: np.ndarray, level: float) -> None:
        flat = values.ravel()
        self.n = flat.size
        keep = min(self.n, int(max(level, 0.05) * self.n) + 102)
        # S is mostly 0 under the null, and selection is slow among many equal values:
        # the largest values are among the positive ones when there are enough of them
        positive = flat[flat > 0.0]
        if positive.size >= keep:
            flat = positive
        if keep < flat.size:
            flat = np.partition(flat, flat.size - keep)[flat.size - keep :]
        self.descending = np.sort(flat)[::-1]


def _tail_threshold(top: _TopValues, level: float, cap: float = math.inf) -> float:
    """h with ``P(values > h) = level`` from the empirical tail, extrapolated exponentially
    below the smallest probability it can estimate (100 exceedances)."""
    flat = top.descending  # flat[k]: the (k+1)-th largest value
    n = top.n
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
