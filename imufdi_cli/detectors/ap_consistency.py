"""ap-consistency: IMU-to-IMU consistency held for a time, in the style of ArduPilot's
pre-arm INS checks.

ArduPilot (GPL-3.0), read for understanding, not copied: ``libraries/AP_Arming/AP_Arming.cpp``,
``AP_Arming::ins_accels_consistent`` and ``ins_gyros_consistent``:

- every accelerometer vector is compared with the primary's; the difference's z component is
  halved ("EKF is less sensitive to Z-axis error"); the limit is ``ARMING_ACCTHRESH``
  (``accel_error_threshold``, default ``AP_ARMING_ACCEL_ERROR_THRESHOLD`` = 0.75 m/s^2),
  three times larger for the third IMU onwards (``i >= 2``: "runs at a different
  temperature ... not used for accel data in the EKF");
- every gyro vector is compared with the primary's against 5 deg/s (``radians(5)``);
- an IMU fails once it has not passed for 10 s (``now - last_pass_ms > 10000``; newer
  releases reset one timer for all IMUs and require 10 s of continuous consistency before
  arming — the per-IMU form is the one that says which IMU disagrees).

Here, per sensor type and sample t, with W = diag(1, 1, z_weight) for accelerometers (I for
gyros), thresholds e_i and h = ``floor(hold * rate) + 1`` samples ("more than ``hold``
seconds since the last pass"):

    d_i(t) = |W (x_i(t) - ref_i(t))| / e_i              x in the body frame
    s_i(t) = min(d_i(t-h+1), ..., d_i(t))             (0 until h samples have been seen)
    alarm(t) = max_i s_i(t) > 1

``ref_i`` is the primary IMU (``reference=primary``, the firmware) or the mean of the other
IMUs (``reference=others``). ``s_i > 1`` exactly when IMU i failed on every one of the last h
samples; the statistic is ``max_i s_i`` and the threshold 1, so scaling the threshold scales
every e_i. Isolation (>= 3 IMUs; NOT_ISOLABLE with 2): with ``reference=primary``, the primary
when every other IMU fails (they all disagree with it), otherwise the failing IMU with the
largest s; with ``reference=others``, the failing IMU with the largest s. The reported sensor
is the isolated IMU's axis with the largest deviation from the mean of the other IMUs (in
its own frame), which is also the amplitude. ``bias=true`` removes each IMU's offset from
the array mean on the calibration window (the firmware's sensors are calibrated). Causal.

Under a false-alarm budget (``false_alarms`` > 0) the rule and the hold are unchanged and
every limit of a type is multiplied by one factor, chosen at fit time so that the IMUs'
calibrated white noise raises at most half the budget
(:func:`~imufdi_cli.detectors.firmware_budget.ap_limit_scale`: the exact run model of
independent differences); ``calibration_warnings`` says when the IMUs disagreed beyond that
noise on the processed log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.base import FALSE_ALARMS, DetectionBlock, Param
from imufdi_cli.detectors.firmware_budget import (
    BUDGET_SHARE,
    Disagreement,
    ap_episode_rate,
    ap_limit_scale,
    difference_noise,
    disagreement_warnings,
    outlier_fraction,
)
from imufdi_cli.detectors.vectors import (
    CausalImuCheck,
    TriadLayout,
    compared_layouts,
    imu_isolation,
    parse_vector_types,
)
from imufdi_cli.errors import CalibrationError, DetectorConfigError
from imufdi_cli.log import ImuBlock

REFERENCES: tuple[str, ...] = ("primary", "others")


def trailing_minimum(history: np.ndarray, values: np.ndarray, length: int) -> np.ndarray:
    """Minimum of each column over the last ``length`` rows, for every row of ``values``.

    The van Herk / Gil-Werman running minimum: the rows (after ``length - 1`` rows of +inf)
    are cut into blocks of ``length``; a window of ``length`` rows spans the end of one
    block and the start of the next, so its minimum is that of the first block's suffix
    minimum and the second's prefix minimum (two ``np.minimum.accumulate`` passes, about 3
    comparisons per value whatever ``length``). Minima are exact, so the result is the
    brute-force one to the bit; it needs no ``scipy.ndimage`` (``minimum_filter1d``: about
    0.5 s of CPU to import for every ``imufdi detect -d ap-consistency``). A NaN propagates to every window that holds it (``imufdi detect``
    replaces invalid samples before any detector sees them).

    Parameters
    ----------
    history : ndarray, shape (H, m)
        Rows before ``values`` (at most ``length - 1`` are used).
    values : ndarray, shape (N, m)
    length : int
        Window length h >= 1.

    Returns
    -------
    ndarray, shape (N, m)
        Row t: min over the h rows ending at t; rows whose window reaches before the start
        of ``history`` are the minimum of what is available.
    """
    if values.shape[0] == 0:
        return values.copy()
    extended = np.concatenate([history[-(length - 1) :] if length > 1 else history[:0], values])
    offset = extended.shape[0] - values.shape[0]
    m = extended.shape[1]
    blocks = -(-(extended.shape[0] + length - 1) // length)
    grid = np.full((blocks * length, m), np.inf)
    # the window of extended row t is grid[t : t + length] (length - 1 rows of +inf first)
    grid[length - 1 : length - 1 + extended.shape[0]] = extended
    grid = grid.reshape(blocks, length, m)
    prefix = np.minimum.accumulate(grid, axis=1).reshape(-1, m)
    suffix = np.minimum.accumulate(grid[:, ::-1], axis=1)[:, ::-1].reshape(-1, m)
    rows = np.arange(offset, extended.shape[0])
    return np.minimum(suffix[rows], prefix[rows + length - 1])


@dataclass
class _TypeState:
    layout: TriadLayout
    limits: np.ndarray  # (m,) e_i
    weight: np.ndarray  # (3,) W diagonal
    offsets: np.ndarray  # (m, 3)
    primary: int  # compared-IMU index of the primary
    history: np.ndarray  # (<= h - 1, m) normalised deviations of the last samples
    seen: int = 0
    scale: float = 1.0  # factor on the firmware limits (a false-alarm budget)
    budget: dict[str, Any] | None = None  # what set it
    disagreement: Disagreement | None = None  # the budget's model, checked on the data


class ApConsistencyDetector(CausalImuCheck):
    """ArduPilot pre-arm style IMU consistency check (module docstring); ``ap-consistency``."""

    name: ClassVar[str] = "ap-consistency"
    #: Causal: every row is decided on its own sample (the hold time is a delay, not look-ahead).
    lookahead_samples: ClassVar[int] = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "accel_threshold": Param(
            "acceleration",
            0.75,
            "accel vector difference limit (ARMING_ACCTHRESH, AP_ARMING_ACCEL_ERROR_THRESHOLD)",
            low=0.0,
            low_open=True,
        ),
        "gyro_threshold": Param(
            "angular_rate",
            math.radians(5.0),
            "gyro vector difference limit (ins_gyros_consistent: radians(5))",
            low=0.0,
            low_open=True,
        ),
        "hold": Param(
            "time", 10.0, "an IMU fails after this long without passing (10000 ms)", low=0.0
        ),
        "z_weight": Param(
            "float", 0.5, "weight of the accel difference's z component (0.5)", low=0.0
        ),
        "backup_factor": Param(
            "float",
            3.0,
            "accel limit multiplier for the third IMU onwards (i >= 2: x3)",
            low=0.0,
            low_open=True,
        ),
        "reference": Param(
            "choice",
            "primary",
            "compare each IMU with the primary (firmware) or with the mean of the others",
            choices=REFERENCES,
        ),
        "primary": Param("int", 0, "array index of the primary IMU", low=0),
        "bias": Param("bool", True, "remove per-IMU offsets found in the calibration window"),
        "false_alarms": FALSE_ALARMS,
        "types": Param("str", "gyro,accel", "sensor types tested: gyro, accel or both"),
    }

    def __init__(
        self,
        accel_threshold: float = 0.75,
        gyro_threshold: float = math.radians(5.0),
        hold: float = 10.0,
        z_weight: float = 0.5,
        backup_factor: float = 3.0,
        reference: str = "primary",
        primary: int = 0,
        bias: bool = True,
        false_alarms: float = 0.0,
        types: str = "gyro,accel",
    ) -> None:
        self.false_alarms = float(false_alarms)
        self.accel_threshold = float(accel_threshold)
        self.gyro_threshold = float(gyro_threshold)
        self.hold = float(hold)
        self.z_weight = float(z_weight)
        self.backup_factor = float(backup_factor)
        self.reference = reference
        self.primary = int(primary)
        self.remove_bias = bool(bias)
        self.types = parse_vector_types(types, self.name)
        self.hold_samples = 1
        self._states: dict[str, _TypeState] = {}

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Check the layout, find per-IMU offsets, and turn ``hold`` into samples.

        Raises
        ------
        DetectorConfigError
            Fewer than 2 IMUs of a tested type, a partial triad, or a primary IMU without
            the tested type.
        CalibrationError
            Fewer than 10 calibration samples or non-finite data (with ``bias=true``).
        """
        self._states = {}
        # "now - last_pass > hold": more than hold seconds of consecutive failures
        self.hold_samples = math.floor(self.hold * array.rate_hz + 1e-9) + 1
        for sensor_type, layout in compared_layouts(array, self.types, self.name).items():
            where = np.flatnonzero(layout.imus == self.primary)
            if where.size == 0:
                raise DetectorConfigError(
                    f"{self.name}.primary: imu{self.primary} has no {sensor_type};"
                    f" IMUs with {sensor_type}: " + ", ".join(f"imu{int(k)}" for k in layout.imus)
                )
            m = layout.n_imus
            if sensor_type == "accel":
                limits = np.full(m, self.accel_threshold)
                limits[2:] *= self.backup_factor  # firmware index i >= 2 (array order)
                weight = np.array([1.0, 1.0, self.z_weight])
            else:
                limits = np.full(m, self.gyro_threshold)
                weight = np.ones(3)
            offsets = (
                layout.calibration_offsets(calibration, self.name)
                if self.remove_bias
                else np.zeros((m, 3))
            )
            state = _TypeState(
                layout=layout,
                limits=limits,
                weight=weight,
                offsets=offsets,
                primary=int(where[0]),
                history=np.zeros((0, m)),
            )
            if self.false_alarms > 0:
                self._fit_budget(state, calibration, array.rate_hz)
            self._states[sensor_type] = state

    def _failing(self, state: _TypeState) -> np.ndarray:
        """The compared IMUs whose difference can fail (all but the primary, which is its
        own reference, with ``reference=primary``)."""
        m = state.layout.n_imus
        if self.reference == "primary":
            return np.delete(np.arange(m), state.primary)
        return np.arange(m)

    def _difference(self, state: _TypeState, vectors: np.ndarray) -> np.ndarray:
        """Each IMU's difference from its reference (N, m, 3), body frame."""
        if self.reference == "primary":
            return vectors - vectors[:, state.primary : state.primary + 1, :]
        total = vectors.sum(axis=1, keepdims=True)
        return vectors - (total - vectors) / (vectors.shape[1] - 1)

    def _fit_budget(self, state: _TypeState, calibration: ImuBlock, rate_hz: float) -> None:
        """Scale every limit of the type so that white noise of the calibrated variances
        raises the budget's share of false episodes (:func:`ap_limit_scale`)."""
        per_sample = BUDGET_SHARE * self.false_alarms / rate_hz
        if not 0.0 < per_sample < 0.5:
            raise DetectorConfigError(
                f"{self.name}: false-alarm budget {self.false_alarms * 3600:g}/h is not"
                f" below half the sample rate ({rate_hz:g} Hz); give a rate such as 1/h"
            )
        vectors = state.layout.body(calibration, self.name) - state.offsets[None, :, :]
        failing = self._failing(state)
        differences = self._difference(state, vectors)[:, failing, :]
        variances, dof = difference_noise(differences)
        if self.remove_bias:
            # the calibrated offsets' error stays in every difference: over calibrations it
            # adds 1/N of the difference's variance (two IMUs' means of N samples)
            variances = variances * (1.0 + 1.0 / vectors.shape[0])
        if not np.all(variances > 0):
            raise CalibrationError(
                f"{self.name}: a {state.layout.sensor_type} difference does not change in the"
                " calibration window (a stuck or constant output); choose a fault-free window"
                " with --calibrate START:END"
            )
        limits = state.limits[failing]
        # outliers: a sample far outside the noise fails whatever the limit (one hold of
        # them is an episode when the hold is short)
        centred = differences - differences.mean(axis=0, keepdims=True)
        contamination = outlier_fraction(centred, variances)
        scale = ap_limit_scale(
            variances, state.weight, limits, self.hold_samples, per_sample, dof, contamination
        )
        state.scale = scale
        state.limits = state.limits * scale
        state.disagreement = Disagreement(variances.sum(axis=1), round(rate_hz))
        state.budget = {
            "false_alarms_per_hour": self.false_alarms * 3600.0,
            "limit_scale": scale,
            "outlier_share": contamination,
            "model_episodes_per_hour": ap_episode_rate(
                scale, variances, state.weight, limits, self.hold_samples, dof, contamination
            )
            * rate_hz
            * 3600.0,
            "difference_sigma": np.sqrt(variances).tolist(),
            "calibration_dof": dof,
        }

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """One row per input sample for every tested sensor type."""
        if not self._states:
            raise DetectorConfigError(f"{self.name}: call fit() before process()")
        return {t: self._process_type(s, block) for t, s in self._states.items()}

    def _process_type(self, state: _TypeState, block: ImuBlock) -> DetectionBlock:
        layout = state.layout
        vectors = layout.body(block, self.name) - state.offsets[None, :, :]
        n_samples, m = vectors.shape[0], layout.n_imus
        if n_samples == 0:
            return DetectionBlock.empty(0, layout.n_sensors)
        total = vectors.sum(axis=1, keepdims=True)
        versus_others = vectors - (total - vectors) / (m - 1)  # x_i - mean_{j != i} x_j
        difference = self._difference(state, vectors)
        if state.disagreement is not None:
            state.disagreement.add(difference[:, self._failing(state), :])
        normalised = np.linalg.norm(difference * state.weight, axis=2) / state.limits  # (N, m)
        held = trailing_minimum(state.history, normalised, self.hold_samples)
        # before h samples have been seen the window is not full: no decision yet
        seen = state.seen + np.arange(1, n_samples + 1)
        held[seen < self.hold_samples] = 0.0
        state.history = np.concatenate([state.history, normalised])[-(self.hold_samples - 1) :]
        if self.hold_samples == 1:
            state.history = normalised[:0]
        state.seen += n_samples

        failing = held > 1.0
        statistic = held.max(axis=1)
        alarm = statistic > 1.0
        worst = np.argmax(held, axis=1)
        if self.reference == "primary":
            others = np.delete(np.arange(m), state.primary)
            every_other = failing[:, others].all(axis=1)
            worst = np.where(every_other, state.primary, worst)
        isolated, amplitude, scores = imu_isolation(layout, alarm, worst, versus_others, held)
        return DetectionBlock(
            statistic=statistic,
            threshold=np.ones(n_samples),
            alarm=alarm,
            isolated=isolated,
            amplitude=amplitude,
            scores=scores,
        )

    def metadata(self) -> dict[str, Any]:
        """Parameters (SI), hold in samples, per-IMU limits and calibration offsets."""
        return {
            "detector": self.name,
            "params": {
                "accel_threshold": self.accel_threshold,
                "gyro_threshold": self.gyro_threshold,
                "hold": self.hold,
                "z_weight": self.z_weight,
                "backup_factor": self.backup_factor,
                "reference": self.reference,
                "primary": self.primary,
                "bias": self.remove_bias,
                "false_alarms_per_hour": self.false_alarms * 3600.0,
                "types": ",".join(self.types),
            },
            "hold_samples": self.hold_samples,
            "lookahead_samples": self.lookahead_samples,
            "types": {
                t: {
                    "imus": [f"imu{int(k)}" for k in s.layout.imus],
                    "isolable": bool(s.layout.n_imus >= 3),
                    "limits": s.limits.tolist(),
                    "offsets": s.offsets.tolist(),
                    **({} if s.budget is None else {"budget": self._budget_metadata(s)}),
                }
                for t, s in self._states.items()
            },
        }

    @staticmethod
    def _budget_metadata(state: _TypeState) -> dict[str, Any]:
        assert state.budget is not None and state.disagreement is not None
        return {**state.budget, **state.disagreement.metadata()}

    def calibration_warnings(self) -> list[str]:
        """Under a budget, one warning per sensor type whose IMUs disagreed, over part of
        the processed log, clearly more than the calibrated white noise the limits were
        scaled for."""
        return disagreement_warnings(self.name, self._states, "limits")


__all__ = ["ApConsistencyDetector", "trailing_minimum"]
