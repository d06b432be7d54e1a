"""The white part of the calibrated noise, from successive differences, and how well the
calibration knows it.

:func:`white_sigma` estimates each sensor's white noise from the differenced calibration
window (slow errors and shifts of the consensus do not enter it);
:func:`white_sigma_covariance`, :func:`white_sigma_excess` and :func:`white_sigma_spread`
give the spread of that estimate, which :func:`_calibration_dof` turns into the
calibration's degrees of freedom in the noise factor's F interval
(:func:`~imufdi_cli.episodes.model_fits._white_noise_fit`) and
:class:`~imufdi_cli.episodes.variance_drop.VarianceDropMonitor` tests against.
"""

from __future__ import annotations

import math

import numpy as np

from imufdi_cli.maths.parity import residual_projector


def successive_difference_dof(n: int) -> float:
    """Degrees of freedom of the successive-difference variance estimate of n white samples.

    ``q = sum_i (e_{i+1} - e_i)^2 / 2`` has mean ``(n - 1) sigma^2`` and variance
    ``(3 n - 4) sigma^4`` (neighbouring differences correlate with -1/2; von Neumann
    1941); a scaled chi-square with the same two moments has ``nu = 2 (n - 1)^2 / (3 n -
    4)`` degrees of freedom (Satterthwaite 1946), about 2 n / 3.
    """
    return 2.0 * (n - 1) ** 2 / max(3 * n - 4, 1)


def _calibration_dof(
    var_hat: float,
    sigma_k: float,
    consensus_sigma: float,
    spread: tuple[float, float, float],
    default: float,
) -> float:
    """Degrees of freedom of the calibration's part of the noise factor's F interval.

    The factor is ``f^2 = (v - c^2) / s_k`` with ``s = sigma_hat^2`` the white variances
    of the calibration (``c^2 = sum_j g_j^2 s_j`` the consensus's) and v the episode's.
    Their errors enter ``log f^2`` with the gradient ``-(g^2 / (v - c^2) + e_k / s_k)``,
    so the calibration adds ``kappa = A / u^2 + 2 B / (u s_k) + D / s_k^2`` to its
    variance (``u = v - c^2``; A, B, D from :func:`white_sigma_spread`). F(nu, nu_cal)
    puts ``a^2 2 / nu_cal`` there (``a = v / u``: the interval is mapped through
    ``v -> sqrt(v - c^2)``), so ``nu_cal = 2 a^2 / kappa`` matches the second moment
    (Satterthwaite 1946). Two things make it differ from the successive-difference
    dof of n_cal samples: each sensor's variance is solved from parity residuals that
    carry the other sensors' noise (non-negative least squares in :func:`white_sigma`:
    1.14 times the variance for 16 co-aligned IMUs), and the consensus's variance, taken
    off, errs with the other sensors' estimates (negatively correlated with sensor k's
    when few sensors share the residuals: the errors partly cancel). ``default`` when
    ``v <= c^2`` or the spread is degenerate.
    """
    a_term, b_term, d_term = spread
    u = var_hat - consensus_sigma**2
    if u <= 0 or sigma_k <= 0:
        return default
    s_k = sigma_k**2
    kappa = a_term / u**2 + 2 * b_term / (u * s_k) + d_term / s_k**2
    if not math.isfinite(kappa) or kappa <= 0:
        return default
    return max(2 * (var_hat / u) ** 2 / kappa, 1.0)


def white_sigma(H: np.ndarray, measurements: np.ndarray) -> np.ndarray:
    """Per-sensor white-noise sigma from successive differences of a fault-free window.

    :func:`~imufdi_cli.maths.parity.residual_sigma` of the differenced measurements,
    divided by sqrt(2): differencing white noise doubles its variance, and what varies
    slowly (motion-dependent scale and misalignment errors, bias wander) nearly vanishes,
    where the parity residuals of the measurements themselves carry it (on conical6, whose
    calibration window spans the start of the motion: 0.041 deg/s against a white 0.030).

    Parameters
    ----------
    H : array_like, shape (n, 3)
    measurements : array_like, shape (N, n), N >= 3, SI

    Returns
    -------
    ndarray, shape (n,), SI
    """
    from imufdi_cli.maths.parity import residual_sigma

    m = np.asarray(measurements, dtype=np.float64)
    return residual_sigma(H, np.diff(m, axis=0)) / math.sqrt(2.0)


