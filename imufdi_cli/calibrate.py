"""``imufdi calibrate``: per-chip calibration of an IMU array from its own log.

Parity-space detection needs the IMUs of an array to agree with each other, not with
truth. This module estimates, for every triad, ``calibrated = M (raw - b)``
(:class:`~imufdi_cli.array.TriadCalibration`) from a log with static intervals in several
orientations (and some motion for the gyro matrices):

**Static intervals** are found automatically: the moving standard deviation (1 s window)
of the array-mean specific force and angular rate in the body frame stays under three
times its own 10th percentile (the noise floor), with absolute caps, for at least
``min_static`` seconds; half a second more is trimmed at each end. Intervals whose gravity
directions lie within 10 degrees are one orientation; the *coverage* of directions is
``3 lambda_min`` of the mean ``u u^T`` over orientations (1: isotropic, 0: coplanar).

**Accelerometers** — multi-position calibration (Skog & Händel, "Calibration of a MEMS
inertial measurement unit", IMEKO XVIII, 2006; Tedaldi, Pretto & Menegatti, "A robust and
easy to implement method for IMU calibration without external equipments", ICRA 2014,
eq. 10-11, there with one triad against ``|f| = g``), here jointly for all triads as in
the array self-calibration of Carlsson, Skog & Jaldén (IEEE Sensors J. 21(6), 2021): at
rest in orientation ``i`` every triad measures the same specific force ``f_i`` with
``|f_i| = g``::

    R_k M_k (a_ki - b_k) = f_i          for every triad k and orientation i

solved by alternating least squares: given the ``M, b``, ``f_i = g normalize(mean_k R_k
M_k (a_ki - b_k))``; given the ``f_i``, each triad's ``[M_k | -M_k b_k]`` is a linear least
squares problem (12 unknowns, 3 equations per orientation: needs >= 4 non-coplanar
orientations; fewer give biases only). The common rotation of all triads is not
observable at rest: it is fixed so that the triads' mean rotation is the nominal one
(polar factor of ``mean_k R_k M_k R_k^T``).

**Gyroscopes** — bias ``b_k`` = mean raw rate over the static intervals; ``M_k`` from the
motion samples (not static, not clipped) relative to the array consensus ``w = mean_k R_k
M_k (w_k - b_k)``, by alternating least squares again, with the gauge ``mean_k R_k M_k
R_k^T = I`` (the array's mean scale and axes stay nominal: agreement, not truth). Without
motion on every axis (RMS consensus rate under :data:`MIN_MOTION_RATE`) only biases are
estimated, with a warning.

**Noise levels** — each sensor's white-noise sigma after calibration, from the parity
residuals of every static interval, pooled over the intervals (:func:`static_noise`). On the MIMU4444 board
the gyro noise changes with the orientation (a narrow-band 8-16 Hz component on some
z-axis gyros, up to 1.5x in sigma, docs/real-arrays.md), so the typical level over many
orientations is a better reference for a parity test than a few seconds in one of them.
Stored per IMU as ``<type>_noise``; glt uses it (``sigma_source=auto``).

**Sampling-time jitter** — the residual between triads grows from the noise at rest to
~45x it in hand motion. Each type's ``sigma_t`` of the model of
:mod:`imufdi_cli.detectors.jitter` (noise variance ``1 + sigma_t^2 |ydot_w|^2 / n`` in
whitened units) is fitted by moments on the motion rows (not near a static interval, not
clipped, predecessor usable) with the calibrated noise levels and the lever-arm design
for accelerometers; stored as ArrayConfig ``[jitter]``, used by glt and pca-parity.

**Chip time offsets** (a diagnostic, not applied) — a chip sampling ``dt_k`` later than
the others reads ``w(t + dt_k) ~ w + w_dot dt_k``; its gyro residual from the consensus in
motion is regressed on the consensus angular acceleration, giving ``dt_k`` (relative to
the array's mean sampling instant) and the share of that chip's residual it explains.
On the MIMU4444 recordings every offset is below 0.01 ms and explains nothing
(docs/real-arrays.md), so no compensation is built; a warning names chips where an offset
explains more than :data:`TIME_OFFSET_WARNING` of the residual.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig, TriadCalibration
from imufdi_cli.detectors.jitter import MAX_JITTER_S, fit_jitter
from imufdi_cli.detectors.parity import residual_projector
from imufdi_cli.detectors.rigid import accel_design
from imufdi_cli.errors import ArrayConfigError, CalibrationError
from imufdi_cli.log import ImuBlock
from imufdi_cli.validity import flag_values

STANDARD_GRAVITY = 9.80665  # m/s^2
#: Static detection: window (s), noise-floor multiple and absolute caps (SI).
STATIC_WINDOW_S = 1.0
STATIC_FLOOR_FACTOR = 3.0
STATIC_CAP = {"accel": 0.3, "gyro": np.radians(3.0)}
#: Two static intervals are the same orientation when their gravity directions are closer.
SAME_ORIENTATION_RAD = np.radians(10.0)
#: Below this many distinct orientations the accelerometer matrices are not estimated.
MIN_ORIENTATIONS_MATRIX = 4
#: Warn below this many orientations or this coverage.
GOOD_ORIENTATIONS = 9
GOOD_COVERAGE = 0.3
#: RMS consensus rate needed on every body axis to estimate the gyro matrices (rad/s).
MIN_MOTION_RATE = np.radians(20.0)
ALS_ITERATIONS = 30
#: Warn when a chip time offset explains more than this share of its motion residual.
TIME_OFFSET_WARNING = 0.1
#: Accelerometer Gauss-Newton: largest step count and step size (M entries, m/s^2) to stop.
ACCEL_GN_MAX_STEPS = 50
ACCEL_GN_TOLERANCE = 1e-9


@dataclass
class StaticInterval:
    start_s: float
    end_s: float
    direction: np.ndarray  # unit gravity-opposite direction (specific force), body frame
    orientation: int = -1

    def to_dict(self) -> dict[str, Any]:
        return {
            "start_s": round(self.start_s, 3),
            "end_s": round(self.end_s, 3),
            "direction": [round(float(v), 4) for v in self.direction],
            "orientation": self.orientation,
        }


@dataclass
class TriadFigures:
    """Printable figures of one triad's calibration."""

    imu: int
    sensor_type: str
    scale_ppm: list[float]  # (M_aa - 1) * 1e6
    misalignment_mrad: float  # largest |off-diagonal| of M, mrad
    bias: list[float]  # SI


