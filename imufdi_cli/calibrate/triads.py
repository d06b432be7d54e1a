"""Per-triad matrices and biases: accelerometers from the static orientations (alternating
least squares, then Gauss-Newton), gyroscopes from the motion against the array consensus."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imufdi_cli.array import ArrayConfig, TriadCalibration

#: Below this many distinct orientations the accelerometer matrices are not estimated.
MIN_ORIENTATIONS_MATRIX = 4
#: Warn below this many orientations or this coverage.
GOOD_ORIENTATIONS = 9
GOOD_COVERAGE = 0.3
#: RMS consensus rate needed on every body axis to estimate the gyro matrices (rad/s).
MIN_MOTION_RATE = np.radians(20.0)
ALS_ITERATIONS = 30
#: Accelerometer Gauss-Newton: largest step count and step size (M entries, m/s^2) to stop.
ACCEL_GN_MAX_STEPS = 50
ACCEL_GN_TOLERANCE = 1e-9


@dataclass
class TriadFigures:
    """Printable figures of one triad's calibration."""

    imu: int
    sensor_type: str
    scale_ppm: list[float]  # (M_aa - 1) * 1e6
    misalignment_mrad: float  # largest |off-diagonal| of M, mrad
    bias: list[float]  # SI


def _rotation_gauge(array: ArrayConfig, mats: list[np.ndarray], scale: bool) -> list[np.ndarray]:
    """Fix the unobservable common transform: mean_k R_k M_k R_k^T -> rotation part (or
    all of it, ``scale``) removed."""
    rot = array.rotations()
    mean = sum(r @ m @ r.T for r, m in zip(rot, mats)) / len(mats)
    if scale:
        fix = np.linalg.inv(mean)
    else:
        u, _, vt = np.linalg.svd(mean)
        fix = (u @ vt).T
    return [r.T @ fix @ r @ m for r, m in zip(rot, mats)]


def calibrate_accel(
    array: ArrayConfig, means: np.ndarray, gravity: float, full: bool
) -> tuple[list[TriadCalibration], int]:
    """Accelerometer ``M, b`` from per-interval raw means (I, m, 3), see module docstring.

    Alternating least squares gets the triads to agree in a few iterations; the common
    mode (|f| = g) converges slowly that way, so Gauss-Newton on all unknowns at once
    (12 per triad, 2 per orientation on the sphere |f| = g) finishes the fit. The
    common rotation, not observable, is left to the minimum-norm step and then fixed by
    the gauge. Returns the calibrations and the number of Gauss-Newton steps.
    """
    rot = array.rotations()  # (m, 3, 3)
    n_int, m, _ = means.shape
    mats: np.ndarray = np.tile(np.eye(3), (m, 1, 1))
    biases: np.ndarray = np.zeros((m, 3))
    design = np.concatenate([means, np.ones((n_int, m, 1))], axis=2).transpose(1, 0, 2)
    normal = np.einsum("kia,kib->kab", design, design)  # (m, 4, 4)
    f: np.ndarray = np.zeros((n_int, 3))
    for _ in range(ALS_ITERATIONS):
        body = np.einsum("kab,ikb->ika", rot @ mats, means - biases)  # (I, m, 3)
        f = body.mean(axis=1)
        f = gravity * f / np.linalg.norm(f, axis=1, keepdims=True)
        target = np.einsum("ia,kab->kib", f, rot)  # R_k^T f_i as rows, (m, I, 3)
        if full:
            sol = np.linalg.solve(normal, np.einsum("kia,kib->kab", design, target))
            mats = sol[:, :3].transpose(0, 2, 1)
            biases = -np.linalg.solve(mats, sol[:, 3][..., None])[..., 0]
        else:
            inv = np.linalg.inv(mats)
            biases = (means.transpose(1, 0, 2) - np.einsum("kib,kab->kia", target, inv)).mean(1)
    steps = 0
    if full:
        mats, biases, steps = _gauss_newton(rot, design, mats, biases, f, gravity)
        mats = np.stack(_rotation_gauge(array, list(mats), scale=False))
    cals = [TriadCalibration(matrix=mt, bias=b) for mt, b in zip(mats, biases)]
    return cals, steps


