"""Parity space of a redundant sensor array: the shared maths of the parity detectors.

For one sensor type with measurement matrix ``H`` (n, 3) the measurements are
``m = H x + f + e`` (x the body-frame quantity, f the faults, e the noise). A parity matrix
``V`` ((n-3), n) has rows that span the left null space of H::

    V H = 0,   V V^T = I_{n-3},   V^T V = I_n - H (H^T H)^{-1} H^T           (1)

so the parity vector ``p = V m = V (f + e)`` does not depend on the motion x (Potter &
Suman, "Thresholdless redundancy management with arrays of skewed instruments",
AGARDograph 224, 1977; Li et al., Micromachines 17(3):374, 2026, §2.1, eqs. 1-4).

Construction (``parity_matrix``): the last n-3 left singular vectors of H give an
orthonormal basis of the left null space (numerically the most robust choice: no
inversion of H^T H, exact orthonormality to rounding). Potter's construction fixes the
basis by requiring V^T V to equal the projector (1) and V to be upper triangular
(``V[i, j] = 0`` for ``j < i``) with a positive diagonal; every orthonormal basis of the
same null space satisfies (1), and two of them differ by an orthogonal (n-3)x(n-3) matrix Q.
We compute the QR factorisation of the SVD basis' leading (n-3) square block, ``A = Q R``,
and return ``Q^T V_svd``, whose leading block is R: upper triangular, positive diagonal.
That is Potter's V (unique when the leading block is invertible). Any orthonormal V gives
the same statistics (they are invariant under p -> Q p), so the choice only matters for
reproducible parity vectors in output files.

The same maths holds for an augmented model ``m = A x + f + e`` with A (n, q), q > 3
columns (the rigid-body accelerometer model of :mod:`.rigid`: specific force plus
lever-arm terms): every function below accepts such a full-column-rank A, and the parity
space then has ``n - q`` dimensions.

Noise whitening: with per-sensor standard deviations sigma (n,), ``H_w = H / sigma[:, None]``
and ``m_w = m / sigma`` have unit white noise, and the parity vector of the whitened
problem is chi-square distributed with n-3 degrees of freedom when there is no fault.
"""

from __future__ import annotations

import numpy as np

from imufdi_cli.errors import ArrayConfigError, CalibrationError

#: Relative tolerance on singular values for the rank test of H.
RANK_RTOL = 1e-9


def check_measurement_matrix(H: np.ndarray) -> np.ndarray:
    """Validate a measurement matrix and return it as float64.

    Parameters
    ----------
    H : array_like, shape (n, 3) or (n, q), q > 3
        Row j is the body-frame direction of sensor j's sensing axis (an augmented model
        appends columns, e.g. lever-arm terms, :mod:`.rigid`).

    Raises
    ------
    ArrayConfigError
        Wrong shape, non-finite values, fewer sensors than columns, or rank < q (the
        sensors do not span the body axes and the extra unknowns).
    """
    H = np.asarray(H, dtype=np.float64)
    if H.ndim != 2 or H.shape[1] < 3:
        raise ArrayConfigError(f"measurement matrix must have shape (n, 3), got {H.shape}")
    if not np.all(np.isfinite(H)):
        raise ArrayConfigError("measurement matrix has non-finite entries")
    q = H.shape[1]
    if H.shape[0] < q:
        raise ArrayConfigError(
            f"measurement matrix has {H.shape[0]} sensors; at least {q} are needed to span"
            f" {'3 axes' if q == 3 else f'its {q} unknowns'}"
        )
    singular = np.linalg.svd(H, compute_uv=False)
    rank = int(np.sum(singular > RANK_RTOL * singular[0])) if singular[0] > 0 else 0
    if rank < q:
        raise ArrayConfigError(
            f"measurement matrix has rank {rank} < {q}: the sensing axes do not span the"
            f" body frame{'' if q == 3 else ' and the lever-arm unknowns'}"
        )
    return H