@dataclass
class CalibrationResult:
    """What ``imufdi calibrate`` estimated and measured."""

    array: ArrayConfig
    intervals: list[StaticInterval]
    orientations: int
    coverage: float
    static_s: float
    motion_s: float
    clipped_rows: int
    figures: list[TriadFigures]
    residual_rms: dict[str, tuple[float, float]]  # type -> (before, after), SI
    warnings: list[str] = field(default_factory=list)
    runtime_s: float = 0.0
    time_offsets_s: list[float] = field(default_factory=list)  # per IMU, gyro motion
    time_offset_explained: list[float] = field(default_factory=list)  # share of residual
    jitter_s: dict[str, float] = field(default_factory=dict)  # per type, sampling jitter

    def to_dict(self) -> dict[str, Any]:
        return {
            "intervals": [i.to_dict() for i in self.intervals],
            "orientations": self.orientations,
            "coverage": self.coverage,
            "static_s": self.static_s,
            "motion_s": self.motion_s,
            "clipped_rows": self.clipped_rows,
            "residual_rms": {k: list(v) for k, v in self.residual_rms.items()},
            "triads": [f.__dict__ for f in self.figures],
            "warnings": self.warnings,
            "time_offsets_s": self.time_offsets_s,
            "time_offset_explained": self.time_offset_explained,
            "jitter_s": self.jitter_s,
        }


# --- static intervals ------------------------------------------------------------------


