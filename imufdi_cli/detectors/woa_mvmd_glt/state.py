"""WOA-MVMD-GLT's calibration state of one sensor type (sigma, biases and parity matrix in
the u_best domain, the outlier clip, the motion and budget parts) and the row scales of
u_best's filter rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.detectors.budget import EvidenceBudget, MotionState
from imufdi_cli.detectors.woa_mvmd_glt.budget import LeakMonitor
from imufdi_cli.detectors.woa_mvmd_glt.windows import _WindowStream
from imufdi_cli.maths.jitter import MotionInflation


@dataclass
class _TypeState:
    sensor_type: str
    n: int
    K: int
    alpha: float
    tuned: dict[str, Any] | None
    sigma: np.ndarray
    bias: np.ndarray
    V: np.ndarray  # whitened parity matrix (n-3, n)
    isolable: np.ndarray
    threshold: float
    stream: _WindowStream
    n_calibration: int = 0  # samples the biases were averaged over
    outlier_variance: float = (
        0.0  # variance added for outliers (variance: SI^2; clip: sigma^2 units)
    )
    outlier_cut: float | None = None  # outliers=clip: level of the standardised residual
    clipped: int = 0  # residual entries clipped so far
    spread: np.ndarray | None = None  # kappa_i folded into sigma (noise_spread), or None
    lever_arm_columns: int = 0  # columns of the rigid-body design beyond H
    motion: MotionState | None = None  # the body-frame estimate (the motion model's state)
    motion_centre: np.ndarray = field(default_factory=lambda: np.zeros(3))  # its calibration mean
    state_gain: float = 1.0  # the filter's mean DC gain over row scale (the state's unit)
    budget: EvidenceBudget | None = None  # sequential decisions under a false-alarm budget
    monitor: LeakMonitor | None = None  # per-sample test: does the evidence follow motion?
    inflation: MotionInflation | None = None  # the array config's jitter model, or None

    @staticmethod
    def clip_probe(
        values: np.ndarray, bias: np.ndarray, sigma: np.ndarray, V: np.ndarray, cut: float
    ) -> np.ndarray:
        """(N, n) bool: the residuals :meth:`clip` cuts."""
        return _TypeState._clip_shift(values, bias, sigma, V, cut)[1]

    @staticmethod
    def _clip_shift(
        values: np.ndarray, bias: np.ndarray, sigma: np.ndarray, V: np.ndarray, cut: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The move of each sensor by :meth:`clip`, (N, n) in the units of ``values``, and
        which entries were cut, (N, n) bool."""
        projector = V.T @ V
        scale = np.sqrt(np.diag(projector))
        current = np.array(values, dtype=np.float64)
        shift = np.zeros_like(current)
        cut_mask = np.zeros(current.shape, dtype=bool)
        active = np.arange(current.shape[0])
        for _ in range(current.shape[1]):  # one sensor per sample and round
            z = (((current[active] - bias) / sigma) @ projector) / scale
            largest = np.argmax(np.abs(z), axis=1)
            top = z[np.arange(active.size), largest]
            over = np.abs(top) > cut
            if not over.any():
                break
            rows, cols, top = active[over], largest[over], top[over]
            delta = np.sign(top) * (np.abs(top) - cut) * sigma[cols] / scale[cols]
            current[rows, cols] -= delta
            shift[rows, cols] += delta
            cut_mask[rows, cols] = True
            active = rows
        return shift, cut_mask

    def clip(self, values: np.ndarray) -> np.ndarray:
        """Clip each sample's standardised parity residuals at ``outlier_cut``, (N, n).

        Whitened residual ``r = P x_w`` (``P = V^T V``, ``x_w = (x - bias) / sigma``),
        standardised ``z_i = r_i / sqrt(P_ii)`` (``z_i^2`` is the GLT isolation statistic
        of sensor i, eq. 6, since V V^T = I). Per sample, the sensor with the largest
        ``|z_i|``, when it exceeds c, is moved by ``(|z_i| - c) sigma_i / sqrt(P_ii)``
        toward the others, so that ``|z_i| = c``; the residuals are computed again and the
        next largest is cut if still beyond c, until none is (two spikes in one sample are
        both cut). A one-sample spike on one sensor is cut to c; a step larger than c sigma
        is cut too, sample by sample, but stays far above the threshold once u_best
        averages it (the amplitude is estimated on the unclipped signal). Gaussian noise is
        left alone but with probability about 2 n Phi(-c) per sample (3e-3 at c = 4, n = 48).

        One at a time: a fault of hundreds of sigma on one sensor also pushes every other
        sensor's residual past c (by about 1/n of it); cutting them all at once moved the
        healthy sensors toward the faulty one and erased the fault (a 10 deg/s^2 drift went
        undetected from about 1.5 s after its onset). Once the faulty sensor is cut, the
        others' residuals are back under c.
        """
        if self.outlier_cut is None:
            return values
        shift, cut_mask = self._clip_shift(values, self.bias, self.sigma, self.V, self.outlier_cut)
        self.clipped += int(np.count_nonzero(cut_mask))
        return np.asarray(values - shift)


def _row_scales(F: np.ndarray, n_calibration: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise gain ``||F[t]||``, DC gain ``sum F[t]`` and row scale of u_best's filter rows
    F (W, R, L): the noise sigma of a row is ``sigma * row_scale``."""
    noise_gain = np.sqrt(np.einsum("wij,wij->wi", F, F))  # sigma_u = sigma * gain
    dc_gain = F.sum(axis=-1)  # (W, L): bias_u = bias * dc_gain
    # the calibration bias (mean of n_cal samples) is off by N(0, sigma^2 / n_cal),
    # carried as dc_gain * error: its variance against the filtered noise is
    # dc_gain^2 / (gain^2 n_cal) (the filter's effective length over n_cal), not
    # negligible once u_best has averaged the noise down
    inflation = 1.0 + (dc_gain / noise_gain) ** 2 / max(n_calibration, 1)
    return noise_gain, dc_gain, noise_gain * np.sqrt(inflation)
