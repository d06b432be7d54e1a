"""cnn-map: a 1-D CNN maps each IMU's accelerometer window to the screened gyro body rate;
the mapping residual grows when that IMU's accelerometer noise grows.

Chen, Su, Xu, fault detection for wearable positioning systems built on arrays of inertial
devices (§2-3): accelerometer noise increase in a 12-IMU array. The paper's method:

1. Reference rate (§2): the array gyros are screened by the GLT (faulty gyros excluded) and
   the remaining ones give the body rate by least squares, ``w_ref = (H_a^T H_a)^-1 H_a^T m_a``
   (:class:`~imufdi_cli.detectors.glt.GltDetector`, ``types=gyro``; a gyro stays excluded
   once the GLT has reported it as isolated).
2. Mapping network (§2): two 1-D convolution layers and a fully connected layer (numpy,
   :mod:`.nn`) map a window of ``L`` samples of one IMU's specific force, rotated to the body
   frame and standardised, to the reference rate at the window's last sample. One network
   is shared by every IMU (12x the training windows of one network per IMU; the per-IMU
   differences due to lever arms stay in the per-IMU residual calibration below). Training
   on the fault-free calibration window: MSE loss, Adam, shuffled mini-batches from a seeded
   Generator, early stopping on the last ``holdout`` fraction of the window (a time-ordered
   split with a gap of ``L`` samples, so no training window overlaps a held-out one); the
   weights of the best held-out epoch are kept.
3. Residuals (§3): ``e_k(t) = CNN(a_k[t-L+1..t]) - w_ref(t)`` (rad/s, 3 components). On the
   held-out part: per-IMU, per-component mean mu_kc and variance v_kc. Online, the windowed
   energy ratio over the last ``w`` samples::

       E_k(t) = 1/(3 w) sum_{window} sum_c (e_kc - mu_kc)^2 / v_kc        (1 when fault-free)

4. Threshold: the residuals are coloured (the network and the reference are smooth), so the
   chi2(3w)/(3w) law of white residuals does not hold. The held-out windowed energies of
   every IMU are pooled and fitted with a gamma law of mean 1 by the method of moments
   (shape kappa = 1/var(E)), which keeps the effective number of degrees of freedom of the
   coloured sum. Threshold ``T = Gamma^-1(1 - a; kappa, 1/kappa)`` with the Šidák level
   ``a = 1 - (1 - alpha)^(1/m)`` over the m tested IMUs. While the window fills (c < w
   samples at the start of the log) the shape is ``kappa c / w``.
5. Isolation: the IMU with the largest E_k. Which of its accelerometer axes: by the network's
   linearised sensitivity. White noise of added variance delta on IMU axis a (body direction
   d_a = R_k[:, a]) raises the expected normalised residual energy of component c by
   ``delta S_k[a, c]`` with ``S_k[a, c] = mean_windows sum_lags (J_c,lag . d_a)^2 / v_kc``
   (J = d CNN / d input, from the held-out windows). With the observed excess
   ``x_c = mean_window((e_c - mu_c)^2 / v_c) - 1``, each axis is fitted alone by least squares:
   ``delta_a = x . S_a / |S_a|^2``, fit ``(x . S_a)^2 / |S_a|^2``; the isolated sensor is the
   axis with the best fit (``x . S_a > 0``). ``scores`` = sqrt(max(delta_a, 0)), the
   estimated added noise standard deviation of every accelerometer axis, m/s^2.
6. ``amplitude`` = E_k of the isolated IMU, the residual energy ratio against calibration
   (dimensionless, like noise-glr's noise ratio; ~1 + delta S for a noise growth).

Only ``accel`` is reported (the gyros are the reference; their screening is in
:meth:`CnnMapDetector.metadata`). The first ``L - 1`` samples of the log have no full
input window: their residual energy counts as its calibrated mean (no alarm possible).
"""

from __future__ import annotations

