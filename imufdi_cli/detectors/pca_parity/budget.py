"""pca-parity under a false-alarm budget: GLR evidence per sensor under the parity noise
covariance learnt in training, and its sequential decisions (docs/algorithms/pca-parity.md,
"Under a false-alarm budget").

The per-sample test compares a moving mean of principal components with a chi-square
region; under a budget the decisions are sequential (:mod:`imufdi_cli.maths.sequential`)
and need, per sample and sensor, standardized signed evidence. pca-parity's contribution
is the covariance it learns: per sensor j the generalized likelihood ratio of "a step on
sensor j" given the whole parity deviation d (Basseville & Nikiforov 1993, §7.2),

    z_j = v_j^T S^-1 d / sqrt(v_j^T S^-1 v_j),     d = p - mu (- leak),  p = V m      (1)

with ``v_j`` column j of Potter's V: a step f on sensor j moves d by ``f v_j`` and z_j by
``f sqrt(v_j^T S^-1 v_j)`` (its sensitivity), and ``argmax_j z_j^2`` is the sensor whose
fault direction makes the smallest angle with d in the metric of S^-1 (isolation by fault
direction, as the per-sample test, in the learnt metric). With S the independent-sensor
covariance ``V D V^T`` this is glt's evidence; a sample covariance of 200 rows in 45
dimensions cannot be inverted as it is (its smallest eigenvalues are 0.3x too small), so S
is regularised as a spiked model (Johnstone 2001):

- the target ``T = V D V^T``, D the per-sensor variances fitted to the residuals
  ``V^T d`` (non-negative least squares on ``(P o P) D = var(V^T d)``, as glt's sigma);
- the sample covariance whitened by it, ``M = T^-1/2 S_hat T^-1/2``: independent noise
  gives eigenvalues inside the Marchenko-Pastur bulk ``[(1 - sqrt g)^2, (1 + sqrt g)^2]``
  (g = q / N); correlated noise (a common mode, vibration seen by several chips) shows as
  eigenvalues beyond its upper edge plus three Tracy-Widom scales. Those are kept, debiased
  (``l`` solving ``lambda = l + g l / (l - 1)``, Baik, Ben Arous & Peche 2005), the rest
  set to 1: ``S = T^1/2 (I + sum_k (l_k - 1) u_k u_k^T) T^1/2``;
- the level out of sample: (1) is computed on each of 10 interleaved folds of the window
  with S, D and mu fitted on the other nine, and the evidence is divided by the root of its
  pooled out-of-fold variance when that exceeds 1 (a misfit of S makes the evidence wider
  than N(0, 1); the out-of-fold variance sees it, the in-sample one does not).

The motion leak (scale-factor and misalignment errors, ``p = mu + K x``) is the bank's
motion model (:class:`~imufdi_cli.maths.sequential.MotionModel`) on the weighted
least-squares body-frame estimate x (:class:`~imufdi_cli.detectors.budget.MotionState`):
fitted on the calibration window under the prior ``MOTION_ERROR``, learnt online, the
test widened by what it does not know yet; with the array's jitter model the rows'
motion variance factors go to the bank (the evidence is standardized at rest).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.detectors.budget import (
    HOLD_S,
    MOTION_ERROR,
    EvidenceBudget,
    MotionState,
    reference_tau,
)
from imufdi_cli.detectors.pca_parity.components import fold_labels
from imufdi_cli.errors import CalibrationError
from imufdi_cli.maths.parity import nonnegative_least_squares, sigma_estimate_variance

#: Tracy-Widom scales above the Marchenko-Pastur edge for an eigenvalue to count as
#: correlated noise (the largest eigenvalue of white noise exceeds mu + 3 sigma with
#: probability about 1e-3).
SPIKE_MARGIN = 3.0
#: Most rounds of the alternating fit of the sensor variances and the spikes.
SPIKE_ROUNDS = 10
#: Interleaved folds of the out-of-fold scale.
FOLDS = 10
#: Samples further than this many robust standard deviations from the median residual of
#: any sensor are left out of the covariance (spikes; as glt's sigma).
OUTLIER_CUT = 4.0


def _inliers(residual: np.ndarray) -> np.ndarray:
    """(N,) bool: rows whose residuals are all within ``OUTLIER_CUT`` robust sd."""
    centre = np.median(residual, axis=0)
    spread = 1.4826 * np.median(np.abs(residual - centre), axis=0)
    spread = np.where(spread > 0, spread, np.inf)
    keep = np.all(np.abs(residual - centre) <= OUTLIER_CUT * spread, axis=1)
    return keep if np.count_nonzero(keep) >= max(2, residual.shape[0] // 2) else np.ones_like(keep)


def sensor_variances(
    projection: np.ndarray, variances: np.ndarray, common: float | None = None
) -> np.ndarray:
    """Per-sensor noise variances D (n,) of independent sensors from the variances (n,) of
    the least-squares residuals ``V^T d`` (``P = V^T V``), which are ``(P o P) D`` for
    independent noise: solved by non-negative least squares; a sensor the fit drives to 0,
    or every sensor where ``P o P`` is singular (e.g. a symmetric cone), gets the common
    variance (``common``: default ``sum / q``).

    Parameters
    ----------
    projection : ndarray, shape (q, n)
        Potter's V (orthonormal rows).
    variances : ndarray, shape (n,)
        Residual variances, SI^2.
    """
    mixing = (projection.T @ projection) ** 2
    if common is None:
        common = float(variances.sum() / max(projection.shape[0], 1))
    singular = np.linalg.svd(mixing, compute_uv=False)
    if not singular[-1] > 1e-8 * singular[0]:
        return np.full(projection.shape[1], common)
    values = nonnegative_least_squares(mixing, variances)
    return np.where(values > 1e-6 * common, values, common)  # type: ignore[no-any-return]


def _roots(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric square root and inverse square root of a positive definite matrix."""
    values, vectors = np.linalg.eigh(matrix)
    values = np.maximum(values, 1e-300)
    return (vectors * np.sqrt(values)) @ vectors.T, (vectors / np.sqrt(values)) @ vectors.T


