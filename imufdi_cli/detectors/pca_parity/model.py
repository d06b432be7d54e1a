"""What pca-parity learns per sensor type: the training motion as a regression design
(``_MotionDesign``) and the fitted parity model with its thresholds (``_TypeModel``)."""

from __future__ import annotations

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.moving import MovingWindow
from imufdi_cli.detectors.pca_parity import choices
from imufdi_cli.detectors.pca_parity.components import mean_variance_inflation, plug_in_quantile


def lever_arm_spread(array: ArrayConfig, sensor_type: str) -> float:
    """Largest distance (m) between the positions of the IMUs carrying ``sensor_type``."""
    imu_idx, _ = array.sensor_index(sensor_type)
    positions = array.positions()[np.unique(imu_idx)]
    if positions.shape[0] < 2:
        return 0.0
    return float(np.max(np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)))


class _MotionDesign:
    """The training motion as a regression design for the leak model.

    Attributes
    ----------
    centre : ndarray, shape (3,)
        Training mean of the body-frame estimate xhat (SI).
    basis : ndarray, shape (3, e)
        Excited directions of xhat (those the leak was fitted on; e = 0 without motion).
    inverse_gram : ndarray, shape (e, e)
        ``(X^T X)^-1`` of the centred training xhat in that basis.
    rms : ndarray, shape (e,)
        RMS of the training motion along each excited direction (SI).
    coverage_inverse : ndarray, shape (3, 3)
        ``(X^T X + N S)^-1`` over all three directions, S the noise covariance of xhat:
        the leverage of a motion along a direction the training did not excite is large.
        Zero when coverage is not tracked (``space=raw``, ``leak=none``).
    """

    def __init__(
        self,
        centre: np.ndarray,
        basis: np.ndarray,
        inverse_gram: np.ndarray,
        rms: np.ndarray,
        coverage_inverse: np.ndarray,
    ) -> None:
        self.centre = centre
        self.basis = basis
        self.inverse_gram = inverse_gram
        self.rms = rms
        self.coverage_inverse = coverage_inverse

    @classmethod
    def static(
        cls, coverage_inverse: np.ndarray | None = None, centre: np.ndarray | None = None
    ) -> _MotionDesign:
        """No excited direction (no leak fitted); coverage tracked if given."""
        coverage = np.zeros((3, 3)) if coverage_inverse is None else coverage_inverse
        middle = np.zeros(3) if centre is None else centre
        return cls(middle, np.zeros((3, 0)), np.zeros((0, 0)), np.zeros(0), coverage)


