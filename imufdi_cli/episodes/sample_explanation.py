"""The one-sample episodes of a per-sample test explained by their alarmed sample alone
(no profile-likelihood fit): which of them may be, and their explanation (the mixin of
:class:`~imufdi_cli.episodes.builder.EpisodeBuilder`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from imufdi_cli.episodes.episode import SAMPLE_EXPLANATION, Episode
from imufdi_cli.episodes.fault_fit import FaultFit, WhiteNoise
from imufdi_cli.episodes.model_fits import SPIKE_CUT
from imufdi_cli.episodes.numerics import _f_quantile, _t_quantile
from imufdi_cli.episodes.white_noise import successive_difference_dof

#: A one-sample episode is explained by its sample when its residual there is at least
#: this many standard deviations (a per-sample test's chance alarms: 2.3 and up for glt at
#: alpha = 1 % on 16 IMUs), ...
SAMPLE_Z = 2.0
#: ... its window's mean within this many standard errors of 0 ...
SCREEN_Z = 4.0
#: ... and its white variance below this upper quantile of its calibrated value.
SCREEN_LEVEL = 1e-4


class SampleExplanations:
    """The sample path of :class:`~imufdi_cli.episodes.builder.EpisodeBuilder` (which
    sets the attributes and the consensus methods declared here)."""

    H: np.ndarray  # (n, 3) measurement matrix
    sensor_ids: list[str]
    sigma: np.ndarray  # (n,) calibrated noise sigma of each sensor
    confidence: float
    calibration_samples: int | None
    calibration_mean: np.ndarray | None  # (n,)
    _biases: dict[int, Any]
    _sample_matrix: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    _gain: Callable[[int], tuple[np.ndarray, float]]
    _white_of: Callable[[int, np.ndarray], WhiteNoise | None]

    def _explain_samples(self, jobs: list[tuple[Episode, np.ndarray, int]]) -> None:
        """One-sample episodes, explained by their alarmed sample alone: the isolated
        sensor's residual against the consensus of the others at that sample (its
        calibrated bias taken out), ``z = r / sigma_r`` with ``sigma_r^2 = sigma_k^2 +
        sigma_c^2``. Beyond the spike model's cut (``|z| > SPIKE_CUT``) it is a spike of
        amplitude ``|r|`` (interval ``|r| +- t sigma_r``, t on the calibration's degrees of
        freedom), else no fault model is needed (``none``: a false alarm of chance). A
        single sample cannot tell a step, a drift or noise growth from chance (no
        profile-likelihood fit over a margin would): those need alarms that last.
        ``fits`` holds the class with ``z`` in ``extra``; ``explained_by`` is
        ``sample``. Without a consensus the episode stays unexplained, as with the fits."""
        rows = np.stack([row for _, row, _ in jobs])
        residuals, sigma_r = self._sample_residuals(rows)  # (E, n), (n,)
        dof = (
            successive_difference_dof(self.calibration_samples)
            if self.calibration_samples
            else None
        )
        for (episode, _, alarm_index), r in zip(jobs, residuals, strict=True):
            names = episode.sensors
            if names:
                k = self.sensor_ids.index(names[0])
            else:  # no isolation: the sensor of the largest normalised residual
                with np.errstate(divide="ignore", invalid="ignore"):
                    scaled = np.where(np.isfinite(sigma_r), np.abs(r) / sigma_r, -np.inf)
                if not np.isfinite(scaled).any():
                    continue
                k = int(np.nanargmax(scaled))
                episode.sensors = [self.sensor_ids[k]]
                episode.isolated_by = "residual"
            if not np.isfinite(sigma_r[k]) or not math.isfinite(float(r[k])):
                continue  # no consensus for it
            z = float(r[k] / sigma_r[k])
            if abs(z) > SPIKE_CUT:
                size = abs(float(r[k]))
                half = _t_quantile(0.5 + self.confidence / 2, dof) if dof else math.inf
                half *= float(sigma_r[k])
                fit = FaultFit(
                    "spikes", size, size - half, size + half, alarm_index, math.nan, {"z": z}
                )
            else:
                fit = FaultFit("none", math.nan, math.nan, math.nan, -1, math.nan, {"z": z})
            episode.fits = [fit]
            episode.explained_by = SAMPLE_EXPLANATION

    def _sample_explains(self, episode: Episode, window: np.ndarray) -> bool:
        """Whether a one-sample episode is its alarmed sample's alone (the last row of
        ``window``): the isolated sensor's residual there is at least :data:`SAMPLE_Z`
        standard deviations (the sample carries the alarm: not so for a windowed
        statistic that one sample tipped over), and its window shows nothing but the
        calibrated noise before it: no exactly repeated raw output (a frozen output), no
        mean beyond :data:`SCREEN_Z` standard errors (a step or a drift under way) and no
        white variance above the :data:`SCREEN_LEVEL` upper quantile of its calibrated
        value (noise growth: its F(nu, nu_cal) law, successive differences). Otherwise, and
        without an isolated sensor or a consensus, the fits decide, with the margin that
        shows the fault (a lone alarm inside a longer fault)."""
        names = episode.sensors
        if not names or window.shape[0] < 5:
            return False
        k = self.sensor_ids.index(names[0])
        try:
            gain, consensus_sigma = self._gain(k)
        except ValueError:
            return False
        margin = window[:-1]
        raw = margin[:, k]
        if bool((raw[1:] == raw[:-1]).any()):  # (the method: what np.any calls)
            return False
        r = raw - margin @ gain
        sample = float(window[-1, k] - window[-1] @ gain)
        if self.calibration_mean is not None:
            bias = self._biases.get(k)
            if bias is None:
                bias = self._biases[k] = self.calibration_mean[k] - self.calibration_mean @ gain
            r = r - bias
            sample -= float(bias)
        n = r.shape[0]
        sigma_r = math.sqrt(float(self.sigma[k]) ** 2 + consensus_sigma**2)
        if not abs(sample) >= SAMPLE_Z * sigma_r:
            return False
        if abs(float(np.add.reduce(r))) / n > SCREEN_Z * sigma_r / math.sqrt(n):
            return False
        white = self._white_of(k, gain)
        if white is None:
            white_var, dof_cal = sigma_r**2, float(self.calibration_samples or n)
        else:
            white_var, dof_cal = white[0] ** 2 + white[1] ** 2, float(white[2])
        d = r[1:] - r[:-1]
        ratio = float(d @ d) / (2 * (n - 1)) / white_var
        return ratio <= _f_quantile(1.0 - SCREEN_LEVEL, successive_difference_dof(n), dof_cal)

    def _sample_residuals(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every sensor's residual against the consensus of the others, calibrated bias
        taken out, of the samples ``rows`` (E, n), and its sigma_r (n,; inf where no
        consensus exists), from the residual matrix computed once."""
        if self._sample_matrix is None:
            n = self.H.shape[0]
            A = np.zeros((n, n))
            sigma_r = np.full(n, np.inf)
            for k in range(n):
                try:
                    gain, consensus_sigma = self._gain(k)
                except ValueError:
                    continue
                A[:, k] = -gain
                A[k, k] += 1.0
                sigma_r[k] = math.sqrt(float(self.sigma[k]) ** 2 + consensus_sigma**2)
            bias = np.zeros(n) if self.calibration_mean is None else self.calibration_mean @ A
            self._sample_matrix = (A, bias, sigma_r)
        A, bias, sigma_r = self._sample_matrix
        return rows @ A - bias, sigma_r
