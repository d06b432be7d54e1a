"""Parity-space helpers: V H = 0, V V^T = I, Potter's form, invariance, isolability."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import ArrayConfigError, CalibrationError
from imufdi_cli.maths.parity import (
    detection_statistic,
    estimated_sigma_threshold,
    fault_directions,
    isolable_sensors,
    isolation_statistics,
    least_squares_estimate,
    parity_matrix,
    parity_vectors,
    residual_sigma,
    residuals,
    sigma_estimate_variance,
    whiten,
)


def conical_H(n: int = 6, half_angle_deg: float = 54.7356) -> np.ndarray:
    """n single-axis sensors evenly spaced on a cone around z."""
    beta = np.deg2rad(half_angle_deg)
    azimuth = 2 * np.pi * np.arange(n) / n
    return np.column_stack(
        [np.sin(beta) * np.cos(azimuth), np.sin(beta) * np.sin(azimuth), np.full(n, np.cos(beta))]
    )


@pytest.mark.parametrize(
    "H",
    [
        ArrayConfig.co_aligned(16).measurement_matrix("gyro"),
        ArrayConfig.co_aligned(2).measurement_matrix("gyro"),
        conical_H(6),
        conical_H(4),
        np.random.default_rng(3).standard_normal((9, 3)),
    ],
)
def test_parity_matrix_properties(H: np.ndarray) -> None:
    V = parity_matrix(H)
    n = H.shape[0]
    assert V.shape == (n - 3, n)
    assert_allclose(V @ H, 0.0, atol=1e-12)
    assert_allclose(V @ V.T, np.eye(n - 3), atol=1e-12)
    projector = np.eye(n) - H @ np.linalg.solve(H.T @ H, H.T)
    assert_allclose(V.T @ V, projector, atol=1e-12)
    # Potter's form: leading block upper triangular with non-negative diagonal
    lead = V[:, : n - 3]
    assert_allclose(np.tril(lead, -1), 0.0, atol=0)
    assert np.all(np.diag(lead) >= 0)


def test_parity_matrix_is_potter_unique_form() -> None:
    """Rotating the null-space basis does not change Potter's V (it is unique)."""
    H = conical_H(6)
    V = parity_matrix(H)
    # Potter's V from the projector by a Cholesky factorisation of its leading block
    projector = np.eye(6) - H @ np.linalg.solve(H.T @ H, H.T)
    upper = np.linalg.cholesky(projector[:3, :3]).T  # V_lead^T V_lead = P_lead
    assert_allclose(V[:, :3], upper, atol=1e-12)


def test_statistics_invariant_under_orthogonal_rotation_of_V(scipy_stats) -> None:
    rng = np.random.default_rng(1)
    H = ArrayConfig.co_aligned(5).measurement_matrix("gyro")
    V = parity_matrix(H)
    Q = scipy_stats.ortho_group.rvs(V.shape[0], random_state=2)
    V_rot = Q @ V
    m = rng.standard_normal((50, 15)) + rng.standard_normal((50, 3)) @ H.T
    m[:, 4] += 3.0
    p, p_rot = parity_vectors(V, m), parity_vectors(V_rot, m)
    assert_allclose(detection_statistic(p), detection_statistic(p_rot), rtol=1e-12)
    d, f = isolation_statistics(p, V)
    d_rot, f_rot = isolation_statistics(p_rot, V_rot)
    assert_allclose(d, d_rot, rtol=1e-10, atol=1e-12)
    assert_allclose(f, f_rot, rtol=1e-10, atol=1e-12)
    # Non-orthonormal V (scaled rows): the (V V^T)^-1 weighting restores the same numbers
    V_scaled = np.diag(np.linspace(0.5, 3.0, V.shape[0])) @ V
    p_scaled = parity_vectors(V_scaled, m)
    assert_allclose(detection_statistic(p_scaled, V_scaled), detection_statistic(p), rtol=1e-10)
    d_s, f_s = isolation_statistics(p_scaled, V_scaled)
    assert_allclose(d_s, d, rtol=1e-9, atol=1e-12)
    assert_allclose(f_s, f, rtol=1e-9, atol=1e-12)