def _gauss_newton(
    rot: np.ndarray,
    design: np.ndarray,
    mats: np.ndarray,
    biases: np.ndarray,
    f: np.ndarray,
    gravity: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Minimise sum ||R_k P_k x_ki - f_i||^2 over P_k = [M_k | -M_k b_k] (3x4) and f_i on
    the sphere of radius g (tangent-plane steps, renormalised)."""
    m, n_int, _ = design.shape
    params = np.concatenate([mats, -(mats @ biases[..., None])], axis=2)  # (m, 3, 4)
    n_p = 12 * m
    # d r_kia / d P_k[p, q] = R_k[a, p] x_ki[q]: one (3, 12) block per (k, i)
    blocks = np.einsum("kap,kiq->kiapq", rot, design).reshape(m, n_int, 3, 12)
    steps = 0
    for steps in range(1, ACCEL_GN_MAX_STEPS + 1):  # noqa: B007 (count returned)
        # tangent basis of each f_i
        u = f / np.linalg.norm(f, axis=1, keepdims=True)
        helper = np.where(np.abs(u[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        t1 = np.cross(u, helper)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(u, t1)
        tangent = np.stack([t1, t2], axis=2)  # (I, 3, 2)
        residual = np.einsum("kab,kib->kia", rot @ params, design) - f[None]  # (m, I, 3)
        jac = np.zeros((m, n_int, 3, n_p + 2 * n_int))
        for k in range(m):
            jac[k, :, :, 12 * k : 12 * k + 12] = blocks[k]
        for i in range(n_int):
            jac[:, i, :, n_p + 2 * i : n_p + 2 * i + 2] = -tangent[i]
        # normal equations with a tiny Levenberg damping: the common rotation (3 gauge
        # directions) is not observable, the damping keeps the step off it
        flat = jac.reshape(-1, n_p + 2 * n_int)
        normal = flat.T @ flat
        normal[np.diag_indices_from(normal)] += 1e-9 * np.trace(normal) / normal.shape[0]
        step = np.linalg.solve(normal, -(flat.T @ residual.reshape(-1)))
        params = params + step[:n_p].reshape(m, 3, 4)
        f = f + np.einsum("iab,ib->ia", tangent, step[n_p:].reshape(n_int, 2))
        f = gravity * f / np.linalg.norm(f, axis=1, keepdims=True)
        if np.abs(step).max() < ACCEL_GN_TOLERANCE:
            break
    mats = params[:, :, :3]
    biases = -np.linalg.solve(mats, params[:, :, 3][..., None])[..., 0]
    return mats, biases, steps


class TriadMoments:
    """Sums over rows of the triads of an array flattened to ``x`` (3m,): the row count,
    ``sum x`` (3m,) and ``sum x x^T`` (3m, 3m). What the gyro fit and the residual RMS
    need of the rows, in memory independent of their number (rows are added in blocks)."""

    def __init__(self, m: int) -> None:
        self.m = m
        self.count = 0
        self.total = np.zeros(3 * m)
        self.outer = np.zeros((3 * m, 3 * m))

    def add(self, triads: np.ndarray) -> None:
        """Rows (k, m, 3)."""
        if triads.shape[0] == 0:
            return
        flat = triads.reshape(triads.shape[0], -1)
        self.count += int(flat.shape[0])
        self.total += flat.sum(axis=0)
        self.outer += flat.T @ flat

    def affine(self, scale: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """``sum y y^T`` of ``y = scale x + offset`` (scale (3m, 3m), offset (3m,))."""
        cross = np.outer(scale @ self.total, offset)
        return (
            scale @ self.outer @ scale.T + cross + cross.T + self.count * np.outer(offset, offset)
        )


def _block_diagonal(blocks: list[np.ndarray] | np.ndarray) -> np.ndarray:
    m = len(blocks)
    out = np.zeros((3 * m, 3 * m))
    for k, block in enumerate(blocks):
        out[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = block
    return out


def calibrate_gyro(
    array: ArrayConfig, gyro: np.ndarray, static: np.ndarray, motion: np.ndarray, full: bool
) -> list[TriadCalibration]:
    """Gyro biases from static rows, matrices from motion rows relative to the consensus
    (in memory: :func:`gyro_calibration` of the rows' sums)."""
    moments = TriadMoments(gyro.shape[1])
    moments.add(gyro[motion])
    return gyro_calibration(array, gyro[static].mean(axis=0), moments, full)


def gyro_calibration(
    array: ArrayConfig, biases: np.ndarray, motion: TriadMoments, full: bool
) -> list[TriadCalibration]:
    """Gyro ``M, b``: biases (m, 3) from the static rows; with ``full``, the matrices by
    alternating least squares against the array consensus on the motion rows, from their
    sums: with ``x`` the bias-free rates, the consensus ``c = mean_k R_k M_k x_k`` and
    each triad's least squares ``x_k M_k^T = c R_k`` need only ``S_kj = sum x_k x_j^T``
    (the normal equations ``S_kk M_k^T = mean_j S_kj M_j^T R_j^T R_k``); each iteration
    ends with the gauge ``mean_k R_k M_k R_k^T = I``."""
    m = biases.shape[0]
    rot = array.rotations()
    mats = [np.eye(3) for _ in range(m)]
    if full:
        flat = biases.reshape(-1)
        centred = motion.affine(np.eye(3 * m), -flat)  # sum (x - b)(x - b)^T
        blocks = [
            [centred[3 * k : 3 * k + 3, 3 * j : 3 * j + 3] for j in range(m)] for k in range(m)
        ]
        for _ in range(ALS_ITERATIONS):
            weights = [mats[j].T @ rot[j].T for j in range(m)]  # the consensus, per triad
            new = []
            for k in range(m):
                target = sum(blocks[k][j] @ weights[j] for j in range(m)) / m @ rot[k]
                new.append(np.linalg.solve(blocks[k][k], target).T)
            mats = _rotation_gauge(array, new, scale=True)
    return [TriadCalibration(matrix=mt, bias=b) for mt, b in zip(mats, biases)]


def consensus_rms(array: ArrayConfig, moments: TriadMoments, biases: np.ndarray) -> np.ndarray:
    """RMS per body axis (3,) of the array consensus ``mean_k R_k (x_k - b_k)`` over the
    rows of ``moments``."""
    m = moments.m
    mean_rotation = np.concatenate(list(array.rotations()), axis=1) / m  # (3, 3m)
    centred = moments.affine(np.eye(3 * m), -biases.reshape(-1))
    with np.errstate(invalid="ignore"):
        return np.sqrt(
            np.maximum(np.diag(mean_rotation @ centred @ mean_rotation.T), 0.0) / moments.count
        )


def _residual_rms(
    array: ArrayConfig, triads: np.ndarray | TriadMoments, cals: list[TriadCalibration] | None
) -> float:
    """RMS over rows, IMUs and axes of each triad's body-frame value minus the array mean,
    from the rows (N, m, 3) or their sums (:class:`TriadMoments`)."""
    if isinstance(triads, np.ndarray):
        moments = TriadMoments(triads.shape[1])
        moments.add(triads)
    else:
        moments = triads
    if moments.count == 0:
        return float("nan")
    m = moments.m
    if cals is None:
        scale, offset = np.eye(3 * m), np.zeros(3 * m)
    else:
        scale = _block_diagonal([c.matrix for c in cals])
        offset = -scale @ np.concatenate([c.bias for c in cals])
    spread = np.eye(3 * m) - np.kron(np.ones((m, m)) / m, np.eye(3))  # minus the mean
    project = spread @ _block_diagonal(list(array.rotations()))
    energy = float(np.trace(project @ moments.affine(scale, offset) @ project.T))
    return float(np.sqrt(max(energy, 0.0) / (moments.count * m * 3)))


def _figures(k: int, sensor_type: str, cal: TriadCalibration) -> TriadFigures:
    off = cal.matrix - np.diag(np.diag(cal.matrix))
    return TriadFigures(
        imu=k,
        sensor_type=sensor_type,
        scale_ppm=[float(v) for v in (np.diag(cal.matrix) - 1.0) * 1e6],
        misalignment_mrad=float(np.abs(off).max() * 1e3),
        bias=[float(v) for v in cal.bias],
    )
