"""px4-selector: IMU inconsistency accumulated over time, in the style of PX4's EKF2 selector.

PX4-Autopilot (BSD-3-Clause), read for understanding, not copied:

- ``src/modules/sensors/voted_sensors_update.cpp`` (``calcGyroInconsistency``,
  ``calcAccelInconsistency``): per update, each IMU's vector minus the mean of all IMUs,
  smoothed by ``diff = 0.95 diff + 0.05 (x_i - mean)``; the inconsistency is ``|diff|``
  (published as ``sensors_status_imu.gyro_inconsistency_rad_s`` / ``accel_inconsistency_m_s_s``).
- ``src/modules/ekf2/EKF2Selector.cpp`` (``UpdateErrorScores``): per IMU
  ``E_i += (|diff_i| - rate_threshold) * dt`` with ``dt = constrain(step, 0, 0.02 s)``, then
  ``E_i = max(E_i, 0)``; an IMU whose accumulated error exceeds the angle (velocity)
  threshold is an exceedance. With >= 3 IMUs the one with the largest accumulated error is
  declared faulty; with 2, a fault is declared but its IMU cannot be identified.
- Parameters (``EKF2Selector.hpp``, ``ekf2_params_selector``): ``EKF2_SEL_IMU_RAT`` 7 deg/s,
  ``EKF2_SEL_IMU_ANG`` 15 deg, ``EKF2_SEL_IMU_ACC`` 1 m/s^2, ``EKF2_SEL_IMU_VEL`` 2 m/s.

Here, per sensor type (gyro and accel separately), on each sample t with step dt_t:

    d_i(t) = (1 - c) d_i(t-1) + c (x_i(t) - mean_j x_j(t))      x in the body frame, (3,)
    E_i(t) = max(0, E_i(t-1) + (|d_i(t)| - r) min(dt_t, dt_max))
    alarm(t) = max_i E_i(t) > A

with (r, A) = (rate_threshold, angle_threshold) for gyros and (accel_threshold,
velocity_threshold) for accelerometers. The statistic is ``max_i E_i`` (rad or m/s), the
threshold A. Isolation: the IMU with the largest E (>= 3 IMUs), NOT_ISOLABLE with 2; the
reported sensor is that IMU's axis with the largest ``|d|`` component in its own frame, and
the amplitude that component times m / (m - 1) (a step f on one of m IMUs moves its deviation
from the mean by f (m - 1) / m). Scores: E of each IMU on each of its axes.

The firmware runs on calibrated sensors; ``bias=true`` (default) removes each IMU's mean
offset from the array mean on the calibration window, standing in for that calibration.
The smoothing constant c acts per sample, as in the firmware per update: at the log's rate
its time constant is ``dt / c`` (0.2 s at 100 Hz). Causal: one row per input sample, no
look-ahead. Lever-arm effects on accelerometers are not compensated (nor are they in PX4).

Under a false-alarm budget (``false_alarms`` > 0) the rule is unchanged and both
thresholds of a type are multiplied by one factor, chosen at fit time so that the IMUs'
calibrated white noise raises at most half the budget
(:func:`~imufdi_cli.detectors.firmware_budget.px4_scale`: the Lundberg exponent of the
smoothed norm's Markov kernel, the calibrated offsets' error bounded);
``calibration_warnings`` says when the IMUs disagreed beyond that noise on the processed log.
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
    accumulate_excess,
    difference_noise,
    disagreement_warnings,
    imu_noise,
    px4_scale,
)
from imufdi_cli.detectors.vectors import (
    CausalImuCheck,
    TriadLayout,
    block_steps,
    compared_layouts,
    imu_isolation,
    parse_vector_types,
)
from imufdi_cli.errors import CalibrationError, DetectorConfigError
from imufdi_cli.log import ImuBlock


def smooth_deviation(deviation: np.ndarray, start: np.ndarray, gain: float) -> np.ndarray:
    """``d_t = (1 - c) d_{t-1} + c x_t`` along axis 0 (the firmware's 0.95/0.05 filter).

    Parameters
    ----------
    deviation : ndarray, shape (N, ...)
    start : ndarray, shape deviation.shape[1:]
        d_0.
    gain : float
        c in (0, 1].

    Returns
    -------
    ndarray, shape (N, ...)
    """
    from scipy.signal import lfilter  # imported when the selector runs, not on import

    if deviation.shape[0] == 0:
        return np.zeros_like(deviation)
    decay = 1.0 - gain
    # lfilter's state for y_t = c x_t + decay y_{t-1}: zi = decay * y_0
    initial = (decay * start)[None, ...]
    smoothed, _ = lfilter([gain], [1.0, -decay], deviation, axis=0, zi=initial)
    return np.asarray(smoothed)


@dataclass
class _TypeState:
    layout: TriadLayout
    rate_threshold: float
    accumulated_threshold: float
    offsets: np.ndarray  # (m, 3) body frame
    smoothed: np.ndarray  # (m, 3) d_i, body frame
    accumulated: np.ndarray  # (m,) E_i
    last_ns: int | None = None
    first_alarm_sample: int | None = None
    scale: float = 1.0  # factor on the firmware thresholds (a false-alarm budget)
    budget: dict[str, Any] | None = None  # what set it
    disagreement: Disagreement | None = None  # the budget's model, checked on the data


class Px4SelectorDetector(CausalImuCheck):
    """PX4 EKF2-selector style IMU consistency check (module docstring); ``px4-selector``."""

    name: ClassVar[str] = "px4-selector"
    #: Causal: every row is decided on its own sample.
    lookahead_samples: ClassVar[int] = 0
    PARAMS: ClassVar[dict[str, Param]] = {
        "rate_threshold": Param(
            "angular_rate",
            math.radians(7.0),
            "gyro inconsistency that starts accumulating angle error (EKF2_SEL_IMU_RAT)",
            low=0.0,
        ),
        "angle_threshold": Param(
            "angle",
            math.radians(15.0),
            "accumulated gyro angle error declaring a fault (EKF2_SEL_IMU_ANG)",
            low=0.0,
            low_open=True,
        ),
        "accel_threshold": Param(
            "acceleration",
            1.0,
            "accel inconsistency that starts accumulating velocity error (EKF2_SEL_IMU_ACC)",
            low=0.0,
        ),
        "velocity_threshold": Param(
            "velocity",
            2.0,
            "accumulated accel velocity error declaring a fault (EKF2_SEL_IMU_VEL)",
            low=0.0,
            low_open=True,
        ),
        "smoothing": Param(
            "float",
            0.05,
            "per-sample gain of the deviation filter (voted_sensors_update.cpp: 0.05)",
            low=0.0,
            high=1.0,
            low_open=True,
        ),
        "max_step": Param(
            "time",
            0.02,
            "largest time step accumulated per sample (EKF2Selector.cpp: 0.02 s)",
            low=0.0,
            low_open=True,
        ),
        "bias": Param("bool", True, "remove per-IMU offsets found in the calibration window"),
        "false_alarms": FALSE_ALARMS,
        "seed": Param(
            "int", 0, "seed of the simulated null that scales the thresholds to a budget", low=0
        ),
        "types": Param("str", "gyro,accel", "sensor types tested: gyro, accel or both"),
    }

    def __init__(
        self,
        rate_threshold: float = math.radians(7.0),
        angle_threshold: float = math.radians(15.0),
        accel_threshold: float = 1.0,
        velocity_threshold: float = 2.0,
        smoothing: float = 0.05,
        max_step: float = 0.02,
        bias: bool = True,
        false_alarms: float = 0.0,
        seed: int = 0,
        types: str = "gyro,accel",
    ) -> None:
        self.false_alarms = float(false_alarms)
        self.seed = int(seed)
        self.rate_threshold = float(rate_threshold)
        self.angle_threshold = float(angle_threshold)
        self.accel_threshold = float(accel_threshold)
        self.velocity_threshold = float(velocity_threshold)
        self.smoothing = float(smoothing)
        self.max_step = float(max_step)
        self.remove_bias = bool(bias)
        self.types = parse_vector_types(types, self.name)
        self._states: dict[str, _TypeState] = {}
        self._nominal_step = 0.01
        self._samples_seen = 0

    def fit(self, calibration: ImuBlock, array: ArrayConfig) -> None:
        """Check the layout (>= 2 IMUs with full triads) and find the per-IMU offsets.

        Raises
        ------
        DetectorConfigError
            A tested type with fewer than 2 IMUs, or an IMU with a partial triad.
        CalibrationError
            Fewer than 10 calibration samples or non-finite data (with ``bias=true``).
        """
        self._states = {}
        self._samples_seen = 0
        self._nominal_step = 1.0 / array.rate_hz
        for sensor_type, layout in compared_layouts(array, self.types, self.name).items():
            if self.remove_bias:
                offsets = layout.calibration_offsets(calibration, self.name)
            else:
                offsets = np.zeros((layout.n_imus, 3))
            gyro = sensor_type == "gyro"
            state = _TypeState(
                layout=layout,
                rate_threshold=self.rate_threshold if gyro else self.accel_threshold,
                accumulated_threshold=self.angle_threshold if gyro else self.velocity_threshold,
                offsets=offsets,
                smoothed=np.zeros((layout.n_imus, 3)),
                accumulated=np.zeros(layout.n_imus),
            )
            if self.false_alarms > 0:
                self._fit_budget(state, calibration, array.rate_hz)
            self._states[sensor_type] = state

    def _fit_budget(self, state: _TypeState, calibration: ImuBlock, rate_hz: float) -> None:
        """Scale the type's two thresholds by one factor so that white noise of the
        calibrated per-IMU sigma raises the budget's share of false episodes
        (:func:`~imufdi_cli.detectors.firmware_budget.px4_scale`)."""
        per_sample = BUDGET_SHARE * self.false_alarms / rate_hz
        if not 0.0 < per_sample < 0.5:
            raise DetectorConfigError(
                f"{self.name}: false-alarm budget {self.false_alarms * 3600:g}/h is not"
                f" below half the sample rate ({rate_hz:g} Hz); give a rate such as 1/h"
            )
        if not (state.rate_threshold > 0 and state.accumulated_threshold > 0):
            raise DetectorConfigError(
                f"{self.name}: a false-alarm budget scales the firmware thresholds; the"
                f" {state.layout.sensor_type} rate threshold must be > 0"
            )
        vectors = state.layout.body(calibration, self.name) - state.offsets[None, :, :]
        deviation = vectors - vectors.mean(axis=1, keepdims=True)
        # the plain variance: outliers pass the filter as impulses, their power counts
        variances, dof = difference_noise(deviation, robust=False)
        if not np.all(variances > 0):
            raise CalibrationError(
                f"{self.name}: a {state.layout.sensor_type} deviation does not change in the"
                " calibration window (a stuck or constant output); choose a fault-free window"
                " with --calibrate START:END"
            )
        noise = imu_noise(variances)
        step = min(1.0 / rate_hz, self.max_step)
        r0, a0 = state.rate_threshold, state.accumulated_threshold
        samples = float(vectors.shape[0]) if self.remove_bias else math.inf
        scale = px4_scale(noise, self.smoothing, step, r0, a0, per_sample, dof, samples, self.seed)
        state.scale = scale
        state.rate_threshold = r0 * scale
        state.accumulated_threshold = a0 * scale
        state.disagreement = Disagreement(variances.sum(axis=1), round(rate_hz))
        state.budget = {
            "false_alarms_per_hour": self.false_alarms * 3600.0,
            "threshold_scale": scale,
            "noise_sigma": np.sqrt(noise).tolist(),
            "calibration_dof": dof,
        }

    def process(self, block: ImuBlock) -> dict[str, DetectionBlock]:
        """One row per input sample for every tested sensor type."""
        if not self._states:
            raise DetectorConfigError(f"{self.name}: call fit() before process()")
        out = {t: self._process_type(s, block) for t, s in self._states.items()}
        self._samples_seen += len(block)
        return out

    def _process_type(self, state: _TypeState, block: ImuBlock) -> DetectionBlock:
        layout = state.layout
        vectors = layout.body(block, self.name) - state.offsets[None, :, :]
        n_samples, m = vectors.shape[0], layout.n_imus
        if n_samples == 0:
            return DetectionBlock.empty(0, layout.n_sensors)
        deviation = vectors - vectors.mean(axis=1, keepdims=True)
        if state.disagreement is not None:
            state.disagreement.add(deviation)
        smoothed = smooth_deviation(deviation, state.smoothed, self.smoothing)
        inconsistency = np.linalg.norm(smoothed, axis=2)  # (N, m)
        steps = np.minimum(
            block_steps(block.t_ns, state.last_ns, self._nominal_step), self.max_step
        )
        steps = np.maximum(steps, 0.0)
        excess = (inconsistency - state.rate_threshold) * steps[:, None]
        accumulated = accumulate_excess(excess, state.accumulated)
        state.smoothed = smoothed[-1].copy()
        state.accumulated = accumulated[-1].copy()
        state.last_ns = int(block.t_ns[-1])

        rows = np.arange(n_samples)
        worst = np.argmax(accumulated, axis=1)
        statistic = accumulated[rows, worst]
        alarm = statistic > state.accumulated_threshold
        isolated, amplitude, scores = imu_isolation(
            layout, alarm, worst, smoothed, accumulated, amplitude_scale=m / (m - 1)
        )
        if state.first_alarm_sample is None and alarm.any():
            state.first_alarm_sample = self._samples_seen + int(np.argmax(alarm))
        return DetectionBlock(
            statistic=statistic,
            threshold=np.full(n_samples, state.accumulated_threshold),
            alarm=alarm,
            isolated=isolated,
            amplitude=amplitude,
            scores=scores,
        )

    def metadata(self) -> dict[str, Any]:
        """Parameters (SI), compared IMUs, calibration offsets and the first alarm sample."""
        return {
            "detector": self.name,
            "params": {
                "rate_threshold": self.rate_threshold,
                "angle_threshold": self.angle_threshold,
                "accel_threshold": self.accel_threshold,
                "velocity_threshold": self.velocity_threshold,
                "smoothing": self.smoothing,
                "max_step": self.max_step,
                "bias": self.remove_bias,
                "false_alarms_per_hour": self.false_alarms * 3600.0,
                "seed": self.seed,
                "types": ",".join(self.types),
            },
            "lookahead_samples": self.lookahead_samples,
            "types": {
                t: {
                    "imus": [f"imu{int(k)}" for k in s.layout.imus],
                    "isolable": bool(s.layout.n_imus >= 3),
                    "offsets": s.offsets.tolist(),
                    "threshold": s.accumulated_threshold,
                    "rate_threshold": s.rate_threshold,
                    "first_alarm_sample": s.first_alarm_sample,
                    **(
                        {}
                        if s.budget is None or s.disagreement is None
                        else {
                            "budget": {
                                **s.budget,
                                **s.disagreement.metadata(),
                            }
                        }
                    ),
                }
                for t, s in self._states.items()
            },
        }

    def calibration_warnings(self) -> list[str]:
        """Under a budget, one warning per sensor type whose IMUs disagreed, over part of
        the processed log, clearly more than the calibrated white noise the thresholds were
        scaled for."""
        return disagreement_warnings(self.name, self._states, "thresholds")


__all__ = ["Px4SelectorDetector", "accumulate_excess", "smooth_deviation"]