def residual_projector(H: np.ndarray) -> np.ndarray:
    """``I - H H^+`` (n, n): the projector onto the complement of H's columns, which maps
    measurements ``m = H x + e`` to their least-squares residuals (x cancels).

    Parameters
    ----------
    H : ndarray, shape (n, q)
        Measurement (or design) matrix, any rank.
    """
    return np.eye(H.shape[0]) - H @ np.linalg.pinv(H)  # type: ignore[no-any-return]


def parity_matrix(H: np.ndarray) -> np.ndarray:
    """Potter's parity matrix V of a measurement matrix (module docstring, eq. 1).

    Parameters
    ----------
    H : array_like, shape (n, 3)
        Measurement matrix (whitened or not), rank 3.

    Returns
    -------
    V : ndarray, shape (n - 3, n)
        ``V H = 0``, ``V V^T = I``, ``V^T V = I - H (H^T H)^-1 H^T``; upper triangular
        (``V[i, j] = 0`` for ``j < i``) with positive diagonal where the leading block is
        invertible. Shape (0, 3) for n = 3 (no redundancy).
    """
    H = check_measurement_matrix(H)
    n, q = H.shape
    n_parity = n - q
    if n_parity == 0:
        return np.zeros((0, n))
    left, _, _ = np.linalg.svd(H, full_matrices=True)
    basis = left[:, q:].T  # (n-q, n), orthonormal rows, basis @ H = 0 to rounding
    q, r = np.linalg.qr(basis[:, :n_parity])
    V = q.T @ basis
    # Fix signs: positive diagonal of the leading triangular block (Potter's convention).
    signs = np.sign(np.diag(r))
    signs[signs == 0] = 1.0
    V *= signs[:, None]
    # Clean the exact zeros of the triangular structure (rounding leaves ~1e-17).
    lower = np.tril_indices(n_parity, -1)
    V[lower] = 0.0
    return V


def whiten(H: np.ndarray, sigma: np.ndarray | float) -> np.ndarray:
    """Whitened measurement matrix ``H_w = diag(1/sigma) H``.

    The matching whitened measurements are ``m / sigma`` (row-wise for (N, n) blocks), so
    that the noise of every whitened channel has unit variance.

    Parameters
    ----------
    H : array_like, shape (n, 3)
    sigma : float or array_like, shape (n,)
        Per-sensor white-noise standard deviation, SI units of the sensor, > 0.

    Returns
    -------
    H_w : ndarray, shape (n, 3), units 1/(sensor unit)
    """
    H = check_measurement_matrix(H)
    sigma_arr = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (H.shape[0],))
    if not np.all(np.isfinite(sigma_arr)) or np.any(sigma_arr <= 0):
        raise CalibrationError(
            "sensor noise sigma must be finite and > 0 for every sensor"
            f" (got min {float(np.min(sigma_arr)):.3g}); check the calibration window"
        )
    return H / sigma_arr[:, None]


def fault_directions(V: np.ndarray) -> np.ndarray:
    """Fault direction vectors v_i: the columns of V, as rows.

    A fault f on sensor i moves the parity vector by ``f v_i`` (p = V (f e_i) = f V[:, i]).

    Returns
    -------
    directions : ndarray, shape (n, n - 3)
        Row i is v_i.
    """
    return np.asarray(V, dtype=np.float64).T.copy()