def white_sigma_covariance(H: np.ndarray, sigma: np.ndarray, n_samples: int) -> np.ndarray:
    """Covariance of the white variances :func:`white_sigma` estimates, SI^4.

    :func:`~imufdi_cli.maths.parity.residual_sigma` solves ``M s = v`` for the
    variances s, ``M = (I - S)∘(I - S)``, v the variances of the parity residuals (here of
    the differenced samples, halved). For Gaussian white noise ``Cov(v) = 2/nu (C∘C)``
    with ``C = (I - S) diag(sigma^2) (I - S)^T`` (Isserlis) and nu the
    successive-difference degrees of freedom of n_samples (:func:`successive_difference_dof`),
    so ``Cov(s) = M^-1 Cov(v) M^-T`` (the same propagation as
    :func:`~imufdi_cli.maths.parity.sigma_estimate_variance`, with nu for N - 1, and
    kept whole: the off-diagonal terms are what the consensus variance shares with
    sigma_k^2).

    Parameters
    ----------
    H : ndarray, shape (n, q)
    sigma : ndarray, shape (n,), SI
        The estimated white sigmas (plugged in for the true ones).
    n_samples : int
        Calibration samples.

    Returns
    -------
    ndarray, shape (n, n); shape (0, 0) without parity residuals, with fewer than 3
    samples, or when M is singular (e.g. six single-axis gyros on a cone: residual_sigma
    then returns one common sigma; its pooled degrees of freedom, about (n - q) times
    more, made conical6's intervals too narrow in the episodes, whose windows carry motion
    errors the calibration does not, so the successive-difference dof of n_samples stays).
    """
    H = np.asarray(H, dtype=np.float64)
    n, q = H.shape
    if n_samples < 3 or n <= q:
        return np.zeros((0, 0))
    projector = residual_projector(H)
    mixing = projector**2
    sig = np.asarray(sigma, dtype=np.float64)
    covariance = projector @ np.diag(sig**2) @ projector.T
    spread = 2.0 / successive_difference_dof(n_samples) * covariance**2  # Cov(v)
    singular = np.linalg.svd(mixing, compute_uv=False)
    if not singular[-1] > 1e-8 * singular[0]:
        return np.zeros((0, 0))
    inverse = np.linalg.inv(mixing)
    return inverse @ spread @ inverse.T