import base64
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.stats import gamma as gamma_distribution

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    NO_ISOLATION,
    DetectionBlock,
    Param,
    parse_params,
)
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.nn import ACTIVATIONS, Adam, Conv1d, Dense, Sequential, mse_loss
from imufdi_cli.detectors.parity import least_squares_matrix
from imufdi_cli.detectors.pca_parity import MovingWindow
from imufdi_cli.errors import CalibrationError, DetectorConfigError, InputDataError
from imufdi_cli.log import ImuBlock

#: Format tag of saved model files.
MODEL_FORMAT = "imufdi-cnn-map-1"
#: Fewest training windows (all IMUs together) for a meaningful fit.
MIN_TRAINING_WINDOWS = 200
#: Held-out windows used for the sensitivity Jacobian (a seeded subsample beyond this).
MAX_JACOBIAN_WINDOWS = 4000


@dataclass
class MappingNetwork:
    """The trained mapping: architecture, standardisation and weights.

    Attributes
    ----------
    input_length : int
        Samples per input window (L).
    filters, kernel : int
        Channels and taps of both convolutions (the second has stride 2).
    activation : str
        ``relu`` or ``tanh``.
    rate_hz : float
        Sample rate the network was trained at.
    input_mean, input_std : ndarray, shape (3,)
        Body-frame specific-force standardisation, m/s^2.
    output_mean, output_std : ndarray, shape (3,)
        Body-rate standardisation, rad/s.
    weights : list of ndarray
        Conv1 W, b, conv2 W, b, dense W, b.
    training : dict
        Training figures (loss curves, best epoch, mean absolute errors).
    """

    input_length: int
    filters: int
    kernel: int
    activation: str
    rate_hz: float
    input_mean: np.ndarray
    input_std: np.ndarray
    output_mean: np.ndarray
    output_std: np.ndarray
    weights: list[np.ndarray] = field(default_factory=list)
    training: dict[str, Any] = field(default_factory=dict)

    def build(self, rng: np.random.Generator | None = None) -> Sequential:
        """The Sequential network; with ``weights`` set, those are loaded."""
        rng = np.random.default_rng(0) if rng is None else rng
        act = ACTIVATIONS[self.activation]
        conv1 = Conv1d(3, self.filters, self.kernel, 1, rng)
        conv2 = Conv1d(self.filters, self.filters, self.kernel, 2, rng)
        shape = conv2.output_shape(conv1.output_shape((self.input_length, 3)))
        if shape[0] < 1:
            raise DetectorConfigError(
                f"cnn-map: input window of {self.input_length} samples is too short for two"
                f" convolutions of kernel {self.kernel}; use a longer input_length"
            )
        network = Sequential([conv1, act(), conv2, act(), Dense(shape[0] * shape[1], 3, rng)])
        if self.weights:
            for param, value in zip(network.params, self.weights):
                if param.shape != value.shape:
                    raise DetectorConfigError("cnn-map: model weights do not fit the architecture")
                param[...] = value
        return network

    def to_npz_bytes(self) -> bytes:
        header = {
            "format": MODEL_FORMAT,
            "input_length": self.input_length,
            "filters": self.filters,
            "kernel": self.kernel,
            "activation": self.activation,
            "rate_hz": self.rate_hz,
            "training": self.training,
        }
        arrays: dict[str, Any] = {f"weight{i}": w for i, w in enumerate(self.weights)}
        arrays.update(
            header=np.array(json.dumps(header)),
            input_mean=self.input_mean,
            input_std=self.input_std,
            output_mean=self.output_mean,
            output_std=self.output_std,
        )
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        return buffer.getvalue()

    @classmethod
    def from_npz_bytes(cls, data: bytes, where: str) -> MappingNetwork:
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                header = json.loads(str(npz["header"]))
                if header.get("format") != MODEL_FORMAT:
                    raise DetectorConfigError(
                        f"{where}: not a cnn-map model (format {header.get('format')!r},"
                        f" expected {MODEL_FORMAT})"
                    )
                n_weights = sum(1 for key in npz.files if key.startswith("weight"))
                return cls(
                    input_length=int(header["input_length"]),
                    filters=int(header["filters"]),
                    kernel=int(header["kernel"]),
                    activation=str(header["activation"]),
                    rate_hz=float(header["rate_hz"]),
                    input_mean=npz["input_mean"],
                    input_std=npz["input_std"],
                    output_mean=npz["output_mean"],
                    output_std=npz["output_std"],
                    weights=[npz[f"weight{i}"] for i in range(n_weights)],
                    training=dict(header.get("training", {})),
                )
        except DetectorConfigError:
            raise
        except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError) as err:
            raise DetectorConfigError(
                f"{where}: not a readable cnn-map model file ({err})"
            ) from err


