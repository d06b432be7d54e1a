"""Noise-growth detector: GLR for a variance change of leave-one-out consensus residuals.

Chen, Su, Xu, fault detection for wearable positioning systems built on arrays of inertial
devices (accelerometer noise increase in a 12-IMU array; §2-3). A sensor whose noise grows
keeps an unbiased output, so bias tests on the parity vector (GLT) barely see it; a
windowed variance test on each sensor's residual against the array consensus does.

Per sensor type with H (n, 3) and sensor j on IMU k(j) at position r_k (body frame, m):

1. Model (rigid body). Gyros: ``m_j = h_j^T w``. Accelerometers (where positions are given
   and gyros are present)::

       m_j = h_j^T (f_0 + dw/dt x r_k + w x (w x r_k))

   The centripetal term uses the known rate w (least-squares gyro consensus) and is
   subtracted; ``dw/dt x r_k = -[r_k]_x dw/dt`` is linear in the unknown angular
   acceleration, so x = (f_0, dw/dt) is estimated jointly with the model matrix
   ``A = [H, -h_j^T [r_k]_x]`` (n, 6). Without lever arms A = H.
2. Leave-one-out residual of sensor j: the prediction error of m_j from the least-squares
   estimate of x made with the OTHER sensors. With the hat matrix P = A A^+ and the full
   residual e = (I - P) m it is ``e_j / (1 - P_jj)`` (the PRESS identity; Allen,
   Technometrics 16(1), 1974), so all n leave-one-out fits cost one (N, n) x (n, n) product.
   Sensors with ``P_jj ~ 1`` are not redundant and are not tested.
3. Calibration: per-sensor residual mean b_j (bias) and variance sigma0_j^2 over the N
   calibration samples.
4. Windowed variance over the last w samples: ``s_j^2 = mean((r_j - b_j)^2)``; its ratio
   ``u_j = s_j^2 / sigma0_j^2``.
5. GLR for N(0, sigma0^2) against N(0, sigma1^2) with sigma1 unknown (maximum likelihood
   sigma1^2 = s^2)::

       ln L(sigma1 = s) - ln L(sigma0) = -w/2 ln s^2 - w/2 + w/2 ln sigma0^2 + w s^2/(2 sigma0^2)
                                       = w/2 (u - 1 - ln u)

   one-sided (noise growth): g = 0 for u <= 1. g is increasing in u for u > 1, so the test
   ``g > h`` is the test ``u > u_c``. Under no fault ``w s^2 / sigma0^2 ~ chi2(w)``; since
   sigma0^2 is itself estimated from N - 1 degrees of freedom the exact law of u is
   ``F(w, N - 1)`` (-> chi2(w)/w as N grows), so ``u_c = F^{-1}(1 - a; w, N - 1)`` and
   ``h = w/2 (u_c - 1 - ln u_c)``. With n tested sensors the per-sensor level is the Šidák
   ``a = 1 - (1 - alpha)^(1/n)`` so that the array-level false-alarm rate is alpha.
   Until the window has filled at the start of the log, w is the number of samples seen.
   End of fault: after the noise returns to nominal, the window still holds faulty samples
   and g stays high for up to w samples. The window is split into its most recent w_r
   samples (``release_window``) and the older w - w_r; with both parts of the same
   variance, the ratio of their mean squared residuals is ``F(w_r, w - w_r)``. When it is
   below ``F^{-1}(release; w_r, w - w_r)`` (a one-sided test for a variance decrease) the
   sensor's g is set to 0. During a fault this drops at most a fraction ``release`` of the
   faulty samples; after it, the alarm ends about w_r samples later instead of w.
6. Output: statistic = max_j g_j (threshold h), scores = g_j, isolated sensor = argmax_j g_j,
   ``amplitude = sqrt(u_j)`` of the isolated sensor: the estimated noise-standard-deviation
   ratio sigma1/sigma0 (dimensionless, the one exception to SI amplitudes).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, ClassVar

import numpy as np
from scipy.stats import f as f_distribution

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    NO_ISOLATION,
    DetectionBlock,
    Param,
    calibration_stats,
    parse_sensor_types,
)
from imufdi_cli.detectors.pca_parity import MovingWindow
from imufdi_cli.errors import CalibrationError
from imufdi_cli.log import ImuBlock

#: Sensors whose leverage P_jj exceeds this are not redundant (their leave-one-out
#: residual is undefined or dominated by the estimate) and are not tested.
MAX_LEVERAGE = 0.99


def skew(vectors: np.ndarray) -> np.ndarray:
    """Cross-product matrices [r]_x (..., 3, 3) with ``[r]_x a = r x a``."""
    vectors = np.asarray(vectors, dtype=np.float64)
    out = np.zeros((*vectors.shape[:-1], 3, 3))
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def centripetal(rate: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """``w x (w x r_k)`` for every sample and IMU.

    Parameters
    ----------
    rate : ndarray, shape (N, 3), rad/s
    positions : ndarray, shape (m, 3), m

    Returns
    -------
    ndarray, shape (N, m, 3), m/s^2
    """
    # w x (w x r) = w (w . r) - r |w|^2
    dot = rate @ positions.T  # (N, m)
    speed2 = np.einsum("ij,ij->i", rate, rate)  # (N,)
    return rate[:, None, :] * dot[:, :, None] - positions[None, :, :] * speed2[:, None, None]


def leave_one_out_operator(model: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Operator giving all leave-one-out residuals of a least-squares fit at once.

    Parameters
    ----------
    model : ndarray, shape (n, p)
        Model matrix A of ``m = A x + e``.

    Returns
    -------
    operator : ndarray, shape (n, n)
        ``R`` with leave-one-out residuals ``r = m @ R.T``: row j of R is row j of
        ``(I - P) / (1 - P_jj)``, P = A A^+ (rows of untestable sensors are zero).
    testable : ndarray, shape (n,), bool
        ``P_jj < MAX_LEVERAGE``.
    """
    n = model.shape[0]
    hat = model @ np.linalg.pinv(model)
    leverage = np.clip(np.diag(hat), 0.0, 1.0)
    testable = leverage < MAX_LEVERAGE
    scale = np.where(testable, 1.0 / np.where(testable, 1.0 - leverage, 1.0), 0.0)
    return (np.eye(n) - hat) * scale[:, None], testable