def spiked_covariance(
    projection: np.ndarray, deviation: np.ndarray, known: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The regularised parity covariance S (q, q) of centred deviations (N, q), the sensor
    variances D (n,) of its independent part and the debiased spikes kept (k,).

    Alternating (as a factor analysis, Joreskog 1967): D from the residual variances less
    what the correlated part explains (a common mode would otherwise be read as extra
    independent noise of each sensor it touches, and stay in the target), then the spikes
    of the sample covariance whitened by ``T = V D V^T``, until the set of spikes and D
    settle (at most ``SPIKE_ROUNDS`` rounds). ``known``: the sensors' noise variances
    (n,) when the array config gives them (``imufdi calibrate`` measures them over many
    orientations): D is not fitted then, only the spikes."""
    n_rows, q = deviation.shape
    sample = deviation.T @ deviation / max(n_rows - 1, 1)
    raw = np.einsum("ij,ik,kj->j", projection, sample, projection)  # var of V^T d
    common = float(raw.sum() / max(q, 1))
    ratio = q / max(n_rows - 1, 1)
    rows = math.sqrt(max(n_rows - 1, 1))
    edge = (1.0 + math.sqrt(ratio)) ** 2
    # Johnstone's centring and scale of the largest eigenvalue, divided by N - 1
    scale = (rows + math.sqrt(q)) * (1.0 / rows + 1.0 / math.sqrt(q)) ** (1.0 / 3.0) / rows**2
    excess = np.zeros((q, q))  # the correlated part, V-space
    debiased = np.zeros(0)
    variances = sensor_variances(projection, raw, common) if known is None else known
    for _ in range(SPIKE_ROUNDS):
        root, inverse_root = _roots((projection * variances) @ projection.T)
        eigenvalues, directions = np.linalg.eigh(inverse_root @ sample @ inverse_root)
        spikes = eigenvalues > edge + SPIKE_MARGIN * scale
        kept = eigenvalues[spikes]
        shifted = kept + 1.0 - ratio
        debiased = 0.5 * (shifted + np.sqrt(np.maximum(shifted**2 - 4.0 * kept, 0.0)))
        low_rank = directions[:, spikes] * (debiased - 1.0) @ directions[:, spikes].T
        excess = root @ low_rank @ root
        if known is not None:
            break
        independent = raw - np.einsum("ij,ik,kj->j", projection, excess, projection)
        updated = sensor_variances(projection, np.maximum(independent, 1e-6 * raw), common)
        settled = np.allclose(updated, variances, rtol=1e-3)
        variances = updated
        if settled or not spikes.any():
            break
    target = (projection * variances) @ projection.T
    return target + excess, variances, debiased


def glr_weights(projection: np.ndarray, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of (1): ``w_j = S^-1 v_j / sqrt(v_j^T S^-1 v_j)`` as a (q, n) matrix (z = d @ W)
    and the sensitivities ``sqrt(v_j^T S^-1 v_j)`` (n,), per SI unit; 0 for a sensor
    without a parity direction."""
    solved = np.linalg.solve(covariance, projection)  # (q, n): S^-1 v_j
    energy = np.einsum("ij,ij->j", projection, solved)
    testable = energy > 1e-12 * max(float(energy.max(initial=0.0)), 1e-300)
    sensitivity = np.where(testable, np.sqrt(np.where(testable, energy, 1.0)), 0.0)
    weights = np.where(testable, solved / np.where(testable, sensitivity, 1.0), 0.0)
    return weights, sensitivity


class PcaBudget:
    """pca-parity's evidence and decisions under a budget, for one sensor type.

    Parameters
    ----------
    projection : ndarray, shape (q, n)
        Potter's V of the type's design H (lever-arm columns included).
    design_matrix : ndarray, shape (n, p)
        H (the motion regressors, and the sigma estimation error of the threshold).
    isolable : ndarray, shape (n,), bool
    rate_hz, budget_per_s : float
    track_bias : float or None
        The bank's reference time constant (None: the default, 60 s).
    leak : bool
        Learn the motion leak (``leak=regress``); False: no regressors.
    sensor_noise : ndarray, shape (n,), optional
        Per-sensor noise sigma from the array config (each IMU's ``<type>_noise``): the
        independent part of S is then known, as for glt's ``sigma_source=auto``; None:
        fitted on the window.
    """

    def __init__(
        self,
        projection: np.ndarray,
        design_matrix: np.ndarray,
        isolable: np.ndarray,
        rate_hz: float,
        budget_per_s: float,
        track_bias: float | None,
        leak: bool = True,
        sensor_noise: np.ndarray | None = None,
        hold_s: float = HOLD_S,
        moving: bool = False,
    ) -> None:
        self.hold_s = float(hold_s)
        self.moving = bool(moving)  # motion factors come with the rows (EvidenceBudget)
        self.known = None if sensor_noise is None else np.asarray(sensor_noise, float) ** 2
        self.projection = np.asarray(projection, float)
        self.design_matrix = np.asarray(design_matrix, float)
        self.isolable = np.asarray(isolable, bool)
        self.rate_hz = float(rate_hz)
        self.budget_per_s = float(budget_per_s)
        self.tau_s = reference_tau(track_bias)
        self.learn_leak = bool(leak)
        self.mean = np.zeros(self.projection.shape[0])
        self.motion = MotionState(self.design_matrix, np.ones(self.projection.shape[1]))
        self.weights = np.zeros((self.projection.shape[0], self.projection.shape[1]))
        self.variances = np.zeros(self.projection.shape[1])
        self.spikes = np.zeros(0)
        self.cv_scale = 1.0
        self.sequential: EvidenceBudget | None = None

    def _fit_parts(
        self, parity: np.ndarray, motion: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """From training rows of parity vectors (N, q) and regressors (N, 3): the mean
        (q,), the leak coefficients (3, q) (ridge fit under the prior, parity units; zeros
        without leak), the GLR weights (q, n) and sensitivities (n,), the sensor variances
        D (n,) and the spikes kept."""
        mean = parity.mean(axis=0)
        centred = parity - mean
        coefficients = np.zeros((3, parity.shape[1]))
        if self.learn_leak:
            x = motion - motion.mean(axis=0)
            # a relative scale error e leaks e h^T x into a sensor (x SI): the prior sd of a
            # coefficient in parity units per unit of the state is MOTION_ERROR
            prior = np.eye(3) / MOTION_ERROR**2
            coefficients = np.linalg.solve(x.T @ x + prior, x.T @ centred)
            centred = centred - x @ coefficients
        keep = _inliers(centred @ self.projection)
        covariance, variances, spikes = spiked_covariance(
            self.projection, centred[keep], self.known
        )
        weights, sensitivity = glr_weights(self.projection, covariance)
        return mean, coefficients, weights, sensitivity, variances, spikes

    def fit(self, measurements: np.ndarray, window: int) -> None:
        """Learn S, the evidence's scale and the leak on a fault-free window (N, n) of the
        type's measurements (``window``: fold block length, samples)."""
        parity = measurements @ self.projection.T
        residual = (parity - parity.mean(axis=0)) @ self.projection
        first = (
            sensor_variances(self.projection, residual.var(axis=0, ddof=1))
            if self.known is None
            else self.known
        )
        self.motion = MotionState(self.design_matrix, np.sqrt(first))
        motion = self.motion(measurements)
        mean, _, weights, sensitivity, variances, spikes = self._fit_parts(parity, motion)
        self.mean = mean
        self.weights = weights
        self.variances = variances
        self.spikes = spikes
        self.cv_scale = self._out_of_fold_scale(parity, motion, window)
        z = (parity - mean) @ weights / self.cv_scale
        sensitivity = sensitivity / self.cv_scale
        if not np.all(np.isfinite(z)):
            raise CalibrationError("pca-parity: the budget's evidence is not finite on the window")
        # the evidence's scale error: that of the sensor variances (the target), as glt's
        # (none when the array config gives them)
        scale_variance = (
            0.0
            if self.known is not None
            else float(
                np.mean(
                    sigma_estimate_variance(
                        self.design_matrix, np.sqrt(self.variances), measurements.shape[0]
                    )
                )
            )
        )
        self.sequential = EvidenceBudget(
            sensitivity,
            self.isolable,
            self.rate_hz,
            self.budget_per_s,
            self.tau_s,
            scale_variance=scale_variance,
            calibration_samples=measurements.shape[0],
            hold_s=self.hold_s,
            moving=self.moving,
        )
        self.sequential.fit(z, motion if self.learn_leak else None)

    def _out_of_fold_scale(self, parity: np.ndarray, motion: np.ndarray, window: int) -> float:
        """sqrt of the pooled variance of (1) on each fold with S, mu and the leak fitted
        on the others (at least 1)."""
        labels = fold_labels(parity.shape[0], window, FOLDS)
        total = 0.0
        count = 0
        for fold in np.unique(labels):
            held = labels == fold
            if np.count_nonzero(~held) <= parity.shape[1] + 3:
                continue
            mean, coefficients, weights, sensitivity, _, _ = self._fit_parts(
                parity[~held], motion[~held]
            )
            x = motion[held] - motion[~held].mean(axis=0)
            z = ((parity[held] - mean - x @ coefficients) @ weights)[:, sensitivity > 0]
            keep = _inliers(z)
            total += float(np.sum(z[keep] ** 2))
            count += int(np.count_nonzero(keep)) * z.shape[1]
        if count == 0:
            return 1.0
        return max(1.0, math.sqrt(total / count))

    def evidence(self, measurements: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(1) for rows (N, n) of measurements, over the out-of-fold scale (standardized at
        rest), and the rows' tested states (N, 3) with the leak model (None without)."""
        z = (measurements @ self.projection.T - self.mean) @ self.weights / self.cv_scale
        return z, (self.motion(measurements) if self.learn_leak else None)

    def process(
        self, measurements: np.ndarray, factors: np.ndarray | None = None
    ) -> DetectionBlock:
        assert self.sequential is not None
        z, state = self.evidence(measurements)
        return self.sequential.decide(z, state, factors)

    def metadata(self) -> dict[str, Any]:
        meta = {} if self.sequential is None else self.sequential.metadata()
        meta.update(
            {
                "evidence": "GLR of a step per sensor under the spiked parity covariance",
                "sensor_sigma": np.sqrt(self.variances).tolist(),
                "sensor_sigma_from": "calibration" if self.known is None else "array config",
                "correlated_components": self.spikes.tolist(),
                "out_of_fold_scale": self.cv_scale,
            }
        )
        return meta
