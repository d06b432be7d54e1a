"""Batched attitude maths for the bank-of-estimators detector (accel/mag IMUs).

Conventions: quaternions are Hamilton ``[w, x, y, z]``; ``C(q)`` is the rotation matrix
body -> navigation frame (``v_nav = C v_body``), so a navigation-frame reference ``r`` is
seen in the body frame as ``C(q)^T r``. Attitude increments are body-frame rotation vectors:
``q <- q (x) [1, delta/2]`` (normalised), i.e. ``C <- C (I + [delta]x)`` to first order.

Every function works on whole batches (leading axes ``...``) with numpy; no per-sample
Python loop. References: Berbra, Gentil, Lesecq, "Identification of multiple faults in an
Inertial Measurement Unit" (the quaternion kinematics ``q_dot = 1/2 Xi(q) w`` and the
nonlinear least-squares attitude estimators of the bank).
"""

from __future__ import annotations

import numpy as np


def quaternion_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p (x) q``; shapes (..., 4) broadcast together."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrices C(q) (body -> nav), shape (..., 3, 3), of unit quaternions (..., 4)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    out = np.empty((*q.shape[:-1], 3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def rotation_to_quaternion(matrix: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) with ``w >= 0`` of rotation matrices (..., 3, 3).

    Shepperd's method: the branch with the largest of ``trace, C_xx, C_yy, C_zz`` is used,
    so the division is always by a number >= 1/2.
    """
    m = np.asarray(matrix, dtype=float)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    candidates = np.stack(
        [
            np.stack(
                [
                    1 + trace,
                    m[..., 2, 1] - m[..., 1, 2],
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + m00 - m11 - m22,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 - m00 + m11 - m22,
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 - m00 - m11 + m22,
                ],
                axis=-1,
            ),
        ],
        axis=-2,
    )  # (..., 4 branches, 4)
    branch = np.argmax(np.stack([trace, m00, m11, m22], axis=-1), axis=-1)
    q = np.take_along_axis(candidates, branch[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def wahba_rotation(
    body_vectors: np.ndarray, nav_vectors: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """Batched SVD solution of Wahba's problem.

    Parameters
    ----------
    body_vectors : ndarray, shape (N, k, 3)
        Observed vectors in the body frame.
    nav_vectors : ndarray, shape (k, 3)
        The same vectors' references in the navigation frame.
    weights : ndarray, shape (k,)

    Returns
    -------
    ndarray, shape (N, 3, 3)
        C (body -> nav) minimising ``sum_i w_i |r_i - C b_i|^2``.
    """
    profile = np.einsum("k,ki,nkj->nij", weights, nav_vectors, body_vectors)
    u, _, vt = np.linalg.svd(profile)
    sign = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    sign[sign == 0] = 1.0
    u[..., :, 2] *= sign[..., None]
    return np.asarray(u @ vt)


def predict_measurements(
    q: np.ndarray, sensor_axes: np.ndarray, references: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted measurements and the body-frame reference vectors.

    Parameters
    ----------
    q : ndarray, shape (..., 4)
        Attitudes (body -> nav).
    sensor_axes : ndarray, shape (c, 3)
        Body-frame direction of each measured axis (rows of H).
    references : ndarray, shape (c, 3)
        Navigation-frame reference vector each axis measures (normalised units).

    Returns
    -------
    predicted : ndarray, shape (..., c)
        ``h_c . C(q)^T r_c``.
    body_refs : ndarray, shape (..., c, 3)
        ``C(q)^T r_c``.
    """
    rot = quaternion_to_rotation(q)
    body_refs = np.matmul(references, rot)  # row c: r_c^T C = (C^T r_c)^T
    # h_c . b_c as (h0 b0 + h1 b1) + h2 b2: the order in which numpy's sum over the last
    # axis of the (..., c, 3) products adds them, without that array and its slow reduction
    # over an axis of three (the same floats; about 7x quicker)
    predicted = body_refs[..., 0] * sensor_axes[:, 0]
    predicted += body_refs[..., 1] * sensor_axes[:, 1]
    predicted += body_refs[..., 2] * sensor_axes[:, 2]
    return predicted, body_refs


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` of rows ``a`` (c, 3) and ``b`` (..., c, 3), shape (..., c, 3).

    numpy's own formulas and order of operations (``cp0 = a1 b2 - a2 b1`` etc.), so the
    same floats, without its copies of both inputs (``astype``) and its broadcasting set-up.
    """
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    np.multiply(a1, b2, out=out[..., 0])
    tmp = a2 * b1
    out[..., 0] -= tmp
    np.multiply(a2, b0, out=out[..., 1])
    np.multiply(a0, b2, out=tmp)
    out[..., 1] -= tmp
    np.multiply(a0, b1, out=out[..., 2])
    np.multiply(a1, b0, out=tmp)
    out[..., 2] -= tmp
    return out


def measurement_jacobian(
    q: np.ndarray, sensor_axes: np.ndarray, references: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted measurements and their Jacobian with respect to a body-frame increment.

    From ``C^T r -> C^T r + (C^T r) x delta`` the row of component c is
    ``d y_hat_c / d delta = h_c x (C(q)^T r_c)``.

    Returns
    -------
    predicted : ndarray, shape (..., c)
    jacobian : ndarray, shape (..., c, 3)
    """
    predicted, body_refs = predict_measurements(q, sensor_axes, references)
    return predicted, _cross(sensor_axes, body_refs)


def gauss_newton_attitude(
    measurements: np.ndarray,
    sensor_axes: np.ndarray,
    references: np.ndarray,
    weights: np.ndarray,
    q_init: np.ndarray,
    iterations: int = 8,
    tolerance: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """A bank of weighted nonlinear least-squares attitude estimators, batched over samples.

    Estimator ``e`` minimises ``sum_c weights[e, c] (y_c - h_c . C(q)^T r_c)^2`` by
    Gauss-Newton on body-frame rotation-vector increments (Jacobian from
    :func:`measurement_jacobian`). The 3x3 normal equations of all E*N problems are solved in
    one ``np.linalg.solve``, with a tiny Levenberg-Marquardt damping so that directions the
    estimator cannot observe get no increment instead of a singular system.

    Parameters
    ----------
    measurements : ndarray, shape (N, c)
        Normalised measurements y.
    sensor_axes, references : ndarray, shape (c, 3)
        See :func:`predict_measurements`.
    weights : ndarray, shape (E, c)
        Weight of each component in each estimator (0 = the estimator is blind to it).
    q_init : ndarray, shape (N, 4) or (E, N, 4)
        Warm start.
    iterations : int
        Maximum Gauss-Newton iterations.
    tolerance : float
        Stop when every increment is below this (rad).

    Returns
    -------
    q : ndarray, shape (E, N, 4)
    last_step : ndarray, shape (E, N)
        Largest component of the last increment, rad (convergence check: near 0 when the
        iteration converged).
    """
    n_est = weights.shape[0]
    q = np.broadcast_to(q_init, (n_est, *measurements.shape[:-1], 4)).copy()
    last_step = np.full(q.shape[:-1], np.inf)
    for _ in range(iterations):
        predicted, jacobian = measurement_jacobian(q, sensor_axes, references)
        residual = measurements[None] - predicted  # (E, N, c)
        weighted = jacobian * weights[:, None, :, None]
        normal = np.matmul(weighted.swapaxes(-1, -2), jacobian)
        damping = (1e-9 * np.trace(normal, axis1=-2, axis2=-1) + 1e-30)[..., None, None] * np.eye(3)
        rhs = np.matmul(weighted.swapaxes(-1, -2), residual[..., None])
        delta = np.linalg.solve(normal + damping, rhs)[..., 0]
        increment = np.concatenate([np.ones((*delta.shape[:-1], 1)), 0.5 * delta], axis=-1)
        q = quaternion_multiply(q, increment)
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        step = np.abs(delta)
        last_step = np.maximum(np.maximum(step[..., 0], step[..., 1]), step[..., 2])
        if np.all(last_step < tolerance):
            break
    return q, last_step


def make_continuous(q: np.ndarray, q_before: np.ndarray | None = None) -> np.ndarray:
    """Flip signs along axis -2 (time) so consecutive quaternions have positive dot products.

    Parameters
    ----------
    q : ndarray, shape (..., N, 4)
    q_before : ndarray, shape (..., 4), optional
        The sample preceding ``q[..., 0, :]`` (already continuous), for streaming.
    """
    if q.shape[-2] == 0:
        return q
    dots = np.einsum("...ni,...ni->...n", q[..., 1:, :], q[..., :-1, :])
    steps = np.where(dots < 0, -1.0, 1.0)
    first = np.ones((*q.shape[:-2], 1))
    if q_before is not None:
        first = np.where(np.einsum("...i,...i->...", q[..., 0, :], q_before) < 0, -1.0, 1.0)[
            ..., None
        ]
    signs = np.cumprod(np.concatenate([first, steps], axis=-1), axis=-1)
    return q * signs[..., None]


def xi_matrix(q: np.ndarray) -> np.ndarray:
    """Xi(q), shape (..., 4, 3), with ``q_dot = 1/2 Xi(q) w`` for the body rate ``w``."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([-x, -y, -z], axis=-1),
            np.stack([w, -z, y], axis=-1),
            np.stack([z, w, -x], axis=-1),
            np.stack([-y, x, w], axis=-1),
        ],
        axis=-2,
    )


def body_rate_from_quaternions(
    q_prev: np.ndarray, q_next: np.ndarray, dt: np.ndarray
) -> np.ndarray:
    """Least-squares body rate over an interval from ``q_dot = 1/2 Xi(q) w``.

    With the finite difference ``q_dot ~ (q_next - q_prev) / dt`` at the interval midpoint
    ``q_mid = normalise(q_prev + q_next)`` and ``Xi^T Xi = I`` for a unit quaternion, the
    least-squares solution is ``w = 2 Xi(q_mid)^T q_dot`` (mean rate over the interval).

    Parameters
    ----------
    q_prev, q_next : ndarray, shape (..., 4)
        Sign-continuous unit quaternions.
    dt : ndarray, shape (...) or scalar
        Interval, seconds.

    Returns
    -------
    ndarray, shape (..., 3), rad/s
    """
    q_mid = q_prev + q_next
    q_mid = q_mid / np.linalg.norm(q_mid, axis=-1, keepdims=True)
    q_dot = (q_next - q_prev) / np.asarray(dt)[..., None]
    return 2.0 * np.einsum("...ij,...i->...j", xi_matrix(q_mid), q_dot)
