"""Bank-of-estimators detector: structured residuals, isolation and identification.

Berbra, Gentil, Lesecq, "Identification of multiple faults in an Inertial Measurement Unit"
(DESIGN.md §6 "bank"). Each estimator of the bank is blind to one measurement, so a fault
on measurement j leaves estimator j intact while it corrupts every other one (the paper's
fault signature tables: Table 1 for accelerometers/magnetometers, Table 2 for gyros). The
residual of the blind measurement against the intact estimator is the fault amplitude
(identification). Two modes, chosen from the data (``mode=auto``):

``marg`` — one IMU with a 3-axis accelerometer, a 3-axis magnetometer and gyros, as in the
paper. Measurements are normalised, ``y = [a / |g|, m / |B|]`` (6 components, sensor frame);
the navigation-frame references are ``g_n = [0, 0, 1]`` and ``h_n = [sin psi, 0, cos psi]``,
psi the angle between specific force and magnetic field measured in the calibration window
(the paper's ``h_m = [1/2, 0, sqrt(3)/2]`` is psi = 30 deg). Estimator ``i`` (i = 1..6)
minimises ``sum_{c != i} (y_c - h_c . C(q)^T r_c)^2`` over the attitude q (nonlinear least
squares, batched Gauss-Newton from an SVD/Wahba warm start), a seventh uses all six. Its
residual vector ``R_i = y - y_hat(q_i)``; with a fault f on component j only ``R_j`` keeps
a single non-zero component, ``R_j[j] = f`` (Table 1). Gyro residuals (Table 2): the
attitude of a fault-free estimator (the full one; during an accel/mag alarm, the clean
series, among those of the estimators blind to a component isolated since the alarm
began, with the smallest peak z^2, the test abstaining while one of them is unobservable;
a series idle for over ``GYRO_MAX_GAP_S`` restarts) gives the body rate from ``q_dot = 1/2 Xi(q) w`` by finite differences
(``w = 2 Xi(q_mid)^T (q_k - q_{k-1}) / Te``); the residual ``g - H_g w`` (gyro averaged over
the same interval) is smoothed by the first-order filter ``y_k = a y_{k-1} + (1 - a) x_k``,
``a = exp(-Te / tau)``. A gyro fault shows only in its own residual.

``array`` — arrays without magnetometers (e.g. 16 IMUs): for each sensor j an estimator of
the body rate (or specific force) from all OTHER sensors of its type by weighted least
squares; the residual of j is normalised by its predicted std. A fault on j shows fully in
residual j and weakly in every residual whose estimator uses j, so isolation proceeds by
exclusion: the strongest residual above threshold is isolated, its sensor removed from
every estimator, the residuals recomputed, and so on up to ``max_faults`` sensors — which
isolates simultaneous faults on different sensors, unlike a single-fault GLT.

Thresholds: residuals normalised to unit variance from calibration; per sample the largest
squared residual is compared with the chi-square(1) quantile at ``1 - alpha / n`` (Bonferroni
over the n residuals of the test, so the per-sample false-alarm rate is at most alpha). In
array mode sigma and bias are estimated from the calibration window, so the quantile is the
F(1, nu) one with nu from the variance of those estimates (``estimated_threshold``): with
chi-square(1) the level was 1.2-1.5 alpha on paper-table4 (48 gyros, 200 samples).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from scipy import signal, stats

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.attitude import (
    body_rate_from_quaternions,
    gauss_newton_attitude,
    make_continuous,
    measurement_jacobian,
    rotation_to_quaternion,
    wahba_rotation,
)
from imufdi_cli.detectors.base import (
    ALPHA,
    NO_ISOLATION,
    NOT_ISOLABLE,
    DetectionBlock,
    DetectorBase,
    Param,
    calibration_stats,
)
from imufdi_cli.detectors.parity import (
    isolable_sensors,
    parity_matrix,
    residual_sigma,
    sigma_estimate_variance,
    whiten,
)
from imufdi_cli.detectors.rigid import accel_design
from imufdi_cli.errors import ArrayTooSmallError, CalibrationError, DetectorConfigError
from imufdi_cli.log import ImuBlock

#: Scale from the median absolute deviation to the standard deviation of a Gaussian.
MAD_TO_STD = 1.4826

#: Smallest standard deviation used to normalise a residual (avoids dividing by 0 on
#: noiseless data), relative to the residual's scale.
SIGMA_FLOOR = 1e-12


def robust_std(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Standard deviation from the median absolute deviation (robust to rare outliers)."""
    centre = np.median(values, axis=axis, keepdims=True)
    return np.asarray(MAD_TO_STD * np.median(np.abs(values - centre), axis=axis))


