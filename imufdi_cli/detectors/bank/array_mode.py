"""bank's array mode (several IMUs, beyond the paper): leave-one-out estimators per sensor,
the structured residual test, isolation and identification.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.detectors.bank.thresholds import SIGMA_FLOOR, estimated_threshold
from imufdi_cli.detectors.base import (
    NO_ISOLATION,
    NOT_ISOLABLE,
    DetectionBlock,
    calibration_stats,
)
from imufdi_cli.errors import ArrayTooSmallError, CalibrationError
from imufdi_cli.maths.parity import (
    isolable_sensors,
    parity_matrix,
    residual_sigma,
    whiten,
)

# --- array mode ------------------------------------------------------------------------


def leave_one_out_matrix(
    H: np.ndarray, sigma: np.ndarray, excluded: frozenset[int] = frozenset()
) -> np.ndarray:
    """Residual matrix of the leave-one-out estimators.

    Row j gives ``e_j = m_j - h_j^T w_hat(-j)`` with ``w_hat(-j) = (H_U^T W H_U)^{-1} H_U^T W m_U``
    the weighted least-squares estimate from the sensors ``U`` = all but j and the
    ``excluded`` ones (W = diag(1/sigma^2)). ``P H = 0`` (motion cancels).

    Parameters
    ----------
    H : ndarray, shape (n, 3)
    sigma : ndarray, shape (n,)
        Per-sensor noise std (only the ratios matter).
    excluded : frozenset of int
        Sensors no estimator may use (isolated faulty sensors).

    Returns
    -------
    P : ndarray, shape (n, n)
        ``e = P m``; rows of sensors whose estimator is not observable (fewer than 3
        independent other sensors) are NaN.
    """
    n, q = H.shape
    P = np.full((n, n), np.nan)
    weights = 1.0 / sigma**2
    usable: list[tuple[int, np.ndarray]] = []
    for j in range(n):  # n small, once per exclusion set (cached)
        used = np.array([i for i in range(n) if i != j and i not in excluded], dtype=np.intp)
        if used.size >= q:
            usable.append((j, used))
    # the rank tests and solves of every estimator of one size in one batched LAPACK call
    # each (the same routine per matrix as one call per matrix: the same floats)
    for size in sorted({used.size for _, used in usable}):
        group = [(j, used) for j, used in usable if used.size == size]
        normals = np.stack([H[used].T @ (weights[used, None] * H[used]) for _, used in group])
        tol = 1e-9 * np.maximum(np.abs(normals).max(axis=(1, 2)), 1e-300)
        full = np.linalg.matrix_rank(normals, tol=tol) >= q
        if not full.any():
            continue
        rhs = np.stack([H[used].T * weights[used] for _, used in group])
        gains = np.linalg.solve(normals[full], rhs[full])  # (k, q, |U|)
        for (j, used), gain in zip([g for g, ok in zip(group, full) if ok], gains):
            row = np.zeros(n)
            row[j] = 1.0
            row[used] -= H[j] @ gain
            P[j] = row
    return P


@dataclass
class _ArrayTest:
    """Calibrated leave-one-out bank for one sensor type."""

    sensor_type: str
    H: np.ndarray
    sigma: np.ndarray
    bias: np.ndarray
    threshold: float
    isolable: np.ndarray
    max_faults: int
    cache: dict[frozenset[int], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def matrix(self, excluded: frozenset[int]) -> tuple[np.ndarray, np.ndarray]:
        """``(P, predicted std of each residual)`` for an exclusion set (cached)."""
        if excluded not in self.cache:
            if len(self.cache) > 4096:
                self.cache.clear()
            P = leave_one_out_matrix(self.H, self.sigma, excluded)
            std = np.sqrt((P**2) @ self.sigma**2)
            self.cache[excluded] = (P, np.maximum(std, SIGMA_FLOOR))
        return self.cache[excluded]

    def residuals(self, m: np.ndarray, excluded: frozenset[int]) -> tuple[np.ndarray, np.ndarray]:
        P, std = self.matrix(excluded)
        e = m @ P.T
        return e, (e / std) ** 2

    def run(self, values: np.ndarray) -> tuple[DetectionBlock, np.ndarray]:
        """Test a block of measurements (N, n); returns the output and isolated sets (N, n)."""
        m = values - self.bias
        n_samples, n = m.shape
        e, z2 = self.residuals(m, frozenset())
        with np.errstate(invalid="ignore"):
            statistic = np.nanmax(np.where(np.isnan(z2), -np.inf, z2), axis=1)
        alarm = statistic > self.threshold
        excluded = np.zeros((n_samples, n), dtype=bool)
        strongest = np.full(n_samples, NO_ISOLATION, dtype=np.int32)
        active = alarm.copy()
        for stage in range(self.max_faults):
            rows = np.flatnonzero(active)
            if rows.size == 0:
                break
            candidate = np.where(excluded[rows] | np.isnan(z2[rows]), -np.inf, z2[rows])
            best = np.argmax(candidate, axis=1)
            best_value = candidate[np.arange(rows.size), best]
            exceeds = best_value > self.threshold
            if stage == 0:
                # A sensor whose fault direction is parallel to another's cannot be told
                # apart: report NOT_ISOLABLE and stop there.
                blocked = ~self.isolable[best]
                strongest[rows[blocked]] = NOT_ISOLABLE
                exceeds &= ~blocked
            active[rows[~exceeds]] = False
            rows, best = rows[exceeds], best[exceeds]
            if rows.size == 0:
                break
            excluded[rows, best] = True
            if stage == 0:
                strongest[rows] = best
            # Recompute the residuals of these samples with the new exclusion sets.
            patterns, inverse = np.unique(excluded[rows], axis=0, return_inverse=True)
            for k, pattern in enumerate(patterns):
                group = rows[inverse.ravel() == k]
                e[group], z2[group] = self.residuals(
                    m[group], frozenset(np.flatnonzero(pattern).tolist())
                )
        isolated_rows = strongest >= 0
        amplitude = np.full(n_samples, np.nan)
        amplitude[isolated_rows] = e[isolated_rows, strongest[isolated_rows]]
        block = DetectionBlock(
            statistic=statistic,
            threshold=np.full(n_samples, self.threshold),
            alarm=alarm,
            isolated=strongest,
            amplitude=amplitude,
            scores=z2,
            # every excluded sensor's residual against the others without the excluded
            # ones: its amplitude (SI)
            amplitudes=np.where(excluded, e, np.nan),
        )
        return block, excluded

    def metadata(self) -> dict[str, Any]:
        return {
            "sigma": self.sigma.tolist(),
            "bias": self.bias.tolist(),
            "threshold": self.threshold,
            "isolable": self.isolable.tolist(),
        }


def _fit_array_test(
    values: np.ndarray,
    H: np.ndarray,
    sensor_type: str,
    alpha: float,
    max_faults: int,
    sigma: np.ndarray | None = None,
) -> _ArrayTest:
    n = H.shape[0]
    if n < H.shape[1] + 1:
        raise ArrayTooSmallError(
            f"bank: {sensor_type} has {n} sensors; the leave-one-out bank needs at least"
            f" {H.shape[1] + 1}"
            + ("" if H.shape[1] == 3 else " with the lever-arm terms of these IMU positions")
        )
    calibration_stats(values)  # checks the window length
    if sigma is None:  # (given: the array config's per-sensor noise, under a budget)
        sigma = residual_sigma(H, values)
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise CalibrationError(
            f"bank: {sensor_type} noise sigma from the calibration window is not positive"
            " (constant or corrupted data); choose another window with --calibrate"
        )
    P = leave_one_out_matrix(H, sigma)
    # Sensor biases: the minimum-norm b with P b = median residual (the part of b along H
    # is unobservable and cancels in every residual).
    mean_residual = np.median(values @ np.nan_to_num(P).T, axis=0)
    bias = np.linalg.lstsq(np.nan_to_num(P), mean_residual, rcond=None)[0]
    isolable = isolable_sensors(parity_matrix(whiten(H, sigma))) & np.all(np.isfinite(P), axis=1)
    return _ArrayTest(
        sensor_type=sensor_type,
        H=H,
        sigma=sigma,
        bias=bias,
        threshold=estimated_threshold(alpha, H, sigma, np.nan_to_num(P), values.shape[0]),
        isolable=isolable,
        max_faults=max_faults,
    )