def test_noiseless_single_fault_isolation_and_amplitude_exact() -> None:
    H = conical_H(6)
    V = parity_matrix(H)
    rate = np.array([[0.3, -0.2, 1.1]])
    m = rate @ H.T
    m[0, 5] += 0.5
    p = parity_vectors(V, m)
    d_fi, amplitude = isolation_statistics(p, V)
    assert int(np.argmax(d_fi[0])) == 5
    assert_allclose(amplitude[0, 5], 0.5, rtol=1e-12)
    # D_FI of the faulty sensor equals D_FD (the whole parity energy is along v_5)
    assert_allclose(d_fi[0, 5], detection_statistic(p)[0], rtol=1e-12)
    assert_allclose(d_fi[0, 5], 0.25 * np.sum(V[:, 5] ** 2), rtol=1e-12)


def test_whitening_gives_chi2_statistic() -> None:
    rng = np.random.default_rng(4)
    H = ArrayConfig.co_aligned(4).measurement_matrix("accel")
    sigma = np.linspace(0.01, 0.05, 12)
    m = rng.standard_normal((40000, 12)) * sigma + rng.standard_normal((40000, 3)) @ H.T
    V = parity_matrix(whiten(H, sigma))
    d_fd = detection_statistic(parity_vectors(V, m / sigma))
    assert_allclose(d_fd.mean(), 9.0, rtol=0.02)
    assert_allclose(d_fd.var(), 18.0, rtol=0.05)


def test_whiten_rejects_bad_sigma() -> None:
    H = conical_H(5)
    with pytest.raises(CalibrationError, match="sigma"):
        whiten(H, np.array([1.0, 1.0, 0.0, 1.0, 1.0]))
    assert_allclose(whiten(H, 2.0), H / 2.0)


def test_bad_measurement_matrix_raises() -> None:
    with pytest.raises(ArrayConfigError, match="rank 2"):
        parity_matrix(np.array([[1.0, 0, 0], [0, 1, 0], [1, 1, 0], [1, -1, 0]]))
    with pytest.raises(ArrayConfigError, match="shape"):
        parity_matrix(np.ones((4, 2)))
    assert parity_matrix(np.eye(3)).shape == (0, 3)


def test_isolability_two_coaligned_imus_not_isolable() -> None:
    V2 = parity_matrix(ArrayConfig.co_aligned(2).measurement_matrix("gyro"))
    assert not isolable_sensors(V2).any()
    V3 = parity_matrix(ArrayConfig.co_aligned(3).measurement_matrix("gyro"))
    assert isolable_sensors(V3).all()
    V4 = parity_matrix(conical_H(4))  # one parity dimension: all v_i parallel
    assert not isolable_sensors(V4).any()
    assert isolable_sensors(parity_matrix(conical_H(6))).all()
    assert fault_directions(V3).shape == (9, 6)


def test_least_squares_and_residuals() -> None:
    rng = np.random.default_rng(5)
    H = conical_H(6)
    x = rng.standard_normal((10, 3))
    m = x @ H.T
    assert_allclose(least_squares_estimate(H, m), x, atol=1e-12)
    assert_allclose(least_squares_estimate(H, m, sigma=np.arange(1.0, 7.0)), x, atol=1e-12)
    assert_allclose(residuals(H, m), 0.0, atol=1e-12)
    bias = np.array([0, 0, 0, 0, 0, 1.0])
    r = residuals(H, m + bias)
    assert_allclose(parity_vectors(parity_matrix(H), r), parity_vectors(parity_matrix(H), m + bias))


def test_residual_sigma_recovers_per_sensor_noise_under_motion() -> None:
    rng = np.random.default_rng(6)
    H = ArrayConfig.co_aligned(8).measurement_matrix("gyro")
    sigma = rng.uniform(0.5, 2.0, 24)
    motion = 50.0 * np.sin(np.linspace(0, 20, 20000))[:, None] * np.ones((1, 3))
    m = motion @ H.T + rng.standard_normal((20000, 24)) * sigma
    assert_allclose(residual_sigma(H, m), sigma, rtol=0.05)
    # one parity dimension: not identifiable per sensor -> common sigma
    H4 = conical_H(4)
    m4 = rng.standard_normal((20000, 4)) * 0.1 + motion @ H4.T
    assert_allclose(residual_sigma(H4, m4), 0.1, rtol=0.05)


def test_residual_sigma_ignores_sparse_outliers() -> None:
    rng = np.random.default_rng(7)
    H = ArrayConfig.co_aligned(16).measurement_matrix("gyro")
    m = rng.standard_normal((400, 48)) * 0.15
    spikes = rng.random((400, 48)) < 0.002
    m_spiky = m + np.where(spikes, 1.0, 0.0) * rng.choice([-1.0, 1.0], size=m.shape)
    robust = residual_sigma(H, m_spiky)
    plain = residual_sigma(H, m_spiky, outlier_cut=None)
    clean = residual_sigma(H, m)
    assert spikes.any()
    assert_allclose(robust.mean(), 0.15, rtol=0.03)
    assert plain.mean() > 1.04 * clean.mean()  # spikes inflate the plain estimate
    with pytest.raises(CalibrationError):
        residual_sigma(H, m[:1])