def _moving_std(x: np.ndarray, w: int) -> np.ndarray:
    """Centred moving standard deviation (N,) of the rows of x (N, 3), summed over axes."""
    n = x.shape[0]
    w = max(2, min(w, n))
    c1 = np.concatenate([np.zeros((1, 3)), np.cumsum(x, axis=0)])
    c2 = np.concatenate([np.zeros((1, 3)), np.cumsum(x * x, axis=0)])
    lo = np.clip(np.arange(n) - w // 2, 0, n - w)
    hi = lo + w
    mean = (c1[hi] - c1[lo]) / w
    var = (c2[hi] - c2[lo]) / w - mean * mean
    return np.sqrt(np.maximum(var, 0.0).sum(axis=1))


def body_consensus(array: ArrayConfig, triads: np.ndarray) -> np.ndarray:
    """Mean over IMUs of ``R_k x_k``: (N, m, 3) -> (N, 3) in the body frame."""
    return np.einsum("kij,nkj->ni", array.rotations(), triads) / triads.shape[1]


def find_static(
    array: ArrayConfig,
    accel: np.ndarray,
    gyro: np.ndarray | None,
    t_s: np.ndarray,
    usable: np.ndarray,
    *,
    min_static_s: float = 5.0,
) -> tuple[list[StaticInterval], np.ndarray]:
    """Static intervals (and their row mask) of raw accel (N, m, 3), gyro (N, m, 3)."""
    rate = array.rate_hz
    w = max(3, round(STATIC_WINDOW_S * rate))
    still = usable.copy()
    for name, data in (("accel", accel), ("gyro", gyro)):
        if data is None:
            continue
        consensus = body_consensus(array, np.where(usable[:, None, None], data, 0.0))
        spread = _moving_std(consensus, w)
        floor = float(np.percentile(spread[usable], 10)) if usable.any() else 0.0
        still &= spread < min(STATIC_CAP[name], max(STATIC_FLOOR_FACTOR * floor, 1e-12))
    # runs of still rows (the centred window already keeps w/2 off a move), trimmed by
    # another half window at each end
    mask = np.zeros(len(t_s), dtype=bool)
    intervals: list[StaticInterval] = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    consensus_a = body_consensus(array, accel)
    for a, b in zip(edges[::2], edges[1::2]):
        a, b = a + w // 2, b - w // 2
        if b <= a or t_s[b - 1] - t_s[a] < min_static_s:
            continue
        mean = consensus_a[a:b].mean(axis=0)
        norm = np.linalg.norm(mean)
        if not np.isfinite(norm) or norm == 0:
            continue
        intervals.append(StaticInterval(float(t_s[a]), float(t_s[b - 1]), mean / norm))
        mask[a:b] = True
    return intervals, mask


def group_orientations(intervals: list[StaticInterval]) -> tuple[int, float]:
    """Assign orientation numbers in place; returns (count, coverage in [0, 1])."""
    centres: list[np.ndarray] = []
    for item in intervals:
        for j, c in enumerate(centres):
            if np.arccos(np.clip(c @ item.direction, -1, 1)) < SAME_ORIENTATION_RAD:
                item.orientation = j
                break
        else:
            item.orientation = len(centres)
            centres.append(item.direction)
    if not centres:
        return 0, 0.0
    u = np.stack(centres)
    scatter = u.T @ u / len(u)
    return len(centres), max(0.0, float(3.0 * np.linalg.eigvalsh(scatter)[0]))


# --- estimation ------------------------------------------------------------------------


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


def calibrate_gyro(
    array: ArrayConfig, gyro: np.ndarray, static: np.ndarray, motion: np.ndarray, full: bool
) -> list[TriadCalibration]:
    """Gyro biases from static rows, matrices from motion rows relative to the consensus."""
    m = gyro.shape[1]
    rot = array.rotations()
    biases = gyro[static].mean(axis=0)  # (m, 3)
    mats = [np.eye(3) for _ in range(m)]
    if full:
        x = gyro[motion] - biases  # (n, m, 3)
        for _ in range(ALS_ITERATIONS):
            consensus = np.stack([x[:, k] @ mats[k].T @ rot[k].T for k in range(m)], 1).mean(1)
            for k in range(m):
                sol, *_ = np.linalg.lstsq(x[:, k], consensus @ rot[k], rcond=None)
                mats[k] = sol.T
            mats = _rotation_gauge(array, mats, scale=True)
    return [TriadCalibration(matrix=mt, bias=b) for mt, b in zip(mats, biases)]


def _residual_rms(
    array: ArrayConfig, triads: np.ndarray, cals: list[TriadCalibration] | None
) -> float:
    """RMS over rows, IMUs and axes of each triad's body-frame value minus the array mean."""
    if triads.shape[0] == 0:
        return float("nan")
    rot = array.rotations()
    body = np.stack(
        [
            (triads[:, k] if cals is None else cals[k].apply(triads[:, k])) @ rot[k].T
            for k in range(triads.shape[1])
        ],
        axis=1,
    )
    return float(np.sqrt(np.mean((body - body.mean(axis=1, keepdims=True)) ** 2)))


def _figures(k: int, sensor_type: str, cal: TriadCalibration) -> TriadFigures:
    off = cal.matrix - np.diag(np.diag(cal.matrix))
    return TriadFigures(
        imu=k,
        sensor_type=sensor_type,
        scale_ppm=[float(v) for v in (np.diag(cal.matrix) - 1.0) * 1e6],
        misalignment_mrad=float(np.abs(off).max() * 1e3),
        bias=[float(v) for v in cal.bias],
    )


def time_offsets(
    array: ArrayConfig, gyro: np.ndarray, t_s: np.ndarray, motion: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-IMU sampling-time offset from calibrated gyro triads in motion.

    Each chip's body-frame rate minus the array consensus ``w`` is regressed on the
    consensus angular acceleration ``w_dot`` (central differences):
    ``R_k w_k - w ~ w_dot dt_k``, least squares over the motion rows and three axes.

    Parameters
    ----------
    array : ArrayConfig
    gyro : ndarray, shape (N, m, 3)
        Calibrated rates, rad/s (IMU frames).
    t_s : ndarray, shape (N,)
    motion : ndarray, shape (N,), bool
        Rows to use (moving, not clipped; their neighbours enter the differences).

    Returns
    -------
    offsets : ndarray, shape (m,), s
        Relative to the array's mean sampling instant (they sum to ~0).
    explained : ndarray, shape (m,)
        Share of each chip's residual energy on those rows that the offset explains.
    """
    m = gyro.shape[1]
    if np.count_nonzero(motion) < 3 or len(t_s) < 3:
        return np.zeros(m), np.zeros(m)
    body = np.einsum("kij,nkj->nki", array.rotations(), gyro)
    consensus = body.mean(axis=1)
    rate_dot = np.gradient(consensus, t_s, axis=0)  # (N, 3)
    x = rate_dot[motion].ravel()
    energy = float(x @ x)
    offsets, explained = np.zeros(m), np.zeros(m)
    if energy <= 0:
        return offsets, explained
    for k in range(m):
        y = (body[motion, k] - consensus[motion]).ravel()
        offsets[k] = float(x @ y) / energy
        total = float(y @ y)
        if total > 0:
            explained[k] = 1.0 - float(np.sum((y - offsets[k] * x) ** 2)) / total
    return offsets, explained


def static_noise(
    array: ArrayConfig,
    accel: np.ndarray,
    gyro: np.ndarray | None,
    t_s: np.ndarray,
    static: np.ndarray,
    intervals: list[StaticInterval],
) -> list[dict[str, np.ndarray]]:
    """Per-IMU, per-type noise sigma (3,) of the calibrated sensors at rest (SI).

    For every sensor type with a parity space (>= 4 sensors), the least-squares residuals
    ``r = (I - H H^+) m`` of each static interval (motion and common offsets cancel) about
    their interval mean give pooled residual variances ``v`` (weighted by the intervals'
    sample counts); per-sensor variances solve ``((I - S) o (I - S)) sigma^2 = v`` as in
    :func:`~imufdi_cli.detectors.parity.residual_sigma` (plain least squares: the pooled
    system is well determined; a non-positive solution falls back to the common
    ``sum v / (n - 3)``). Axes a type lacks keep no entry.

    Parameters
    ----------
    array : ArrayConfig
        Geometry with the chip calibration to apply.
    accel, gyro : ndarray, shape (N, m, 3)
        Raw samples (SI).
    t_s : ndarray, shape (N,)
    static : ndarray, shape (N,), bool
    intervals : list of StaticInterval
    """
    out: list[dict[str, np.ndarray]] = [{} for _ in range(array.n_imus)]
    for sensor_type, raw in (("accel", accel), ("gyro", gyro)):
        if raw is None or array.n_sensors(sensor_type) < 4:
            continue
        projector, residual = _parity_residuals(array, raw, sensor_type)
        n = projector.shape[0]
        squares = np.zeros(n)
        dof = 0
        for item in intervals:
            lo, hi = np.searchsorted(t_s, [item.start_s, item.end_s], side="left")
            part = residual[lo : hi + 1][static[lo : hi + 1]]
            if part.shape[0] < 10:
                continue
            squares += part.var(axis=0) * part.shape[0]
            dof += part.shape[0] - 1
        if dof == 0:
            continue
        variances = squares / dof
        sigma2, *_ = np.linalg.lstsq(projector**2, variances, rcond=None)
        if not np.all(sigma2 > 0):
            sigma2 = np.full(n, variances.sum() / (n - 3))
        _scatter_triads(array, sensor_type, np.sqrt(sigma2), out)
    return out


def _parity_residuals(
    array: ArrayConfig, raw: np.ndarray, sensor_type: str
) -> tuple[np.ndarray, np.ndarray]:
    """``(I - H H^+)`` (n, n) and the parity residuals (N, n) of the calibrated sensors of
    one type: motion and the array's common offsets cancel in them."""
    values = array.select(array.calibrate_triads(raw, sensor_type), sensor_type)
    H = array.measurement_matrix(sensor_type)
    projector = residual_projector(H)
    return projector, values @ projector.T


def _scatter_triads(
    array: ArrayConfig, sensor_type: str, per_sensor: np.ndarray, out: list[dict[str, np.ndarray]]
) -> None:
    """Store per-sensor values (n,) as each complete IMU triad's (3,) in ``out[imu][type]``."""
    imu_idx, axis_idx = array.sensor_index(sensor_type)
    for k in range(array.n_imus):
        mine = imu_idx == k
        if np.count_nonzero(mine) == 3:
            triad = np.empty(3)
            triad[axis_idx[mine]] = per_sensor[mine]
            out[k][sensor_type] = triad


def expected_normal_range(count: int) -> float:
    """E[max - min] of ``count`` independent standard normal variables.

    ``d_n = integral of (1 - Phi(x)^n - (1 - Phi(x))^n) dx`` (Tippett, *Biometrika* 17,
    1925); 0 for n < 2, 1.128 for n = 2, 3.735 for n = 20.
    """
    if count < 2:
        return 0.0
    from scipy.stats import norm

    grid = np.linspace(-10.0, 10.0, 20001)
    cdf = norm.cdf(grid)
    inside = 1.0 - cdf**count - (1.0 - cdf) ** count
    return float(np.sum(inside) * (grid[1] - grid[0]))


#: An orientation enters the noise spread with at least this many successive differences.
SPREAD_MIN_DIFFERENCES = 50


def noise_spread(
    array: ArrayConfig,
    accel: np.ndarray,
    gyro: np.ndarray | None,
    t_s: np.ndarray,
    static: np.ndarray,
    intervals: list[StaticInterval],
) -> tuple[list[dict[str, np.ndarray]], dict[str, np.ndarray]]:
    """Each sensor's healthy white-noise variance spread over the static orientations.

    For every sensor type with a parity space (>= 4 sensors) and every orientation o (the
    static intervals grouped by :func:`group_orientations`), the mean square of the
    successive differences of the parity residuals ``r = (I - H H^+) m`` inside its static
    intervals gives ``v_o`` (n,); per-sensor difference variances solve
    ``((I - S) o (I - S)) s_o = v_o`` (as :func:`static_noise` does for the pooled
    variances; successive differences remove each interval's mean and slow drift, as
    noise-glr's own differences do). The spread of sensor j is::

        ln kappa_j = max(0, max_o ln s_jo - min_o ln s_jo - d_O se)

    with ``se = sqrt(2 / nu)`` the standard error of ``ln s_jo`` (``nu = 2 N^2 / (3 N - 1)``
    equivalent degrees of freedom of the mean square of N differences of white noise,
    lag-1 correlation -1/2; root-mean-square over the orientations) and ``d_O`` the
    expected range of O standard normals (:func:`expected_normal_range`): the range of O
    estimates of one constant variance is about ``d_O se`` in the log, so a sensor whose
    noise does not change with the orientation gets kappa ~ 1, and one whose variance
    changes by a factor F gets about F (slightly less: the correction assumes no change).
    The per-sensor solution's sampling error is taken as that of ``v_o`` (the operator
    is close to diagonal for 24 sensors and 3 unknowns); coloured noise has fewer
    degrees of freedom, which leaves kappa slightly high (the conservative side for a
    test whose null hypothesis is ``sigma^2 <= kappa sigma_cal^2``).

    Parameters
    ----------
    array : ArrayConfig
        Geometry with the chip calibration to apply.
    accel, gyro : ndarray, shape (N, m, 3)
        Raw samples (SI).
    t_s : ndarray, shape (N,)
    static : ndarray, shape (N,), bool
    intervals : list of StaticInterval
        With their ``orientation`` numbers set.

    Returns
    -------
    spread : list of dict
        Per IMU, per sensor type, kappa (3,) (>= 1, dimensionless).
    per_orientation : dict
        Per sensor type, ``s_o`` (O, n): the difference variances per orientation (SI^2),
        sensor-id order.
    """
    out: list[dict[str, np.ndarray]] = [{} for _ in range(array.n_imus)]
    tables: dict[str, np.ndarray] = {}
    for sensor_type, raw in (("accel", accel), ("gyro", gyro)):
        if raw is None or array.n_sensors(sensor_type) < 4:
            continue
        projector, residual = _parity_residuals(array, raw, sensor_type)
        n = projector.shape[0]
        sums: dict[int, np.ndarray] = {}
        counts: dict[int, int] = {}
        for item in intervals:
            lo, hi = np.searchsorted(t_s, [item.start_s, item.end_s], side="left")
            rows = np.arange(lo, min(hi + 1, len(t_s)))
            rows = rows[static[rows]]
            if rows.size < 2:
                continue
            consecutive = np.diff(rows) == 1
            diffs = np.diff(residual[rows], axis=0)[consecutive]
            sums[item.orientation] = sums.get(item.orientation, np.zeros(n)) + np.sum(
                diffs**2, axis=0
            )
            counts[item.orientation] = counts.get(item.orientation, 0) + diffs.shape[0]
        used = sorted(o for o in counts if counts[o] >= SPREAD_MIN_DIFFERENCES)
        if len(used) < 2:
            continue
        weights = projector**2
        variances = []
        for o in used:
            s_o, *_ = np.linalg.lstsq(weights, sums[o] / counts[o], rcond=None)
            if not np.all(s_o > 0):  # as static_noise: fall back to the common level
                s_o = np.full(n, float(np.sum(sums[o] / counts[o])) / (n - 3))
            variances.append(s_o)
        table = np.stack(variances)  # (O, n)
        tables[sensor_type] = table
        count = np.array([counts[o] for o in used], dtype=float)
        dof = 2.0 * count**2 / (3.0 * count - 1.0)
        se = float(np.sqrt(np.mean(2.0 / dof)))
        logs = np.log(table)
        excess = logs.max(axis=0) - logs.min(axis=0) - expected_normal_range(len(used)) * se
        _scatter_triads(array, sensor_type, np.exp(np.maximum(excess, 0.0)), out)
    return out, tables


def _zero_clipped_rows(
    array: ArrayConfig, accel: np.ndarray, gyro: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Rows with any clipped or invalid accel/gyro value (per the array's ranges), zeroed.

    Returns ``(accel (N, m, 3), gyro (N, m, 3) or None, clipped (N,) bool)``.
    """
    clipped = np.zeros(accel.shape[0], dtype=bool)
    for s, data in (("accel", accel), ("gyro", gyro)):
        if data is not None:
            c, i = flag_values(data, s, array.range.get(s))
            clipped |= (c | i).any(axis=(1, 2))
    accel = np.where(clipped[:, None, None], 0.0, accel)
    gyro = None if gyro is None else np.where(clipped[:, None, None], 0.0, gyro)
    return accel, gyro, clipped


def motion_rows(array: ArrayConfig, static: np.ndarray, clipped: np.ndarray) -> np.ndarray:
    """Rows (N,) bool more than one static window away from any static row, not clipped."""
    w = round(STATIC_WINDOW_S * array.rate_hz)
    near_static = np.convolve(static.astype(float), np.ones(2 * w + 1), "same") > 0
    return np.asarray(~near_static & ~clipped)


#: ``calibrate --jitter-fit`` choices: the per-sample level the fit holds in motion.
JITTER_FITS = ("level", "moments", "off")
JITTER_LEVEL_ALPHA = 0.01


def jitter_stage(
    array: ArrayConfig,
    fields: dict[str, np.ndarray | None],
    t_s: np.ndarray,
    static: np.ndarray,
    clipped: np.ndarray,
    method: str = "level",
) -> dict[str, float]:
    """Sampling-time jitter sigma_t (s) per sensor type with a parity space and per-sensor
    noise, fitted on the motion rows (:func:`imufdi_cli.detectors.jitter.fit_jitter`):
    ``method`` ``level`` (the per-sample test at alpha = 1 % holds its level on those rows),
    ``moments`` or ``off`` (nothing fitted).

    Parameters
    ----------
    array : ArrayConfig
        With the chip calibration and noise levels to use.
    fields : dict
        Raw triads (N, m, 3) per sensor type (None: absent), clipped rows zeroed.
    t_s : (N,) s; static, clipped : (N,) bool.
    """
    motion = motion_rows(array, static, clipped)
    rows = motion & np.roll(motion, 1)
    out: dict[str, float] = {}
    if method == "off" or not rows[1:].any():
        return out
    alpha = JITTER_LEVEL_ALPHA if method == "level" else None
    for sensor_type, raw in fields.items():
        sigma = array.sensor_noise(sensor_type)
        if raw is None or sigma is None or array.n_sensors(sensor_type) < 4:
            continue
        design = array.measurement_matrix(sensor_type)
        if sensor_type == "accel":
            try:
                design = accel_design(array, sensor_type)
            except ArrayConfigError:
                pass
        if design.shape[0] <= design.shape[1]:
            continue
        white = array.select(array.calibrate_triads(raw, sensor_type), sensor_type) / sigma
        offset = white[static].mean(axis=0) if static.any() else None
        out[sensor_type] = fit_jitter(design / sigma[:, None], white, t_s, rows, offset, alpha)
    return out


def _gyro_stage(
    array: ArrayConfig,
    gyro: np.ndarray,
    t_s: np.ndarray,
    static: np.ndarray,
    clipped: np.ndarray,
    warnings: list[str],
) -> tuple[list[TriadCalibration], float, np.ndarray, np.ndarray, tuple[float, float]]:
    """Gyro calibration of :func:`calibrate_block`: biases from the static rows, matrices
    when the motion excites every body axis, chip time offsets (reported, not compensated).

    Parameters
    ----------
    gyro : (N, m, 3) rad/s, clipped rows zeroed; t_s : (N,) s; static, clipped : (N,) bool.
    warnings : appended to.

    Returns
    -------
    (per-IMU gyro calibrations, motion duration s, time offsets (m,) s or empty,
    share of the residual they explain (m,) or empty, residual RMS before/after, rad/s)
    """
    offsets = explained = np.zeros(0)
    motion = motion_rows(array, static, clipped)
    motion_s = float(np.count_nonzero(motion) / array.rate_hz)
    full_gyro = False
    if motion.any():
        consensus = body_consensus(array, gyro[motion] - gyro[static].mean(axis=0))
        rms = np.sqrt(np.mean(consensus**2, axis=0))
        full_gyro = bool(np.all(rms >= MIN_MOTION_RATE))
        if not full_gyro:
            warnings.append(
                "motion RMS rate per body axis "
                + "/".join(f"{np.degrees(v):.1f}" for v in rms)
                + f" deg/s: gyro matrices need >= {np.degrees(MIN_MOTION_RATE):g} deg/s on"
                " every axis; gyro biases only"
            )
    else:
        warnings.append("no motion in the log: gyro biases only (matrices need motion)")
    gyro_cal = calibrate_gyro(array, gyro, static, motion, full_gyro)
    if full_gyro:
        calibrated = array.with_calibration([{"gyro": c} for c in gyro_cal])
        # motion rows whose neighbours are usable too (central differences)
        inner = motion & np.roll(~clipped, 1) & np.roll(~clipped, -1)
        inner[[0, -1]] = False
        offsets, explained = time_offsets(
            array, calibrated.calibrate_triads(gyro, "gyro"), t_s, inner
        )
        if np.any(explained > TIME_OFFSET_WARNING):
            worst = int(np.argmax(explained))
            warnings.append(
                f"chip sampling-time offsets (up to {abs(offsets[worst]) * 1e3:.3g} ms on"
                f" imu{worst}) explain {explained[worst]:.0%} of its gyro residual in"
                " motion; they are not compensated"
            )
    sample = gyro[motion] if motion.any() else gyro[static]
    residual = (_residual_rms(array, sample, None), _residual_rms(array, sample, gyro_cal))
    return gyro_cal, motion_s, offsets, explained, residual


def calibrate_block(
    array: ArrayConfig,
    block: ImuBlock,
    *,
    gravity: float = STANDARD_GRAVITY,
    min_static_s: float = 5.0,
    jitter_fit: str = "level",
) -> CalibrationResult:
    """Estimate every triad's calibration from raw samples (see the module docstring).

    Parameters
    ----------
    array : ArrayConfig
        Geometry (rotations) of the array; its own calibration is ignored (replaced).
    block : ImuBlock
        Raw (uncalibrated) samples, N rows, accelerometers required.
    gravity : float
        |f| at rest, m/s^2.
    min_static_s : float
        Shortest static interval used, s.
    jitter_fit : {"level", "moments", "off"}
        How the sampling-time jitter is fitted (:func:`jitter_stage`).

    Raises
    ------
    CalibrationError
        No accelerometers or no static interval (exit 3).
    """
    started = time.perf_counter()
    warnings: list[str] = []
    if block.accel is None:
        raise CalibrationError("calibrate needs accelerometers (the log has none)")
    if len(block) == 0:
        raise CalibrationError("calibrate: no samples in the selected time range")
    accel, gyro, clipped = _zero_clipped_rows(array, block.accel, block.gyro)
    t_s = block.t_s()
    intervals, static = find_static(array, accel, gyro, t_s, ~clipped, min_static_s=min_static_s)
    if not intervals:
        raise CalibrationError(
            f"no static interval of at least {min_static_s:g} s found "
            f"({t_s[-1] - t_s[0]:.3g} s examined): calibrate needs the array at rest in several"
            " orientations (accelerometers) and at rest at least once (gyro biases)"
        )
    orientations, coverage = group_orientations(intervals)
    full_accel = orientations >= MIN_ORIENTATIONS_MATRIX and coverage > 0.05
    if not full_accel:
        warnings.append(
            f"only {orientations} orientation(s) (coverage {coverage:.2f}): accelerometer"
            f" matrices need >= {MIN_ORIENTATIONS_MATRIX} non-coplanar orientations;"
            " biases only (relative to the array consensus)"
        )
    elif orientations < GOOD_ORIENTATIONS or coverage < GOOD_COVERAGE:
        warnings.append(
            f"{orientations} orientations, coverage {coverage:.2f}: the accelerometer"
            f" matrices are weakly determined (aim for >= {GOOD_ORIENTATIONS} orientations"
            f" spread over the sphere, coverage >= {GOOD_COVERAGE})"
        )
    means = []
    for item in intervals:
        rows = (t_s >= item.start_s) & (t_s <= item.end_s) & static
        means.append(accel[rows].mean(axis=0))
    mean_arr = np.stack(means)  # (I, m, 3)
    accel_cal, iterations = calibrate_accel(array, mean_arr, gravity, full_accel)
    if full_accel and iterations >= ACCEL_GN_MAX_STEPS:
        warnings.append(
            f"accelerometer fit stopped after {iterations} iterations without converging"
        )
    residual = {
        "accel": (_residual_rms(array, mean_arr, None), _residual_rms(array, mean_arr, accel_cal))
    }
    cals: list[dict[str, TriadCalibration]] = [{"accel": c} for c in accel_cal]
    motion_s = 0.0
    offsets = explained = np.zeros(0)
    if gyro is not None:
        gyro_cal, motion_s, offsets, explained, residual["gyro"] = _gyro_stage(
            array, gyro, t_s, static, clipped, warnings
        )
        for k, gcal in enumerate(gyro_cal):
            cals[k]["gyro"] = gcal
    calibrated = array.with_calibration(cals)
    noise = static_noise(calibrated, accel, gyro, t_s, static, intervals)
    spread, _ = noise_spread(calibrated, accel, gyro, t_s, static, intervals)
    figures = [
        _figures(k, s, c)
        for k, per in enumerate(cals)
        for s, c in sorted(per.items(), reverse=True)
    ]
    out = calibrated.with_sensor_noise(noise).with_noise_spread(spread)
    jitter = jitter_stage(out, {"accel": accel, "gyro": gyro}, t_s, static, clipped, jitter_fit)
    for sensor_type, value in jitter.items():
        if value >= MAX_JITTER_S:
            warnings.append(
                f"{sensor_type}: no sampling-time jitter up to {MAX_JITTER_S * 1e3:g} ms holds the"
                " level in this log's motion (residuals unrelated to the motion?); the tests"
                " will be blind in motion: check the calibration, or --jitter-fit moments/off"
            )
    out = out.with_jitter(jitter)
    result = CalibrationResult(
        array=out,
        intervals=intervals,
        orientations=orientations,
        coverage=coverage,
        static_s=float(np.count_nonzero(static) / array.rate_hz),
        motion_s=motion_s,
        clipped_rows=int(np.count_nonzero(clipped)),
        figures=figures,
        residual_rms=residual,
        warnings=warnings,
        runtime_s=time.perf_counter() - started,
        jitter_s=jitter,
    )
    if offsets.size:
        result.time_offsets_s = [float(v) for v in offsets]
        result.time_offset_explained = [float(v) for v in explained]
    return result


def calibrate_file(
    source: str,
    *,
    window: tuple[float, float | None] | None = None,
    base: ArrayConfig | None = None,
    gravity: float = STANDARD_GRAVITY,
    min_static_s: float = 5.0,
    topics: list[str] | None = None,
    jitter_fit: str = "level",
) -> CalibrationResult:
    """Read a log, recover raw chip values and estimate the calibration.

    ``base`` (``--array``) gives the geometry; default the log's ``imufdi.array``. The
    log's own calibration (if it was ingested with one) is undone first, so the result is
    relative to the raw chip output, as ``ingest --array`` and ``detect --array`` expect.
    """
    from imufdi_cli.mcapio import read_array

    started = time.perf_counter()
    log_array, block = read_array(source, topics=topics)
    if len(block) == 0:
        raise CalibrationError(f"{source}: no aligned IMU samples")
    array = log_array if base is None else base.check_matches(log_array)
    array = array.with_range(log_array.range)
    fields: dict[str, np.ndarray | None] = {}
    for s in ("gyro", "accel", "mag"):
        data = block.get(s)
        fields[s] = None if data is None else log_array.calibrate_triads(data, s, undo=True)
    raw = ImuBlock(t_ns=block.t_ns, **fields)
    if window is not None:
        rel = raw.t_s()
        keep = rel >= window[0]
        if window[1] is not None:
            keep &= rel < window[1]
        raw = raw.mask(keep)
    result = calibrate_block(
        array.with_calibration(None),
        raw,
        gravity=gravity,
        min_static_s=min_static_s,
        jitter_fit=jitter_fit,
    )
    result.runtime_s = time.perf_counter() - started
    return result
