"""bank's thresholds: robust noise scale, thresholds estimated on calibration residuals or
set by Bonferroni on the normal distribution.
"""

from __future__ import annotations

import math

import numpy as np

from imufdi_cli.detectors.base import (
    DetectionBlock,
)
from imufdi_cli.maths.parity import (
    sigma_estimate_variance,
)
from imufdi_cli.maths.quantiles import chi2, f

#: Scale from the median absolute deviation to the standard deviation of a Gaussian.
MAD_TO_STD = 1.4826

#: Smallest standard deviation used to normalise a residual (avoids dividing by 0 on
#: noiseless data), relative to the residual's scale.
SIGMA_FLOOR = 1e-12


def robust_std(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Standard deviation from the median absolute deviation (robust to rare outliers)."""
    centre = np.median(values, axis=axis, keepdims=True)
    return np.asarray(MAD_TO_STD * np.median(np.abs(values - centre), axis=axis))


def estimated_threshold(
    alpha: float, H: np.ndarray, sigma: np.ndarray, P: np.ndarray, n_samples: int
) -> float:
    """Bonferroni threshold of ``max_j z_j^2`` with sigma and bias from the calibration.

    ``z_j = e_j / s_j`` with the predicted std ``s_j^2 = sum_k P_jk^2 sigma_k^2`` made of
    estimated variances ``sigma_hat_k^2 = sigma_k^2 (1 + delta_k)``
    (:func:`imufdi_cli.maths.parity.sigma_estimate_variance`): ``s_hat_j^2 / s_j^2 - 1`` has variance
    ``sum_k (P_jk^2 sigma_k^2)^2 Var delta_k / s_j^4``, so z_j^2 is ``F(1, nu_j)`` with
    ``nu_j = 2 / that`` rather than chi2(1) (the mean nu over sensors is used). The bias is
    a median of N residuals: its error multiplies the residual variance by
    ``1 + pi / (2 N)``. Level ``alpha / n`` per residual (Bonferroni).
    """
    n = H.shape[0]
    scale_variance = sigma_estimate_variance(H, sigma, n_samples)
    parts = P**2 * sigma[None, :] ** 2  # (n, n)
    relative = (parts**2 @ scale_variance) / np.maximum(parts.sum(axis=1) ** 2, 1e-300)
    nu = 2.0 / float(np.mean(relative))
    quantile = float(f.ppf(1.0 - alpha / n, 1, nu))
    return quantile * (1.0 + math.pi / (2.0 * n_samples))


def bonferroni_threshold(alpha: float, n_tests: int) -> float:
    """chi-square(1) quantile at ``1 - alpha / n_tests`` for a squared unit-normal residual."""
    return float(chi2.ppf(1.0 - alpha / n_tests, 1))


def _empty_block(n_sensors: int) -> DetectionBlock:
    return DetectionBlock.empty(0, n_sensors)