def estimated_threshold(
    alpha: float, H: np.ndarray, sigma: np.ndarray, P: np.ndarray, n_samples: int
) -> float:
    """Bonferroni threshold of ``max_j z_j^2`` with sigma and bias from the calibration.

    ``z_j = e_j / s_j`` with the predicted std ``s_j^2 = sum_k P_jk^2 sigma_k^2`` made of
    estimated variances ``sigma_hat_k^2 = sigma_k^2 (1 + delta_k)``
    (:func:`.parity.sigma_estimate_variance`): ``s_hat_j^2 / s_j^2 - 1`` has variance
    ``sum_k (P_jk^2 sigma_k^2)^2 Var delta_k / s_j^4``, so z_j^2 is ``F(1, nu_j)`` with
    ``nu_j = 2 / that`` rather than chi2(1) (the mean nu over sensors is used). The bias is
    a median of N residuals: its error multiplies the residual variance by
    ``1 + pi / (2 N)``. Level ``alpha / n`` per residual (Bonferroni).
    """
    n = H.shape[0]
    scale_variance = sigma_estimate_variance(H, sigma, n_samples)
    parts = P**2 * sigma[None, :] ** 2  # (n, n)
    relative = (parts**2 @ scale_variance) / np.maximum(parts.sum(axis=1) ** 2, 1e-300)
    nu = 2.0 / float(np.mean(relative))
    quantile = float(stats.f.ppf(1.0 - alpha / n, 1, nu))
    return quantile * (1.0 + math.pi / (2.0 * n_samples))


def bonferroni_threshold(alpha: float, n_tests: int) -> float:
    """chi-square(1) quantile at ``1 - alpha / n_tests`` for a squared unit-normal residual."""
    return float(stats.chi2.ppf(1.0 - alpha / n_tests, 1))


def _empty_block(n_sensors: int) -> DetectionBlock:
    return DetectionBlock.empty(0, n_sensors)


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
    n = H.shape[0]
    P = np.full((n, n), np.nan)
    weights = 1.0 / sigma**2
    for j in range(n):  # n small, once per exclusion set (cached)
        used = np.array([i for i in range(n) if i != j and i not in excluded], dtype=np.intp)
        if used.size < H.shape[1]:
            continue
        H_used = H[used]
        normal = H_used.T @ (weights[used, None] * H_used)
        rank = np.linalg.matrix_rank(normal, tol=1e-9 * max(np.abs(normal).max(), 1e-300))
        if rank < H.shape[1]:
            continue
        gain = np.linalg.solve(normal, H_used.T * weights[used])  # (q, |U|)
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
    values: np.ndarray, H: np.ndarray, sensor_type: str, alpha: float, max_faults: int
) -> _ArrayTest:
    n = H.shape[0]
    if n < H.shape[1] + 1:
        raise ArrayTooSmallError(
            f"bank: {sensor_type} has {n} sensors; the leave-one-out bank needs at least"
            f" {H.shape[1] + 1}"
            + ("" if H.shape[1] == 3 else " with the lever-arm terms of these IMU positions")
        )
    calibration_stats(values)  # checks the window length
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


