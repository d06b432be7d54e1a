"""The cnn-map detector: parameters and construction, fit, the per-block decision that
combines the input and mapping tests, and metadata.
"""

from __future__ import annotations

import base64
from dataclasses import replace
from typing import Any, ClassVar

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    FALSE_ALARMS,
    NO_ISOLATION,
    DetectionBlock,
    DetectorBase,
    Param,
)
from imufdi_cli.detectors.cnn_map.mapping import _MappingTest
from imufdi_cli.detectors.cnn_map.network import _MappingReport
from imufdi_cli.detectors.cnn_map.signals import (
    MAPPING_MODES,
    MIN_TRAINING_WINDOWS,
    READMIT_S,
    check_motion,
    noise_across_accels,
    noise_across_gyros,
)
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.nn import ACTIVATIONS
from imufdi_cli.detectors.noise_glr import budget_warning
from imufdi_cli.errors import (
    CalibrationError,
    DetectorConfigError,
    InputDataError,
)
from imufdi_cli.log import ImuBlock


class CnnMapDetector(_MappingTest, DetectorBase):
    """CNN accelerometer-to-rate mapping residuals (Chen, Su, Xu); see the module docstring.

    Parameters
    ----------
    alpha : float
        False-alarm level per sample over the tested IMUs.
    window : float
        Residual energy window, s.
    whiten : int
        Order p of the AR filter that prewhitens the mapping residuals (0: none).
    input_length : float
        CNN input window, s (rounded to samples).
    filters, kernel : int
        Channels and taps of the two convolutions.
    activation : {"relu", "tanh"}
    epochs, batch, patience : int
        Adam epochs (at most), mini-batch size, early-stopping patience (epochs).
    learning_rate : float
    holdout : float
        Fraction of the calibration window held out (early stopping, residual calibration).
    seed : int
        Seed of the weight initialisation and batch shuffling.
    model : str or None
        Path of a saved model (:meth:`save_model`): reuse it instead of training.
    input_test : bool
        Also run the input test (step 8, beyond the paper).
    mapping_test : {"off", "report", "alarm"}
        ``off`` (default): no network is trained, the input test alone decides.
        ``report``: the network is trained and the mapping test computed, but it does not
        alarm; samples over its threshold are counted in the metadata (``mapping_report``),
        the input test alarms at ``alpha`` (the same alarms as ``off``). ``alarm``: both
        tests alarm, each at ``alpha / 2`` (Bonferroni); with ``input_test=false`` the
        mapping test alone at ``alpha``; refused under a false-alarm budget. If the input
        test cannot run on the array, ``report`` falls back to the mapping test alarming
        at ``alpha``.
    false_alarms : float
        False-alarm budget, episodes per second (0: the per-sample tests at ``alpha``):
        the input test is then noise-glr's sequential test of the accelerometers.
    """

    name: ClassVar[str] = "cnn-map"
    #: Causal: the row of sample i depends on samples up to i only.
    lookahead_samples: int = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": replace(
            ALPHA, default=0.001, help="false-alarm level per sample over the tested IMUs"
        ),
        "window": Param("time", 0.4, "residual energy window (e.g. 0.4s)", low=0.0, low_open=True),
        "input_length": Param(
            "time", 0.24, "CNN input window (e.g. 0.24s)", low=0.0, high=10.0, low_open=True
        ),
        "filters": Param("int", 8, "channels of both convolutions", low=1, high=256),
        "kernel": Param("int", 5, "taps of both convolutions", low=1, high=64),
        "activation": Param("choice", "relu", "activation", choices=tuple(ACTIVATIONS)),
        "epochs": Param("int", 80, "training epochs (at most)", low=1),
        "batch": Param("int", 64, "mini-batch size", low=1),
        "patience": Param("int", 10, "early-stopping patience, epochs", low=1),
        "learning_rate": Param("float", 2e-3, "Adam learning rate", low=0.0, low_open=True),
        "holdout": Param("float", 0.4, "held-out fraction of calibration", low=0.05, high=0.5),
        "seed": Param("int", 0, "seed of initialisation and shuffling", low=0),
        "model": Param("path", None, "saved model file to reuse instead of training"),
        "whiten": Param(
            "int",
            8,
            "order of the residual prewhitening AR filter (0 = plain residual)",
            low=0,
            high=32,
        ),
        "input_test": Param(
            "bool",
            True,
            "also test every accelerometer axis for a noise growth of its leave-one-out"
            " residual (CUSUM, beyond the paper; off = the mapping test alone)",
        ),
        "mapping_test": Param(
            "choice",
            "off",
            "the paper's mapping test: off (no network trained; the alarms are the same as"
            " with report), report (trained, computed and counted in the metadata, no alarm:"
            " its threshold does not hold out of sample), alarm (alarms at alpha/2 beside"
            " the input test; refused under a false-alarm budget)",
            choices=MAPPING_MODES,
        ),
        "false_alarms": FALSE_ALARMS,
    }

    def __init__(
        self,
        alpha: float = 0.001,
        window: float = 0.4,
        input_length: float = 0.24,
        filters: int = 8,
        kernel: int = 5,
        activation: str = "relu",
        epochs: int = 80,
        batch: int = 64,
        patience: int = 10,
        learning_rate: float = 2e-3,
        holdout: float = 0.4,
        seed: int = 0,
        model: str | None = None,
        whiten: int = 8,
        input_test: bool = True,
        mapping_test: str = "off",
        false_alarms: float = 0.0,
    ) -> None:
        self.false_alarms = float(false_alarms)
        if self.false_alarms > 0 and (mapping_test == "alarm" or not input_test):
            raise DetectorConfigError(
                "cnn-map: the mapping test cannot decide under a false-alarm budget (its"
                " threshold is fitted on the calibration window and does not hold its level"
                " out of sample, docs/algorithms/cnn-map.md); with --false-alarms use"
                " mapping_test=off or report and input_test=true"
            )
        self.alpha = float(alpha)
        self.window_s = float(window)
        self.input_length_s = float(input_length)
        self.filters = int(filters)
        self.kernel = int(kernel)
        self.activation = str(activation)
        self.epochs = int(epochs)
        self.batch = int(batch)
        self.patience = int(patience)
        self.learning_rate = float(learning_rate)
        self.holdout = float(holdout)
        self.seed = int(seed)
        self.model_path = model
        self.whiten = int(whiten)
        self.input_test = bool(input_test)
        self.mapping_test = str(mapping_test)
        if self.mapping_test not in MAPPING_MODES:
            raise DetectorConfigError(
                f"cnn-map.mapping_test: {self.mapping_test!r} is not one of"
                f" {', '.join(MAPPING_MODES)}"
            )
        if not self.input_test and self.mapping_test != "alarm":
            raise DetectorConfigError(
                "cnn-map: input_test=false leaves only the mapping test; it needs"
                " mapping_test=alarm"
            )
        self.mapping_alarms = self.mapping_test == "alarm"
        self.mapping_report = _MappingReport()
        self.input_mean_window = 1
        self.array = None
        self.mapping = None
        self.network = None
        self._glt = None
        self._input = None
        self.input_note = "not fitted"
        self.mapping_alpha = self.alpha

    # --- training ------------------------------------------------------------------------

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Train (or load) the mapping network and calibrate residuals and threshold.

        Raises
        ------
        DetectorConfigError
            Array without accelerometer triads or 3-axis gyros; unreadable ``model`` file or
            one trained at another sample rate.
        CalibrationError
            Calibration window without gyro/accel data, non-finite, or too short for the
            windows (use ``--calibrate`` for a longer fault-free window, e.g. 0s:10s).
        """
        self._setup(array)
        if calibration.gyro is None or calibration.accel is None:
            raise CalibrationError("cnn-map: the calibration window needs gyro and accel data")
        if not (np.all(np.isfinite(calibration.gyro)) and np.all(np.isfinite(calibration.accel))):
            raise CalibrationError("cnn-map: the calibration window has non-finite samples")
        self._glt = None
        if array.n_sensors("gyro") >= 4 and self.mapping_test != "off":  # the mapping's
            glt = GltDetector(types="gyro")
            glt.fit(ImuBlock(t_ns=calibration.t_ns, gyro=calibration.gyro), array)
            self._glt = glt
        self.mapping_alarms = self.mapping_test == "alarm"
        self.mapping_report = _MappingReport()
        if self.mapping_test != "off":  # before the input test's threshold simulation
            gyro = array.select(calibration.gyro, "gyro")
            reference = gyro @ self._estimator.T  # fault-free window: every gyro
            body = self._body_accel(calibration)
            self.calibration_motion = check_motion(
                reference,
                body,
                noise_across_gyros(gyro, self.gyro_H),
                noise_across_accels(body, array.positions()[self.tested]),
            )
        self._fit_input_test(calibration, array)
        if self.mapping_test == "off":
            if self._input is None:
                raise CalibrationError(
                    f"cnn-map: mapping_test=off needs the input test, which cannot run here"
                    f" ({self.input_note})"
                )
            self.mapping = None
            self.network = None
            return
        if self._input is None:  # nothing else can alarm: the mapping test does, at alpha
            self.mapping_alarms = True

        if self.model_path is not None:
            mapping = self._load(self.model_path)
            length = mapping.input_length
            windows_n = len(calibration) - length + 1
            if windows_n < 20:
                raise CalibrationError(
                    f"cnn-map: calibration window has {len(calibration)} samples; the model's"
                    f" input needs {length} + 20 (use --calibrate START:END)"
                )
            self.mapping = mapping
            self.network = mapping.build()
        else:
            length = max(self.kernel * 2 + 2, round(self.input_length_s * array.rate_hz))
            windows_n = len(calibration) - length + 1
            n_holdout = round(self.holdout * windows_n)
            n_train = windows_n - n_holdout - length
            if n_train * len(self.tested) < MIN_TRAINING_WINDOWS or n_holdout < 2 * length:
                raise CalibrationError(
                    f"cnn-map: calibration window of {len(calibration)} samples is too short to"
                    f" train the mapping (input {length} samples, holdout {self.holdout:g});"
                    " use a longer fault-free window, e.g. --calibrate 0s:10s"
                )
            holdout_start = windows_n - n_holdout
            self._train(body, reference, length, n_train, holdout_start, array.rate_hz)
        self.input_length = length
        self._calibrate_residuals(body, reference)

    # --- online ------------------------------------------------------------------------

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """Test one block; one ``accel`` row per input sample (causal)."""
        if self.array is None or (self.mapping_test != "off" and self.network is None):
            raise CalibrationError(f"{self.name}: process() called before fit()")
        if block.gyro is None or block.accel is None:
            raise InputDataError("cnn-map: the block needs gyro and accel data")
        n_samples = len(block)
        if n_samples == 0:
            return {"accel": DetectionBlock.empty(0, self.n_accel)}
        mapped = self._mapping_block(block) if self.network is not None else None
        self._samples_seen += n_samples
        if self._input is None:  # the mapping test alone (it alarms, see fit)
            assert mapped is not None
            return {"accel": mapped}
        if self.false_alarms > 0:  # the input test decides under the budget
            decisions = self._budget_statistics(block)
            if mapped is not None:
                self.mapping_report.add(mapped.statistic / mapped.threshold, mapped.isolated)
            return {"accel": decisions}
        # Step 9: the input test, with the mapping test alarming or only reporting
        rows = np.arange(n_samples)
        cusum, energy, added = self._input_statistics(block)
        filled = np.where(np.isnan(cusum), -np.inf, cusum)
        channel = np.argmax(filled, axis=1)
        statistic = filled[rows, channel] / self.input_threshold
        alarm = statistic > 1.0
        isolated = np.where(alarm, channel, NO_ISOLATION)
        amplitude = np.where(alarm, energy[rows, channel], np.nan)
        if mapped is not None:
            mapping_statistic = mapped.statistic / mapped.threshold
            self.mapping_report.add(mapping_statistic, mapped.isolated)
            if self.mapping_alarms:
                statistic = np.maximum(mapping_statistic, statistic)
                isolated = np.where(alarm, channel, mapped.isolated)
                amplitude = np.where(alarm, amplitude, mapped.amplitude)
                alarm = alarm | mapped.alarm
        return {
            "accel": DetectionBlock(
                statistic=statistic,
                threshold=np.ones(n_samples),
                alarm=alarm,
                isolated=isolated.astype(np.int32),
                amplitude=amplitude,
                scores=added,
            )
        }

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal detector: nothing is held back."""
        return {"accel": DetectionBlock.empty(0, self.n_accel if self.array else 0)}

    def calibration_warnings(self) -> list[str]:
        """Under a budget, one line when the accelerometers' residual variance over the
        processed log was clearly above the calibrated one on most sensors (the input
        test's level does not hold there; :func:`~imufdi_cli.detectors.noise_glr.budget_warning`)."""
        if self._input is None or self.false_alarms <= 0:
            return []
        budget = self._input.models["accel"].budget
        note = None if budget is None else budget_warning(self.name, "accel", budget)
        return [] if note is None else [note]

    def metadata(self) -> dict[str, Any]:
        """Parameters, training figures, weights (base64 npz), residual calibration."""
        params = {
            "alpha": self.alpha,
            "window_s": self.window_s,
            "input_length_s": self.input_length_s,
            "filters": self.filters,
            "kernel": self.kernel,
            "activation": self.activation,
            "epochs": self.epochs,
            "batch": self.batch,
            "patience": self.patience,
            "learning_rate": self.learning_rate,
            "holdout": self.holdout,
            "seed": self.seed,
            "model": self.model_path,
            "whiten": self.whiten,
            "input_test": self.input_test,
            "mapping_test": self.mapping_test,
            "false_alarms_per_hour": self.false_alarms * 3600.0,
        }
        out: dict[str, Any] = {"detector": self.name, "params": params}
        if self.array is None:
            return out
        out.update(
            {
                "mapping_test": self.mapping_test,
                "mapping_alarms": self.mapping_alarms,
                "mapping_alpha": self.mapping_alpha,
                "input_test": self._input_metadata(),
                "scores": "estimated added noise std per accel axis, m/s^2",
            }
        )
        if self._input is None:
            out["statistic"] = "mapping: max_k R_k against its threshold"
        elif self.false_alarms > 0:
            out["statistic"] = (
                "input: largest variance-growth CUSUM of the leave-one-out residuals' Helmert"
                " contrasts (a false-alarm budget; noise-glr's test); the mapping test only"
                " reports"
            )
        elif self.mapping_alarms:
            out["statistic"] = "max(mapping: max_k R_k / T_map, input: max_j S_j / h); threshold 1"
        else:
            out["statistic"] = "input: max_j S_j / h; threshold 1 (the mapping test only reports)"
        out["amplitude"] = (
            "the variance ratio of the isolated axis's recent residuals (input test), or the"
            " energy ratio R_k of the isolated IMU against the other IMUs (mapping test)"
        )
        if self.mapping is None:
            return out
        mp = self.mapping
        out.update(
            {
                "architecture": (
                    f"conv1d(3->{mp.filters}, k={mp.kernel}, s=1) {mp.activation} -> "
                    f"conv1d({mp.filters}->{mp.filters}, k={mp.kernel}, s=2) {mp.activation} ->"
                    " dense(->3)"
                ),
                "input_samples": int(mp.input_length),
                "window_samples": int(self.window_samples),
                "training": mp.training,
                "model_npz_base64": base64.b64encode(mp.to_npz_bytes()).decode("ascii"),
                "tested_imus": self.tested.tolist(),
                "residual_rms_rad_s": self.residual_rms,
                "ar_coefficients": self.ar_coefficients.tolist(),
                "whitened_mean_rad_s": self.residual_mean.tolist(),
                "whitened_variance_rad2_s2": self.residual_variance.tolist(),
                "gamma_shape": float(self.gamma_shape),
                "imu_level": float(self.imu_level),
                "threshold": float(self.thresholds[-1]),
                "calibration_alarm_rate": self.calibration_alarm_rate,
                "gyro_screening": "glt" if self._glt is not None else "none (< 4 gyros)",
                "excluded_gyros": list(self.gyro_events),
                "excluded_now": [self.gyro_ids[i] for i in self.excluded_gyros],
                "readmit_s": READMIT_S,
                "calibration_motion_ratio": self.calibration_motion,
                "mapping_statistic": (
                    "max_k R_k, R_k = E_k / mean_(j!=k) E_j, E_k = windowed mean of"
                    " (z_kc - mu_kc)^2 / v_c, z = AR-whitened mapping residual"
                ),
                "mapping_report": self._report_metadata(),
            }
        )
        return out
