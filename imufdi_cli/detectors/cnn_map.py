"""cnn-map: a 1-D CNN maps each IMU's accelerometer window to the screened gyro body rate;
the mapping residual grows when that IMU's accelerometer noise grows.

Chen, Su, Xu, fault detection for wearable positioning systems built on arrays of inertial
devices (§2-3): accelerometer noise increase in a 12-IMU array. The paper's method:

1. Reference rate (§2): the array gyros are screened by the GLT (faulty gyros excluded) and
   the remaining ones give the body rate by least squares, ``w_ref = (H_a^T H_a)^-1 H_a^T m_a``
   (:class:`~imufdi_cli.detectors.glt.GltDetector`, ``types=gyro``; a gyro is excluded
   while the GLT isolates it and re-admitted ``READMIT_S`` = 0.5 s after its last
   isolation, so a GLT false alarm does not remove a healthy gyro for good; every
   exclusion and re-admission is logged in the metadata, ``excluded_gyros``). The
   calibration window must contain motion: rotation and specific-force change of at least
   10x their noise on one body axis (``check_motion``), else fit refuses it.
2. Mapping network (§2): two 1-D convolution layers and a fully connected layer (numpy,
   :mod:`.nn`) map a window of ``L`` samples of one IMU's specific force, rotated to the body
   frame and standardised, to the reference rate at the window's last sample. One network
   is shared by every IMU (12x the training windows of one network per IMU; the IMUs'
   lever arms change their inputs only slightly, and step 4 compares IMUs). Training
   on the fault-free calibration window: MSE loss, Adam, shuffled mini-batches from a seeded
   Generator, early stopping on the last ``holdout`` fraction of the window (a time-ordered
   split with a gap of ``L`` samples, so no training window overlaps a held-out one); the
   weights of the best held-out epoch are kept.
3. Residuals (§3): ``e_k(t) = CNN(a_k[t-L+1..t]) - w_ref(t)`` (rad/s, 3 components).
   Beyond the paper (see docs/algorithms/cnn-map.md for the measurements behind each step):
   the plain residual is dominated by the smooth mapping error, so it is prewhitened by an
   autoregressive filter of order ``p = whiten`` fitted by least squares on the calibration
   residuals (per component, pooled over IMUs)::

       z_kc(t) = e_kc(t) - sum_{i=1..p} phi_ci e_kc(t - i)

   This removes the predictable mapping error and leaves the accelerometer noise the
   network passes through (broadband, independent between IMUs). ``whiten=0`` keeps the
   plain residual.
4. Energy ratio: per IMU, ``s_k(t) = 1/3 sum_c (z_kc - mu_kc)^2 / v_c`` with mu_kc the
   calibration mean and v_c the calibration variance of component c averaged over the
   IMUs; ``E_k(t)`` = mean of s_k over the last ``w`` samples. The network's noise gain
   changes with the motion phase, by a factor of 2-3 over a swing, and every IMU sees the
   same motion. The test therefore compares each IMU with the others at the same time::

       R_k(t) = E_k(t) / mean_{j != k} E_j(t)        (about 1 when fault-free)

5. Threshold: the windowed energies are sums of coloured terms, so the chi2 law of white
   residuals does not hold. Every IMU's R_k over the calibration window is pooled and
   fitted with a gamma law by the method of moments (shape ``kappa = mean^2 / var``, scale
   ``mean / kappa``). Threshold ``T = Gamma^-1(1 - a)`` with the Šidák level
   ``a = 1 - (1 - alpha)^(1/m)`` over the m tested IMUs. While the window fills (c < w
   samples at the start of the log) the shape is ``kappa c / w``.
6. Isolation: the IMU with the largest R_k. Which of its accelerometer axes: by the
   network's linearised sensitivity. White noise of added variance delta on IMU axis a
   (body direction d_a = R_k[:, a]) raises the expected energy of component c by
   ``delta S_k[a, c]`` with ``S_k[a, c] = sum_lags ((K * J_c) . d_a)^2 / v_c``. Here
   J = d CNN / d input of the current window (from backpropagation) and K is the
   whitening kernel ``[1, -phi_1, .., -phi_p]`` convolved along the lags (J is taken as
   constant over p consecutive windows). With the observed excess of each component's
   energy ratio against the other IMUs, ``x_c``, each axis is fitted alone by least
   squares: ``delta_a = x . S_a / |S_a|^2``. The isolated sensor is the axis with the best
   fit ``(sum x . S_a)^2 / sum |S_a|^2`` (positive sum), the sums running over the alarm
   episode on that IMU so far (:meth:`CnnMapDetector._episode_axes`). ``scores`` =
   sqrt(max(delta_a, 0)), the estimated added noise standard deviation of every
   accelerometer axis, m/s^2.
7. ``statistic`` = max_k R_k; ``amplitude`` = R_k of the isolated IMU, the residual energy
   ratio against the other IMUs (dimensionless; 1 = nominal, ~1 + delta S for a noise
   growth).

8. Input test (beyond the paper; ``input_test``, default on). The mapping passes an
   accelerometer axis's noise to its output only as far as the network uses that axis: on
   wearable12 the linearised gain ``sum_c S_k[a, c]`` is 9x (y) and 16x (z) smaller than
   for x, so a noise growth on y or z hardly moves R_k (detection 10-14 % at x3). Every
   axis is therefore also tested on its own: the leave-one-out residual of each
   accelerometer against the rigid-body consensus of the others (lever arms modelled; the
   residual model of :class:`~imufdi_cli.detectors.noise_glr.NoiseGlrDetector`), minus
   the mean of its ``INPUT_MEAN_S`` (8) previous samples and standardized by the
   calibrated variance of that quantity (``z``, :func:`.cusum.local_mean_residual`),
   feeds a capped variance CUSUM (:mod:`.cusum`, design ratio ``K = 9``, ``z^2`` clipped
   at 25, cap ``INPUT_RELEASE_S`` of null drift above h). The threshold h is the
   per-channel Šidák share of ``alpha``, from a seeded simulation of the null
   (:func:`.cusum.cusum_threshold`).
9. Output. By default (``mapping_test=report``) the mapping test (steps 1-7) does not
   alarm: its threshold, fitted in-sample on the calibration window, does not hold its
   level out of sample (alone at alpha: 5.05 alpha mean, 24.5 alpha worst of 10 fresh seeds; see
   docs/algorithms/cnn-map.md), so it is computed and the samples over its threshold are
   counted in the metadata (``mapping_report``), and the output is the input test's:
   ``statistic = max_j S_j / h``, threshold 1, an alarm isolates its channel (the axis
   itself) with ``amplitude`` = the variance ratio of its recent residuals (mean z^2 over
   ``window``). With ``mapping_test=alarm`` both tests alarm, each at ``alpha / 2``
   (Bonferroni): ``statistic = max(max_k R_k / T_map, max_j S_j / h)``, the mapping's
   isolation and amplitude where only it alarms. ``mapping_test=off`` trains no network
   (the output is the same as with ``report``). ``scores`` = the added noise standard
   deviation of every axis, ``sqrt(max(mean z^2 - 1, 0) s^2)`` with s^2 the nominal
   residual variance, m/s^2.

Only ``accel`` is reported (the gyros are the reference; their screening is in
:meth:`CnnMapDetector.metadata`). The first ``L - 1 + p`` samples of the log have no
whitened residual: their energy counts as the calibrated mean (R = 1, no alarm possible).
At least two IMUs with accelerometer triads are needed (step 4 compares them).
"""