class BankDetector(DetectorBase):
    """Bank of estimators with structured residuals (Berbra, Gentil, Lesecq).

    Parameters
    ----------
    alpha : float
        Per-sample false-alarm level of each tested sensor type (Bonferroni over residuals).
    mode : {"auto", "marg", "array"}
        ``auto``: ``marg`` for a single IMU with magnetometer, ``array`` otherwise.
    tau : float
        marg mode: time constant of the first-order filter of the gyro residuals, s.
    max_faults : int
        array mode: most simultaneous faulty sensors isolated per sensor type.
    iterations : int
        marg mode: most Gauss-Newton iterations per block.
    """

    name: ClassVar[str] = "bank"
    #: Causal: the row of sample i depends on samples up to i only.
    lookahead_samples: int = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "mode": Param(
            "choice",
            "auto",
            "marg (one IMU with accel+mag+gyro) or array (leave-one-out bank); auto picks",
            choices=("auto", "marg", "array"),
        ),
        "tau": Param(
            "time", 0.5, "marg: time constant of the gyro residual filter", low=0.0, low_open=True
        ),
        "max_faults": Param(
            "int", 2, "array: simultaneous faulty sensors isolated per type", low=1, high=5
        ),
        "iterations": Param("int", 20, "marg: maximum Gauss-Newton iterations", low=1, high=50),
    }

    def __init__(
        self,
        alpha: float = 0.01,
        mode: str = "auto",
        tau: float = 0.5,
        max_faults: int = 2,
        iterations: int = 20,
    ) -> None:
        self.alpha = float(alpha)
        self.mode = mode
        self.tau = float(tau)
        self.max_faults = int(max_faults)
        self.iterations = int(iterations)
        self.array: ArrayConfig | None = None
        self.resolved_mode: str | None = None
        self.tests: dict[str, _ArrayTest] = {}
        self.last_details: BankDetails | None = None
        # marg state
        self._model: _MargModel | None = None
        self._marg_threshold = math.inf
        self._gyro_bias: np.ndarray | None = None
        self._gyro_variance: np.ndarray | None = None
        self._bias_weight_energy = 0.0
        self._gyro_threshold = math.inf
        self._filter_pole = 0.0
        self._sample_period = 0.0
        self._gyro_H: np.ndarray | None = None
        self._gyro_chosen = np.zeros(0, dtype=np.intp)
        self._reset_stream()

    # --- streaming state ---------------------------------------------------------------

    def _reset_stream(self) -> None:
        self._q_last: np.ndarray | None = None  # (7, 4)
        self._gyro_last: np.ndarray | None = None  # (n_g,)
        self._t_last: int | None = None
        self._filter_state: np.ndarray | None = None  # (7, 1, n_g)
        self._episode_counts = np.zeros(6)  # accel/mag isolations in the current alarm
        self._variance_state: np.ndarray | None = None  # (7, 1, n_g)
        self._gyro_integral = np.zeros(0)  # (n_g,) running gyro integral, rad
        self._t_origin = 0  # ns, origin of the float times below
        # per estimator: attitude, gyro integral and time of its last clean sample
        self._clean_q = np.tile([1.0, 0.0, 0.0, 0.0], (7, 1))
        self._clean_integral = np.zeros((7, 0))
        self._clean_t = np.full(7, np.nan)

    # --- fit ---------------------------------------------------------------------------

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Calibrate residual biases, noise and thresholds on a fault-free block."""
        self.array = array
        mode = self.mode
        if mode == "auto":
            mode = "marg" if array.has("mag") and array.n_imus == 1 else "array"
        self.resolved_mode = mode
        self.tests = {}
        self._reset_stream()
        if mode == "marg":
            self._fit_marg(calibration, array)
        else:
            self._fit_array(calibration, array)

    def _fit_array(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        for sensor_type in array.sensor_types():
            data = calibration.get(sensor_type)
            if data is None:
                raise CalibrationError(f"bank: calibration block has no {sensor_type} data")
            values = array.select(data, sensor_type)
            self.tests[sensor_type] = _fit_array_test(
                values,
                # accelerometers at different points: rigid-body lever arms (detectors/rigid.py)
                accel_design(array)
                if sensor_type == "accel"
                else array.measurement_matrix(sensor_type),
                sensor_type,
                self.alpha,
                self.max_faults,
            )

    def _fit_marg(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        imu = array.imus[0]
        if (
            array.n_imus != 1
            or imu.axes_of("accel") != ("x", "y", "z")
            or imu.axes_of("mag") != ("x", "y", "z")
        ):
            raise DetectorConfigError(
                "bank: mode=marg needs exactly one IMU with 3-axis accel and 3-axis mag"
                f" (got {array.n_imus} IMUs); use mode=array for arrays"
            )
        if calibration.accel is None or calibration.mag is None:
            raise CalibrationError("bank: mode=marg needs accel and mag data in the calibration")
        calibration_stats(np.zeros((len(calibration), 1)))  # window length check
        accel = calibration.accel[:, 0, :]
        mag = calibration.mag[:, 0, :]
        accel_norm = np.linalg.norm(accel, axis=1)
        mag_norm = np.linalg.norm(mag, axis=1)
        gravity_norm = float(np.median(accel_norm))
        field_norm = float(np.median(mag_norm))
        if not (gravity_norm > 0 and field_norm > 0):
            raise CalibrationError("bank: accel or mag is zero in the calibration window")
        cosine = float(np.median(np.einsum("ni,ni->n", accel, mag) / (accel_norm * mag_norm)))
        angle = math.acos(min(1.0, max(-1.0, cosine)))
        if math.sin(angle) < 0.05:
            raise CalibrationError(
                f"bank: specific force and magnetic field are {math.degrees(angle):.1f} deg"
                " apart in the calibration window; attitude is not observable from them"
            )
        g_ref = np.array([0.0, 0.0, 1.0])
        h_ref = np.array([math.sin(angle), 0.0, math.cos(angle)])
        H_accel = array.measurement_matrix("accel")
        H_mag = array.measurement_matrix("mag")
        scale = np.array([gravity_norm] * 3 + [field_norm] * 3)
        y_calibration = (
            np.concatenate(
                [array.select(calibration.accel, "accel"), array.select(calibration.mag, "mag")],
                axis=1,
            )
            / scale
        )
        noise = self._component_noise(array, y_calibration, gravity_norm, field_norm)
        self._model = _MargModel(
            sensor_axes=np.vstack([H_accel, H_mag]),
            references=np.vstack([np.tile(g_ref, (3, 1)), np.tile(h_ref, (3, 1))]),
            gravity_norm=gravity_norm,
            field_norm=field_norm,
            angle=angle,
            accel_to_body=np.linalg.inv(H_accel),
            mag_to_body=np.linalg.inv(H_mag),
            noise=noise,
        )
        solution = self._model.solve(y_calibration, self.iterations)
        self._marg_threshold = bonferroni_threshold(self.alpha, 6)

        self._gyro_H = None
        if array.has("gyro") and calibration.gyro is not None:
            self._fit_gyro(calibration, array, solution.q[FULL_ESTIMATOR])

    @staticmethod
    def _component_noise(
        array: ArrayConfig, y: np.ndarray, gravity_norm: float, field_norm: float
    ) -> np.ndarray:
        """White-noise std (6,) of the normalised accel/mag components.

        From ``ArrayConfig.noise`` when given, else from second differences of the
        calibration window (``Var(D^2 y) = 6 sigma^2`` for white noise; smooth motion
        cancels to O(Te^2)).
        """
        from_data = robust_std(np.diff(y, n=2, axis=0)) / math.sqrt(6.0)
        noise = from_data.copy()
        if "accel" in array.noise:
            noise[:3] = array.noise["accel"] / gravity_norm
        if "mag" in array.noise:
            noise[3:] = array.noise["mag"] / field_norm
        if not np.all(np.isfinite(noise)) or np.any(noise <= 0):
            raise CalibrationError(
                "bank: accel/mag noise from the calibration window is not positive"
                " (constant data?); give noise in the array config or another --calibrate"
            )
        return noise

    def _fit_gyro(self, calibration: ImuBlock, array: ArrayConfig, q_full: np.ndarray) -> None:
        """Gyro residual bias and white-noise variance (Table 2 residuals)."""
        assert calibration.gyro is not None
        n = len(calibration)
        if n < 12:
            raise CalibrationError(f"bank: calibration window has {n} samples; need >= 12")
        H_gyro = array.measurement_matrix("gyro")
        dt = np.diff(calibration.t_ns).astype(float) * 1e-9
        if np.any(dt <= 0):
            raise CalibrationError("bank: calibration timestamps are not increasing")
        self._sample_period = float(np.median(dt))
        self._filter_pole = math.exp(-self._sample_period / self.tau)
        q = make_continuous(q_full)
        rate = body_rate_from_quaternions(q[:-1], q[1:], dt) @ H_gyro.T  # (n-1, n_g)
        gyro = array.select(calibration.gyro, "gyro")
        gyro_mid = 0.5 * (gyro[1:] + gyro[:-1])
        raw = gyro_mid - rate
        # Bias: Hann-weighted mean of the raw residual. The finite-difference rate noise
        # telescopes (sum w_k (n_k - n_{k-1}) = -sum n_k (w_{k+1} - w_k), tiny for a smooth
        # window), so the estimate's error is mainly the gyro noise, sigma_g^2 sum w_k^2;
        # that variance is added to the residual's (the bias is not known exactly).
        taper = np.hanning(raw.shape[0] + 2)[1:-1]
        taper /= taper.sum()
        self._gyro_bias = taper @ raw
        self._bias_weight_energy = float(taper @ taper)
        if "gyro" in array.noise:
            self._gyro_variance = np.full(H_gyro.shape[0], array.noise["gyro"] ** 2)
        else:
            # white noise: Var(D^2 g) = 6 sigma_g^2; smooth motion cancels to O(Te^2)
            self._gyro_variance = robust_std(np.diff(gyro, n=2, axis=0)) ** 2 / 6.0
        if not np.all(np.isfinite(self._gyro_variance)) or np.any(self._gyro_variance <= 0):
            raise CalibrationError(
                "bank: gyro noise from the calibration window is not positive (constant data?);"
                " give noise.gyro in the array config or choose another --calibrate window"
            )
        self._gyro_threshold = bonferroni_threshold(self.alpha, H_gyro.shape[0])
        self._gyro_H = H_gyro

    # --- process -----------------------------------------------------------------------

    def _require_fit(self) -> ArrayConfig:
        if self.array is None or self.resolved_mode is None:
            raise DetectorConfigError("bank: call fit() with a calibration block before process()")
        return self.array

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """One row per input sample for every tested sensor type (causal)."""
        array = self._require_fit()
        if self.resolved_mode == "marg":
            return self._process_marg(block, array)
        out: dict[str, DetectionBlock] = {}
        isolated_sets: dict[str, np.ndarray] = {}
        for sensor_type, test in self.tests.items():
            data = block.get(sensor_type)
            if data is None:
                raise CalibrationError(f"bank: block has no {sensor_type} data")
            out[sensor_type], isolated_sets[sensor_type] = test.run(array.select(data, sensor_type))
            out[sensor_type].isolated_set = isolated_sets[sensor_type]
        self.last_details = BankDetails(isolated_sets=isolated_sets)
        return out

    def _process_marg(self, block: ImuBlock, array: ArrayConfig) -> dict[str, DetectionBlock]:
        model = self._model
        assert model is not None
        n_samples = len(block)
        y = model.normalised(block, array)
        solution = model.solve(y, self.iterations)
        q, residuals, blind, fit_cost = (
            solution.q,
            solution.residuals,
            solution.blind,
            solution.fit_cost,
        )
        blind_z2 = (blind / solution.blind_std) ** 2  # (N, 6), chi-square(1) when fault-free
        statistic = np.max(np.nan_to_num(blind_z2, nan=0.0), axis=1)
        alarm = statistic > self._marg_threshold
        # Table 1: the faulty component j is the one whose blind residual exceeds the
        # threshold while its estimator (blind to j) fits the other five: argmin of the
        # fit cost among the components above threshold.
        with np.errstate(invalid="ignore"):
            candidates = np.where(blind_z2 > self._marg_threshold, fit_cost, np.inf)
        best = np.argmin(candidates, axis=1)
        isolated = np.where(alarm, best, NO_ISOLATION).astype(np.int32)
        scale = np.array([model.gravity_norm] * 3 + [model.field_norm] * 3)
        rows = np.arange(n_samples)
        amplitude = np.where(alarm, blind[rows, best] * scale[best], np.nan)

        out: dict[str, DetectionBlock] = {}
        isolated_sets: dict[str, np.ndarray] = {}
        threshold = np.full(n_samples, self._marg_threshold)
        for sensor_type, offset in (("accel", 0), ("mag", 3)):
            mine = alarm & (isolated >= offset) & (isolated < offset + 3)
            out[sensor_type] = DetectionBlock(
                statistic=statistic.copy(),
                threshold=threshold.copy(),
                alarm=mine,
                isolated=np.where(mine, isolated - offset, NO_ISOLATION).astype(np.int32),
                amplitude=np.where(mine, amplitude, np.nan),
                scores=blind_z2[:, offset : offset + 3].copy(),
            )
            isolated_sets[sensor_type] = np.zeros((n_samples, 3), dtype=bool)
            isolated_sets[sensor_type][mine, isolated[mine] - offset] = True

        clean, candidates, abstain = self._gyro_candidates(solution, model.noise, alarm, best)
        chosen = np.where(alarm & clean[np.arange(n_samples), best], best, FULL_ESTIMATOR)
        q = make_continuous(q, self._q_last)
        gyro_residuals = None
        if self._gyro_H is not None and block.gyro is not None and n_samples > 0:
            out["gyro"], isolated_sets["gyro"], gyro_residuals = self._gyro_test(
                block, array, q, clean, candidates, solution.covariance, abstain
            )
            chosen = self._gyro_chosen
        if n_samples > 0:
            self._q_last = q[:, -1, :].copy()
        self.last_details = BankDetails(
            isolated_sets=isolated_sets,
            estimator_residuals=np.moveaxis(residuals, 0, 1),
            attitude=np.moveaxis(q, 0, 1),
            gyro_residuals=gyro_residuals,
            chosen_estimator=chosen,
        )
        for sensor_type, det in out.items():
            chosen_set = isolated_sets.get(sensor_type)
            if chosen_set is not None and chosen_set.shape == det.scores.shape:
                det.isolated_set = chosen_set
        return out

    def _gyro_candidates(
        self, solution: _MargSolution, noise: np.ndarray, alarm: np.ndarray, best: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which estimators' attitudes the gyro test may use: ``clean`` (N, 7), the
        ``candidates`` (N, 7) it chooses among, and where it ``abstain``s (N,).

        An estimator is clean at a sample when it converged, observes the attitude and
        does not use the component isolated there. During an accel/mag alarm, every
        component isolated since the alarm began is a candidate for the faulty one (the
        isolation hesitates at an onset while the faulty component's blind estimator drops
        in and out of observability). Only the series of the estimator blind to the faulty
        component is fault-free; a gyro fault shows in every series. The gyro test takes,
        per sample, the clean candidate series with the smallest largest z^2
        (``_gyro_decision``), and abstains where any candidate is not clean (its series
        could be the only fault-free one).
        """
        well_conditioned = np.ones_like(solution.usable)
        well_conditioned[:, :6] = solution.blind_std <= GYRO_BLIND_STD_RATIO * noise
        clean = solution.usable & well_conditioned & ~alarm[:, None]
        seen = self._episode_components(alarm, best)  # (N, 6)
        usable = (solution.usable & well_conditioned)[:, :6]
        candidates = np.zeros_like(clean)
        candidates[:, :6] = seen & usable
        candidates[:, FULL_ESTIMATOR] = ~alarm
        clean[:, :6] |= candidates[:, :6]
        abstain = ~candidates.any(axis=1) | np.any(seen & ~usable, axis=1)
        return clean, candidates, abstain

    def _episode_components(self, alarm: np.ndarray, best: np.ndarray) -> np.ndarray:
        """Accel/mag components isolated at least once since the current alarm began,
        (N, 6) bool (all False where no alarm). State carries over blocks."""
        n = alarm.shape[0]
        if n == 0:
            return np.zeros((0, 6), dtype=bool)
        onehot = np.zeros((n, 6))
        onehot[np.flatnonzero(alarm), best[alarm]] = 1.0
        previous = np.concatenate([[self._episode_counts.sum() > 0], alarm[:-1]])
        starts = alarm & ~previous
        segment = np.cumsum(starts)  # 0: the episode carried over from the last block
        cumulative = np.cumsum(onehot, axis=0)
        start_rows = np.flatnonzero(starts)
        base = np.empty((start_rows.size + 1, 6))
        base[0] = -self._episode_counts
        base[1:] = np.where((start_rows > 0)[:, None], cumulative[np.maximum(start_rows - 1, 0)], 0)
        counts = cumulative - base[segment]
        self._episode_counts = counts[-1].copy() if alarm[-1] else np.zeros(6)
        return (counts > 0) & alarm[:, None]  # type: ignore[no-any-return]

    def _gyro_test(
        self,
        block: ImuBlock,
        array: ArrayConfig,
        q: np.ndarray,
        clean: np.ndarray,
        candidates: np.ndarray,
        covariance: np.ndarray,
        abstain: np.ndarray,
    ) -> tuple[DetectionBlock, np.ndarray, np.ndarray]:
        """Table 2 residuals: filtered ``gyro - H_g w(attitude of a fault-free estimator)``.

        One filtered residual series per estimator (7 x n_g channels), each built from its
        own attitude only, so that choosing another estimator never inserts a jump; an
        interval where the estimator is not clean at both ends contributes 0. The output
        takes, per sample, the candidate series with the smallest largest z^2. Steps:
        :meth:`_gyro_integral_of` (gyro integral), :meth:`_raw_gyro_residuals` (per series,
        against its attitude change), :meth:`_filtered_gyro_residuals` (first-order filter
        and noise model), :meth:`_gyro_decision` (series choice, alarm, isolation).

        Parameters
        ----------
        q : ndarray, shape (7, N, 4)
            Sign-continuous attitudes of the estimators.
        clean : ndarray, shape (N, 7), bool
        candidates : ndarray, shape (N, 7), bool
            Series the output may take per sample (the full one without an accel/mag
            alarm); the one with the smallest largest z^2 is taken.
        covariance : ndarray, shape (7, N, 3, 3)
        abstain : ndarray, shape (N,), bool
            Samples without a clean candidate: no gyro decision (statistic 0; the
            residual shown is the full estimator's).

        Returns
        -------
        detection : DetectionBlock
        isolated_set : ndarray, shape (N, n_g), bool
        residual : ndarray, shape (N, n_g)
            The chosen series' filtered residual, rad/s.
        """
        assert block.gyro is not None and self._gyro_H is not None
        gyro = array.select(block.gyro, "gyro")
        dt, integral, t_s = self._gyro_integral_of(block, gyro, q.shape[0])
        raw, valid = self._raw_gyro_residuals(q, clean, integral, t_s)
        self._gyro_integral = integral[-1].copy()
        filtered, variances = self._filtered_gyro_residuals(raw, valid, covariance, dt)
        self._gyro_last = gyro[-1].copy()
        self._t_last = int(block.t_ns[-1])
        return self._gyro_decision(filtered, variances, candidates, abstain)

    def _gyro_integral_of(
        self, block: ImuBlock, gyro: np.ndarray, n_est: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample intervals dt (N,) s, the running trapezoid integral (N, n_g) of the
        bias-corrected gyro, rad, and sample times (N,) s from the stream's origin; starts
        the stream state on the first block."""
        assert self._gyro_bias is not None
        if self._gyro_last is None or self._t_last is None:
            self._t_origin = int(block.t_ns[0])
            self._gyro_integral = np.zeros(gyro.shape[1])
            self._clean_integral = np.zeros((n_est, gyro.shape[1]))
            self._clean_q = np.tile([1.0, 0.0, 0.0, 0.0], (n_est, 1))
            self._clean_t = np.full(n_est, np.nan)
            gyro_prev = np.concatenate([gyro[:1], gyro[:-1]])
            t_prev = np.concatenate([block.t_ns[:1], block.t_ns[:-1]])
            integral_start = np.zeros(gyro.shape[1])
        else:
            gyro_prev = np.concatenate([self._gyro_last[None], gyro[:-1]])
            t_prev = np.concatenate([[self._t_last], block.t_ns[:-1]])
            integral_start = self._gyro_integral
        dt = (block.t_ns - t_prev).astype(float) * 1e-9
        dt = np.where(dt > 0, dt, 0.0)
        integral = integral_start + np.cumsum(
            (0.5 * (gyro + gyro_prev) - self._gyro_bias) * dt[:, None], axis=0
        )
        t_s = (block.t_ns - self._t_origin).astype(float) * 1e-9
        return dt, integral, t_s

    def _raw_gyro_residuals(
        self, q: np.ndarray, clean: np.ndarray, integral: np.ndarray, t_s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Unfiltered residual of every series (7, N, n_g), rad/s, and where it is valid
        (7, N); remembers each series' last clean sample for the next block.

        Each series compares the gyro integral with the attitude change since its last
        clean sample L (L = k - 1 normally): x_k = (int_L^k g - H w (t_k - t_L)) / Te with
        w the least-squares rate of q_dot = 1/2 Xi(q) w between q_L and q_k. Unclean
        samples give x = 0 and the next clean one takes the whole gap, so the filtered sum
        still telescopes (no spike when estimators drop out).
        """
        assert self._gyro_H is not None
        n_est, n_samples = q.shape[0], q.shape[1]
        index = np.arange(n_samples)
        marker = np.where(clean.T, index[None, :], -1)  # (7, N)
        last_clean = np.concatenate(
            [np.full((n_est, 1), -1), np.maximum.accumulate(marker, axis=1)[:, :-1]], axis=1
        )
        from_block = last_clean >= 0
        safe = np.maximum(last_clean, 0)
        est = np.arange(n_est)[:, None]
        q_from = np.where(from_block[..., None], q[est, safe], self._clean_q[:, None])
        integral_from = np.where(
            from_block[..., None], integral[safe], self._clean_integral[:, None]
        )
        t_from = np.where(from_block, t_s[safe], self._clean_t[:, None])
        span = t_s[None, :] - t_from  # (7, N), inf/nan where there is no clean sample yet
        # A series idle for longer than GYRO_MAX_GAP_S restarts instead of taking the gap:
        # its attitude change over a long gap is not a constant-rate rotation (an a_y step
        # made the long-unobservable a_y-blind estimator clean again after seconds, and its
        # first sample raised gyro alarms on healthy gyros for 0.5 s).
        valid = clean.T & np.isfinite(span) & (span > 0) & (span <= GYRO_MAX_GAP_S)
        span = np.where(valid, span, self._sample_period)
        q_from = np.where(valid[..., None], q_from, q)
        rate = body_rate_from_quaternions(q_from, q, span)  # (7, N, 3)
        raw = (
            integral[None] - integral_from - (rate @ self._gyro_H.T) * span[..., None]
        ) / self._sample_period
        raw[~valid] = 0.0
        has_clean = np.asarray(clean.any(axis=0), dtype=bool)
        last_index = n_samples - 1 - np.argmax(clean[::-1], axis=0)
        self._clean_q = np.where(has_clean[:, None], q[np.arange(n_est), last_index], self._clean_q)
        self._clean_integral = np.where(
            has_clean[:, None], integral[last_index], self._clean_integral
        )
        self._clean_t = np.where(has_clean, t_s[last_index], self._clean_t)
        return raw, valid

    def _filtered_gyro_residuals(
        self, raw: np.ndarray, valid: np.ndarray, covariance: np.ndarray, dt: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """First-order filtered residuals (7, N, n_g), rad/s, and their variances, (rad/s)^2.

        Noise of the filtered residual ``y = (1-a) sum_i a^i x_{k-i}``: the trapezoid gyro
        average of white noise sigma_g gives ``sigma_g^2 (1-a)/2``; the finite-difference
        rate ``(n_k - n_{k-1}) / Te`` of white attitude noise n (covariance P from the
        estimator, ``s^2 = h^T P h / Te^2``, smoothed by the same filter) gives
        ``2 s^2 (1-a)^2 / (1+a)``; the calibrated bias adds ``sigma_g^2 sum w^2``.
        """
        assert self._gyro_H is not None and self._gyro_variance is not None
        H = self._gyro_H
        dt = np.where(dt > 0, dt, self._sample_period)
        rate_variance = np.einsum("gi,enij,gj->eng", H, covariance, H) / dt[None, :, None] ** 2
        rate_variance[~valid] = 0.0
        raw = np.nan_to_num(raw)
        a = self._filter_pole
        if self._filter_state is None or self._variance_state is None:
            self._filter_state = np.zeros((raw.shape[0], 1, raw.shape[2]))
            self._variance_state = np.zeros((raw.shape[0], 1, raw.shape[2]))
        filtered, self._filter_state = signal.lfilter(
            [1.0 - a], [1.0, -a], raw, axis=1, zi=self._filter_state
        )
        smoothed_rate_variance, self._variance_state = signal.lfilter(
            [1.0 - a], [1.0, -a], rate_variance, axis=1, zi=self._variance_state
        )
        variances = self._gyro_variance * (
            (1 - a) / 2 + self._bias_weight_energy
        ) + 2 * smoothed_rate_variance * (1 - a) ** 2 / (1 + a)  # (7, N, n_g)
        return filtered, variances

    def _gyro_decision(
        self,
        filtered: np.ndarray,
        variances: np.ndarray,
        candidates: np.ndarray,
        abstain: np.ndarray,
    ) -> tuple[DetectionBlock, np.ndarray, np.ndarray]:
        """Per sample, the candidate series with the smallest largest z^2; alarm when its
        largest z^2 exceeds the threshold; every gyro above it is isolated and gets its
        filtered residual as amplitude (several simultaneous gyro faults)."""
        n_samples = filtered.shape[1]
        rows = np.arange(n_samples)
        z2_all = filtered**2 / np.maximum(variances, SIGMA_FLOOR**2)
        peak = np.where(candidates.T, z2_all.max(axis=2), np.inf)  # (7, N)
        chosen = np.where(abstain, FULL_ESTIMATOR, np.argmin(peak, axis=0))
        self._gyro_chosen = chosen
        residual = filtered[chosen, rows]  # (N, n_g)
        z2 = z2_all[chosen, rows]
        z2[abstain] = 0.0
        statistic = z2.max(axis=1)
        alarm = statistic > self._gyro_threshold
        best = np.argmax(z2, axis=1)
        isolated = np.where(alarm, best, NO_ISOLATION).astype(np.int32)
        amplitude = np.where(alarm, residual[rows, best], np.nan)
        isolated_set = z2 > self._gyro_threshold
        detection = DetectionBlock(
            statistic=statistic,
            threshold=np.full(n_samples, self._gyro_threshold),
            alarm=alarm,
            isolated=isolated,
            amplitude=amplitude,
            scores=z2,
            amplitudes=np.where(isolated_set, residual, np.nan),
        )
        return detection, isolated_set, residual

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal detector: nothing is held back."""
        array = self._require_fit()
        types = list(self.tests) if self.resolved_mode == "array" else ["accel", "mag"]
        if self.resolved_mode == "marg" and self._gyro_H is not None:
            types.append("gyro")
        return {s: _empty_block(array.n_sensors(s)) for s in types}

    def metadata(self) -> dict[str, Any]:
        """Parameters and calibration results (JSON-ready)."""
        meta: dict[str, Any] = {
            "params": {
                "alpha": self.alpha,
                "mode": self.mode,
                "tau": self.tau,
                "max_faults": self.max_faults,
                "iterations": self.iterations,
            },
            "mode": self.resolved_mode,
        }
        if self.resolved_mode == "array":
            meta["calibration"] = {s: t.metadata() for s, t in self.tests.items()}
        elif self.resolved_mode == "marg" and self._model is not None:
            calibration: dict[str, Any] = {
                "gravity_norm": self._model.gravity_norm,
                "field_norm": self._model.field_norm,
                "field_angle_deg": math.degrees(self._model.angle),
                "component_noise": self._model.noise.tolist(),
                "accel_mag_threshold": self._marg_threshold,
            }
            if self._gyro_variance is not None and self._gyro_bias is not None:
                calibration.update(
                    gyro_bias=self._gyro_bias.tolist(),
                    gyro_noise_sigma=np.sqrt(self._gyro_variance).tolist(),
                    gyro_threshold=self._gyro_threshold,
                    filter_pole=self._filter_pole,
                )
            meta["calibration"] = calibration
        return meta
