"""The figures of one detector on one sensor type (:class:`Metrics`, per fault
:class:`FaultFigures`), the faults they are measured against (:class:`FaultWindow`), and
the names gates and tables may use (:data:`METRIC_NAMES`); docs/metrics.md defines each."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np


@dataclass(frozen=True)
class FaultWindow:
    """One injected fault, as seen by one sensor type's test.

    Attributes
    ----------
    fault_id : str
        Identifier of the fault (from the truth record).
    sensors : tuple of int
        Indices of the faulty sensors in ``ArrayConfig.sensor_ids(type)``.
    start_ns : int
        Onset, ns.
    end_ns : int or None
        End of the fault, ns; None when it lasts to the end of the log.
    model : str
        Fault model (``step``, ``drift``, ...; empty when unknown).
    size : float or None
        True size the detector's amplitude estimates are compared to, SI: a step's ``amp``,
        a drift's ``rate`` (per second); None for the other models.
    """

    fault_id: str
    sensors: tuple[int, ...]
    start_ns: int
    end_ns: int | None = None
    model: str = ""
    size: float | None = None


@dataclass
class FaultFigures:
    """Per-fault event figures (delays in seconds, at decision time)."""

    fault_id: str
    detected: bool
    detection_delay_s: float | None
    isolation_delay_s: float | None
    recovery_delay_s: float | None
    isolated_correctly: float | None  # fraction of the fault's detected samples isolated to it
    faulty_samples: int
    rate_after_first_detection: float | None  # alarmed / faulty samples from the first alarm on
    #: per faulty sensor the detector gave an amplitude for (:class:`AmplitudeFigure`)
    amplitudes: list[AmplitudeFigure] = field(default_factory=list)
    #: under a budget: the optimal sequential test's delay for this fault (Lorden), s
    reference_delay_s: float | None = None
    #: detection delay / reference delay
    delay_ratio: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class AmplitudeFigure:
    """A detector's estimate of one faulty sensor's fault size, from its status rows.

    Over the fault's detected samples on which the sensor is isolated and has an estimated
    amplitude (``amplitudes`` of the status): for a drift the least-squares slope of the
    amplitude against time (``size_name`` ``rate``, SI per second: a filter's lag shifts the
    line but not its slope), otherwise the median amplitude (``amp``, SI).

    Attributes
    ----------
    sensor : str
        Sensor id (or its index when the ids are unknown).
    size_name : str
        ``amp`` or ``rate``.
    estimate : float
    true : float or None
        The injected size (step ``amp``, drift ``rate``); None for other models.
    ratio : float or None
        ``estimate / true``.
    samples : int
        Samples the estimate is made of.
    """

    sensor: str
    size_name: str
    estimate: float
    true: float | None
    ratio: float | None
    samples: int


@dataclass
class Metrics:
    """Per-sample figures for one detector and sensor type.

    Ratios are fractions (0..1); ``None`` where undefined. Sample counts other than
    ``samples`` and ``calibration_samples`` are outside the calibration window.
    """

    samples: int
    fault_free_samples: int
    faulty_samples: int
    false_alarms: int
    missed: int
    detected_faulty: int
    false_isolations: int
    unisolated: int
    far: float | None
    mar: float | None
    accuracy: float | None
    fir: float | None
    isolation_accuracy: float | None
    detection_delay_s: float | None  # mean over detected faults
    recovery_delay_s: float | None  # mean over faults that ended and recovered
    alarm_rate: float | None  # alarms / samples, truth or not
    alarm_events: int
    false_alarm_events_per_hour: float | None
    duration_s: float  # first to last row plus one mean interval (gaps included)
    faults: list[FaultFigures] = field(default_factory=list)
    calibration_samples: int = 0
    far_calibration: float | None = None
    isolation_delay_s: float | None = None  # mean over faults isolated to a faulty sensor
    decision_latency_s: float | None = None
    rate_after_first_detection: float | None = None
    mar_at_far: float | None = None
    fir_at_far: float | None = None
    detection_delay_at_far_s: float | None = None
    threshold_scale_at_far: float | None = None
    target_far: float | None = None
    #: the tested, fault-free time of the per-hour figures (:func:`fault_free_tested_hours`)
    fault_free_hours: float = 0.0
    #: the time one row stands for: the median interval between rows, s
    sample_period_s: float | None = None
    false_episodes: int | None = None  # None: no sample rate for the joining rule
    false_episodes_per_hour: float | None = None
    false_episodes_per_hour_upper95: float | None = None
    mtbfa_h: float | None = None  # mean time between false alarm episodes, hours
    mtbfa_h_lower95: float | None = None
    target_budget_per_hour: float | None = None
    threshold_scale_at_budget: float | None = None
    mar_at_budget: float | None = None
    fir_at_budget: float | None = None
    detection_delay_s_at_budget: float | None = None
    isolation_delay_s_at_budget: float | None = None
    reference_delay_s: float | None = None  # mean over the faults with a reference
    delay_ratio: float | None = None  # mean over the detected faults with a reference

    def to_dict(self) -> dict[str, Any]:
        # field by field: dataclasses.asdict deep-copies every value, 10x slower
        data = {f.name: getattr(self, f.name) for f in fields(self)}
        data["faults"] = [f.to_dict() for f in self.faults]
        data["detection_rate"] = self.value("detection_rate")
        return data

    def value(self, name: str) -> float | None:
        """A scalar figure by name (for gates): see :data:`METRIC_NAMES`."""
        if name not in METRIC_NAMES:
            raise KeyError(name)
        if name == "detection_rate":
            return None if self.mar is None else 1.0 - self.mar
        if name == "detection_probability":
            if not self.faults:
                return None
            return sum(f.detected for f in self.faults) / len(self.faults)
        value = getattr(self, name)
        return None if value is None else float(value)


#: Scalar figures that gates and tables may name.
METRIC_NAMES: dict[str, str] = {
    "far": "false alarm rate outside the calibration window (alarms on fault-free samples"
    " / fault-free samples)",
    "far_calibration": "false alarm rate inside the calibration window (in-sample)",
    "mar": "missed alarm rate (faulty samples without alarm / faulty samples)",
    "accuracy": "detection accuracy, 1 - FAR - MAR",
    "fir": "false isolation rate (detected faulty samples isolated to a healthy sensor)",
    "isolation_accuracy": "1 - FIR",
    "detection_rate": "1 - MAR",
    "rate_after_first_detection": "alarmed / faulty samples from each fault's first alarm"
    " on (secondary; the detection rate is 1 - MAR)",
    "detection_delay_s": "mean detection delay over detected faults, at decision time, s",
    "isolation_delay_s": "mean delay to the first alarm isolated to a faulty sensor, s",
    "decision_latency_s": "mean decision time - sample time, s",
    "recovery_delay_s": "mean recovery delay over faults that ended, s",
    "detection_probability": "fraction of injected faults that were detected",
    "alarm_rate": "alarms / samples (outside the calibration window)",
    "alarm_events": "number of alarm events (rising edges) outside the calibration window",
    "false_alarm_events_per_hour": "alarm events that start on fault-free samples, per hour",
    "mar_at_far": "MAR with the threshold scaled to the matched FAR (--match-far)",
    "fir_at_far": "FIR at the matched FAR",
    "detection_delay_at_far_s": "mean detection delay at the matched FAR, s",
    "threshold_scale_at_far": "threshold scale giving the matched FAR",
    "false_episodes": "false alarm episodes (the episodes' joining rule) starting on a"
    " fault-free sample outside the calibration window",
    "false_episodes_per_hour": "false alarm episodes per hour of fault-free tested time",
    "false_episodes_per_hour_upper95": "exact Poisson 95 % upper bound of false_episodes_per_hour",
    "mtbfa_h": "mean time between false alarm episodes, hours (1 / false_episodes_per_hour)",
    "mtbfa_h_lower95": "95 % lower bound of mtbfa_h (1 / the upper bound of the rate)",
    "fault_free_hours": "fault-free tested hours the per-hour figures rest on",
    "target_budget_per_hour": "target of the matched budget, false episodes per hour",
    "threshold_scale_at_budget": "threshold scale giving the matched budget",
    "mar_at_budget": "MAR with the threshold scaled to the matched budget (--match-budget)",
    "fir_at_budget": "FIR at the matched budget",
    "detection_delay_s_at_budget": "mean detection delay at the matched budget, s",
    "isolation_delay_s_at_budget": "mean isolation delay at the matched budget, s",
    "reference_delay_s": "under a budget: mean delay the optimal sequential test (Lorden)"
    " needs for the faults, s",
    "delay_ratio": "under a budget: mean detection delay / reference delay over the"
    " detected faults",
    "samples": "number of samples",
    "faulty_samples": "number of samples with an active fault",
}


def _ratio(numerator: int, denominator: int) -> float | None:
    return None if denominator == 0 else numerator / denominator


def mean_metrics(values: Sequence[float | None]) -> tuple[float | None, float | None, int]:
    """Mean and sample standard deviation over runs, ignoring undefined values.

    Returns ``(mean, std, count)``; mean is None when every value is undefined, std is None
    with fewer than two defined values.
    """
    defined = [float(v) for v in values if v is not None and not math.isnan(float(v))]
    if not defined:
        return None, None, 0
    mean = float(np.mean(defined))
    std = float(np.std(defined, ddof=1)) if len(defined) > 1 else None
    return mean, std, len(defined)