class _TypeModel:
    def __init__(
        self,
        operator: np.ndarray,
        testable: np.ndarray,
        lever_arm: bool,
        bias: np.ndarray,
        variance: np.ndarray,
        n_train: int,
        window: int,
        alpha: float,
        release_window: int = 1,
        release_level: float = 0.0,
    ) -> None:
        self.operator = operator
        self.testable = testable
        self.lever_arm = lever_arm
        self.bias = bias
        self.variance = variance
        self.n_train = n_train
        n_tested = max(int(testable.sum()), 1)
        self.sensor_level = -np.expm1(np.log1p(-alpha) / n_tested)  # Šidák
        counts = np.arange(1, window + 1, dtype=np.float64)
        critical_ratio = f_distribution.ppf(1.0 - self.sensor_level, counts, n_train - 1)
        self.critical_ratio = critical_ratio  # u_c per window fill, (w,)
        self.threshold = 0.5 * counts * (critical_ratio - 1.0 - np.log(critical_ratio))
        self.window = MovingWindow(window, operator.shape[0])
        self.release_window = MovingWindow(release_window, operator.shape[0])
        self.release_level = release_level
        # lower critical ratio of F(recent, older) per (recent count, older count)
        recent = np.arange(1, release_window + 1, dtype=np.float64)[:, None]
        older = np.arange(0, window, dtype=np.float64)[None, :]
        with np.errstate(invalid="ignore"):
            release_ratio = f_distribution.ppf(release_level, recent, np.maximum(older, 1.0))
        self.release_ratio = np.where(older >= 1.0, release_ratio, 0.0)  # (w_r, w)