def isolable_sensors(V: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Which sensors a single-fault isolation test can tell apart.

    Sensor i is isolable iff v_i is non-zero and not parallel to any other v_j (the
    isolation statistics of parallel directions are identical, so argmax would guess).
    With 2 sensors on an axis and n - 3 small, their v_i are parallel.

    Parameters
    ----------
    V : array_like, shape (k, n)
    tol : float
        Directions with ``1 - |cos angle| < tol`` count as parallel; norms below ``tol``
        times the largest count as zero.

    Returns
    -------
    isolable : ndarray, shape (n,), bool
    """
    directions = fault_directions(V)
    n = directions.shape[0]
    if directions.shape[1] == 0:
        return np.zeros(n, dtype=bool)
    norms = np.linalg.norm(directions, axis=1)
    nonzero = norms > tol * max(float(norms.max()), np.finfo(float).tiny)
    unit = np.zeros_like(directions)
    unit[nonzero] = directions[nonzero] / norms[nonzero, None]
    cosines = np.abs(unit @ unit.T)
    np.fill_diagonal(cosines, 0.0)
    parallel = (cosines > 1.0 - tol) & nonzero[:, None] & nonzero[None, :]
    return nonzero & ~parallel.any(axis=1)


def least_squares_matrix(H: np.ndarray, sigma: np.ndarray | float | None = None) -> np.ndarray:
    """(Weighted) least-squares estimator ``L`` with ``x_hat = L m``.

    ``L = (H^T W H)^{-1} H^T W`` with ``W = diag(1/sigma^2)`` (W = I when sigma is None).

    Returns
    -------
    L : ndarray, shape (3, n)
    """
    H = check_measurement_matrix(H)
    if sigma is None:
        return np.linalg.pinv(H)
    H_w = whiten(H, sigma)
    sigma_arr = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (H.shape[0],))
    return np.linalg.pinv(H_w) / sigma_arr[None, :]


def least_squares_estimate(
    H: np.ndarray, measurements: np.ndarray, sigma: np.ndarray | float | None = None
) -> np.ndarray:
    """Least-squares body-frame quantity from array measurements.

    Parameters
    ----------
    H : array_like, shape (n, 3)
    measurements : array_like, shape (N, n)
        SI units of the sensor type.
    sigma : optional, float or shape (n,)
        Per-sensor noise standard deviation for weighting.

    Returns
    -------
    x_hat : ndarray, shape (N, 3), same units.
    """
    return np.asarray(measurements, dtype=np.float64) @ least_squares_matrix(H, sigma).T


def residuals(
    H: np.ndarray, measurements: np.ndarray, sigma: np.ndarray | float | None = None
) -> np.ndarray:
    """Measurement residuals ``m - H x_hat`` (the part of m not explained by H).

    Returns
    -------
    r : ndarray, shape (N, n), SI units.
    """
    H = check_measurement_matrix(H)
    measurements = np.asarray(measurements, dtype=np.float64)
    hat = H @ least_squares_matrix(H, sigma)  # (n, n)
    return measurements - measurements @ hat.T


def parity_vectors(V: np.ndarray, measurements: np.ndarray) -> np.ndarray:
    """Parity vectors ``p = V m`` of a block of samples.

    Parameters
    ----------
    V : array_like, shape (k, n)
    measurements : array_like, shape (N, n)

    Returns
    -------
    p : ndarray, shape (N, k)
    """
    return np.asarray(measurements, dtype=np.float64) @ np.asarray(V, dtype=np.float64).T


def gram_inverse(V: np.ndarray) -> np.ndarray:
    """``(V V^T)^{-1}``, shape (k, k) (identity for an orthonormal V)."""
    V = np.asarray(V, dtype=np.float64)
    return np.linalg.inv(V @ V.T)


def detection_statistic(p: np.ndarray, V: np.ndarray | None = None) -> np.ndarray:
    """GLT detection statistic ``D_FD = p^T (V V^T)^{-1} p`` (Li et al. 2026, eq. 5).

    For whitened measurements and no fault, D_FD ~ chi2(n - 3).

    Parameters
    ----------
    p : ndarray, shape (N, k)
    V : optional, shape (k, n)
        When given and not orthonormal, ``(V V^T)^{-1}`` weights the quadratic form.

    Returns
    -------
    D_FD : ndarray, shape (N,)
    """
    p = np.asarray(p, dtype=np.float64)
    if V is None:
        return np.einsum("ij,ij->i", p, p)
    weighted = p @ gram_inverse(V)
    return np.einsum("ij,ij->i", weighted, p)


def isolation_statistics(p: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GLT isolation statistics and fault amplitudes for every sensor (Li et al., eqs. 6-7).

    ``D_FI,i = (p^T G v_i)^2 / (v_i^T G v_i)`` and ``f_i = p^T G v_i / (v_i^T G v_i)`` with
    ``G = (V V^T)^{-1}``; ``f_i`` is the maximum-likelihood amplitude of a fault on sensor i
    (in the units of the measurements V was applied to). Sensors with a zero direction get
    NaN.

    Parameters
    ----------
    p : ndarray, shape (N, k)
    V : ndarray, shape (k, n)

    Returns
    -------
    D_FI : ndarray, shape (N, n)
    amplitude : ndarray, shape (N, n)
    """
    p = np.asarray(p, dtype=np.float64)
    V = np.asarray(V, dtype=np.float64)
    weighted_directions = gram_inverse(V) @ V  # (k, n): column i = G v_i
    projections = p @ weighted_directions  # (N, n): p^T G v_i
    energies = np.einsum("ij,ij->j", V, weighted_directions)  # (n,): v_i^T G v_i
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse_energy = np.where(energies > 0, 1.0 / np.where(energies > 0, energies, 1.0), np.nan)
    amplitude = projections * inverse_energy
    return projections * amplitude, amplitude


def residual_sigma(
    H: np.ndarray, measurements: np.ndarray, *, outlier_cut: float | None = 4.0
) -> np.ndarray:
    """Per-sensor white-noise sigma from the least-squares residuals of a fault-free window.

    Residuals ``r = (I - S) m`` with the hat matrix ``S = H H^+`` remove any motion, and for
    independent noise ``Var(r_i) = sum_j (I - S)_ij^2 sigma_j^2``. That linear system is
    solved for sigma^2 (non-negative least squares). When it is rank-deficient (little
    redundancy, e.g. n - 3 = 1) the per-sensor sigmas are not identifiable and one common
    sigma is returned, from ``E |r|^2 = (n - 3) sigma^2``; so does any sensor whose fitted
    variance is zero (residuals that are not white noise, e.g. unmodelled motion).

    Sparse outliers (spikes) would inflate the variances and make the Gaussian test blind:
    samples where any residual is further than ``outlier_cut`` robust standard deviations
    (1.4826 median absolute deviation) from its median are left out before the variances
    are taken (at 4, a Gaussian sample of 48 sensors is dropped with probability 0.3 %, so
    the variance is biased by far less than its sampling error).

    Parameters
    ----------
    H : array_like, shape (n, 3)
    measurements : array_like, shape (N, n), fault-free, N >= 2
    outlier_cut : float or None
        Rejection threshold in robust standard deviations; None keeps every sample.

    Returns
    -------
    sigma : ndarray, shape (n,), SI units of the sensor type.
    """
    H = check_measurement_matrix(H)
    measurements = np.asarray(measurements, dtype=np.float64)
    if measurements.shape[0] < 2:
        raise CalibrationError("calibration window needs at least 2 samples to estimate sigma")
    n, q = H.shape
    n_parity = n - q
    if n_parity == 0:
        raise CalibrationError(
            f"with {n} sensors and {q} unknowns there are no residuals to estimate sigma from"
        )
    r = residuals(H, measurements)
    if outlier_cut is not None:
        centre = np.median(r, axis=0)
        robust_std = 1.4826 * np.median(np.abs(r - centre), axis=0)
        inlier = np.all(np.abs(r - centre) <= outlier_cut * robust_std, axis=1)
        if np.count_nonzero(inlier) >= max(2, r.shape[0] // 2):
            r = r[inlier]
    variances = r.var(axis=0, ddof=1)
    mixing = residual_projector(H) ** 2
    singular = np.linalg.svd(mixing, compute_uv=False)
    common = variances.sum() / n_parity
    if singular[-1] > 1e-8 * singular[0]:
        sigma2 = nonnegative_least_squares(mixing, variances)
        # A sensor the non-negative fit drives to zero means the residuals are not white
        # per-sensor noise (e.g. unmodelled lever-arm motion): no per-sensor sigma can be
        # identified for it, so it gets the common sigma rather than an infinite weight.
        sigma2 = np.where(sigma2 > 1e-6 * common, sigma2, common)
    else:
        sigma2 = np.full(n, common)
    return np.sqrt(sigma2)


def nonnegative_least_squares(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``argmin ||A x - b||_2`` subject to ``x >= 0``, as ``scipy.optimize.nnls``.

    The unconstrained least-squares solution (``numpy.linalg.lstsq``) is computed first:
    when none of its components is negative it satisfies the Karush-Kuhn-Tucker conditions
    of the constrained problem with every multiplier zero (the gradient ``A^T (A x - b)``
    vanishes and x is feasible), so it is the constrained minimum as well (the only one
    when A has full column rank) and is returned. Otherwise some constraints are active
    and Lawson & Hanson's active-set solver (``scipy.optimize.nnls``) finds them. Noise
    calibrations nearly always take the first branch, so ``imufdi detect`` does not import
    ``scipy.optimize`` (about 0.25 s of CPU) for it.

    Parameters
    ----------
    A : ndarray, shape (m, n)
    b : ndarray, shape (m,)

    Returns
    -------
    x : ndarray, shape (n,), non-negative.
    """
    A = np.asarray(A, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    if np.all(np.isfinite(x)) and np.all(x >= 0.0):
        return x  # type: ignore[no-any-return]
    from scipy.optimize import nnls  # imported only when a constraint is active

    constrained, _ = nnls(A, b)
    return constrained  # type: ignore[no-any-return]


__all__ = [
    "check_measurement_matrix",
    "detection_statistic",
    "estimated_sigma_threshold",
    "fault_directions",
    "gram_inverse",
    "isolable_sensors",
    "isolation_statistics",
    "least_squares_estimate",
    "least_squares_matrix",
    "nonnegative_least_squares",
    "parity_matrix",
    "parity_vectors",
    "residual_sigma",
    "residuals",
    "sigma_estimate_variance",
    "two_moment_threshold",
    "whiten",
]


def sigma_estimate_variance(H: np.ndarray, sigma: np.ndarray, n_samples: int) -> np.ndarray:
    """Relative variance ``Var(sigma_hat_j^2) / sigma_j^4`` of ``residual_sigma``'s estimate.

    The estimate solves ``M sigma^2 = s`` with ``M = (I - S)∘(I - S)`` and s the residual
    sample variances; for Gaussian noise ``Cov(s) = 2/(N - 1) (C∘C)``, ``C = (I - S)
    diag(sigma^2) (I - S)^T``, so ``Cov(sigma_hat^2) = M^+ Cov(s) M^+T`` (the
    non-negativity constraints inactive). For 16 co-aligned IMUs this is 1.14 x the
    ``2/(N - 1)`` of a directly observed variance.

    Returns
    -------
    ndarray, shape (n,)
    """
    mixing = residual_projector(H)
    covariance = mixing @ np.diag(sigma**2) @ mixing.T
    inverse = np.linalg.pinv(mixing**2)
    spread = inverse @ (2.0 / max(n_samples - 1, 1) * covariance**2) @ inverse.T
    return np.diag(spread) / sigma**4


def estimated_sigma_threshold(
    h_white: np.ndarray, alpha: float, scale_variance: np.ndarray | None, mean_samples: float
) -> tuple[float, float, float]:
    """Threshold of ``D = |P m_w|^2`` when sigma and bias come from a calibration window.

    With known sigma and bias, ``D ~ chi2(n - 3)``. With per-sensor variances estimated,
    ``sigma_hat_j^2 = sigma_j^2 (1 + delta_j)`` with ``Var delta_j`` from
    ``sigma_estimate_variance``, the statistic is ``z^T A(delta) z`` with z the truly
    whitened noise, ``A = D P_D D``, ``D = diag((1 + delta)^-1/2)`` and P_D the parity
    projector in the estimated metric. Its mean ``E tr A`` and variance
    ``2 E tr A^2 + Var tr A`` over the calibration draw follow from the second-order delta
    method (the ``delta_j`` are independent, so only the gradient and the diagonal of the
    Hessian enter). The derivatives are analytic: for any orthonormal parity basis V of
    ``H_w`` (k = n - q rows, ``V^T V = P``), the generalised-least-squares residual identity
    ``O^-1 - O^-1 H (H^T O^-1 H)^-1 H^T O^-1 = V^T (V O V^T)^-1 V`` with
    ``O = diag(1 + delta)`` gives::

        A = V^T M^-1 V,  M = I_k + sum_j delta_j v_j v_j^T,
        tr A = tr M^-1,  tr A^2 = tr M^-2                                     (2)

    (v_j the j-th column of V, ``|v_j|^2 = P_jj``). Along one ``delta_j`` M has the single
    eigenvalue ``1 + delta_j P_jj`` off 1, so at delta = 0::

        d tr A / d delta_j = -P_jj,   d2 tr A / d delta_j2 = 2 P_jj^2,
        d2 tr A^2 / d delta_j2 = 6 P_jj^2                                     (3)

    and, with ``s = sum_j P_jj^2 Var delta_j``, ``E tr A = tr P + s``,
    ``E tr A^2 = tr P^2 + 3 s`` and ``Var tr A = s``. (Central differences of (2) agree
    with (3) to their O(step^2) truncation error, ``tests/maths/test_parity.py``.)
    The bias (calibration mean of N samples) adds its own error: every residual variance
    is multiplied by ``1 + 1/N``. The null law is then approximated by matching two
    moments, ``D ~ g chi2(h)`` (Satterthwaite), the estimation-uncertainty analogue of
    Hotelling's F for one common variance.

    Parameters
    ----------
    h_white : ndarray, shape (n, q)
        Whitened measurement matrix of the active sensors (q = 3, or more columns for an
        augmented model).
    alpha : float
        Level per sample.
    scale_variance : ndarray, shape (n,), or None
        ``Var delta_j`` of each variance estimate (None: sigma known).
    mean_samples : float
        Samples of the bias estimate (``inf``: no bias removed).

    Returns
    -------
    threshold, scale, dof : float
        ``g chi2_{1-alpha}(h)``, g and h.
    """
    h_white = np.asarray(h_white, dtype=np.float64)
    projector = np.eye(h_white.shape[0]) - h_white @ np.linalg.pinv(h_white)
    mean = float(np.trace(projector))
    square = float(np.sum(projector * projector.T))
    spread = 0.0
    if scale_variance is not None:
        # s = sum_j P_jj^2 Var delta_j, eqs. (2)-(3)
        leverage = float(np.diagonal(projector) ** 2 @ np.asarray(scale_variance, dtype=np.float64))
        mean += leverage
        square += 3.0 * leverage
        spread = leverage
    return two_moment_threshold(mean, square, spread, alpha, mean_samples)


def two_moment_threshold(
    mean: float, square: float, spread: float, alpha: float, mean_samples: float
) -> tuple[float, float, float]:
    """``g chi2_{1-alpha}(h)`` of ``D = z^T A z`` from ``E tr A`` (``mean``), ``E tr A^2``
    (``square``) and ``Var tr A`` (``spread``), each residual variance inflated by
    ``1 + 1/N`` for a bias from the calibration mean of ``mean_samples`` (``inf``: none):
    ``E D = m``, ``Var D = 2 E tr A^2 + Var tr A`` (times the inflation and its square),
    matched by ``g chi2(h)`` (Satterthwaite): ``g = Var D / (2 E D)``, ``h = 2 (E D)^2 /
    Var D``.

    Returns
    -------
    threshold, scale, dof : float
    """
    from imufdi_cli.maths.quantiles import chi2

    inflation = 1.0 + (1.0 / mean_samples if np.isfinite(mean_samples) else 0.0)
    total_mean = mean * inflation
    total_variance = (2.0 * square + spread) * inflation**2
    scale = total_variance / (2.0 * total_mean)
    dof = 2.0 * total_mean**2 / total_variance
    return float(scale * chi2.ppf(1.0 - alpha, dof)), float(scale), float(dof)
