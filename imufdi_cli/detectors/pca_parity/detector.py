"""The pca-parity detector: training per sensor type, the online T and Q tests with
isolation by fault direction (the method is described in the package docstring)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    FALSE_ALARMS,
    NO_ISOLATION,
    NOT_ISOLABLE,
    TYPES,
    DetectionBlock,
    DetectorBase,
    Param,
    calibration_stats,
    parse_sensor_types,
)
from imufdi_cli.detectors.budget import (
    HOLD,
    SPATIAL_TYPES,
    check_hold,
    configured_noise,
    reference_tau,
)
from imufdi_cli.detectors.pca_parity import choices
from imufdi_cli.detectors.pca_parity.budget import PcaBudget
from imufdi_cli.detectors.pca_parity.components import (
    _lag_one_autocorrelation,
    plug_in_quantile,
    principal_components,
)
from imufdi_cli.detectors.pca_parity.model import _MotionDesign, _TypeModel, lever_arm_spread
from imufdi_cli.detectors.tracking import TRACK_BIAS, BiasTracker
from imufdi_cli.errors import ArrayTooSmallError, CalibrationError, DetectorConfigError
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.jitter import MotionInflation, array_inflation
from imufdi_cli.maths.parity import isolable_sensors, parity_matrix
from imufdi_cli.maths.quantiles import f as f_distribution
from imufdi_cli.maths.rigid import accel_design


class PcaParityDetector(DetectorBase):
    """PCA of parity vectors with a moving-mean test (Hao & Wang); see the package docstring.

    Parameters
    ----------
    alpha : float
        False-alarm level per sample.
    components : int
        Number of principal components kept (capped at n - 3, or n with ``space=raw``).
    window : float
        Moving-mean window, seconds.
    space : {"parity", "raw"}
        Test the parity vectors (default) or the raw measurements (demonstration).
    residual_test : bool
        Also test the discarded components (Q statistic).
    leak : {"regress", "none"}
        Fit and remove the motion leaking into the parity space through scale-factor and
        misalignment errors (needs motion in the training window to have any effect).
    types : str
        Comma-separated sensor types to test (those present with enough sensors are used);
        ``sensors``, its old name, is still accepted with a warning.
    track_bias : float or None
        Slow bias tracking time constant, s (per-sample test: off by default; under a
        budget the time constant of the sequential test's own reference, 60 s by default).
    false_alarms : float
        False-alarm budget, episodes per second per status channel (0: the per-sample
        test at ``alpha``); positive: sequential decisions on the GLR evidence of each
        sensor under the learnt parity covariance (:mod:`.budget`).
    """

    name: ClassVar[str] = "pca-parity"
    RENAMED_PARAMS: ClassVar[dict[str, str]] = {"sensors": "types"}
    #: Causal: the row of sample i depends on samples up to i only.
    lookahead_samples: int = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "components": Param("int", 2, "number of principal components kept", low=1, high=64),
        "window": Param(
            "time", 0.2, "moving-mean window (e.g. 0.2s)", low=0.0, high=60.0, low_open=True
        ),
        "space": Param(
            "choice", "parity", "test parity vectors or raw measurements", choices=("parity", "raw")
        ),
        "residual_test": Param("bool", True, "also test the discarded components (Q statistic)"),
        "leak": Param(
            "choice",
            "regress",
            "remove motion leaking into the parity space (scale/misalignment errors)",
            choices=("regress", "none"),
        ),
        "types": TYPES,
        "track_bias": TRACK_BIAS,
        "hold": HOLD,
        "false_alarms": FALSE_ALARMS,
    }

    def __init__(
        self,
        alpha: float = 0.01,
        components: int = 2,
        window: float = 0.2,
        space: str = "parity",
        residual_test: bool = True,
        leak: str = "regress",
        types: str = "gyro,accel",
        track_bias: float | None = None,
        false_alarms: float = 0.0,
        hold: str = "10s",
    ) -> None:
        self.false_alarms = float(false_alarms)
        self.hold_s = check_hold("pca-parity", hold, self.false_alarms)
        if self.false_alarms > 0:
            fixed = {
                "window": window != 0.2,
                "components": components != 2,
                "residual_test": not residual_test,
                "space": space != "parity",
            }
            given = [name for name, changed in fixed.items() if changed]
            if given:
                raise DetectorConfigError(
                    f"pca-parity.{given[0]} applies to the per-sample test; with a false-alarm"
                    " budget pca-parity decides sequentially on the GLR evidence of each sensor"
                    " (docs/algorithms/pca-parity.md): leave it out"
                )
        self.track_bias = track_bias
        self.alpha = float(alpha)
        self.components = int(components)
        self.window_s = float(window)
        self.space = space
        self.residual_test = bool(residual_test)
        self.leak = leak
        self.sensor_types = parse_sensor_types(types, self.name)
        # under a budget the bank's own reference follows the biases (frozen in alarms)
        self.tracker = BiasTracker(0.0 if self.false_alarms > 0 else track_bias)
        self.budgets: dict[str, PcaBudget] = {}
        self.array: ArrayConfig | None = None
        self.models: dict[str, _TypeModel] = {}
        self.untested: dict[str, str] = {}
        self.window_samples = 0
        self.inflations: dict[str, MotionInflation | None] = {}  # jitter model (maths/jitter)

    # --- training ----------------------------------------------------------------------

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Learn mean, principal components, autocorrelation and leak per sensor type.

        Raises
        ------
        ArrayTooSmallError
            No sensor type with enough sensors to test (exit 3, with a hint).
        CalibrationError
            Window too short, or degenerate (zero-variance) data.
        """
        self.array = array
        designs = {s: self._design(array, s) for s in array.sensor_types()}
        self.tracker.fit(calibration, array, designs)
        self.window_samples = max(1, round(self.window_s * array.rate_hz))
        self.models = {}
        self.untested = {}
        self.inflations = {}
        self.budgets = {}
        minimum = 3 if self.space == "parity" else 0
        for sensor_type in self.sensor_types:
            triads = calibration.get(sensor_type)
            if triads is None or array.n_sensors(sensor_type) <= minimum:
                continue
            design = designs[sensor_type]
            if self.space == "parity" and design.shape[0] <= design.shape[1]:
                self.untested[sensor_type] = (
                    f"{design.shape[0]} sensors: with the lever-arm terms of these IMU"
                    f" positions the parity space needs at least {design.shape[1] + 1}"
                )
                continue
            measurements = array.select(triads, sensor_type)
            self.models[sensor_type] = self._fit_type(measurements, design, sensor_type)
            inflation = array_inflation(array, sensor_type, design, self.window_samples)
            self.inflations[sensor_type] = inflation if self.space == "parity" else None
            if self.false_alarms > 0:
                model = self.models[sensor_type]
                budget = PcaBudget(
                    model.projection,
                    design,
                    model.isolable,
                    array.rate_hz,
                    self.false_alarms,
                    self.track_bias,
                    leak=self.leak == "regress",
                    sensor_noise=self._configured_noise(array, sensor_type),
                    hold_s=self.hold_s,
                    moving=self.inflations[sensor_type] is not None
                    and sensor_type in SPATIAL_TYPES,
                )
                budget.fit(measurements, self.window_samples)
                self.budgets[sensor_type] = budget
        if not self.models:
            need = "at least 4 sensors of a type" if self.space == "parity" else "sensors"
            if self.untested:
                need += " (" + "; ".join(f"{k}: {v}" for k, v in self.untested.items()) + ")"
            raise ArrayTooSmallError(
                f"{self.name}: nothing to test: the calibration block has no "
                f"{'/'.join(self.sensor_types)} data with {need}"
            )

    @staticmethod
    def _configured_noise(array: ArrayConfig, sensor_type: str) -> np.ndarray | None:
        """The per-sensor noise sigma of the array config when every IMU carrying the type
        has its own ``<type>_noise`` (what ``imufdi calibrate`` measures), else None; times
        ``sqrt(kappa_i)`` when the array carries the healthy noise-variance spread kappa
        (``<type>_noise_spread``): the level is held at the top of each chip's healthy
        range (as woa-mvmd-glt's ``noise_spread``)."""
        return configured_noise(array, sensor_type)

    @staticmethod
    def _design(array: ArrayConfig, sensor_type: str) -> np.ndarray:
        """H (n, 3); for accelerometers of IMUs more than MAX_LEVER_ARM apart, the rigid-body
        design [H | lever-arm columns] (n, 3 + q) of :mod:`.rigid`, so the parity space
        cancels w x (w x r) and dw/dt x r."""
        if sensor_type == "accel" and lever_arm_spread(array, sensor_type) > choices.MAX_LEVER_ARM:
            return accel_design(array, sensor_type)
        return array.measurement_matrix(sensor_type)

    def _fit_type(self, measurements: np.ndarray, H: np.ndarray, sensor_type: str) -> _TypeModel:
        n_train = measurements.shape[0]
        minimum = max(10, 2 * self.window_samples)
        calibration_stats(measurements, min_samples=minimum)
        n = H.shape[0]
        estimator = np.linalg.pinv(H)[:3]  # (3, n): the body-frame quantity (f_0 with levers)
        if self.space == "parity":
            projection = parity_matrix(H)  # (n-3, n), Potter's V
            isolable = isolable_sensors(projection)
        else:
            projection = np.eye(n)
            isolable = np.zeros(n, dtype=bool)
        parity = measurements @ projection.T  # (N, q)
        q = projection.shape[0]
        leak = np.zeros((q, 3))
        motion = _MotionDesign.static()
        if self.space == "parity" and self.leak == "regress":
            leak, motion = self._fit_leak(parity, measurements @ estimator.T, estimator)
        compensated = parity - (measurements @ estimator.T) @ leak.T
        mean = compensated.mean(axis=0)
        centred = compensated - mean
        n_components = min(self.components, q)
        eigenvalues, eigenvectors, variance_rows = principal_components(
            centred, n_components, self.window_samples
        )
        if not np.all(np.isfinite(eigenvalues)) or float(np.min(eigenvalues)) <= 1e-30 * max(
            float(np.max(eigenvalues)), 1e-300
        ):
            raise CalibrationError(
                f"{self.name}: {sensor_type} training data is degenerate (a zero-variance"
                " direction); check the calibration window"
            )
        rho = _lag_one_autocorrelation(centred @ eigenvectors)
        return _TypeModel(
            projection=projection,
            estimator=estimator,
            leak=leak,
            mean=mean,
            eigenvalues=eigenvalues,
            eigenvectors=eigenvectors,
            rho=rho,
            n_train=n_train,
            window=self.window_samples,
            n_components=n_components,
            isolable=isolable,
            motion=motion,
            variance_rows=variance_rows,
        )

    @staticmethod
    def _fit_leak(
        parity: np.ndarray, estimate: np.ndarray, estimator: np.ndarray
    ) -> tuple[np.ndarray, _MotionDesign]:
        """Least-squares leak matrix K ((q, 3)) of ``p = mu + K xhat`` on excited directions,
        and the training motion as a regression design (for the prediction variance)."""
        q = parity.shape[1]
        n_train = parity.shape[0]
        if q == 0:
            return np.zeros((0, 3)), _MotionDesign.static()
        parity_c = parity - parity.mean(axis=0)
        estimate_c = estimate - estimate.mean(axis=0)
        # Noise scale: with V V^T = I the parity covariance trace is sum of noise variances
        # (for equal sigmas q sigma^2); xhat noise covariance = sigma^2 (H^T H)^-1.
        noise_variance = float(np.trace(parity_c.T @ parity_c)) / (parity.shape[0] - 1) / q
        xhat_noise = noise_variance * (estimator @ estimator.T)  # (3, 3)
        covariance = estimate_c.T @ estimate_c / (estimate.shape[0] - 1)
        eigenvalues, directions = np.linalg.eigh(covariance)
        noise_along = np.einsum("ij,ik,kj->j", directions, xhat_noise, directions)
        excited = eigenvalues > choices.EXCITATION_RATIO * noise_along
        coverage_inverse = np.linalg.pinv(estimate_c.T @ estimate_c + n_train * xhat_noise)
        if not np.any(excited):
            return np.zeros((q, 3)), _MotionDesign.static(coverage_inverse, estimate.mean(axis=0))
        basis = directions[:, excited]  # (3, e)
        scores = estimate_c @ basis  # (N, e)
        design = _MotionDesign(
            centre=estimate.mean(axis=0),
            basis=basis,
            inverse_gram=np.linalg.inv(scores.T @ scores),
            rms=np.sqrt(np.mean(scores**2, axis=0)),
            coverage_inverse=coverage_inverse,
        )
        coefficients, *_ = np.linalg.lstsq(scores, parity_c, rcond=None)  # (e, q)
        # Keep only parity components whose leak is significant (regression F test at
        # LEAK_SIGNIFICANCE): fitting noise would extrapolate badly when the motion later
        # leaves the range seen in training.
        n_train, n_excited = scores.shape
        explained = ((scores @ coefficients) ** 2).sum(axis=0)  # (q,)
        unexplained = ((parity_c - scores @ coefficients) ** 2).sum(axis=0)
        dof = n_train - n_excited - 1
        ratio = (explained / n_excited) / np.maximum(unexplained / dof, 1e-300)
        significant = f_distribution.sf(ratio, n_excited, dof) < choices.LEAK_SIGNIFICANCE / q
        if choices.KEEP_LEAKS_IF_ANY and significant.any():
            # Scale-factor and misalignment errors leak into every parity component: once
            # one component shows it, a component whose leak the test could not see on this
            # window still has one (up to the test's critical value, several standard
            # errors), and dropping it leaves that whole leak in the test. Kept, its error
            # is the regression error, which the prediction variance carries.
            significant[:] = True
        return (basis @ (coefficients * significant[None, :])).T, design  # (q, 3)

    # --- online --------------------------------------------------------------------------

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """Test one block; one row per input sample (causal)."""
        if self.array is None:
            raise CalibrationError(f"{self.name}: process() called before fit()")
        block = self.tracker.apply(block)
        out: dict[str, DetectionBlock] = {}
        for sensor_type, model in self.models.items():
            triads = block.get(sensor_type)
            n_sensors = model.projection.shape[1]
            if triads is None:
                out[sensor_type] = DetectionBlock.empty(len(block), n_sensors)
                continue
            measurements = self.array.select(triads, sensor_type)
            inflation = self.inflations.get(sensor_type)
            factors = None if inflation is None else inflation.factors(measurements, block.t_ns)
            budget = self.budgets.get(sensor_type)
            if budget is not None:
                out[sensor_type] = budget.process(measurements, factors)
                continue
            out[sensor_type] = self._process_type(model, measurements, factors)
        return out

    def _process_type(
        self, model: _TypeModel, measurements: np.ndarray, factors: np.ndarray | None = None
    ) -> DetectionBlock:
        n_samples = measurements.shape[0]
        n_sensors = model.projection.shape[1]
        deviation = model.transform(measurements)  # (N, q)
        sums, counts = model.window.push(deviation)
        mean_deviation = sums / counts[:, None]  # dp_t, (N, q)
        components = mean_deviation @ model.eigenvectors  # (N, q)
        extra, coverage = model.leverage(measurements @ model.estimator.T)
        extra = extra * model.leak_tolerance  # SCHEFFE_LEAK: the mean worst-motion ratio
        # prediction variance: moving-mean noise + error of the fitted mean and leak at xbar_t
        leverage = 1.0 / model.n_train + extra[:, None] * model.leak_weight[None, :]  # (N, q)
        variance = model.eigenvalues[None, :] * (
            model.inflation_l[counts - 1] + model.inflation_n[None, :] * leverage
        )  # (N, q)
        model.samples_seen += n_samples
        model.samples_beyond += int(np.sum(coverage > choices.COVERAGE_LEVERAGE))
        if n_samples:
            model.max_leverage_ratio = max(model.max_leverage_ratio, float(coverage.max()))
        normalised = components**2 / variance
        k = model.n_components
        q = model.projection.shape[0]
        tests_residual = self.residual_test and q > k
        level = self.alpha / 2.0 if tests_residual else self.alpha
        statistic = normalised[:, :k].sum(axis=1) / plug_in_quantile(
            level, np.array([k]), float(np.min(model.variance_dof[:k]))
        )
        if tests_residual:
            residual = (components[:, k:] ** 2).sum(axis=1)  # Q, squared norm
            leverage_q = 1.0 / model.n_train + extra * model.leak_weight_q
            threshold_q = model.residual_threshold(level)[counts - 1] * model.residual_scale(
                counts, leverage_q
            )
            statistic = np.maximum(statistic, residual / threshold_q)
        if factors is not None:  # sampling-time jitter in motion (maths/jitter.py)
            statistic = statistic / factors
        alarm = statistic > 1.0
        scores = np.full((n_samples, n_sensors), np.nan)
        isolated = np.full(n_samples, NO_ISOLATION, dtype=np.int32)
        amplitude = np.full(n_samples, np.nan)
        if self.space == "parity" and q >= 2:
            valid = model.direction_norms > 0
            projections = mean_deviation @ model.projection  # (N, n): v_j . dp
            lengths = np.linalg.norm(mean_deviation, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                cosines = np.abs(projections) / (
                    lengths[:, None] * np.where(valid, model.direction_norms, np.nan)[None, :]
                )
            scores = np.arccos(np.clip(cosines, 0.0, 1.0))
            best = np.argmin(np.where(np.isnan(scores), np.inf, scores), axis=1)
            rows = np.flatnonzero(alarm)
            chosen = best[rows]
            isolable = model.isolable[chosen] & np.isfinite(scores[rows, chosen])
            isolated[rows] = np.where(isolable, chosen, NOT_ISOLABLE)
            norms2 = model.direction_norms[chosen] ** 2
            amplitude[rows] = np.where(isolable, projections[rows, chosen] / norms2, np.nan)
        else:
            isolated[alarm] = NOT_ISOLABLE
        return DetectionBlock(
            statistic=statistic,
            threshold=np.ones(n_samples),
            alarm=alarm,
            isolated=isolated,
            amplitude=amplitude,
            scores=scores,
        )

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal detector: nothing is held back."""
        return {
            s: DetectionBlock.empty(0, model.projection.shape[1])
            for s, model in self.models.items()
        }

    def calibration_warnings(self) -> list[str]:
        """Warnings about the calibration window, from what was processed so far.

        One per sensor type whose motion left the range the calibration window covered on
        more than ``COVERAGE_WARNING`` of the samples (prediction leverage above
        ``COVERAGE_LEVERAGE`` times that of the training centre): there the leak model
        extrapolates, the threshold widens with the prediction variance and the test loses
        power (without the widening it would raise false alarms).
        """
        messages = []
        for sensor_type, model in self.models.items():
            if not model.samples_seen or not np.any(model.motion.coverage_inverse):
                continue
            if not model.leak_fitted and model.motion.basis.shape[1] > 0:
                continue  # motion in calibration, and no leak: its range does not matter
            share = model.samples_beyond / model.samples_seen
            if share <= choices.COVERAGE_WARNING:
                continue
            unit, scale = ("deg/s", np.rad2deg(1.0)) if sensor_type == "gyro" else ("m/s^2", 1.0)
            rms = ", ".join(f"{v * scale:.3g}" for v in model.motion.rms) or "none"
            messages.append(
                f"{self.name}: {sensor_type}: the calibration window lacks the motion the leak"
                f" model needs: {share:.0%} of the samples move beyond its range (leverage up"
                f" to {model.max_leverage_ratio:.0f}x the training centre's;"
                f" {model.motion.basis.shape[1]} of 3 axes excited in calibration, RMS"
                f" {rms} {unit} along its principal axes); thresholds were widened there. Calibrate on a window that"
                " covers the motion (--calibrate START:END)"
            )
        return messages

    def metadata(self) -> dict[str, Any]:
        """Parameters and training results (JSON-ready)."""
        types: dict[str, Any] = {}
        for sensor_type, model in self.models.items():
            k = model.n_components
            q = model.projection.shape[0]
            total = float(model.eigenvalues.sum())
            types[sensor_type] = {
                "n_sensors": int(model.projection.shape[1]),
                "dimension": int(q),
                "components": int(k),
                "eigenvalues": model.eigenvalues.tolist(),
                "variance_dof": model.variance_dof.tolist(),
                "explained_variance": float(model.eigenvalues[:k].sum() / total) if total else None,
                "lag1_autocorrelation": model.rho.tolist(),
                "training_mean": model.mean.tolist(),
                "leak_matrix": model.leak.tolist(),
                "isolable": model.isolable.tolist(),
                "residual_test": bool(self.residual_test and q > k),
                "calibration_motion_rms": model.motion.rms.tolist(),
                "excited_axes": int(model.motion.basis.shape[1]),
                "samples_beyond_calibrated_motion": int(model.samples_beyond),
                "max_leverage_ratio": float(model.max_leverage_ratio),
            }
            budget = self.budgets.get(sensor_type)
            if budget is not None:
                types[sensor_type]["budget"] = budget.metadata()
        meta: dict[str, Any] = {
            "detector": self.name,
            "params": {
                "alpha": self.alpha,
                "components": self.components,
                "window_s": self.window_s,
                "window_samples": self.window_samples,
                "space": self.space,
                "residual_test": self.residual_test,
                "leak": self.leak,
                "types": ",".join(self.sensor_types),
                "track_bias": self.tracker.tau_s,
            },
            "tracked_bias_change": self.tracker.metadata(),
            "variances": (
                f"{choices.VARIANCE_ESTIMATE} (kept components: sample eigenvalues; discarded:"
                f" out of {choices.FOLDS} folds)"
                if choices.VARIANCE_ESTIMATE == "mixed"
                else choices.VARIANCE_ESTIMATE
            ),
            "statistic": "max(T/chi2_{1-a}(k), Q/chi2_{1-a}(q-k)), a = alpha/2; threshold 1",
            "untested": dict(self.untested),
            "scores": "angle between each sensor's parity direction and the mean parity"
            " deviation, rad (smallest = isolated)",
            "types": types,
        }
        if self.false_alarms > 0:  # (the per-sample test's metadata is unchanged)
            meta["params"]["false_alarms_per_hour"] = self.false_alarms * 3600.0
            meta["params"]["track_bias"] = reference_tau(self.track_bias)
            meta["statistic"] = "largest CUSUM of the GLR evidence per sensor (budget)"
            meta["scores"] = "largest CUSUM statistic of each sensor over signs and shifts"
        return meta