from __future__ import annotations

import base64
import io
import json
import math
from dataclasses import dataclass, field, replace
from itertools import pairwise
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
    DetectorBase,
    Param,
)
from imufdi_cli.detectors.cusum import (
    CusumDesign,
    cusum_threshold,
    local_mean_residual,
    run_cusum,
)
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.detectors.nn import ACTIVATIONS, Adam, Conv1d, Dense, Sequential, mse_loss
from imufdi_cli.detectors.noise_glr import (
    NoiseGlrDetector,
    clipped_square_moments,
    robust_scale,
)
from imufdi_cli.detectors.parity import least_squares_matrix
from imufdi_cli.detectors.pca_parity import MovingWindow
from imufdi_cli.errors import (
    ArrayTooSmallError,
    CalibrationError,
    DetectorConfigError,
    InputDataError,
)
from imufdi_cli.log import ImuBlock

#: Format tag of saved model files.
MODEL_FORMAT = "imufdi-cnn-map-1"
#: Fewest training windows (all IMUs together) for a meaningful fit.
MIN_TRAINING_WINDOWS = 200
#: Scale from the median absolute deviation to the standard deviation of a Gaussian.
MAD_TO_STD = 1.4826
#: The calibration window must rotate, and move the specific force, by at least this
#: multiple of the noise (standard deviations) on one body axis (``check_motion``).
MIN_MOTION_RATIO = 10.0
#: A gyro the GLT screen isolated is re-admitted to the reference this long after its last
#: isolation, seconds.
READMIT_S = 0.5
#: Input test (step 8): design variance ratio K of the CUSUM (a noise growth x3) and clip of
#: the standardized differences, sigma.
INPUT_DESIGN = CusumDesign(ratio=9.0, clip=5.0)
#: Input test: the CUSUM is capped this long (at its null drift) above its threshold, s, so
#: that an alarm ends about this long after the noise returns to nominal.
INPUT_RELEASE_S = 0.25
#: Input test: each leave-one-out residual is compared with the mean of its previous
#: samples over this span, s (8 samples at 100 Hz; :func:`.cusum.local_mean_residual`).
INPUT_MEAN_S = 0.08
#: What the mapping test does: ``report`` (computed, exceedances of its threshold counted
#: in the metadata, no alarm), ``alarm`` (alarms, at alpha / 2 beside the input test) or
#: ``off`` (no network is trained).
MAPPING_MODES = ("report", "alarm", "off")