class NoiseGlrDetector:
    """Windowed-variance GLR on leave-one-out consensus residuals; see the module docstring.

    Parameters
    ----------
    alpha : float
        Array-level false-alarm probability per sample (per sensor type).
    window : float
        Variance window, seconds.
    release : float
        Level of the end-of-fault variance-decrease F test (0 disables it).
    release_window : float
        Recent part of the window compared against the older part, seconds.
    lever_arm : bool
        Model lever arms of accelerometers (needs positions and gyros).
    sensors : str
        Comma-separated sensor types to test.
    """

    name: ClassVar[str] = "noise-glr"
    #: Causal: the row of sample i depends on samples up to i only.
    lookahead_samples: int = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": replace(
            ALPHA, default=0.001, help="array-level false-alarm level per sample and sensor type"
        ),
        "window": Param(
            "time", 0.3, "variance window (e.g. 0.3s)", low=0.0, high=60.0, low_open=True
        ),
        "release": Param(
            "float",
            0.01,
            "level of the end-of-fault variance-decrease F test (0: off)",
            low=0.0,
            high=0.5,
        ),
        "release_window": Param(
            "time",
            0.1,
            "recent part of the window tested for a variance decrease",
            low=0.0,
            high=60.0,
            low_open=True,
        ),
        "lever_arm": Param("bool", True, "model accelerometer lever arms (w x (w x r), dw/dt x r)"),
        "sensors": Param("str", "gyro,accel", "sensor types to test, comma-separated"),
    }

    def __init__(
        self,
        alpha: float = 0.001,
        window: float = 0.3,
        release: float = 0.01,
        release_window: float = 0.1,
        lever_arm: bool = True,
        sensors: str = "gyro,accel",
    ) -> None:
        self.alpha = float(alpha)
        self.window_s = float(window)
        self.release_level = float(release)
        self.release_window_s = float(release_window)
        self.lever_arm = bool(lever_arm)
        self.sensor_types = parse_sensor_types(sensors, self.name)
        self.array: ArrayConfig | None = None
        self.models: dict[str, _TypeModel] = {}
        self.window_samples = 0
        self.release_window_samples = 0
        self._rate_estimator: np.ndarray | None = None

    # --- residuals -----------------------------------------------------------------------

    def _uses_lever_arm(self, sensor_type: str, array: ArrayConfig) -> bool:
        return (
            self.lever_arm
            and sensor_type == "accel"
            and array.n_sensors("gyro") >= 3
            and bool(np.any(array.positions() != 0.0))
        )

    def _model_matrix(self, sensor_type: str, array: ArrayConfig, lever_arm: bool) -> np.ndarray:
        H = array.measurement_matrix(sensor_type)
        if not lever_arm:
            return H
        imu_idx, _ = array.sensor_index(sensor_type)
        cross = skew(array.positions()[imu_idx])  # (n, 3, 3)
        # dw/dt x r = -[r]_x dw/dt  ->  row j: -h_j^T [r_k]_x
        return np.hstack([H, -np.einsum("jb,jbc->jc", H, cross)])

    def _residuals(self, sensor_type: str, model: _TypeModel, block: ImuBlock) -> np.ndarray:
        """Leave-one-out residuals (N, n) of one sensor type, SI."""
        assert self.array is not None
        triads = block.get(sensor_type)
        assert triads is not None
        measurements = self.array.select(triads, sensor_type)
        if model.lever_arm and block.gyro is not None and self._rate_estimator is not None:
            rate = self.array.select(block.gyro, "gyro") @ self._rate_estimator.T  # (N, 3)
            imu_idx, _ = self.array.sensor_index(sensor_type)
            terms = centripetal(rate, self.array.positions())[:, imu_idx, :]  # (N, n, 3)
            H = self.array.measurement_matrix(sensor_type)
            measurements = measurements - np.einsum("ijb,jb->ij", terms, H)
        return measurements @ model.operator.T

    # --- training ----------------------------------------------------------------------

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Calibrate per-sensor residual bias and variance; set the thresholds.

        Raises
        ------
        CalibrationError
            Window too short, no testable sensors, or a zero residual variance.
        """
        self.array = array
        self.window_samples = max(2, round(self.window_s * array.rate_hz))
        self.release_window_samples = min(
            max(1, round(self.release_window_s * array.rate_hz)), self.window_samples - 1
        )
        self.models = {}
        self._rate_estimator = None
        if array.n_sensors("gyro") >= 3:
            self._rate_estimator = np.linalg.pinv(array.measurement_matrix("gyro"))
        for sensor_type in self.sensor_types:
            if calibration.get(sensor_type) is None or array.n_sensors(sensor_type) < 4:
                continue
            lever_arm = self._uses_lever_arm(sensor_type, array) and calibration.gyro is not None
            operator, testable = leave_one_out_operator(
                self._model_matrix(sensor_type, array, lever_arm)
            )
            if not testable.any():
                continue
            probe = _TypeModel(
                operator, testable, lever_arm, np.zeros(len(testable)), np.ones(len(testable)),
                n_train=2, window=1, alpha=self.alpha,
            )  # fmt: skip
            residuals = self._residuals(sensor_type, probe, calibration)
            bias, std = calibration_stats(residuals, min_samples=max(20, 2 * self.window_samples))
            variance = std**2
            triads = calibration.get(sensor_type)
            assert triads is not None
            signal = array.select(triads, sensor_type)
            floor = (1e-9 * float(np.sqrt(np.mean(signal**2)))) ** 2  # rounding level
            if np.any(variance[testable] <= floor) or not np.all(np.isfinite(variance)):
                raise CalibrationError(
                    f"{self.name}: {sensor_type} residual variance is zero or not finite for"
                    " some sensor; check the calibration window"
                )
            self.models[sensor_type] = _TypeModel(
                operator,
                testable,
                lever_arm,
                bias,
                np.where(testable, variance, 1.0),
                n_train=residuals.shape[0],
                window=self.window_samples,
                alpha=self.alpha,
                release_window=self.release_window_samples,
                release_level=self.release_level,
            )
        if not self.models:
            raise CalibrationError(
                f"{self.name}: nothing to test: the calibration block has no "
                f"{'/'.join(self.sensor_types)} data with at least 4 redundant sensors"
            )

    # --- online --------------------------------------------------------------------------

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """Test one block; one row per input sample (causal)."""
        if self.array is None:
            raise CalibrationError(f"{self.name}: process() called before fit()")
        out: dict[str, DetectionBlock] = {}
        for sensor_type, model in self.models.items():
            n_sensors = model.operator.shape[0]
            if block.get(sensor_type) is None:
                out[sensor_type] = DetectionBlock.empty(len(block), n_sensors)
                continue
            out[sensor_type] = self._process_type(model, self._residuals(sensor_type, model, block))
        return out

    @staticmethod
    def _process_type(model: _TypeModel, residuals: np.ndarray) -> DetectionBlock:
        n_samples = residuals.shape[0]
        squared = (residuals - model.bias) ** 2 / model.variance  # (N, n)
        sums, counts = model.window.push(squared)
        ratio = sums / counts[:, None]  # u_j = s_j^2 / sigma0_j^2
        with np.errstate(divide="ignore"):
            glr = np.where(
                ratio > 1.0,
                0.5 * counts[:, None] * (ratio - 1.0 - np.log(np.maximum(ratio, 1e-300))),
                0.0,
            )
        recent_sums, recent_counts = model.release_window.push(squared)
        older_counts = counts - recent_counts
        with np.errstate(divide="ignore", invalid="ignore"):
            change = (recent_sums / recent_counts[:, None]) / (
                (sums - recent_sums) / np.maximum(older_counts, 1)[:, None]
            )
        released = change < model.release_ratio[recent_counts - 1, older_counts][:, None]
        glr = np.where(released, 0.0, glr)
        glr[:, ~model.testable] = np.nan
        scores = glr
        filled = np.where(model.testable, glr, -np.inf)
        best = np.argmax(filled, axis=1)
        statistic = filled[np.arange(n_samples), best]
        threshold = model.threshold[counts - 1]
        alarm = statistic > threshold
        isolated = np.where(alarm, best, NO_ISOLATION).astype(np.int32)
        amplitude = np.where(alarm, np.sqrt(ratio[np.arange(n_samples), best]), np.nan)
        return DetectionBlock(
            statistic=statistic,
            threshold=threshold,
            alarm=alarm,
            isolated=isolated,
            amplitude=amplitude,
            scores=scores,
        )

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal detector: nothing is held back."""
        return {
            s: DetectionBlock.empty(0, model.operator.shape[0]) for s, model in self.models.items()
        }

    def metadata(self) -> dict[str, Any]:
        """Parameters and calibration results (JSON-ready)."""
        types: dict[str, Any] = {}
        for sensor_type, model in self.models.items():
            types[sensor_type] = {
                "lever_arm": bool(model.lever_arm),
                "testable": model.testable.tolist(),
                "residual_bias": model.bias.tolist(),
                "residual_sigma": np.sqrt(model.variance).tolist(),
                "calibration_samples": int(model.n_train),
                "sensor_level": float(model.sensor_level),
                "critical_variance_ratio": float(model.critical_ratio[-1]),
                "threshold": float(model.threshold[-1]),
            }
        return {
            "detector": self.name,
            "params": {
                "alpha": self.alpha,
                "window_s": self.window_s,
                "window_samples": self.window_samples,
                "release": self.release_level,
                "release_window_samples": self.release_window_samples,
                "lever_arm": self.lever_arm,
                "sensors": ",".join(self.sensor_types),
            },
            "statistic": "max_j w/2 (u_j - 1 - ln u_j), u_j = s_j^2/sigma0_j^2 > 1",
            "amplitude": "noise standard-deviation ratio sqrt(u) of the isolated sensor",
            "types": types,
        }
