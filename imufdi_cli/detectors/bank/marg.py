"""bank's marg mode model (the paper, one IMU with accelerometer, magnetometer and gyros):
the bank of attitude estimators each blind to one normalised component (Wahba start,
Gauss-Newton), its solution and details.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.attitude import (
    gauss_newton_attitude,
    measurement_jacobian,
    rotation_to_quaternion,
    wahba_rotation,
)
from imufdi_cli.log import ImuBlock

# --- marg mode (one IMU with accel + mag + gyro) --------------------------------------

#: Estimator masks: rows 0..5 blind to component i, row 6 uses all six.
ESTIMATOR_MASKS = np.vstack([1.0 - np.eye(6), np.ones((1, 6))])
FULL_ESTIMATOR = 6

#: A blind residual is computed only where its predicted std is at most this multiple of the
#: measurement noise (elsewhere the blind estimator cannot observe the attitude well enough:
#: a fault there would be invisible, and the nonlinear estimate is unreliable).
MAX_BLIND_STD_RATIO = 20.0

#: Blind estimators feed the gyro residuals only where their blind residual's predicted std
#: is at most this multiple of the noise (weakly observable attitudes are too noisy there).
GYRO_BLIND_STD_RATIO = 3.0

#: marg mode: a gyro-residual series whose estimator was not clean for longer than this, s,
#: restarts from its next clean sample instead of comparing across the gap.
GYRO_MAX_GAP_S = 0.05

#: Gauss-Newton counts as converged when its last increment is below this, rad.
CONVERGED_STEP = 1e-6


@dataclass
class BankDetails:
    """Intermediate results of the last ``process`` call (for plots, tests, debugging).

    Attributes
    ----------
    isolated_sets : dict of str to ndarray, shape (N, n_s), bool
        Every sensor isolated at each sample (several for simultaneous faults).
    estimator_residuals : ndarray, shape (N, 7, 6), or None
        marg mode: ``R_i`` (normalised units, calibrated bias removed) of the estimators blind
        to a1, a2, a3, m1, m2, m3 and of the full estimator.
    attitude : ndarray, shape (N, 7, 4), or None
        marg mode: quaternions (body -> nav) of the seven estimators.
    gyro_residuals : ndarray, shape (N, n_g), or None
        marg mode: filtered gyro residuals, rad/s (Table 2).
    chosen_estimator : ndarray, shape (N,), or None
        marg mode: estimator whose attitude feeds the gyro residuals (6 = full).
    """

    isolated_sets: dict[str, np.ndarray]
    estimator_residuals: np.ndarray | None = None
    attitude: np.ndarray | None = None
    gyro_residuals: np.ndarray | None = None
    chosen_estimator: np.ndarray | None = None


@dataclass
class _MargModel:
    sensor_axes: np.ndarray  # (6, 3) body-frame axis of a_x, a_y, a_z, m_x, m_y, m_z
    references: np.ndarray  # (6, 3) nav-frame reference measured by each component
    gravity_norm: float  # m/s^2
    field_norm: float  # tesla
    angle: float  # rad between specific force and magnetic field
    accel_to_body: np.ndarray  # (3, 3)
    mag_to_body: np.ndarray  # (3, 3)
    noise: np.ndarray  # (6,) white-noise std of each normalised component

    def normalised(self, block: ImuBlock, array: ArrayConfig) -> np.ndarray:
        assert block.accel is not None and block.mag is not None
        accel = array.select(block.accel, "accel") / self.gravity_norm
        mag = array.select(block.mag, "mag") / self.field_norm
        return np.concatenate([accel, mag], axis=1)

    def solve(self, y: np.ndarray, iterations: int) -> _MargSolution:
        """Run the seven estimators on normalised measurements (N, 6).

        The full estimator starts from the SVD (Wahba) solution of the two measured
        vectors; the six blind estimators start from the full one's attitude (warm start:
        they differ from it by noise, or by the attitude error a fault causes).
        """
        body = np.stack([y[:, :3] @ self.accel_to_body.T, y[:, 3:] @ self.mag_to_body.T], axis=1)
        start = rotation_to_quaternion(
            wahba_rotation(body, self.references[[0, 3]], np.array([1.0, 1.0]))
        )
        weights = ESTIMATOR_MASKS / self.noise**2  # (7, 6)
        q_full, step_full = gauss_newton_attitude(
            y, self.sensor_axes, self.references, weights[FULL_ESTIMATOR:], start, iterations
        )
        q_blind, step_blind = gauss_newton_attitude(
            y, self.sensor_axes, self.references, weights[:FULL_ESTIMATOR], q_full[0], iterations
        )
        q = np.concatenate([q_blind, q_full], axis=0)
        predicted, jacobian = measurement_jacobian(q, self.sensor_axes, self.references)
        residuals = y[None] - predicted  # (7, N, 6)
        # Predicted variance of the blind residual R_j[j] = e_j - J_j dq_j with
        # Cov(dq_j) = (J^T W_j J)^{-1} (linearised weighted least squares), evaluated at the
        # well-determined full attitude. It grows without bound where estimator j cannot
        # observe the attitude (g x h along sensor axis j, see docs): there the residual is
        # not computed (NaN).
        blind = np.arange(6)
        j_full = np.broadcast_to(jacobian[FULL_ESTIMATOR], (7, *jacobian.shape[1:]))
        information = np.matmul((j_full * weights[:, None, :, None]).swapaxes(-1, -2), j_full)
        information += (1e-12 * np.trace(information, axis1=-2, axis2=-1) + 1e-30)[
            ..., None, None
        ] * np.eye(3)
        covariance = np.linalg.inv(information)  # (7, N, 3, 3) rad^2
        j_blind = j_full[blind, :, blind, :]  # (6, N, 3)
        spread = (np.matmul(covariance[:6], j_blind[..., None])[..., 0] * j_blind).sum(axis=-1)
        blind_std = np.sqrt((self.noise**2)[:, None] + spread).T  # (N, 6)
        # Each estimator's own attitude covariance (its Jacobian at its own attitude): feeds
        # the gyro residual variance of the series built from that estimator's attitude.
        own_information = np.matmul(
            (jacobian * weights[:, None, :, None]).swapaxes(-1, -2), jacobian
        )
        own_information += (1e-12 * np.trace(own_information, axis1=-2, axis2=-1) + 1e-30)[
            ..., None, None
        ] * np.eye(3)
        own_covariance = np.linalg.inv(own_information)  # (7, N, 3, 3) rad^2
        # (At the full attitude instead, an a_y fault, which tilts the full attitude by
        # ~17 deg, made the a_y-blind series' variance 5x too small: 42 % gyro alarms.)
        converged = np.concatenate([step_blind, step_full], axis=0).T < CONVERGED_STEP  # (N, 7)
        observable = (blind_std <= MAX_BLIND_STD_RATIO * self.noise) & converged[:, :6]
        fit_cost = np.einsum("enc,ec->en", residuals[:6] ** 2, weights[:6]).T  # (N, 6)
        return _MargSolution(
            q=q,
            residuals=residuals,
            blind=np.where(observable, residuals[blind, :, blind].T, np.nan),
            blind_std=blind_std,
            fit_cost=np.where(observable, fit_cost, np.inf),
            covariance=own_covariance,
            usable=np.concatenate([observable, converged[:, 6:]], axis=1),
            full_jacobian=jacobian[FULL_ESTIMATOR],
        )


@dataclass
class _MargSolution:
    q: np.ndarray  # (7, N, 4)
    residuals: np.ndarray  # (7, N, 6)
    blind: np.ndarray  # (N, 6) R_j[j]
    blind_std: np.ndarray  # (N, 6) predicted std of R_j[j]
    fit_cost: np.ndarray  # (N, 6) weighted SSR of estimator j on its 5 components
    covariance: np.ndarray  # (7, N, 3, 3) linearised attitude covariance, rad^2
    usable: np.ndarray  # (N, 7) estimator observable and converged
    full_jacobian: np.ndarray | None = None  # (N, 6, 3) of the full estimator, rad^-1

    def parity_evidence(self, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per component j, the standardized residual of the full estimator linearised at
        its attitude, ``z_j = r_w,j / sqrt(P_jj)`` (N, 6), and ``sqrt(P_jj)`` (N, 6).

        ``r_w = (y - y_hat(q_full)) / noise``, ``P = I - J_w (J_w^T J_w)^-1 J_w^T`` the
        projector on the residual space (``J_w`` the Jacobian over the noise): the parity
        evidence of glt for this nonlinear model (to first order the blind residual
        ``R_j[j]`` over its standard deviation, but from the well-determined full attitude,
        so without the heavy tails of a weakly observable blind estimator)."""
        assert self.full_jacobian is not None
        white = self.residuals[FULL_ESTIMATOR] / noise
        jacobian = self.full_jacobian / noise[None, :, None]
        # (J_w^T J_w)^-1 is the full estimator's attitude covariance
        spread = np.einsum("nji,nik,njk->nj", jacobian, self.covariance[FULL_ESTIMATOR], jacobian)
        energy = np.sqrt(np.clip(1.0 - spread, 1e-12, 1.0))
        return white / energy, energy