def white_sigma_excess(
    H: np.ndarray, measurements: np.ndarray, *, outlier_cut: float = 4.0
) -> float:
    """How much more the white variances of :func:`white_sigma` spread than Gaussian white
    noise says, measured on the calibration window itself (>= 1).

    :func:`white_sigma_covariance` assumes Gaussian white noise. The variances are
    ``s = M^-1 v`` (:func:`white_sigma_covariance`), v the means of ``x_t = r_t^2`` (the
    squared parity residuals of the differenced samples), so each ``s_k`` is the mean of
    the series ``z_t = (M^-1 x_t)_k``, whose mean has the variance ``(g0 + 2 g1) / N'``
    (autocovariances of z to lag 1: neighbouring differences correlate, the others do
    not). Under Gaussian white noise ``g0 + 2 g1 = 3 w^T (C∘C) w`` (w the row k of
    ``M^-1``, C the covariance of the differenced residuals; Isserlis, neighbouring
    differences correlating with -1/2). Outliers that pass the 4-sigma cut once
    differenced (each spreads over two differences, at 1/sqrt(2) of its size; on
    paper-table4 about a quarter of them) and heavy-tailed noise make the measured value
    larger. The factor is the measured over the Gaussian value, averaged over the sensors
    (one window then estimates it to a few per cent), times ``N_diff / N'`` for the rows
    the cut left out (the same cut as
    :func:`~imufdi_cli.maths.parity.residual_sigma`); floored at 1, the Gaussian value.

    Parameters
    ----------
    H : array_like, shape (n, 3)
    measurements : array_like, shape (N, n), N >= 4, fault-free, SI

    Returns
    -------
    float
        1 for Gaussian white noise (up to its sampling error), more with outliers; 1 when
        the per-sensor variances are not identifiable (singular M) or too few samples.
    """
    from imufdi_cli.maths.parity import residuals

    H = np.asarray(H, dtype=np.float64)
    m = np.asarray(measurements, dtype=np.float64)
    n, q = H.shape
    if m.ndim != 2 or m.shape[0] < 4 or n <= q:
        return 1.0
    projector = residual_projector(H)
    mixing = projector**2
    singular = np.linalg.svd(mixing, compute_uv=False)
    if not singular[-1] > 1e-8 * singular[0]:
        return 1.0
    inverse = np.linalg.inv(mixing)
    r = residuals(H, np.diff(m, axis=0))
    centre = np.median(r, axis=0)
    robust_std = 1.4826 * np.median(np.abs(r - centre), axis=0)
    inlier = np.all(np.abs(r - centre) <= outlier_cut * robust_std, axis=1)
    kept = r[inlier] if np.count_nonzero(inlier) >= max(2, r.shape[0] // 2) else r
    if kept.shape[0] < 3:
        return 1.0
    z = (kept**2) @ inverse.T  # (N', n): z_t,k has mean s_k (differenced: 2 sigma_k^2)
    variance = np.clip(z.mean(axis=0), 0.0, None)
    zc = z - z.mean(axis=0)
    measured = np.mean(zc**2, axis=0) + 2 * np.sum(zc[1:] * zc[:-1], axis=0) / z.shape[0]
    covariance = projector @ np.diag(variance) @ projector.T
    gaussian = 3 * np.einsum("ki,ij,kj->k", inverse, covariance**2, inverse)
    use = gaussian > 0
    if not np.any(use):
        return 1.0
    ratio = float(np.mean(measured[use] / gaussian[use]))
    factor = max(ratio, 1.0) * r.shape[0] / kept.shape[0]
    return factor if math.isfinite(factor) else 1.0


def white_sigma_spread(cov: np.ndarray, gain: np.ndarray, k: int) -> tuple[float, float, float]:
    """``(A, B, D)`` for :func:`_calibration_dof`: with ``g2 = gain^2`` (the consensus
    weights of sensor k, :func:`leave_one_out`) and ``cov`` from
    :func:`white_sigma_covariance`, ``A = g2^T cov g2`` (the consensus variance's),
    ``B = (cov g2)_k`` (shared with sigma_k^2) and ``D = cov_kk`` (sigma_k^2's), SI^4."""
    g2 = np.asarray(gain, dtype=np.float64) ** 2
    shared = cov @ g2
    return float(g2 @ shared), float(shared[k]), float(cov[k, k])


def white_variance_dof(
    cov: np.ndarray, gain: np.ndarray, k: int, variance: float, default: float
) -> float:
    """Degrees of freedom of the calibrated white variance of sensor k's leave-one-out
    residual, ``v_k = s_k + sum_i g_i^2 s_i`` (s the white variances, g the consensus
    gain): with ``(A, B, D)`` of :func:`white_sigma_spread`, ``Var v_k = D + 2 B + A``, and
    a scaled chi-square with that variance has ``2 v_k^2 / Var v_k`` degrees of freedom
    (Satterthwaite 1946). For Gaussian noise on 16 co-aligned triads and 200 samples that is
    132 (sensor k's own estimate mixes the others' noise, 1.14 times the variance, but the
    consensus variance's error partly cancels it), about the successive-difference dof of
    the samples (133); with paper-table4's outliers (the measured excess) about 124.
    ``default`` when the spread is degenerate.

    Parameters
    ----------
    cov : ndarray, shape (n, n)
        :func:`white_sigma_covariance` (times the excess), SI^4.
    gain : ndarray, shape (n,)
    k : int
    variance : float
        ``v_k``, SI^2.
    default : float

    Returns
    -------
    float
    """
    a_term, b_term, d_term = white_sigma_spread(cov, gain, k)
    spread = a_term + 2 * b_term + d_term
    if not (math.isfinite(spread) and spread > 0 and math.isfinite(variance)):
        return default
    return 2 * variance**2 / spread