# --- the level with sigma and bias estimated from a calibration window ---------


def _levels_with_estimated_sigma(alpha: float, reps: int, seed: int) -> tuple[np.ndarray, float]:
    """Per-calibration false-alarm rates of D = |P m_w|^2 at the corrected threshold."""
    H = ArrayConfig.co_aligned(16, 100.0, sensors=("gyro",)).measurement_matrix("gyro")
    n, sigma = H.shape[0], 0.0026
    variance = sigma_estimate_variance(H, np.full(n, sigma), 200)
    threshold = estimated_sigma_threshold(whiten(H, np.full(n, sigma)), alpha, variance, 200)[0]
    rng = np.random.default_rng(seed)
    levels = []
    for _ in range(reps):
        calibration = rng.standard_normal((200, n)) * sigma
        test = rng.standard_normal((2000, n)) * sigma
        estimate = residual_sigma(H, calibration)
        bias = residuals(H, calibration.mean(axis=0)[None, :])[0]
        V = parity_matrix(whiten(H, estimate))
        statistic = ((((test - bias) / estimate) @ V.T) ** 2).sum(axis=1)
        levels.append(np.mean(statistic > threshold))
    return np.array(levels), threshold


def test_sigma_estimate_variance_matches_the_direct_variance_for_co_aligned_imus():
    H = ArrayConfig.co_aligned(16, 100.0, sensors=("gyro",)).measurement_matrix("gyro")
    variance = sigma_estimate_variance(H, np.full(48, 0.01), 201)
    # one residual per sensor, 15/16 of it its own noise: 1.14 x 2/(N - 1), all equal
    assert_allclose(variance, variance[0])
    assert 1.0 < variance[0] / (2 / 200) < 1.3


def test_known_sigma_threshold_is_the_chi_square_quantile(scipy_stats):
    chi2 = scipy_stats.chi2  # (tests/conftest.py: imported at first use, on the first worker)

    H = ArrayConfig.co_aligned(16, 100.0, sensors=("gyro",)).measurement_matrix("gyro")
    threshold, scale, dof = estimated_sigma_threshold(H, 0.01, None, float("inf"))
    assert_allclose((threshold, scale, dof), (chi2.ppf(0.99, 45), 1.0, 45.0), rtol=1e-9)