@dataclass
class _MappingReport:
    """Running account of the mapping test when it only reports (``mapping_test=report``):
    samples and episodes over its threshold, per isolated accelerometer axis."""

    samples: int = 0
    over: int = 0
    episodes: int = 0
    first_over: int = -1
    max_ratio: float = 0.0
    by_sensor: dict[int, int] = field(default_factory=dict)
    _was_over: bool = False

    def add(self, ratio: np.ndarray, isolated: np.ndarray) -> None:
        """Account one block.

        Parameters
        ----------
        ratio : ndarray, shape (N,)
            Mapping statistic over its threshold (> 1: over).
        isolated : ndarray, shape (N,), int
            The mapping test's isolated accelerometer (valid where over).
        """
        over = ratio > 1.0
        if over.any():
            rows = np.flatnonzero(over)
            if self.first_over < 0:
                self.first_over = self.samples + int(rows[0])
            previous = np.concatenate([[self._was_over], over[:-1]])
            self.episodes += int(np.sum(over & ~previous))
            for sensor, count in zip(*np.unique(isolated[rows], return_counts=True)):
                self.by_sensor[int(sensor)] = self.by_sensor.get(int(sensor), 0) + int(count)
            self.max_ratio = max(self.max_ratio, float(ratio.max()))
        self.over += int(over.sum())
        self.samples += int(ratio.size)
        if ratio.size:
            self._was_over = bool(over[-1])


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


def fit_autoregression(series: np.ndarray, order: int) -> np.ndarray:
    """Least-squares AR coefficients shared by several series (step 3).

    Parameters
    ----------
    series : ndarray, shape (N, m)
        m series of N samples each, fitted jointly.
    order : int
        p >= 0.

    Returns
    -------
    ndarray, shape (p,): phi with ``x(t) ~ sum_i phi_i x(t - i)``.
    """
    n = series.shape[0]
    if order == 0:
        return np.zeros(0)
    lags = np.stack([series[order - 1 - i : n - 1 - i] for i in range(order)], axis=-1)
    design, target = lags.reshape(-1, order), series[order:].ravel()
    return np.linalg.lstsq(design, target, rcond=None)[0]  # type: ignore[no-any-return]