def input_windows(body_accel: np.ndarray, length: int) -> np.ndarray:
    """Every full window of ``length`` samples, per IMU.

    Parameters
    ----------
    body_accel : ndarray, shape (N, m, 3)
    length : int

    Returns
    -------
    ndarray, shape (N - length + 1, m, length, 3) (a view); window i ends at sample
    ``i + length - 1``.
    """
    return np.moveaxis(sliding_window_view(body_accel, length, axis=0), -1, 2)


def gamma_shape(energies: np.ndarray) -> float:
    """Method-of-moments gamma shape of energies with mean ~1: ``mean^2 / var``."""
    mean = float(np.mean(energies))
    variance = float(np.var(energies, ddof=1))
    if not (variance > 0 and mean > 0):
        raise CalibrationError("cnn-map: held-out residual energies have zero variance")
    return mean * mean / variance


class CnnMapDetector:
    """CNN accelerometer-to-rate mapping residuals (Chen, Su, Xu); see the module docstring.

    Parameters
    ----------
    alpha : float
        False-alarm level per sample over the tested IMUs.
    window : float
        Residual energy window, s.
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
    """

    name: ClassVar[str] = "cnn-map"
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "window": Param("time", 0.2, "residual energy window (e.g. 0.2s)", low=0.0, low_open=True),
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
        "relative": Param(
            "bool", False, "divide each IMU's energy by the across-IMU median energy"
        ),
        "difference": Param(
            "int", 1, "order of the time difference of the residuals (0 = none)", low=0, high=3
        ),
        "common_mode": Param(
            "choice",
            "none",
            "remove the across-IMU median of the mapping residuals (median) or not (none)",
            choices=("median", "none"),
        ),
    }

    def __init__(
        self,
        alpha: float = 0.01,
        window: float = 0.2,
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
        common_mode: str = "none",
        difference: int = 1,
        relative: bool = False,
    ) -> None:
        self.alpha = float(alpha)
        self.window_s = float(window)
        self.input_length_s = float(input_length)
        self.filters = int(filters)
        self.kernel = int(kernel)
        self.activation = str(activation)
        if self.activation not in ACTIVATIONS:
            raise DetectorConfigError(
                f"cnn-map.activation: {activation!r} is not valid; valid: {', '.join(ACTIVATIONS)}"
            )
        self.epochs = int(epochs)
        self.batch = int(batch)
        self.patience = int(patience)
        self.learning_rate = float(learning_rate)
        self.holdout = float(holdout)
        self.seed = int(seed)
        self.model_path = model
        if common_mode not in ("median", "none"):
            raise DetectorConfigError(
                f"cnn-map.common_mode: {common_mode!r} is not valid; valid: median, none"
            )
        self.common_mode = common_mode
        self.difference = int(difference)
        self.relative = bool(relative)
        self.array: ArrayConfig | None = None
        self.mapping: MappingNetwork | None = None
        self.network: Sequential | None = None
        self._glt: GltDetector | None = None

    @classmethod
    def from_params(cls, raw: dict[str, Any] | None = None) -> CnnMapDetector:
        """Construct from raw (string) parameters, as the CLI does."""
        return cls(**parse_params(cls.PARAMS, raw or {}, cls.name))

    # --- geometry and reference --------------------------------------------------------

    def _setup(self, array: ArrayConfig) -> None:
        tested = [k for k, imu in enumerate(array.imus) if len(imu.axes_of("accel")) == 3]
        if not tested:
            raise DetectorConfigError(
                "cnn-map needs IMUs with full accelerometer triads; this array has none"
            )
        if (
            array.n_sensors("gyro") < 3
            or np.linalg.matrix_rank(array.measurement_matrix("gyro")) < 3
        ):
            raise DetectorConfigError(
                "cnn-map needs gyros spanning 3 axes for the reference rate; this array has"
                f" {array.n_sensors('gyro')} gyros"
            )
        self.array = array
        self.tested = np.asarray(tested, dtype=np.intp)  # IMUs with an accel triad
        self.rotations = array.rotations()[self.tested]  # (m, 3, 3) IMU -> body
        imu_idx, axis_idx = array.sensor_index("accel")
        self.n_accel = int(imu_idx.size)
        # accel sensor index of (tested IMU position, axis)
        lookup = {(int(k), int(a)): j for j, (k, a) in enumerate(zip(imu_idx, axis_idx))}
        self.sensor_of = np.array([[lookup[(int(k), a)] for a in range(3)] for k in self.tested])
        self.gyro_H = array.measurement_matrix("gyro")
        self.gyro_ids = array.sensor_ids("gyro")
        self.excluded_gyros: list[int] = []
        self.gyro_events: list[dict[str, Any]] = []
        self._estimator = least_squares_matrix(self.gyro_H)  # (3, n_g)
        self._samples_seen = 0

    def _body_accel(self, block: ImuBlock) -> np.ndarray:
        """Specific force of the tested IMUs in the body frame, (N, m, 3), m/s^2."""
        assert block.accel is not None
        return np.einsum("kab,nkb->nka", self.rotations, block.accel[:, self.tested, :])

    def _reference_rate(self, block: ImuBlock) -> np.ndarray:
        """GLT-screened least-squares body rate (N, 3), rad/s (paper §2)."""
        assert self.array is not None and block.gyro is not None
        gyro = self.array.select(block.gyro, "gyro")
        n_samples = gyro.shape[0]
        if self._glt is None:
            return gyro @ self._estimator.T  # type: ignore[no-any-return]
        isolated = self._glt.process(ImuBlock(t_ns=block.t_ns, gyro=block.gyro))["gyro"].isolated
        rate = np.empty((n_samples, 3))
        start = 0
        # New exclusions: the first sample at which GLT reports each not-yet-excluded gyro.
        fresh = (isolated >= 0) & ~np.isin(isolated, self.excluded_gyros)
        for index in np.flatnonzero(fresh):
            sensor = int(isolated[index])
            if sensor in self.excluded_gyros:
                continue
            rate[start:index] = gyro[start:index] @ self._estimator.T
            start = int(index)
            self.excluded_gyros.append(sensor)
            self.gyro_events.append(
                {"sample": self._samples_seen + start, "excluded": self.gyro_ids[sensor]}
            )
            active = np.setdiff1d(np.arange(len(self.gyro_ids)), self.excluded_gyros)
            estimator = np.zeros((3, len(self.gyro_ids)))
            if np.linalg.matrix_rank(self.gyro_H[active]) == 3:
                estimator[:, active] = least_squares_matrix(self.gyro_H[active])
                self._estimator = estimator
        rate[start:] = gyro[start:] @ self._estimator.T
        return rate

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
        if array.n_sensors("gyro") >= 4:
            glt = GltDetector(types="gyro")
            glt.fit(ImuBlock(t_ns=calibration.t_ns, gyro=calibration.gyro), array)
            self._glt = glt
        gyro = array.select(calibration.gyro, "gyro")
        reference = gyro @ self._estimator.T  # fault-free window: every gyro
        body = self._body_accel(calibration)

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
            holdout_start = 0  # the whole window calibrates the residuals
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
        self._calibrate_residuals(body, reference, holdout_start)

    def _load(self, path: str) -> MappingNetwork:
        try:
            data = Path(path).read_bytes()
        except OSError as err:
            raise DetectorConfigError(f"cnn-map.model: cannot read {path!r} ({err})") from err
        mapping = MappingNetwork.from_npz_bytes(data, f"cnn-map.model {path!r}")
        assert self.array is not None
        if not math.isclose(mapping.rate_hz, self.array.rate_hz, rel_tol=1e-6):
            raise DetectorConfigError(
                f"cnn-map.model: trained at {mapping.rate_hz:g} Hz but the array runs at"
                f" {self.array.rate_hz:g} Hz; retrain without model="
            )
        return mapping

    def _train(
        self,
        body: np.ndarray,
        reference: np.ndarray,
        length: int,
        n_train: int,
        holdout_start: int,
        rate_hz: float,
    ) -> None:
        """Adam on shuffled mini-batches, early stopping on the held-out windows (paper §2)."""
        rng = np.random.default_rng(self.seed)
        windows = input_windows(body, length)  # (W, m, L, 3)
        targets = reference[length - 1 :]  # (W, 3)
        m = windows.shape[1]
        train_x = windows[:n_train].reshape(-1, length, 3)
        train_y = np.repeat(targets[:n_train], m, axis=0)
        hold_x = windows[holdout_start:].reshape(-1, length, 3)
        hold_y = np.repeat(targets[holdout_start:], m, axis=0)
        flat = body[: n_train + length - 1].reshape(-1, 3)
        input_mean, input_std = flat.mean(axis=0), flat.std(axis=0)
        output_mean, output_std = targets[:n_train].mean(axis=0), targets[:n_train].std(axis=0)
        if np.any(input_std <= 0) or np.any(output_std <= 0):
            raise CalibrationError(
                "cnn-map: no motion in the calibration window (constant specific force or rate);"
                " the mapping needs a window with motion"
            )
        mapping = MappingNetwork(
            input_length=length,
            filters=self.filters,
            kernel=self.kernel,
            activation=self.activation,
            rate_hz=float(rate_hz),
            input_mean=input_mean,
            input_std=input_std,
            output_mean=output_mean,
            output_std=output_std,
        )
        network = mapping.build(rng)
        train_in = (train_x - input_mean) / input_std
        train_out = (train_y - output_mean) / output_std
        hold_in = (hold_x - input_mean) / input_std
        hold_out = (hold_y - output_mean) / output_std
        optimiser = Adam(network.params, learning_rate=self.learning_rate)
        train_curve: list[float] = []
        hold_curve: list[float] = []
        best_loss, best_epoch = math.inf, -1
        best = [p.copy() for p in network.params]
        n = train_in.shape[0]
        for epoch in range(self.epochs):
            order = rng.permutation(n)
            total = 0.0
            for start in range(0, n, self.batch):
                pick = order[start : start + self.batch]
                loss, grad = mse_loss(network.forward(train_in[pick]), train_out[pick])
                network.backward(grad)
                optimiser.step(network.grads)
                total += loss * pick.size
            train_curve.append(total / n)
            hold_loss = mse_loss(network.predict(hold_in), hold_out)[0]
            hold_curve.append(hold_loss)
            if hold_loss < best_loss:
                best_loss, best_epoch = hold_loss, epoch
                best = [p.copy() for p in network.params]
            elif epoch - best_epoch >= self.patience:
                break
        for param, value in zip(network.params, best):
            param[...] = value
        train_mae = np.abs(network.predict(train_in) * output_std + output_mean - train_y)
        hold_mae = np.abs(network.predict(hold_in) * output_std + output_mean - hold_y)
        mapping.weights = [p.copy() for p in network.params]
        mapping.training = {
            "train_windows": int(n),
            "holdout_windows": int(hold_in.shape[0]),
            "epochs_run": len(train_curve),
            "best_epoch": int(best_epoch),
            "train_loss": [float(v) for v in train_curve],
            "holdout_loss": [float(v) for v in hold_curve],
            "mae_rad_s": float(hold_mae.mean()),
            "mae_rad_s_per_axis": hold_mae.mean(axis=0).tolist(),
            "train_mae_rad_s": float(train_mae.mean()),
            "reference_rms_rad_s": float(np.sqrt(np.mean(targets**2))),
        }
        self.mapping = mapping
        self.network = network

    def _predict(self, windows: np.ndarray) -> np.ndarray:
        """Mapped rate (..., 3) rad/s of windows (..., L, 3) of body specific force."""
        assert self.mapping is not None and self.network is not None
        mp = self.mapping
        lead = windows.shape[:-2]
        flat = windows.reshape(-1, mp.input_length, 3)
        out = self.network.predict((flat - mp.input_mean) / mp.input_std)
        return (out * mp.output_std + mp.output_mean).reshape(*lead, 3)  # type: ignore[no-any-return]

    def _residuals(self, predicted: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Mapping residuals (N, m, 3) rad/s of predictions (N, m, 3) against the reference
        (N, 3); with ``common_mode=median`` minus their across-IMU median (step 3b)."""
        residual = predicted - reference[:, None, :]
        if self.common_mode == "median" and residual.shape[1] >= 3:
            residual = residual - np.median(residual, axis=1, keepdims=True)
        return residual

    def _axis_gains(self, windows: np.ndarray) -> np.ndarray:
        """Linearised noise gains of the (differenced) mapping residual, per IMU axis.

        ``G[n, k, a, c] = sum_lags (D J_c . R_k[:, a])^2`` with J = d CNN_c / d input (rad/s
        per m/s^2, body frame) of window n of IMU k and D the difference of order
        ``difference`` along the lags (J taken constant over consecutive windows): white
        noise of variance delta on IMU axis a adds ``delta G[.., a, c]`` to the variance of
        residual component c.

        Parameters
        ----------
        windows : ndarray, shape (n, m, L, 3)

        Returns
        -------
        ndarray, shape (n, m, 3, 3), (rad/s)^2 per (m/s^2)^2
        """
        assert self.mapping is not None and self.network is not None
        mp = self.mapping
        n, m = windows.shape[:2]
        flat = ((windows - mp.input_mean) / mp.input_std).reshape(-1, mp.input_length, 3)
        gains = np.empty((flat.shape[0], 3, 3))
        rotations = np.broadcast_to(self.rotations, (n, m, 3, 3)).reshape(-1, 3, 3)
        scale = mp.output_std[None, :, None, None] / mp.input_std[None, None, None, :]
        for lo in range(0, flat.shape[0], 2048):  # bounded memory
            jac = self.network.input_gradients(flat[lo : lo + 2048]) * scale  # (b, c, L, 3)
            directed = np.einsum("bclj,bja->bacl", jac, rotations[lo : lo + 2048])
            if self.difference:
                pad = [(0, 0)] * 3 + [(self.difference, self.difference)]
                directed = np.diff(np.pad(directed, pad), n=self.difference, axis=3)
            gains[lo : lo + 2048] = np.sum(directed**2, axis=3)
        return gains.reshape(n, m, 3, 3)

    def _calibrate_residuals(self, body: np.ndarray, reference: np.ndarray, start: int) -> None:
        """Residual variance model, energy threshold (steps 3-4)."""
        assert self.array is not None and self.mapping is not None and self.network is not None
        length = self.input_length
        windows = input_windows(body, length)[start:]  # (W_h, m, L, 3)
        target = reference[length - 1 :][start:]  # (W_h, 3)
        residual = self._residuals(self._predict(windows), target)  # (W_h, m, 3)
        residual = np.diff(residual, n=self.difference, axis=0)
        gain = self._axis_gains(windows)[self.difference :].sum(axis=2)  # (W, m, 3) isotropic
        self.residual_mean = residual.mean(axis=0)  # (m, 3)
        power = (residual - self.residual_mean) ** 2
        # Variance model v = a g + b per IMU and component (least squares, a, b > 0 floors)
        g_mean, p_mean = gain.mean(axis=0), power.mean(axis=0)
        g_var = gain.var(axis=0)
        cov = ((gain - g_mean) * (power - p_mean)).mean(axis=0)
        slope = np.where(g_var > 0, cov / np.where(g_var > 0, g_var, 1.0), 0.0)
        floor = 0.05 * p_mean
        slope = np.clip(slope, 0.0, None)
        offset = np.maximum(p_mean - slope * g_mean, floor)
        if not np.all(p_mean > 0):
            raise CalibrationError("cnn-map: zero residual variance; check the calibration window")
        self.noise_slope = slope  # (m, 3) ~ accel noise variance seen through the network
        self.noise_offset = offset  # (m, 3) residual variance not explained by the gain
        variance = slope * gain + offset
        squared = (power / variance).mean(axis=2)  # (W, m)
        self.window_samples = max(1, round(self.window_s * self.array.rate_hz))
        w = self.window_samples
        if squared.shape[0] < 2 * w:
            raise CalibrationError(
                f"cnn-map: {squared.shape[0]} held-out samples cannot calibrate a {w}-sample"
                " energy window; use a longer --calibrate window"
            )
        scale = squared.mean(axis=0)  # renormalise to mean 1 per IMU
        self.noise_slope = self.noise_slope * scale[:, None]
        self.noise_offset = self.noise_offset * scale[:, None]
        squared = squared / scale
        cumulative = np.concatenate([np.zeros((1, squared.shape[1])), np.cumsum(squared, axis=0)])
        energies = (cumulative[w:] - cumulative[:-w]) / w  # (W - w + 1, m)
        if self.relative and energies.shape[1] >= 3:
            energies = energies / np.median(energies, axis=1, keepdims=True)
        self.gamma_shape = gamma_shape(energies.ravel())
        m = len(self.tested)
        self.imu_level = -math.expm1(math.log1p(-self.alpha) / m)  # Šidák
        counts = np.arange(1, w + 1, dtype=np.float64)
        shapes = self.gamma_shape * counts / w
        self.thresholds = gamma_distribution.ppf(1.0 - self.imu_level, shapes, scale=1.0 / shapes)
        self.holdout_far = float(np.mean(energies.max(axis=1) > self.thresholds[-1]))
        self.residual_sigma = np.sqrt(p_mean)
        self._energy_window = MovingWindow(w, m * 3 + m * 9)
        self._tail = np.zeros((0, m, 3))
        self._residual_tail = np.zeros((0, m, 3))
        self._samples_seen = 0

    # --- online ------------------------------------------------------------------------

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """Test one block; one ``accel`` row per input sample (causal)."""
        if self.network is None or self.array is None:
            raise CalibrationError(f"{self.name}: process() called before fit()")
        if block.gyro is None or block.accel is None:
            raise InputDataError("cnn-map: the block needs gyro and accel data")
        n_samples = len(block)
        m = len(self.tested)
        if n_samples == 0:
            return {"accel": DetectionBlock.empty(0, self.n_accel)}
        reference = self._reference_rate(block)
        body = self._body_accel(block)
        joined = np.concatenate([self._tail, body], axis=0)
        length = self.input_length
        n_full = joined.shape[0] - length + 1  # windows ending in this block
        # before the first full window: calibrated mean energy, no sensitivity
        squared = np.ones((n_samples, m, 3))
        sensitivity = np.zeros((n_samples, m, 3, 3))
        if n_full > 0:
            windows = input_windows(joined, length)
            residual = self._residuals(self._predict(windows), reference[n_samples - n_full :])
            joined_residual = np.concatenate([self._residual_tail, residual], axis=0)
            differenced = np.diff(joined_residual, n=self.difference, axis=0)
            n_new = min(differenced.shape[0], n_full)
            if n_new > 0:
                gains = self._axis_gains(windows[n_full - n_new :])  # (n_new, m, axis, c)
                variance = self.noise_slope * gains.sum(axis=2) + self.noise_offset
                squared[n_samples - n_new :] = (
                    differenced[-n_new:] - self.residual_mean
                ) ** 2 / variance
                # Step 5: S[a, c] = G[a, c] / v_c (normalised energy per added variance)
                sensitivity[n_samples - n_new :] = gains / variance[:, :, None, :]
            self._residual_tail = joined_residual[joined_residual.shape[0] - self.difference :]
        self._tail = joined[joined.shape[0] - (length - 1) :]
        stacked = np.concatenate(
            [squared.reshape(n_samples, -1), sensitivity.reshape(n_samples, -1)], axis=1
        )
        sums, counts = self._energy_window.push(stacked)
        means = sums / counts[:, None]
        component = means[:, : m * 3].reshape(n_samples, m, 3)  # (N, m, c)
        window_sensitivity = means[:, m * 3 :].reshape(n_samples, m, 3, 3)  # (N, m, a, c)
        energy = component.mean(axis=2)  # E_k, (N, m)
        if self.relative and m >= 3:
            common = np.median(energy, axis=1, keepdims=True)
            energy = energy / common
            component = component / common[:, :, None]
        best_imu = np.argmax(energy, axis=1)
        rows = np.arange(n_samples)
        statistic = energy[rows, best_imu]
        threshold = self.thresholds[counts - 1]
        alarm = statistic > threshold
        # Step 5: per-axis least-squares fit of the excess energy with the sensitivities
        excess = component - 1.0  # (N, m, c)
        projection = np.einsum("nkc,nkac->nka", excess, window_sensitivity)  # x . S_a
        norm2 = np.einsum("nkac,nkac->nka", window_sensitivity, window_sensitivity)
        safe = np.where(norm2 > 0, norm2, 1.0)
        delta = np.where(norm2 > 0, projection / safe, 0.0)  # added variance, (m/s^2)^2
        fit = np.where((projection > 0) & (norm2 > 0), projection**2 / safe, 0.0)
        scores = np.full((n_samples, self.n_accel), np.nan)
        scores[:, self.sensor_of.ravel()] = np.sqrt(np.maximum(delta, 0.0)).reshape(n_samples, -1)
        best_axis = np.argmax(fit[rows, best_imu], axis=1)
        isolated = np.where(alarm, self.sensor_of[best_imu, best_axis], NO_ISOLATION)
        amplitude = np.where(alarm, statistic, np.nan)
        self._samples_seen += n_samples
        return {
            "accel": DetectionBlock(
                statistic=statistic,
                threshold=threshold,
                alarm=alarm,
                isolated=isolated.astype(np.int32),
                amplitude=amplitude,
                scores=scores,
            )
        }

    def flush(self) -> dict[str, DetectionBlock]:
        """Causal detector: nothing is held back."""
        return {"accel": DetectionBlock.empty(0, self.n_accel if self.array else 0)}

    # --- model files and metadata --------------------------------------------------------

    def save_model(self, path: str | Path) -> None:
        """Write the trained network (architecture, standardisation, weights, training
        figures) as an ``.npz`` file reusable with ``model=PATH``.

        Raises
        ------
        DetectorConfigError
            No trained model yet, or the file cannot be written.
        """
        if self.mapping is None:
            raise DetectorConfigError("cnn-map: no model to save; call fit() first")
        try:
            Path(path).write_bytes(self.mapping.to_npz_bytes())
        except OSError as err:
            raise DetectorConfigError(f"cnn-map: cannot write model {str(path)!r} ({err})") from err

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
            "common_mode": self.common_mode,
            "difference": self.difference,
            "relative": self.relative,
        }
        out: dict[str, Any] = {"detector": self.name, "params": params}
        if self.mapping is None or self.array is None:
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
                "residual_mean_rad_s": self.residual_mean.tolist(),
                "residual_sigma_rad_s": self.residual_sigma.tolist(),
                "noise_slope": self.noise_slope.tolist(),
                "noise_offset_rad2_s2": self.noise_offset.tolist(),
                "gamma_shape": float(self.gamma_shape),
                "imu_level": float(self.imu_level),
                "threshold": float(self.thresholds[-1]),
                "holdout_alarm_rate": self.holdout_far,
                "gyro_screening": "glt" if self._glt is not None else "none (< 4 gyros)",
                "excluded_gyros": list(self.gyro_events),
                "statistic": "max_k E_k, E_k = windowed mean of (e_kc - mu_kc)^2 / v_kc",
                "amplitude": "residual energy ratio E_k of the isolated IMU (1 = calibration)",
                "scores": "estimated added noise std per accel axis, m/s^2",
            }
        )
        return out
