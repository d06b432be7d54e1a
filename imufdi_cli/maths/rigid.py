"""Rigid-body lever arms: the accelerometer measurement model of a distributed IMU array.

Accelerometers at different points of a rigid body do not measure the same specific force.
With ``f_0`` the specific force at the body origin, ``w`` the angular rate and ``w_dot``
the angular acceleration (body frame), the accelerometer at position ``r_k`` measures::

    f_k = f_0 + w_dot x r_k + w x (w x r_k) = f_0 + K r_k,
    K = [w_dot x] + [w x]^2                                                   (1)

(e.g. Schopp, Klingbeil, Peters & Manoli, "Design, geometry evaluation, and calibration of
a gyroscope-free inertial measurement unit", Sens. Actuators A 162, 2010; Skog, Nilsson,
Händel & Nehorai, "Inertial sensor arrays, maximum likelihood, and Cramér-Rao bound",
IEEE Trans. Signal Process. 64(16), 2016, eq. 3). Sensor j, axis ``h_j`` of IMU k, reads
``h_j^T f_0 + sum_pq h_jp r_kq K_pq``: linear in the 12 unknowns ``(f_0, K)``. A parity
test built on the augmented measurement matrix::

    A = [H | G],   G[j, 3 p + q] = h_jp r_kq                                  (2)

instead of H alone is blind to every rigid motion (``V A = 0``), whatever w and w_dot, and
keeps ``n - rank(A)`` parity dimensions for faults. K is treated as a free 3x3 matrix (its
structure, symmetric part ``[w x]^2`` plus skew part ``[w_dot x]``, is not imposed: the
model stays linear and exact). Columns of K that the geometry cannot see are dropped: for
a planar array (every ``r_kz`` equal) the third column of K multiplies a constant and
merges with ``f_0``; a common offset of all positions likewise. The kept columns are an
orthonormal basis of the span of ``G`` outside that of ``H`` (rank by SVD, relative
tolerance :data:`RANK_RTOL` on the positions scaled by their RMS spread), so ``A`` has full
column rank.

Gyros and magnetometers are not affected by lever arms (a rigid body has one angular rate):
their design stays ``H``.
"""

from __future__ import annotations

import numpy as np

from imufdi_cli.array import ArrayConfig

#: Relative singular-value tolerance for the observable lever-arm directions (scaled
#: positions): below it a direction of K is treated as unobservable.
RANK_RTOL = 1e-6


def lever_arm_spread(array: ArrayConfig, sensor_type: str = "accel") -> float:
    """RMS distance (m) of the IMUs carrying ``sensor_type`` from their centroid."""
    imu_idx, _ = array.sensor_index(sensor_type)
    if imu_idx.size == 0:
        return 0.0
    positions = array.positions()[np.unique(imu_idx)]
    centred = positions - positions.mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(centred**2, axis=1))))


def lever_arm_columns(array: ArrayConfig, sensor_type: str = "accel") -> np.ndarray:
    """The raw lever-arm columns ``G`` of eq. (2), shape (n_s, 9), metres.

    Column ``3 p + q`` multiplies ``K_pq`` (1/s^2); row order is the sensor-id order of
    :meth:`ArrayConfig.measurement_matrix`.
    """
    imu_idx, _ = array.sensor_index(sensor_type)
    H = array.measurement_matrix(sensor_type)
    r = array.positions()[imu_idx]  # (n, 3)
    return np.einsum("jp,jq->jpq", H, r).reshape(H.shape[0], 9)


def observable_lever_arm(array: ArrayConfig, sensor_type: str = "accel") -> np.ndarray:
    """Orthonormal basis (n_s, q) of the lever-arm directions outside the span of H.

    q is 0 when every IMU sits at the same point, 6 for a planar array, 9 for a
    three-dimensional one (fewer if the sensors cannot see them). The basis is
    dimensionless (unit columns): it spans the same space as the observable columns of
    ``G``, which is all a parity test needs.
    """
    H = array.measurement_matrix(sensor_type)
    n = H.shape[0]
    spread = lever_arm_spread(array, sensor_type)
    if n == 0 or spread == 0.0:
        return np.zeros((n, 0))
    G = lever_arm_columns(array, sensor_type) / spread
    q_h, _ = np.linalg.qr(H)
    outside = G - q_h @ (q_h.T @ G)  # the part of every column not explained by H
    left, singular, _ = np.linalg.svd(outside, full_matrices=False)
    scale = max(float(np.linalg.norm(H, 2)), 1.0)
    keep = singular > RANK_RTOL * scale * np.sqrt(n)
    return left[:, keep]


def accel_design(array: ArrayConfig, sensor_type: str = "accel") -> np.ndarray:
    """Augmented measurement matrix ``[H | B]`` (n_s, 3 + q) of the rigid-body model.

    ``B`` is :func:`observable_lever_arm`; the unknowns of the least-squares fit are the
    specific force at the origin (m/s^2) and q combinations of the entries of K. For the
    parity space only the column span matters, so a parity test on this matrix is
    insensitive to any rigid motion (eq. 1).
    """
    H = array.measurement_matrix(sensor_type)
    return np.concatenate([H, observable_lever_arm(array, sensor_type)], axis=1)


def rigid_specific_force(
    positions: np.ndarray,
    specific_force: np.ndarray,
    rate: np.ndarray,
    angular_acceleration: np.ndarray,
) -> np.ndarray:
    """Specific force (N, m, 3) at each IMU position of a rigid body, eq. (1).

    Parameters
    ----------
    positions : ndarray, shape (m, 3), m
    specific_force : ndarray, shape (N, 3), m/s^2, at the origin
    rate : ndarray, shape (N, 3), rad/s
    angular_acceleration : ndarray, shape (N, 3), rad/s^2
    """
    w = rate[:, None, :]
    lever = np.cross(angular_acceleration[:, None, :], positions[None]) + np.cross(
        w, np.cross(w, positions[None])
    )
    return specific_force[:, None, :] + lever


__all__ = [
    "accel_design",
    "lever_arm_columns",
    "lever_arm_spread",
    "observable_lever_arm",
    "rigid_specific_force",
]