def whiten(residual: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """Apply the AR prewhitening filter per component (step 3).

    Parameters
    ----------
    residual : ndarray, shape (N, m, 3)
    coefficients : ndarray, shape (3, p)
        phi per component.

    Returns
    -------
    ndarray, shape (N - p, m, 3): row i is ``e(i + p) - sum_j phi_j e(i + p - j)``.
    """
    p = coefficients.shape[1]
    n = residual.shape[0]
    out = residual[p:].copy()
    for i in range(p):
        out -= coefficients[:, i] * residual[p - 1 - i : n - 1 - i]
    return out


def _excursion_ratio(series: np.ndarray) -> np.ndarray:
    """Per-column motion excursion over the white-noise level, (c,) for (N, c) series.

    Noise from second differences (``Var(D^2 x) = 6 sigma^2`` for white noise, smooth
    motion cancels to O(Te^2)); excursion = the standard deviation left after the noise.
    """
    noise = MAD_TO_STD * np.median(np.abs(np.diff(series, n=2, axis=0)), axis=0) / np.sqrt(6.0)
    spread = np.sqrt(np.maximum(series.var(axis=0) - noise**2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(noise > 0, spread / noise, np.where(spread > 0, np.inf, 0.0))


def check_motion(reference: np.ndarray, body: np.ndarray) -> dict[str, list[float]]:
    """Refuse a calibration window without the motion the mapping needs.

    The mapping learns the body rate from windows of specific force: the window must
    rotate (reference rate) and move the specific force, each by at least
    ``MIN_MOTION_RATIO`` times its noise on one body axis.

    Parameters
    ----------
    reference : ndarray, shape (N, 3), rad/s
    body : ndarray, shape (N, m, 3), m/s^2

    Returns
    -------
    dict
        ``rate`` and ``specific_force``: excursion / noise per body axis (for metadata).

    Raises
    ------
    CalibrationError
        Neither ratio reaches ``MIN_MOTION_RATIO`` on any axis; the message names which.
    """
    rate = _excursion_ratio(reference)
    force = _excursion_ratio(body.mean(axis=1))
    missing = [
        f"{what} (excursion {', '.join(f'{v:.2g}' for v in ratio)} x its noise about x, y, z)"
        for what, ratio in (("rotation", rate), ("specific-force change", force))
        if not np.any(ratio >= MIN_MOTION_RATIO)
    ]
    if missing:
        raise CalibrationError(
            "cnn-map: the calibration window lacks the motion the mapping needs: no "
            + " and no ".join(missing)
            + f"; it needs at least {MIN_MOTION_RATIO:g}x on one axis. Calibrate on a window"
            " where the array moves (--calibrate START:END)"
        )
    return {"rate": rate.tolist(), "specific_force": force.tolist()}


def gamma_shape(energies: np.ndarray) -> float:
    """Method-of-moments gamma shape of energies with mean ~1: ``mean^2 / var``."""
    mean = float(np.mean(energies))
    variance = float(np.var(energies, ddof=1))
    if not (variance > 0 and mean > 0):
        raise CalibrationError("cnn-map: held-out residual energies have zero variance")
    return mean * mean / variance


class CnnMapDetector(DetectorBase):
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
    mapping_test : {"report", "alarm", "off"}
        ``report`` (default): the mapping test is computed but does not alarm; samples over
        its threshold are counted in the metadata (``mapping_report``), the input test
        alarms at ``alpha``. ``alarm``: both tests alarm, each at ``alpha / 2``
        (Bonferroni); with ``input_test=false`` the mapping test alone at ``alpha``.
        ``off``: no network is trained, the input test alone. If the input test cannot run
        on the array, ``report`` falls back to the mapping test alarming at ``alpha``.
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
            "report",
            "the mapping test: report (computed and counted in the metadata, no alarm: its"
            " threshold does not hold out of sample), alarm (alarms at alpha/2 beside the"
            " input test), off (no network trained)",
            choices=MAPPING_MODES,
        ),
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
        mapping_test: str = "report",
    ) -> None:
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
        self.array: ArrayConfig | None = None
        self.mapping: MappingNetwork | None = None
        self.network: Sequential | None = None
        self._glt: GltDetector | None = None
        self._input: NoiseGlrDetector | None = None
        self.input_note = "not fitted"
        self.mapping_alpha = self.alpha

    # --- geometry and reference --------------------------------------------------------

    def _setup(self, array: ArrayConfig) -> None:
        tested = [k for k, imu in enumerate(array.imus) if len(imu.axes_of("accel")) == 3]
        if len(tested) < 2:
            raise ArrayTooSmallError(
                "cnn-map compares IMUs with each other and needs at least 2 with full"
                f" accelerometer triads; this array has {len(tested)}"
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
        self._full_estimator = self._estimator
        self._estimators: dict[frozenset[int], np.ndarray] = {}
        # stream index of each gyro's last GLT isolation (-inf: never)
        self._last_isolated = np.full(len(self.gyro_ids), -np.inf)
        self._readmit_samples = max(1, round(READMIT_S * array.rate_hz))
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
        # A gyro is left out of the reference while the GLT isolates it and for READMIT_S
        # after its last isolation; then it is re-admitted (a GLT false alarm must not
        # remove a healthy gyro for good). Exclusions and re-admissions are logged.
        n_gyros = len(self.gyro_ids)
        stamp = np.full((n_samples, n_gyros), -np.inf)
        hits = np.flatnonzero(isolated >= 0)
        stamp[hits, isolated[hits]] = self._samples_seen + hits
        last = np.maximum.accumulate(np.vstack([self._last_isolated[None], stamp]), axis=0)[1:]
        position = self._samples_seen + np.arange(n_samples)
        excluded = (position[:, None] - last) < self._readmit_samples  # (N, n_g)
        if n_samples:
            self._last_isolated = last[-1].copy()
        previous = np.zeros(n_gyros, dtype=bool)
        previous[self.excluded_gyros] = True
        stacked = np.vstack([previous[None], excluded])
        changes = np.flatnonzero(np.any(stacked[1:] != stacked[:-1], axis=1))
        rate = np.empty((n_samples, 3))
        bounds = [0, *changes.tolist(), n_samples]
        state = previous
        for start, stop in pairwise(bounds):
            if stop <= start:
                continue
            now = excluded[start]
            for sensor in np.flatnonzero(now & ~state):
                self.gyro_events.append(
                    {"sample": int(position[start]), "excluded": self.gyro_ids[sensor]}
                )
            for sensor in np.flatnonzero(state & ~now):
                self.gyro_events.append(
                    {"sample": int(position[start]), "readmitted": self.gyro_ids[sensor]}
                )
            state = now
            rate[start:stop] = gyro[start:stop] @ self._estimator_without(now).T
        self.excluded_gyros = np.flatnonzero(state).tolist()
        return rate

    def _estimator_without(self, excluded: np.ndarray) -> np.ndarray:
        """Least-squares rate estimator (3, n_g) of the gyros not ``excluded`` (cached); the
        full one if the rest do not span 3 axes."""
        key = frozenset(np.flatnonzero(excluded).tolist())
        if not key:
            return self._full_estimator
        if key not in self._estimators:
            active = np.flatnonzero(~excluded)
            estimator = self._full_estimator
            if active.size >= 3 and np.linalg.matrix_rank(self.gyro_H[active]) == 3:
                estimator = np.zeros((3, len(self.gyro_ids)))
                estimator[:, active] = least_squares_matrix(self.gyro_H[active])
            if len(self._estimators) > 1024:
                self._estimators.clear()
            self._estimators[key] = estimator
        return self._estimators[key]

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
        self.mapping_alarms = self.mapping_test == "alarm"
        self.mapping_report = _MappingReport()
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
        gyro = array.select(calibration.gyro, "gyro")
        reference = gyro @ self._estimator.T  # fault-free window: every gyro
        body = self._body_accel(calibration)
        self.calibration_motion = check_motion(reference, body)

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

    def _fit_input_test(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Step 8: leave-one-out accelerometer residuals and the CUSUM threshold.

        The residual model (rigid body with lever arms) is
        :class:`~imufdi_cli.detectors.noise_glr.NoiseGlrDetector`'s (accelerometers only).
        Each residual minus the mean of its ``INPUT_MEAN_S`` previous samples
        (:func:`.cusum.local_mean_residual`) is standardized by its variance, estimated on
        the calibration window robustly (Huber's proposal 2 at the clip, noise-glr's
        ``robust_scale``). The per-channel level is the Šidák share over the tested
        channels of ``alpha`` (``alpha / 2`` when the mapping test alarms too); the
        threshold comes from :func:`.cusum.cusum_threshold` (simulated null, seeded by
        ``seed``). Arrays whose accelerometers have no leave-one-out redundancy run the
        mapping test alone (at ``alpha``), noted in the metadata.
        """
        self._input = None
        self.input_note = "off (input_test=false)"
        self.mapping_alpha = self.alpha
        if not self.input_test:
            return
        glr = NoiseGlrDetector(alpha=self.alpha, types="accel")
        try:
            glr.fit(calibration, array)
        except CalibrationError as err:
            self.input_note = f"not run: {err}"
            return
        if "accel" not in glr.models:
            self.input_note = "not run: no redundant accelerometers"
            return
        model = glr.models["accel"]
        share = self.alpha / 2.0 if self.mapping_alarms else self.alpha
        self.input_mean_window = max(1, round(INPUT_MEAN_S * array.rate_hz))
        residuals = glr._residuals("accel", model, calibration)
        centred = local_mean_residual(residuals, self.input_mean_window)[self.input_mean_window :]
        if centred.shape[0] < 20:
            self.input_note = "not run: calibration window too short for the input test"
            return
        self._input = glr
        self.mapping_alpha = share
        moments = clipped_square_moments(INPUT_DESIGN.clip, 0.0)
        scale = robust_scale(centred, INPUT_DESIGN.clip, moments[0])
        self.input_scale = np.where(model.testable & (scale > 0), scale, 1.0)  # (n,), (m/s^2)^2
        self._input_past = np.zeros((0, model.operator.shape[0]))
        n_tested = int(model.testable.sum())
        self.input_level = -math.expm1(math.log1p(-share) / n_tested)
        self.input_margin = (
            INPUT_RELEASE_S
            * array.rate_hz
            * (INPUT_DESIGN.offset - INPUT_DESIGN.gain)  # |null drift| per sample
        )
        self.input_threshold = cusum_threshold(
            self.input_level,
            INPUT_DESIGN,
            self.input_margin,
            model.calibration_dof,
            np.random.default_rng([self.seed, 0x1C5]),
            mean_window=self.input_mean_window,
        )
        self.input_note = "on"
        self._input_state = np.zeros(model.operator.shape[0])
        self._input_window = MovingWindow(
            max(1, round(self.window_s * array.rate_hz)), model.operator.shape[0]
        )

    def _input_statistics(self, block: ImuBlock) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Step 8 on one block: CUSUM (N, n_accel) (NaN for untested channels), windowed
        mean of z^2 (N, n_accel) and the added noise std estimate (N, n_accel), m/s^2."""
        assert self._input is not None
        model = self._input.models["accel"]
        residuals = self._input._residuals("accel", model, block)  # (N, n)
        z = local_mean_residual(residuals, self.input_mean_window, self._input_past)
        z /= np.sqrt(self.input_scale)
        self._input_past = np.concatenate([self._input_past, residuals])[-self.input_mean_window :]
        increments = INPUT_DESIGN.increments(z)
        increments[:, ~model.testable] = 0.0
        cusum, self._input_state = run_cusum(
            increments, self._input_state, self.input_threshold + self.input_margin
        )
        cusum[:, ~model.testable] = np.nan
        sums, counts = self._input_window.push(np.where(np.isnan(z), 1.0, np.square(z)))
        energy = sums / counts[:, None]  # variance ratio of the recent residuals
        # added variance: (energy - 1) x the nominal variance, scale / (1 + 1/W)
        nominal = self.input_scale / (1.0 + 1.0 / self.input_mean_window)
        added = np.sqrt(np.maximum(energy - 1.0, 0.0) * nominal)
        added[:, ~model.testable] = np.nan
        return cusum, energy, added

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
        (N, 3) (step 3)."""
        return predicted - reference[:, None, :]  # type: ignore[no-any-return]

    def _axis_gains(self, windows: np.ndarray) -> np.ndarray:
        """Linearised noise gains of the whitened mapping residual, per IMU axis (step 6).

        ``G[n, k, a, c] = sum_lags ((K_c * J_c) . R_k[:, a])^2``, J = d CNN_c / d input
        (rad/s per m/s^2, body frame) of window n of IMU k, K_c the whitening kernel
        ``[1, -phi_c1, .., -phi_cp]`` convolved along the lags: white noise of variance
        delta on IMU axis a adds ``delta G[.., a, c]`` to the variance of whitened
        component c.

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
        kernel = np.concatenate([np.ones((3, 1)), -self.ar_coefficients], axis=1)  # (c, p+1)
        p = kernel.shape[1] - 1
        length = mp.input_length
        for lo in range(0, flat.shape[0], 2048):  # bounded memory
            jac = self.network.input_gradients(flat[lo : lo + 2048]) * scale  # (b, c, L, 3)
            directed = np.einsum("bclj,bja->bacl", jac, rotations[lo : lo + 2048])
            filtered = np.zeros((*directed.shape[:3], length + p))
            for i in range(p + 1):  # y(t - i) reads the samples i earlier
                filtered[..., p - i : p - i + length] += kernel[:, i, None] * directed
            gains[lo : lo + 2048] = np.sum(filtered**2, axis=3)
        return gains.reshape(n, m, 3, 3)

    @staticmethod
    def _ratio_to_others(energy: np.ndarray) -> np.ndarray:
        """``E_k / mean_{j != k} E_j`` along axis 1 (step 4)."""
        m = energy.shape[1]
        others = (energy.sum(axis=1, keepdims=True) - energy) / (m - 1)
        return energy / others  # type: ignore[no-any-return]

    def _calibrate_residuals(self, body: np.ndarray, reference: np.ndarray) -> None:
        """Whitening filter, residual statistics and energy-ratio threshold (steps 3-5) on
        the whole calibration window."""
        assert self.array is not None and self.mapping is not None and self.network is not None
        length = self.input_length
        windows = input_windows(body, length)  # (W, m, L, 3)
        residual = self._residuals(self._predict(windows), reference[length - 1 :])
        p = self.whiten
        self.window_samples = max(1, round(self.window_s * self.array.rate_hz))
        w = self.window_samples
        if residual.shape[0] - p < 2 * w or residual.shape[0] < 4 * p:
            raise CalibrationError(
                f"cnn-map: {residual.shape[0]} calibration residuals cannot fit an order-{p}"
                f" whitening filter and a {w}-sample energy window; use a longer --calibrate"
                " window"
            )
        # Step 3: AR(p) per component, least squares pooled over IMUs
        self.ar_coefficients = np.stack(
            [fit_autoregression(residual[:, :, c], p) for c in range(3)]
        ).reshape(3, p)
        whitened = whiten(residual, self.ar_coefficients)  # (W - p, m, 3)
        self.residual_mean = whitened.mean(axis=0)  # (m, 3)
        centred = whitened - self.residual_mean
        self.residual_variance = centred.var(axis=0).mean(axis=0)  # (3,) shared by IMUs
        if not np.all(self.residual_variance > 0):
            raise CalibrationError("cnn-map: zero residual variance; check the calibration window")
        squared = (centred**2 / self.residual_variance).mean(axis=2)  # (W - p, m)
        cumulative = np.concatenate([np.zeros((1, squared.shape[1])), np.cumsum(squared, axis=0)])
        energies = (cumulative[w:] - cumulative[:-w]) / w  # (W - p - w + 1, m)
        ratios = self._ratio_to_others(energies)
        # Step 5: gamma law of the pooled energy ratios, Šidák level over the m IMUs
        # (fitting it on the held-out windows alone was tried: 1.5-24 alpha, worse)
        mean = float(ratios.mean())
        self.gamma_shape = gamma_shape(ratios.ravel())
        m = len(self.tested)
        self.imu_level = -math.expm1(math.log1p(-self.mapping_alpha) / m)
        counts = np.arange(1, w + 1, dtype=np.float64)
        shapes = self.gamma_shape * counts / w
        self.thresholds = gamma_distribution.ppf(1.0 - self.imu_level, shapes, scale=mean / shapes)
        self.calibration_alarm_rate = float(np.mean(ratios.max(axis=1) > self.thresholds[-1]))
        self.residual_rms = float(np.sqrt(np.mean(residual**2)))
        self._energy_window = MovingWindow(w, m * 3 + m * 9)
        self._tail = np.zeros((0, m, 3))
        self._residual_tail = np.zeros((0, m, 3))
        self._episode_imu = -1
        self._episode_sums = (np.zeros(3), np.zeros(3))
        self._samples_seen = 0

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

    def _mapping_block(self, block: ImuBlock) -> DetectionBlock:
        """Steps 1-7 on one block: the mapping test's own output (statistic max_k R_k
        against its threshold, isolation, amplitude, scores); stream state is kept."""
        assert self.network is not None and self.array is not None
        assert block.accel is not None
        n_samples = len(block)
        m = len(self.tested)
        reference = self._reference_rate(block)
        body = self._body_accel(block)
        joined = np.concatenate([self._tail, body], axis=0)
        length = self.input_length
        p = self.whiten
        n_full = joined.shape[0] - length + 1  # windows ending in this block
        # before the first whitened residual: calibrated mean energy, no sensitivity
        squared = np.ones((n_samples, m, 3))
        sensitivity = np.zeros((n_samples, m, 3, 3))
        if n_full > 0:
            windows = input_windows(joined, length)
            residual = self._residuals(self._predict(windows), reference[n_samples - n_full :])
            joined_residual = np.concatenate([self._residual_tail, residual], axis=0)
            n_new = min(joined_residual.shape[0] - p, n_full)
            if n_new > 0:
                whitened = whiten(joined_residual[-(n_new + p) :], self.ar_coefficients)
                squared[n_samples - n_new :] = (
                    whitened - self.residual_mean
                ) ** 2 / self.residual_variance
                gains = self._axis_gains(windows[n_full - n_new :])  # (n_new, m, axis, c)
                # Step 6: S[a, c] = G[a, c] / v_c (energy per added variance)
                sensitivity[n_samples - n_new :] = gains / self.residual_variance
            self._residual_tail = joined_residual[max(0, joined_residual.shape[0] - p) :]
        self._tail = joined[joined.shape[0] - (length - 1) :]
        stacked = np.concatenate(
            [squared.reshape(n_samples, -1), sensitivity.reshape(n_samples, -1)], axis=1
        )
        sums, counts = self._energy_window.push(stacked)
        means = sums / counts[:, None]
        component = means[:, : m * 3].reshape(n_samples, m, 3)  # (N, m, c)
        window_sensitivity = means[:, m * 3 :].reshape(n_samples, m, 3, 3)  # (N, m, a, c)
        ratio = self._ratio_to_others(component.mean(axis=2))  # R_k, (N, m)
        best_imu = np.argmax(ratio, axis=1)
        rows = np.arange(n_samples)
        statistic = ratio[rows, best_imu]
        threshold = self.thresholds[counts - 1]
        alarm = statistic > threshold
        # Step 6: per-axis least-squares fit of the excess component energy ratios
        excess = self._ratio_to_others(component) - 1.0  # (N, m, c)
        projection = np.einsum("nkc,nkac->nka", excess, window_sensitivity)  # x . S_a
        norm2 = np.einsum("nkac,nkac->nka", window_sensitivity, window_sensitivity)
        safe = np.where(norm2 > 0, norm2, 1.0)
        delta = np.where(norm2 > 0, projection / safe, 0.0)  # added variance, (m/s^2)^2
        scores = np.full((n_samples, self.n_accel), np.nan)
        scores[:, self.sensor_of.ravel()] = np.sqrt(np.maximum(delta, 0.0)).reshape(n_samples, -1)
        best_axis = self._episode_axes(
            alarm, best_imu, projection[rows, best_imu], norm2[rows, best_imu]
        )
        return DetectionBlock(
            statistic=statistic,
            threshold=threshold,
            alarm=alarm,
            isolated=np.where(alarm, self.sensor_of[best_imu, best_axis], NO_ISOLATION).astype(
                np.int32
            ),
            amplitude=np.where(alarm, statistic, np.nan),
            scores=scores,
        )

    def _episode_axes(
        self, alarm: np.ndarray, imu: np.ndarray, projection: np.ndarray, norm2: np.ndarray
    ) -> np.ndarray:
        """Accelerometer axis of the isolated IMU from the evidence of the whole alarm
        episode (step 6): ``x . S_a`` and ``|S_a|^2`` are summed over the samples since the
        alarm on this IMU began, and the axis with the best fit ``(sum x.S_a)^2 /
        sum |S_a|^2`` (positive sum) is chosen. State carries over blocks.

        Parameters
        ----------
        alarm : ndarray, shape (N,), bool, N >= 1
        imu : ndarray, shape (N,), int
            Most significant IMU per sample.
        projection, norm2 : ndarray, shape (N, 3)
            ``x . S_a`` and ``|S_a|^2`` of that IMU's axes.

        Returns
        -------
        ndarray, shape (N,), int: axis per sample (meaningful where ``alarm``).
        """
        previous_alarm = np.concatenate([[self._episode_imu >= 0], alarm[:-1]])
        previous_imu = np.concatenate([[self._episode_imu], imu[:-1]])
        starts = alarm & ~(previous_alarm & (previous_imu == imu))
        segment = np.cumsum(starts)  # 0: the episode carried over from the last block
        start_rows = np.flatnonzero(starts)
        sums = []
        for values, carried in (
            (projection, self._episode_sums[0]),
            (norm2, self._episode_sums[1]),
        ):
            masked = np.where(alarm[:, None], values, 0.0)
            cumulative = np.cumsum(masked, axis=0)
            base = np.empty((start_rows.size + 1, 3))
            base[0] = -carried
            base[1:] = np.where(
                (start_rows > 0)[:, None], cumulative[np.maximum(start_rows - 1, 0)], 0.0
            )
            sums.append(cumulative - base[segment])
        total_projection, total_norm2 = sums
        safe = np.where(total_norm2 > 0, total_norm2, 1.0)
        fit = np.where((total_projection > 0) & (total_norm2 > 0), total_projection**2 / safe, 0.0)
        if alarm[-1]:
            self._episode_imu = int(imu[-1])
            self._episode_sums = (total_projection[-1].copy(), total_norm2[-1].copy())
        else:
            self._episode_imu = -1
            self._episode_sums = (np.zeros(3), np.zeros(3))
        return np.argmax(fit, axis=1)  # type: ignore[no-any-return]

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
            from imufdi_cli.fileio import open_atomic

            with open_atomic(path) as handle:
                handle.write(self.mapping.to_npz_bytes())
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
            "whiten": self.whiten,
            "input_test": self.input_test,
            "mapping_test": self.mapping_test,
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

    def _report_metadata(self) -> dict[str, Any]:
        """Samples and episodes over the mapping test's threshold so far (JSON-ready)."""
        report = self.mapping_report
        ids = self.array.sensor_ids("accel") if self.array is not None else []
        return {
            "samples": report.samples,
            "over_threshold": report.over,
            "rate": report.over / report.samples if report.samples else 0.0,
            "episodes": report.episodes,
            "first_over_sample": report.first_over,
            "max_statistic_over_threshold": report.max_ratio,
            "by_sensor": {ids[k]: v for k, v in sorted(report.by_sensor.items())},
        }

    def _input_metadata(self) -> dict[str, Any]:
        """Step 8 calibration (JSON-ready)."""
        info: dict[str, Any] = {"status": self.input_note}
        if self._input is None:
            return info
        model = self._input.models["accel"]
        info.update(
            {
                "design_variance_ratio": INPUT_DESIGN.ratio,
                "mean_window_samples": int(self.input_mean_window),
                "clip_sigma": INPUT_DESIGN.clip,
                "channel_level": float(self.input_level),
                "threshold": float(self.input_threshold),
                "cap_above_threshold": float(self.input_margin),
                "lever_arm": bool(model.lever_arm),
                "tested": model.testable.tolist(),
                "residual_sigma": np.sqrt(
                    self.input_scale / (1.0 + 1.0 / self.input_mean_window)
                ).tolist(),
                "calibration_dof": float(model.calibration_dof),
            }
        )
        return info