class _TypeModel:
    """Everything learned in training for one sensor type."""

    def __init__(
        self,
        projection: np.ndarray,
        estimator: np.ndarray,
        leak: np.ndarray,
        mean: np.ndarray,
        eigenvalues: np.ndarray,
        eigenvectors: np.ndarray,
        rho: np.ndarray,
        n_train: int,
        window: int,
        n_components: int,
        isolable: np.ndarray,
        motion: _MotionDesign | None = None,
        variance_rows: float | np.ndarray = np.inf,
    ) -> None:
        self.projection = projection  # (q, n): V (parity) or I (raw)
        self.estimator = estimator  # (3, n): H^+ (least-squares body-frame estimate)
        self.leak = leak  # (q, 3): K
        self.mean = mean  # (q,)
        self.eigenvalues = eigenvalues  # (q,), descending
        self.eigenvectors = eigenvectors  # (q, q), columns
        self.rho = rho  # (q,)
        self.n_components = n_components
        self.n_train = n_train
        # Equivalent degrees of freedom of each component's variance estimate (rows of the
        # half it was measured on, less for autocorrelated rows); inf: treated as known.
        self.variance_dof = variance_rows * (1.0 - rho**2) / (1.0 + rho**2)  # (q,)
        self.isolable = isolable  # (n,) bool
        lengths = np.arange(1, window + 1)
        # Variance of the moving-mean deviation of each component, per window fill (L, q).
        self.mean_variance = eigenvalues[None, :] * (
            mean_variance_inflation(rho, lengths) / lengths[:, None]
            + mean_variance_inflation(rho, np.array([n_train]))[0][None, :] / n_train
        )
        self.window = MovingWindow(window, projection.shape[0])
        self.window_length = window
        self._residual_thresholds: dict[float, np.ndarray] = {}
        norms = np.linalg.norm(projection, axis=0)
        self.direction_norms = norms  # |v_j|, (n,)
        self.motion = motion if motion is not None else _MotionDesign.static()
        # Scheffe allowance on the leak error (``SCHEFFE_LEAK``): e, the mean of chi2(e).
        excited = self.motion.basis.shape[1]
        self.leak_tolerance = float(excited) if excited and choices.SCHEFFE_LEAK else 1.0
        self.motion_window = MovingWindow(window, 3)
        self.inflation_n = mean_variance_inflation(rho, np.array([n_train]))[0]  # g(rho_i, N)
        self.inflation_l = mean_variance_inflation(rho, lengths) / lengths[:, None]  # (L, q)
        tail = eigenvalues[n_components:]
        pooled = float(np.sum(tail * rho[n_components:]) / np.sum(tail)) if tail.size else 0.0
        self.pooled_rho = np.array([pooled])
        # Share of each principal component in the parity components whose leak was fitted:
        # only those carry the leak-estimate error (the others carry the mean error only).
        fitted = np.any(leak != 0.0, axis=1).astype(np.float64)  # (q,)
        self.leak_weight = (eigenvectors**2).T @ fitted  # (q,)
        self.leak_fitted = bool(fitted.any())
        tail_weight = self.leak_weight[n_components:]
        self.leak_weight_q = float(np.sum(tail * tail_weight) / np.sum(tail)) if tail.size else 0.0
        # Online extrapolation of the leak model, accumulated for the coverage report.
        self.samples_seen = 0
        self.samples_beyond = 0
        self.max_leverage_ratio = 0.0

    def leverage(self, estimates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Prediction leverage ``h_t`` of the moving mean of the motion, per sample.

        ``h_t = 1/N + xbar_t^T G xbar_t`` where xbar_t is the moving mean of the motion
        estimate (centred on the training mean, in the excited basis) and G the inverse Gram
        matrix of the training motion: the variance of the fitted mean and leak at xbar_t
        in units of the noise variance (the regression prediction variance). 1/N at the
        training centre; it grows as the motion leaves the training range.

        Returns
        -------
        extra : ndarray, shape (N,)
            ``xbar_t^T G xbar_t`` (the leverage is ``1/N + extra``).
        coverage : ndarray, shape (N,)
            The same ratio ``N h_t`` over all three directions (``coverage_inverse``): 1 at
            the training centre, large where the motion leaves what training covered.
        """
        design = self.motion
        sums, counts = self.motion_window.push(estimates - design.centre)
        means = sums / counts[:, None]  # (N, 3)
        excited = means @ design.basis  # (N, e)
        extra = np.einsum("ij,jk,ik->i", excited, design.inverse_gram, excited)
        coverage = 1.0 + self.n_train * np.einsum(
            "ij,jk,ik->i", means, design.coverage_inverse, means
        )
        return extra, coverage

    def residual_threshold(self, level: float) -> np.ndarray:
        """Threshold of Q = |discarded components of the mean deviation|^2, per window fill,
        for a deviation at the training centre (leverage 1/N); see ``residual_scale``.

        Q is a weighted sum of chi2(1) variables with weights v_i (the moving-mean variances
        of the discarded components); Box's approximation Q ~ g chi2(h), g = sum v^2 / sum v,
        h = (sum v)^2 / sum v^2 (Box 1954; Jackson & Mudholkar 1979). It uses only sums of
        eigenvalues, which are far less biased than the individual small eigenvalues of a
        sample covariance (in high dimension the smallest ones are grossly underestimated),
        and one pooled autocorrelation for the discarded components.

        Returns
        -------
        ndarray, shape (window,)
        """
        if level not in self._residual_thresholds:
            k = self.n_components
            tail = self.eigenvalues[k:]
            rho = np.array([float(np.sum(tail * self.rho[k:]) / np.sum(tail))])
            lengths = np.arange(1, self.window_length + 1)
            factor = (
                mean_variance_inflation(rho, lengths)[:, 0] / lengths
                + mean_variance_inflation(rho, np.array([self.n_train]))[0, 0] / self.n_train
            )
            weights = tail[None, :] * factor[:, None]  # (L, q-k)
            scale = (weights**2).sum(axis=1) / weights.sum(axis=1)
            dof = weights.sum(axis=1) ** 2 / (weights**2).sum(axis=1)
            tail_dof = self.variance_dof[k:]
            estimate_dof = float(np.sum(tail) ** 2 / np.sum(tail**2 / tail_dof))
            self._residual_thresholds[level] = scale * plug_in_quantile(level, dof, estimate_dof)
        return self._residual_thresholds[level]

    def residual_scale(self, counts: np.ndarray, leverage: np.ndarray) -> np.ndarray:
        """Factor (N,) on ``residual_threshold`` for the prediction leverage of each sample.

        The discarded components share one pooled autocorrelation, so their moving-mean
        variances are ``tail_i f_t`` with a common factor
        ``f_t = g(rho, L)/L + g(rho, N) h_t``; Box's dof does not depend on a common factor
        and the threshold scales with it.
        """
        rho = self.pooled_rho
        lengths = np.arange(1, self.window_length + 1)
        per_length = mean_variance_inflation(rho, lengths)[:, 0] / lengths  # (L,)
        g_n = mean_variance_inflation(rho, np.array([self.n_train]))[0, 0]
        at_centre = per_length[counts - 1] + g_n / self.n_train
        return (per_length[counts - 1] + g_n * leverage) / at_centre

    def transform(self, measurements: np.ndarray) -> np.ndarray:
        """Leak-compensated deviations ``p - K xhat - mu``, shape (N, q)."""
        parity = measurements @ self.projection.T
        if np.any(self.leak):
            parity = parity - (measurements @ self.estimator.T) @ self.leak.T
        return parity - self.mean
