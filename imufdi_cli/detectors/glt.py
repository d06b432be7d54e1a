"""GLT: generalized likelihood test on the parity vector, with reconfiguration.

Li et al., Micromachines 17(3):374, 2026, §2.1. Per sensor type s (gyros and
accelerometers are separate tests) with measurement matrix H (n, 3), per-sensor noise sigma
and per-sensor bias b (from a fault-free calibration window):

- whitened measurements ``m_w = (m - b) / sigma``, ``H_w = H / sigma`` (so the noise is white
  with unit variance), Potter's parity matrix ``V`` of ``H_w`` (:mod:`.parity`), ``p = V m_w``;
- detection (eq. 5): ``D_FD = p^T (V V^T)^-1 p`` against ``T_D = chi2_{1-alpha}(n - 3)``
  when sigma and bias are known; estimated from N calibration samples, sigma and bias
  make D_FD heavier-tailed (1.3-1.4 alpha at N = 200 on 48 gyros), so T_D is the
  two-moment ``g chi2_{1-alpha}(h)`` of :func:`.parity.estimated_sigma_threshold`;
- isolation (eq. 6): ``D_FI,i = (p^T (V V^T)^-1 v_i)^2 / (v_i^T (V V^T)^-1 v_i)``, isolated
  sensor ``argmax_i D_FI,i``;
- amplitude (eq. 7): ``f_i = p^T (V V^T)^-1 v_i / (v_i^T (V V^T)^-1 v_i)``, times sigma_i (SI).

V is orthonormal, so with the projector ``P = V^T V = I - H_w (H_w^T H_w)^-1 H_w^T`` and
the whitened residual ``r = P m_w = m_w - H_w x_hat`` (``x_hat = H_w^+ m_w``, the weighted
least-squares estimate): ``D_FD = |r|^2``, ``p^T v_i = r_i``, ``v_i^T v_i = P_ii``. Two thin
products per block, (N, n) x (n, 3) and (N, 3) x (3, n), give every statistic (the same
x_hat serves the monitoring of excluded sensors).

Beyond the paper (all optional):

- ``persistence``: an alarm needs that many consecutive samples over the threshold;
- ``confirm``: an isolation is reported once the same isolable sensor has been the argmax
  on that many consecutive over-threshold samples;
- ``reconfigure``: after a confirmed isolation the sensor is removed, V rebuilt from the
  remaining sensors (threshold dof n' - 3) and the removed sensor monitored against the
  least-squares estimate of the remaining ones: normalized residual
  ``z_j = (m_w,j - h_w,j x_hat) / sqrt(1 + h_w,j (H_w'^T H_w')^-1 h_w,j^T)`` with
  ``z_j^2`` against ``chi2_{1-alpha}(1)``, so the alarm stays on while its fault lasts;
- ``window``: moving average of the whitened measurements over w samples (k < w at the
  start); statistics are multiplied by k so that they stay chi2(n - 3) / chi2(1).

- ``jitter`` (default on): when the array config has a sampling-time jitter
  ``[jitter] <type> = sigma_t`` (``imufdi calibrate`` fits it), the noise covariance in
  motion is ``(1 + A_t) I`` in whitened units with ``A_t = sigma_t^2 |ydot_w,t|^2 / n``
  (:mod:`.jitter`): every statistic (D_FD, D_FI,i, the excluded sensors' z_j^2) is divided
  by ``1 + A_t`` (its mean over ``window``), so the level holds in motion at the price of
  sensitivity there. No jitter in the config: unchanged.
- ``lever_arm`` (default on): accelerometers at different positions of a rigid body
  measure ``f_0 + K r_k`` (:mod:`.rigid`, eq. 1), so H is augmented with the observable
  lever-arm columns (``[H | B]``, q = 3 + 6 for a planar array, 3 + 9 in 3-D) and the parity
  space (n - q dimensions) is blind to every rigid motion; without it, rotation of a
  distributed array is alarmed as a fault. No effect on gyros or on co-located IMUs.

Isolation is impossible for a sensor whose fault direction v_i is parallel to another
(e.g. 2 co-aligned IMUs): an alarm whose argmax is such a sensor reports NOT_ISOLABLE.
Sensor types with fewer than 4 sensors have no parity space: they are not tested (listed
under ``untested`` in :meth:`GltDetector.metadata`); if no type can be tested, ``fit``
raises DetectorConfigError.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from imufdi_cli.array import SENSOR_TYPES, ArrayConfig
from imufdi_cli.detectors.base import (
    ALPHA,
    FALSE_ALARMS,
    NO_ISOLATION,
    NOT_ISOLABLE,
    DetectionBlock,
    DetectorBase,
    Param,
)
from imufdi_cli.detectors.budget import (
    HOLD,
    SPATIAL_TYPES,
    ParityBudget,
    check_hold,
    reference_tau,
)
from imufdi_cli.detectors.tracking import TRACK_BIAS, BiasTracker
from imufdi_cli.errors import (
    ArrayConfigError,
    ArrayTooSmallError,
    CalibrationError,
    DetectorConfigError,
    InputDataError,
)
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.jitter import MotionInflation
from imufdi_cli.maths.parity import (
    estimated_sigma_threshold,
    isolable_sensors,
    parity_matrix,
    residual_sigma,
    residuals,
    sigma_estimate_variance,
    whiten,
)
from imufdi_cli.maths.quantiles import chi2
from imufdi_cli.maths.quantiles import f as f_distribution
from imufdi_cli.maths.rigid import accel_design

#: Minimum number of calibration samples.
MIN_CALIBRATION_SAMPLES = 10
#: Fewest sensors left after a reconfiguration (keeps one parity dimension).
MIN_ACTIVE_SENSORS = 4


def _check_types(value: str) -> str | None:
    if value == "auto":
        return None
    for item in value.split(","):
        if item.strip() not in SENSOR_TYPES:
            return f"unknown sensor type {item.strip()!r}; valid: auto or a list of " + ", ".join(
                SENSOR_TYPES
            )
    return None


def _run_lengths(flag: np.ndarray, carry: int) -> np.ndarray:
    """Length of the run of True ending at each sample (0 where False); ``carry`` continues
    a run from the previous block."""
    index = np.arange(flag.size)
    last_false = np.maximum.accumulate(np.where(flag, -1, index))
    runs = index - last_false
    runs[last_false < 0] += carry
    return np.where(flag, runs, 0)


def _equal_run_lengths(key: np.ndarray, previous_key: int, carry: int) -> np.ndarray:
    """Length of the run of equal ``key`` values ending at each sample, continuing a run of
    ``previous_key`` of length ``carry`` from the previous block."""
    index = np.arange(key.size)
    change = np.empty(key.size, dtype=bool)
    if key.size:
        change[0] = key[0] != previous_key
        change[1:] = key[1:] != key[:-1]
    start = np.maximum.accumulate(np.where(change, index, -1))
    runs = index - start + 1
    continued = start < 0
    runs[continued] = index[continued] + 1 + carry
    return runs


@dataclass
class _Configuration:
    """Active sensors of one type and everything derived from them (rebuilt on reconfig)."""

    active: np.ndarray  # (n_a,) global sensor indices
    excluded: np.ndarray  # (n_x,) global sensor indices, in exclusion order
    all_active: bool  # active == every sensor, in order (no gather needed)
    estimator_t: np.ndarray  # (n_a, 3) (H_wa^+)^T: x_hat = m_a @ estimator_t
    h_active_t: np.ndarray  # (3, n_a) H_wa^T
    h_excluded_t: np.ndarray  # (3, n_x) H_wx^T
    inverse_energy: np.ndarray  # (n_a,) 1 / (v_i^T v_i) = 1 / P_ii
    isolable: np.ndarray  # (n_a,) bool
    threshold: float  # g chi2_{1-alpha}(h): chi2_{1-alpha}(n_a - q) corrected for estimation
    excluded_scale: np.ndarray  # (n_x,) 1/sqrt(1 + h (H^T H)^-1 h^T)
    removable: np.ndarray  # (n_a,) bool: excluding it leaves a parity space of full rank

    @classmethod
    def build(
        cls,
        h_white: np.ndarray,
        active: np.ndarray,
        excluded: np.ndarray,
        alpha: float,
        scale_variance: np.ndarray | None = None,
        mean_samples: float = float("inf"),
    ) -> _Configuration:
        h_active = h_white[active]
        V = parity_matrix(h_active)  # Potter's V, (n_a - q, n_a)
        energy = np.einsum("ij,ij->j", V, V)  # v_i^T v_i = P_ii
        h_excluded = h_white[excluded]  # (n_x, 3)
        normal_inverse = np.linalg.inv(h_active.T @ h_active)
        variance = 1.0 + np.einsum("ij,jk,ik->i", h_excluded, normal_inverse, h_excluded)
        q = h_active.shape[1]
        removable = np.zeros(active.size, dtype=bool)
        if active.size - 1 >= max(MIN_ACTIVE_SENSORS, q + 1):
            # every leave-one-out H stacked (n_a, n_a - 1, q): one batched SVD, the same
            # LAPACK call on each matrix as one at a time (so the same singular values)
            n_active = active.size
            keep = np.arange(n_active - 1)[None, :]
            rows = keep + (keep >= np.arange(n_active)[:, None])  # row i skips sensor i
            singular = np.linalg.svd(h_active[rows], compute_uv=False)
            removable = singular[:, -1] > 1e-9 * singular[:, 0]
        return cls(
            active=active,
            excluded=excluded,
            all_active=bool(excluded.size == 0 and np.array_equal(active, np.arange(len(h_white)))),
            estimator_t=np.linalg.pinv(h_active).T.copy(),
            h_active_t=h_active.T.copy(),
            h_excluded_t=h_excluded.T.copy(),
            inverse_energy=1.0 / energy,
            isolable=isolable_sensors(V),
            threshold=estimated_sigma_threshold(
                h_active,
                alpha,
                None if scale_variance is None else scale_variance[active],
                mean_samples,
            )[0],
            excluded_scale=1.0 / np.sqrt(variance),
            removable=removable,
        )


@dataclass
class _TypeState:
    """Calibration and streaming state of one sensor type."""

    sensor_type: str
    sensor_ids: list[str]
    imu_index: np.ndarray  # (n,) IMU of each sensor (ArrayConfig.sensor_index)
    axis_index: np.ndarray  # (n,) axis 0..2 of each sensor
    H: np.ndarray  # (n, q): directions (n, 3), then lever-arm columns (q = 3 without)
    sigma: np.ndarray  # (n,) SI
    sigma_from_config: bool  # sigma from the array config (else the calibration window)
    bias: np.ndarray  # (n,) SI
    h_white: np.ndarray  # (n, q)
    inverse_sigma: np.ndarray  # (n,) 1 / sigma
    bias_white: np.ndarray  # (n,) bias / sigma
    scale_variance: np.ndarray | None  # (n,) Var(sigma_hat^2)/sigma^4; None: sigma known
    mean_samples: float  # samples of the bias estimate (inf: no bias removed)
    full_triads: bool  # sensors are imu0.x, imu0.y, imu0.z, imu1.x, ... (all axes, in order)
    config: _Configuration
    history: np.ndarray  # (<= w-1, n) last whitened samples, for the moving average
    inflation: MotionInflation | None = None  # motion (jitter) variance factor, None: off
    budget: ParityBudget | None = None  # sequential decisions under a false-alarm budget
    exceed_run: int = 0
    candidate: int = NO_ISOLATION
    candidate_run: int = 0
    events: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class _Segment:
    statistic: np.ndarray
    alarm: np.ndarray
    isolated: np.ndarray
    amplitude: np.ndarray
    scores: np.ndarray
    exceed_runs: np.ndarray
    keys: np.ndarray
    key_runs: np.ndarray
    event: int | None  # local index of the confirmed isolation that triggers reconfiguration


class GltDetector(DetectorBase):
    """Generalized likelihood test on the parity vector (Li et al. 2026, §2.1).

    Parameters
    ----------
    alpha : float
        False-alarm level of each per-sample test (default 0.01).
    persistence : int
        Consecutive samples over the threshold needed to raise the alarm (1 = plain test).
    confirm : int
        Consecutive over-threshold samples with the same argmax sensor needed to report
        (and, with ``reconfigure``, exclude) it; 1 = the paper's per-sample isolation.
    reconfigure : bool
        Remove a confirmed faulty sensor, rebuild V, keep monitoring it.
    window : int
        Moving average of the whitened measurements over this many samples (1 = none).
    sigma_source : {"auto", "calibration", "config"}
        Per-sensor sigma from the calibration residuals, or from the array config (each
        IMU's ``<type>_noise``, else ``noise.<type>``). ``auto``: the IMUs' own
        ``<type>_noise`` when every sensor of the type has one (what ``imufdi calibrate``
        measures over many orientations), else the calibration window.
    bias : bool
        Remove per-sensor biases (calibration residual means); false = plain GLT.
    types : str
        ``auto`` (every type with >= 4 sensors) or a comma list such as ``gyro``.
    lever_arm : bool
        Model rigid-body lever arms between accelerometers (positions from the array
        config, :mod:`.rigid`).
    jitter : bool
        Widen the tests in motion by the array config's sampling-time jitter
        (``[jitter]``, :mod:`.jitter`); no effect when the config has none.
    """

    name: ClassVar[str] = "glt"
    #: Causal: the row of sample i depends on samples up to i only.
    lookahead_samples: int = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "alpha": ALPHA,
        "persistence": Param("int", 1, "consecutive samples over threshold for an alarm", low=1),
        "confirm": Param(
            "int", 1, "consecutive samples isolating the same sensor to confirm it", low=1
        ),
        "reconfigure": Param("bool", False, "exclude a confirmed faulty sensor and rebuild V"),
        "window": Param("int", 1, "moving average of the parity vector, samples", low=1),
        "sigma_source": Param(
            "choice",
            "auto",
            "per-sensor sigma from the calibration window or from the array config noise"
            " (auto: the per-IMU noise imufdi calibrate measured, when present)",
            choices=("auto", "calibration", "config"),
        ),
        "bias": Param("bool", True, "remove per-sensor biases found in the calibration window"),
        "track_bias": TRACK_BIAS,
        "false_alarms": FALSE_ALARMS,
        "hold": HOLD,
        "lever_arm": Param(
            "bool",
            True,
            "model rigid-body lever arms between accelerometers (IMU positions)",
        ),
        "types": Param(
            "str", "auto", "sensor types to test: auto or e.g. gyro,accel", check=_check_types
        ),
        "jitter": Param(
            "bool",
            True,
            "widen the test in motion by the array config's sampling-time jitter (if any)",
        ),
    }

    def __init__(
        self,
        alpha: float = 0.01,
        persistence: int = 1,
        confirm: int = 1,
        reconfigure: bool = False,
        window: int = 1,
        sigma_source: str = "auto",
        bias: bool = True,
        types: str = "auto",
        track_bias: float | None = None,
        false_alarms: float = 0.0,
        lever_arm: bool = True,
        jitter: bool = True,
        hold: str = "10s",
    ) -> None:
        self.false_alarms = float(false_alarms)
        self.hold_s = check_hold("glt", hold, self.false_alarms)
        if self.false_alarms > 0:
            fixed = {
                "persistence": persistence != 1,
                "confirm": confirm != 1,
                "reconfigure": reconfigure,
                "window": window != 1,
            }
            given = [name for name, changed in fixed.items() if changed]
            if given:
                raise DetectorConfigError(
                    f"glt.{given[0]} applies to the per-sample test; with a false-alarm budget"
                    " glt decides sequentially (docs/algorithms/sequential.md): leave it out"
                )
        self.alpha = float(alpha)
        self.persistence = int(persistence)
        self.confirm = int(confirm)
        self.reconfigure = bool(reconfigure)
        self.window = int(window)
        self.sigma_source = sigma_source
        self.remove_bias = bool(bias)
        self.types = types
        self.lever_arm = bool(lever_arm)
        self.jitter = bool(jitter)
        # under a budget the bank's own reference follows the biases (frozen in alarms)
        self.reference_tau_s = reference_tau(track_bias)
        self.tracker = BiasTracker(
            0.0 if self.false_alarms > 0 or track_bias is None else track_bias
        )
        self.threshold_excluded = float(chi2.ppf(1.0 - self.alpha, 1))
        self._states: dict[str, _TypeState] = {}
        self._untested: dict[str, str] = {}
        self._samples_seen = 0

    # --- calibration ----------------------------------------------------------------

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Per-sensor sigma and bias of every tested sensor type from a fault-free block.

        Raises
        ------
        DetectorConfigError
            No sensor type has >= 4 sensors, a requested type is absent, or
            ``sigma_source=config`` without ``noise.<type>`` in the array config.
        CalibrationError
            Fewer than 10 calibration samples, non-finite data or a zero sigma.
        """
        designs = {s: self._design(array, s) for s in array.sensor_types()}
        self.tracker.fit(calibration, array, designs)
        if self.types == "auto":
            requested = array.sensor_types()
        else:
            requested = [item.strip() for item in self.types.split(",")]
        self._states.clear()
        self._untested.clear()
        self._samples_seen = 0
        for sensor_type in requested:
            n = array.n_sensors(sensor_type)
            if n < MIN_ACTIVE_SENSORS:
                self._untested[sensor_type] = (
                    f"{n} sensors: a parity test needs at least {MIN_ACTIVE_SENSORS}"
                )
                continue
            design = designs.get(sensor_type)
            if design is not None and n <= design.shape[1]:
                self._untested[sensor_type] = (
                    f"{n} sensors: with the lever-arm terms of these positions a parity test"
                    f" needs at least {design.shape[1] + 1} (or glt.lever_arm=false)"
                )
                continue
            self._states[sensor_type] = self._calibrate(calibration, array, sensor_type, design)
        if not self._states:
            counts = ", ".join(f"{s}: {array.n_sensors(s)}" for s in requested) or "none"
            raise ArrayTooSmallError(
                f"glt needs at least {MIN_ACTIVE_SENSORS} sensors of a type (parity space"
                f" n - 3 >= 1); this array has {counts}"
            )

    def _design(self, array: ArrayConfig, sensor_type: str) -> np.ndarray:
        """Measurement matrix of a type: H, with the lever-arm columns for accelerometers."""
        if sensor_type == "accel" and self.lever_arm:
            try:
                return accel_design(array, sensor_type)
            except ArrayConfigError:
                pass
        return array.measurement_matrix(sensor_type)

    def _calibrate(
        self,
        calibration: ImuBlock,
        array: ArrayConfig,
        sensor_type: str,
        design: np.ndarray | None = None,
    ) -> _TypeState:
        triads = calibration.get(sensor_type)
        if triads is None:
            raise CalibrationError(f"calibration window has no {sensor_type} data")
        values = array.select(triads, sensor_type)
        if values.shape[0] < MIN_CALIBRATION_SAMPLES:
            raise CalibrationError(
                f"calibration window has {values.shape[0]} samples; at least"
                f" {MIN_CALIBRATION_SAMPLES} are needed (use --calibrate START:END)"
            )
        if not np.all(np.isfinite(values)):
            raise CalibrationError(f"calibration window has non-finite {sensor_type} samples")
        H = array.measurement_matrix(sensor_type) if design is None else design
        imu_index, axis_index = array.sensor_index(sensor_type)
        n = H.shape[0]
        configured = array.sensor_noise(sensor_type)
        from_config = self.sigma_source == "config" or (
            self.sigma_source == "auto"
            and configured is not None
            and all(sensor_type in array.imus[k].noise for k in set(imu_index.tolist()))
        )
        if from_config:
            if configured is None:
                raise DetectorConfigError(
                    f"glt.sigma_source=config but the array config has no noise.{sensor_type}"
                    f" (nor {sensor_type}_noise on every IMU); add it or use"
                    " sigma_source=calibration"
                )
            sigma = configured
        else:
            sigma = residual_sigma(H, values)
        # Bias: the part of the calibration mean not explained by H (any LS fit gives the same
        # parity vectors, since V H = 0 for every subset of sensors).
        bias = residuals(H, values.mean(axis=0)[None, :])[0] if self.remove_bias else np.zeros(n)
        h_white = whiten(H, sigma)
        scale_variance = None if from_config else sigma_estimate_variance(H, sigma, values.shape[0])
        mean_samples = float(values.shape[0]) if self.remove_bias else float("inf")
        config = _Configuration.build(
            h_white,
            np.arange(n),
            np.zeros(0, dtype=np.intp),
            self.alpha,
            scale_variance,
            mean_samples,
        )
        # Excluded sensors: z^2 with the sensor's own estimated variance, F(1, nu) with
        # nu = 2 / Var(delta), and the bias error (1 + 1/N).
        if scale_variance is not None:
            nu = 2.0 / float(np.mean(scale_variance))
            excluded = float(f_distribution.ppf(1.0 - self.alpha, 1, nu))
        else:
            excluded = float(chi2.ppf(1.0 - self.alpha, 1))
        self.threshold_excluded = excluded * (1.0 + 1.0 / mean_samples)
        jitter_s = array.jitter.get(sensor_type, 0.0) if self.jitter else 0.0
        inflation = (
            MotionInflation(h_white, sigma, jitter_s, array.rate_hz, self.window)
            if jitter_s > 0
            else None
        )
        budget = None
        if self.false_alarms > 0:
            budget = ParityBudget(
                h_white,
                sigma,
                config.isolable,
                array.rate_hz,
                self.false_alarms,
                self.reference_tau_s,
                scale_variance=None if scale_variance is None else float(np.mean(scale_variance)),
                calibration_samples=values.shape[0],
                hold_s=self.hold_s,
                moving=inflation is not None and sensor_type in SPATIAL_TYPES,
            )
            budget.fit(values / sigma - bias / sigma)
        return _TypeState(
            sensor_type=sensor_type,
            sensor_ids=array.sensor_ids(sensor_type),
            imu_index=imu_index,
            axis_index=axis_index,
            H=H,
            sigma=sigma,
            sigma_from_config=from_config,
            bias=bias,
            h_white=h_white,
            inverse_sigma=1.0 / sigma,
            bias_white=bias / sigma,
            scale_variance=scale_variance,
            mean_samples=mean_samples,
            full_triads=bool(np.array_equal(imu_index * 3 + axis_index, np.arange(n))),
            config=config,
            history=np.zeros((0, n)),
            inflation=inflation,
            budget=budget,
        )

    # --- streaming ------------------------------------------------------------------

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """Test one block; one row per input sample for every tested sensor type."""
        if not self._states:
            raise DetectorConfigError("glt: call fit() before process()")
        block = self.tracker.apply(block)
        out: dict[str, DetectionBlock] = {}
        for sensor_type, state in self._states.items():
            triads = block.get(sensor_type)
            if triads is None:
                raise InputDataError(
                    f"block has no {sensor_type} data but glt was calibrated to test it"
                )
            if triads.shape[1] <= int(state.imu_index.max()):
                raise InputDataError(
                    f"block has {triads.shape[1]} IMUs but glt was calibrated on"
                    f" {int(state.imu_index.max()) + 1}"
                )
            if state.full_triads and triads.shape[1] * 3 == state.imu_index.size:
                values = triads.reshape(triads.shape[0], -1)  # every axis of every IMU: a view
            else:
                values = triads[:, state.imu_index, state.axis_index]
            out[sensor_type] = self._process_type(state, values, block.t_ns)
        self._samples_seen += len(block)
        return out

    def flush(self) -> dict[str, DetectionBlock]:
        """GLT is causal: nothing is held back."""
        return {s: DetectionBlock.empty(0, len(st.sensor_ids)) for s, st in self._states.items()}

    def _whitened_average(
        self, state: _TypeState, values: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Whitened (moving-averaged) measurements (N, n) and the averaged count k (N,)."""
        white = values * state.inverse_sigma
        white -= state.bias_white
        n_samples = white.shape[0]
        if self.window == 1:
            return white, np.ones(n_samples)
        history = state.history
        extended = np.concatenate([history, white], axis=0)
        cumulative = np.concatenate([np.zeros((1, white.shape[1])), np.cumsum(extended, axis=0)])
        ends = np.arange(history.shape[0] + 1, extended.shape[0] + 1)
        starts = np.maximum(ends - self.window, 0)
        counts = (ends - starts).astype(np.float64)
        averaged = (cumulative[ends] - cumulative[starts]) / counts[:, None]
        state.history = extended[-(self.window - 1) :].copy()
        return averaged, counts

    def _motion_factors(
        self, state: _TypeState, values: np.ndarray, t_ns: np.ndarray
    ) -> np.ndarray | None:
        """``1 + A_t`` (N,) of the jitter model, averaged over ``window`` (None: off)."""
        return None if state.inflation is None else state.inflation.factors(values, t_ns)

    def _process_type(
        self, state: _TypeState, values: np.ndarray, t_ns: np.ndarray
    ) -> DetectionBlock:
        n_samples, n = values.shape
        factors = self._motion_factors(state, values, t_ns)
        if state.budget is not None:
            white = values * state.inverse_sigma
            white -= state.bias_white
            return state.budget.process(white, factors)
        averaged, counts = self._whitened_average(state, values)
        pieces: list[DetectionBlock] = []
        start = 0
        while start < n_samples:
            config = state.config
            segment = self._segment(
                state,
                averaged[start:],
                counts[start:],
                None if factors is None else factors[start:],
            )
            stop = n_samples - start if segment.event is None else segment.event + 1
            pieces.append(
                DetectionBlock(
                    statistic=segment.statistic[:stop],
                    threshold=np.full(stop, config.threshold),
                    alarm=segment.alarm[:stop],
                    isolated=segment.isolated[:stop],
                    amplitude=segment.amplitude[:stop],
                    scores=segment.scores[:stop],
                )
            )
            state.exceed_run = int(segment.exceed_runs[stop - 1])
            state.candidate = int(segment.keys[stop - 1])
            state.candidate_run = int(segment.key_runs[stop - 1])
            if segment.event is not None:
                sensor = int(segment.isolated[segment.event])
                active = config.active[config.active != sensor]
                excluded = np.append(config.excluded, sensor).astype(np.intp)
                state.config = _Configuration.build(
                    state.h_white,
                    active,
                    excluded,
                    self.alpha,
                    state.scale_variance,
                    state.mean_samples,
                )
                state.candidate = NO_ISOLATION
                state.candidate_run = 0
                state.events.append(
                    {
                        "sample": self._samples_seen + start + segment.event,
                        "excluded": state.sensor_ids[sensor],
                        "active_sensors": int(active.size),
                    }
                )
            start += stop
        if not pieces:
            return DetectionBlock.empty(0, n)
        return pieces[0] if len(pieces) == 1 else DetectionBlock.concatenate(pieces)

    def _segment(
        self,
        state: _TypeState,
        averaged: np.ndarray,
        counts: np.ndarray,
        factors: np.ndarray | None = None,
    ) -> _Segment:
        """All statistics of a run of samples under the current configuration; ``factors``
        (N,): the jitter model's variance factors ``1 + A_t`` (None: 1)."""
        config = state.config
        n_samples, n = averaged.shape
        active_values = averaged if config.all_active else averaged[:, config.active]
        # r = P m_w = m_w - H_w x_hat: D_FD = |r|^2, D_FI,i = r_i^2 / P_ii (eqs. 5-6)
        x_hat = active_values @ config.estimator_t  # (N, 3), whitened LS estimate
        parity_residual = active_values - x_hat @ config.h_active_t
        amplitude_white = parity_residual * config.inverse_energy  # eq. 7, whitened units
        isolation_scores = parity_residual * amplitude_white
        statistic = np.einsum("ij,ij->i", parity_residual, parity_residual)
        if self.window > 1:
            statistic *= counts
            isolation_scores *= counts[:, None]
        if factors is not None:
            statistic /= factors
            isolation_scores /= factors[:, None]
        parity_exceed = statistic > config.threshold

        if config.all_active:
            scores = isolation_scores
        else:
            scores = np.full((n_samples, n), np.nan)
            scores[:, config.active] = isolation_scores
        best_local = np.argmax(isolation_scores, axis=1)
        best_sensor = config.active[best_local]
        best_isolable = config.isolable[best_local]

        exceed = parity_exceed.copy()
        excluded_alarm = np.zeros(n_samples, dtype=bool)
        excluded_best = np.full(n_samples, NO_ISOLATION, dtype=np.intp)
        excluded_amplitude = np.full(n_samples, np.nan)
        if config.excluded.size:
            # Excluded sensors against the LS estimate of the active ones (chi2, 1 dof)
            residual_white = averaged[:, config.excluded] - x_hat @ config.h_excluded_t
            normalized = residual_white * config.excluded_scale
            excluded_scores = normalized**2 * counts[:, None]
            if factors is not None:
                excluded_scores /= factors[:, None]
            scores[:, config.excluded] = excluded_scores
            worst = np.argmax(excluded_scores, axis=1)
            rows = np.arange(n_samples)
            excluded_alarm = excluded_scores[rows, worst] > self.threshold_excluded
            excluded_best = config.excluded[worst]
            excluded_amplitude = residual_white[rows, worst] * state.sigma[excluded_best]
            exceed |= excluded_alarm

        exceed_runs = _run_lengths(exceed, state.exceed_run)
        alarm = exceed_runs >= self.persistence

        keys = np.where(parity_exceed & best_isolable, best_sensor, NO_ISOLATION)
        key_runs = _equal_run_lengths(keys, state.candidate, state.candidate_run)
        confirmed = alarm & (keys >= 0) & (key_runs >= self.confirm)

        isolated = np.full(n_samples, NO_ISOLATION, dtype=np.int32)
        amplitude = np.full(n_samples, np.nan)
        show_excluded = alarm & excluded_alarm & ~confirmed
        isolated[show_excluded] = excluded_best[show_excluded]
        amplitude[show_excluded] = excluded_amplitude[show_excluded]
        not_isolable = alarm & parity_exceed & ~best_isolable & ~show_excluded
        isolated[not_isolable] = NOT_ISOLABLE
        isolated[confirmed] = best_sensor[confirmed]
        amplitude[confirmed] = (
            amplitude_white[confirmed, best_local[confirmed]] * state.sigma[best_sensor[confirmed]]
        )

        event: int | None = None
        if self.reconfigure and config.removable.any():
            hits = np.flatnonzero(confirmed & config.removable[best_local])
            if hits.size:
                event = int(hits[0])
        return _Segment(
            statistic=statistic,
            alarm=alarm,
            isolated=isolated,
            amplitude=amplitude,
            scores=scores,
            exceed_runs=exceed_runs,
            keys=keys,
            key_runs=key_runs,
            event=event,
        )

    # --- reporting ------------------------------------------------------------------

    def metadata(self) -> dict[str, Any]:
        """Parameters, calibration (sigma, bias in SI) and reconfiguration events."""
        types: dict[str, Any] = {}
        for sensor_type, state in self._states.items():
            config = state.config
            types[sensor_type] = {
                "sensor_ids": state.sensor_ids,
                "sigma": state.sigma.tolist(),
                "sigma_from": "array config" if state.sigma_from_config else "calibration",
                "bias": state.bias.tolist(),
                "threshold": config.threshold,
                "threshold_excluded": self.threshold_excluded,
                "active": [state.sensor_ids[i] for i in config.active],
                "excluded": [state.sensor_ids[i] for i in config.excluded],
                "not_isolable": [state.sensor_ids[i] for i in config.active[~config.isolable]],
                "lever_arm_columns": int(state.H.shape[1] - 3),
                "jitter_s": 0.0 if state.inflation is None else state.inflation.jitter_s,
                "reconfigurations": list(state.events),
            }
            if state.budget is not None:
                types[sensor_type]["threshold"] = state.budget.threshold
                types[sensor_type]["budget"] = state.budget.metadata()
        return {
            "detector": self.name,
            "params": {
                "alpha": self.alpha,
                "persistence": self.persistence,
                "confirm": self.confirm,
                "reconfigure": self.reconfigure,
                "window": self.window,
                "sigma_source": self.sigma_source,
                "bias": self.remove_bias,
                "types": self.types,
                "track_bias": self.reference_tau_s if self.false_alarms > 0 else self.tracker.tau_s,
                "false_alarms_per_hour": self.false_alarms * 3600.0,
                "lever_arm": self.lever_arm,
                "jitter": self.jitter,
            },
            "tracked_bias_change": self.tracker.metadata(),
            "types": types,
            "untested": dict(self._untested),
        }
