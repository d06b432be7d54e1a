"""A detection of its own: the variance drop of a frozen output.

A frozen output on a motion the sensor tracks exactly (a constant-rate turntable) loses
only its noise, which no mean-shift detector sees: :class:`VarianceDropMonitor`, a
one-sided successive-difference variance test, raises episodes of its own under the name
``variance-drop`` (one builder per sensor type runs it,
:class:`~imufdi_cli.episodes.builder.EpisodeBuilder`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imufdi_cli.episodes.numerics import _f_quantile
from imufdi_cli.episodes.white_noise import successive_difference_dof

#: name under which variance-drop episodes are written (``detector`` field)
VARIANCE_DROP = "variance-drop"


@dataclass
class _Rows:
    """Status rows in the shape :meth:`EpisodeBuilder.rows` reads (a DetectionBlock's
    alarm, isolated, statistic and threshold)."""

    alarm: np.ndarray
    isolated: np.ndarray
    statistic: np.ndarray
    threshold: np.ndarray


class VarianceDropMonitor:
    """One-sided test that a sensor's white noise has dropped: a frozen (stuck) output.

    A frozen output on a motion the sensor would have tracked exactly (a constant-rate
    turntable) equals the truth plus its bias; only its noise is gone, so the mean-shift
    tests of the detectors cannot see it. Against the consensus of the others its
    residual ``r_k`` (:func:`leave_one_out`) then carries only the consensus noise. Over
    the last ``W`` successive differences, ``q_k = sum (r_{k,i+1} - r_{k,i})^2 / (2 W)``
    estimates the white variance of ``r_k`` (slow motion errors do not enter it) and is
    compared with its calibrated value ``v_k = sigma_k^2 + sigma_c^2`` (white parts,
    :func:`white_sigma`). Both are successive-difference estimates, so ``q_k / v_k`` is
    about F(nu_W, nu_cal,k) (nu_W from :func:`successive_difference_dof`, nu_cal,k the
    calibrated v_k's own degrees of freedom,
    :func:`~imufdi_cli.episodes.white_noise.white_variance_dof`); the test alarms when a
    sensor's ratio falls below its F quantile at ``alpha``, and isolates the sensor whose
    ratio is furthest below (relative to its quantile). The test is one-sided: more noise, outliers and unmodelled motion only
    raise ``q_k``.

    The status row of a sample is decided at that sample (no look-ahead); ``statistic``
    is ``-ln`` of the smallest ratio, each rescaled from its sensor's quantile to the
    median one (``ratio_k * quantile / quantile_k``), and ``threshold`` ``-ln(quantile)``
    of that median (an alarm when statistic > threshold; with one dof for all sensors,
    ``-ln(min ratio)`` against the common quantile). Memory: the last W differences per
    sensor.

    Parameters
    ----------
    residual_matrix : ndarray, shape (n, n)
        ``measurements @ residual_matrix`` are the leave-one-out residuals of all sensors
        (column k: ``e_k - g_k``); sensors without a consensus have a zero column.
    white_variance : ndarray, shape (n,)
        Calibrated white variance of each residual, SI^2 (inf: never tested).
    window : int
        W, successive differences per test.
    alpha : float
        Probability that one healthy sensor's window falls below the threshold.
    calibration_dof : float or array_like, shape (n,)
        Degrees of freedom of the white variances' calibration estimates (one for all
        sensors, or one each).
    """

    def __init__(
        self,
        residual_matrix: np.ndarray,
        white_variance: np.ndarray,
        *,
        window: int,
        alpha: float,
        calibration_dof: float | np.ndarray,
    ) -> None:
        self.A = np.asarray(residual_matrix, dtype=np.float64)
        self.variance = np.asarray(white_variance, dtype=np.float64)
        self.window = int(window)
        dof_window = successive_difference_dof(self.window + 1)
        dofs = np.broadcast_to(np.asarray(calibration_dof, dtype=np.float64), self.variance.shape)
        #: (n,) each sensor's quantile of q_k / v_k at alpha
        self.quantiles = np.array([_f_quantile(alpha, dof_window, float(d)) for d in dofs])
        #: the quantile the statistic is expressed against: the sensors' median
        self.quantile = float(np.median(self.quantiles)) if self.quantiles.size else 1.0
        with np.errstate(divide="ignore", invalid="ignore"):
            #: (n,) ``quantile / quantiles``: each sensor's rescaling to the median quantile
            self._rescale = self.quantile / self.quantiles
        self._last: np.ndarray | None = None  # last residual row
        self._tail = np.zeros((0, self.A.shape[1]))  # last W half squared differences

    def update(self, measurements: np.ndarray) -> _Rows:
        """Status rows of the next N samples (N, n) in SI units."""
        # (each step below is an elementwise operation of the plain formula, done in place
        # in one buffer: the same floats, without a 1.7 MB temporary per step)
        r = np.asarray(measurements, dtype=np.float64) @ self.A
        n = r.shape[0]
        first = self._last is None
        held = self._tail.shape[0]
        fresh = n - 1 if first and n else n  # the first sample has no difference
        # [the last W half squared differences held | the new ones], one buffer
        joined = np.empty((held + fresh, r.shape[1]))
        joined[:held] = self._tail
        half_sq = joined[held:]
        if fresh:
            if self._last is None:
                np.subtract(r[1:], r[:-1], out=half_sq)
            else:
                np.subtract(r[:1], self._last[None, :], out=half_sq[:1])
                np.subtract(r[1:], r[:-1], out=half_sq[1:])
            np.square(half_sq, out=half_sq)
            np.multiply(0.5, half_sq, out=half_sq)
            # an invalid sample gives no evidence either way: its difference counts as
            # expected
            if not math.isfinite(float(np.add.reduce(half_sq, axis=None))):
                # (a finite sum: every value finite; else look, overflow included)
                invalid = ~np.isfinite(half_sq)
                np.copyto(half_sq, np.broadcast_to(self.variance, half_sq.shape), where=invalid)
        if n:
            self._last = r[-1].copy()
        del r  # (the block's residuals are not needed past here: memory)
        cumulative = np.empty((joined.shape[0] + 1, joined.shape[1]))
        cumulative[0] = 0.0
        np.cumsum(joined, axis=0, out=cumulative[1:])
        tail = joined[-self.window :].copy()
        stop = np.arange(held + 1, held + fresh + 1)  # window of the j-th new difference
        ready = stop >= self.window
        if held + 1 >= self.window:  # every window complete: the same rows as slices
            ratio = np.subtract(
                cumulative[held + 1 : held + fresh + 1],
                cumulative[held + 1 - self.window : held + fresh + 1 - self.window],
                out=joined[:fresh],  # (joined is summed: its buffer holds the ratios)
            )
        else:
            ratio = cumulative[stop] - cumulative[np.maximum(stop - self.window, 0)]
        del cumulative
        with np.errstate(divide="ignore", invalid="ignore"):
            # each ratio against its own sensor's quantile, expressed against the median
            np.divide(ratio, self.window, out=ratio)
            np.divide(ratio, self.variance, out=ratio)
            np.multiply(ratio, self._rescale, out=ratio)
        if not math.isfinite(float(np.add.reduce(ratio, axis=None))):
            ratio[~np.isfinite(ratio)] = np.inf
        worst = np.argmin(ratio, axis=1) if ratio.shape[0] else np.zeros(0, np.int64)
        lowest = ratio[np.arange(ratio.shape[0]), worst]
        alarm = ready & (lowest < self.quantile)
        statistic = np.where(ready, -np.log(np.maximum(lowest, 1e-300)), -np.inf)
        self._tail = tail
        pad = n - fresh  # the very first sample of the log: no test yet
        return _Rows(
            alarm=np.concatenate([np.zeros(pad, bool), alarm]),
            isolated=np.concatenate([np.full(pad, -1), np.where(alarm, worst, -1)]).astype(
                np.int64
            ),
            statistic=np.concatenate([np.full(pad, -np.inf), statistic]),
            threshold=np.full(n, -math.log(self.quantile)),
        )