def _direct_traces(h_white: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``(tr A, tr A^2)`` of ``A = D P_D D``, ``D = diag((1 + delta)^-1/2)``, by definition."""
    weights = 1.0 / np.sqrt(1.0 + delta)
    h_est = weights[:, None] * h_white
    projector = np.eye(h_white.shape[0]) - h_est @ np.linalg.pinv(h_est)
    form = weights[:, None] * projector * weights[None, :]
    return np.array([np.trace(form), np.sum(form * form.T)])


def _difference_derivatives(h_white: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of the traces in every delta_j: (n,) gradient of tr A and
    (n, 2) diagonal Hessian of (tr A, tr A^2)."""
    n = h_white.shape[0]
    base = _direct_traces(h_white, np.zeros(n))
    first, second = np.zeros(n), np.zeros((n, 2))
    for j in range(n):
        delta = np.zeros(n)
        delta[j] = step
        up, down = _direct_traces(h_white, delta), _direct_traces(h_white, -delta)
        first[j] = (up[0] - down[0]) / (2 * step)
        second[j] = (up + down - 2 * base) / step**2
    return first, second


def _threshold_cases() -> list[tuple[np.ndarray, np.ndarray, int]]:
    rng = np.random.default_rng(3)
    co_aligned = ArrayConfig.co_aligned(4, 100.0, sensors=("gyro",)).measurement_matrix("gyro")
    return [
        (co_aligned, rng.uniform(0.5, 2.0, 12), 50),
        (rng.standard_normal((7, 3)), rng.uniform(0.5, 2.0, 7), 100),
        (rng.standard_normal((20, 9)), rng.uniform(0.5, 2.0, 20), 300),  # augmented model
    ]


@pytest.mark.parametrize("case", range(3))
def test_trace_derivatives_match_the_analytic_form(case: int) -> None:
    """Eq. (3) of estimated_sigma_threshold: d trA = -P_jj, d2 trA = 2 P_jj^2,
    d2 trA^2 = 6 P_jj^2. Central differences carry an O(step^2) truncation error:
    Richardson's (4 D(h/2) - D(h)) / 3 cancels it, leaving O(h^4) ~ 1e-12 and rounding
    ~ eps k / h^2 < 1e-8, so it must match to 1e-7 while the raw h = 1e-3 differences
    are off by about h^2 P_jj^2 (relative)."""
    H, sigma, _ = _threshold_cases()[case]
    h_white = whiten(H, sigma)
    leverage = np.diag(np.eye(H.shape[0]) - h_white @ np.linalg.pinv(h_white))
    analytic_first = -leverage
    analytic_second = np.column_stack([2 * leverage**2, 6 * leverage**2])
    first_h, second_h = _difference_derivatives(h_white, 1e-3)
    first_half, second_half = _difference_derivatives(h_white, 5e-4)
    assert_allclose((4 * first_half - first_h) / 3, analytic_first, rtol=0, atol=1e-7)
    assert_allclose((4 * second_half - second_h) / 3, analytic_second, rtol=0, atol=1e-7)
    # the raw step-1e-3 differences: right to their truncation error, not better
    assert_allclose(second_h, analytic_second, rtol=1e-5)
    assert np.max(np.abs(second_h - analytic_second)) > 1e-8


@pytest.mark.parametrize("case", range(3))
def test_estimated_sigma_threshold_is_the_delta_method_of_the_traces(
    case: int, scipy_stats
) -> None:
    """The two moments, g and h rebuilt from extrapolated differences of the defining
    traces (second-order delta method, independent delta_j), agree to 1e-8. Steps 4e-3 and
    2e-3: extrapolated, their O(h^4) error is ~1e-11 (the co-aligned case, whose traces
    carry no rounding, is off by 1.0e-11), while the rounding of the traces, eps k / h^2
    amplified by the conditioning of the whitened model, reaches 1.5e-9 on the augmented
    case with some SIMD levels and BLAS kernels (numpy's AVX-512, AVX2 and SSE4.2 loops,
    five OpenBLAS kernels, numpy 2.0 and 2.4: 3.5e-10 to 1.5e-9; larger steps trade it for
    truncation). 1e-8 bounds both; an error of the delta method is far outside it (the
    1/N inflation alone is 3e-3 of the moments, the second-order terms more)."""
    chi2 = scipy_stats.chi2  # the oracle's quantile (tests/conftest.py: first worker)
    H, sigma, n_samples = _threshold_cases()[case]
    h_white = whiten(H, sigma)
    variance = sigma_estimate_variance(H, sigma, n_samples)
    first_h, second_h = _difference_derivatives(h_white, 4e-3)
    first_half, second_half = _difference_derivatives(h_white, 2e-3)
    first = (4 * first_half - first_h) / 3
    second = (4 * second_half - second_h) / 3
    base = _direct_traces(h_white, np.zeros(H.shape[0]))
    inflation = 1 + 1 / n_samples
    mean = (base[0] + 0.5 * second[:, 0] @ variance) * inflation
    var = (2 * (base[1] + 0.5 * second[:, 1] @ variance) + first**2 @ variance) * inflation**2
    scale, dof = var / (2 * mean), 2 * mean**2 / var
    expected = (scale * chi2.ppf(0.99, dof), scale, dof)
    got = estimated_sigma_threshold(h_white, 0.01, variance, float(n_samples))
    assert_allclose(got, expected, rtol=1e-8)
    # the estimated-sigma correction is material here (g > 1 + 1/N + 1 %, h < n - q)
    assert scale > 1.01 + 1 / n_samples and dof < H.shape[0] - H.shape[1]


@pytest.mark.slow
def test_parity_test_holds_its_level_with_sigma_estimated_from_200_samples():
    """16 IMUs, sigma per sensor and bias from 200 samples (paper-table4's 2 s window).

    chi2(45) gives 1.41 alpha here. The corrected threshold is a second-order
    approximation: allow 0.1 alpha for it, plus 4 standard errors of the mean level
    over the calibrations (measured from the spread of the per-calibration levels).
    """
    alpha = 0.01
    levels, _ = _levels_with_estimated_sigma(alpha, reps=150, seed=11)
    standard_error = levels.std(ddof=1) / np.sqrt(levels.size)
    assert abs(levels.mean() - alpha) <= 0.1 * alpha + 4 * standard_error
    assert 4 * standard_error < 0.2 * alpha  # the check can tell 1.41 alpha from alpha
