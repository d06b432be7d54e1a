"""Detection and isolation metrics from ground truth and alarms (DESIGN.md §7).

All figures are per sample and per sensor type, with the definitions of Li et al.
(Micromachines 17(3):374, 2026), Table 4:

- FAR = alarms on fault-free samples / fault-free samples
- MAR = faulty samples without alarm / faulty samples
- detection accuracy = 1 - FAR - MAR   (Table 4: 100 - 4.98 - 26.58 = 68.44 %)
- FIR = detected faulty samples isolated to a sensor that is not faulty / detected faulty
  samples; isolation accuracy = 1 - FIR
- detection delay = first alarm at or after onset (and before the fault ends) - onset;
  optionally the first alarm that persists ``persist`` samples
- recovery delay = first sample at or after the fault end with the alarm cleared - fault end

A figure whose denominator is empty (no faulty samples, no detections, a fault never
detected) is ``None`` — "undefined" — never 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

NS_PER_S = 1_000_000_000


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
    """

    fault_id: str
    sensors: tuple[int, ...]
    start_ns: int
    end_ns: int | None = None


@dataclass
class FaultFigures:
    """Per-fault event figures."""

    fault_id: str
    detected: bool
    detection_delay_s: float | None
    recovery_delay_s: float | None
    isolated_correctly: float | None  # fraction of the fault's detected samples isolated to it
    faulty_samples: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Metrics:
    """Per-sample figures for one detector and sensor type.

    Ratios are fractions (0..1); ``None`` where undefined.
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
    duration_s: float
    faults: list[FaultFigures] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["faults"] = [f.to_dict() for f in self.faults]
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
    "far": "false alarm rate (alarms on fault-free samples / fault-free samples)",
    "mar": "missed alarm rate (faulty samples without alarm / faulty samples)",
    "accuracy": "detection accuracy, 1 - FAR - MAR",
    "fir": "false isolation rate (detected faulty samples isolated to a healthy sensor)",
    "isolation_accuracy": "1 - FIR",
    "detection_rate": "1 - MAR",
    "detection_delay_s": "mean detection delay over detected faults, s",
    "recovery_delay_s": "mean recovery delay over faults that ended, s",
    "detection_probability": "fraction of injected faults that were detected",
    "alarm_rate": "alarms / samples",
    "alarm_events": "number of alarm events (rising edges)",
    "false_alarm_events_per_hour": "alarm events that start on fault-free samples, per hour",
    "samples": "number of samples",
    "faulty_samples": "number of samples with an active fault",
}


def _ratio(numerator: int, denominator: int) -> float | None:
    return None if denominator == 0 else numerator / denominator


def faulty_matrix(t_ns: np.ndarray, windows: Sequence[FaultWindow], n_sensors: int) -> np.ndarray:
    """Ground truth per sample and sensor from fault windows.

    Returns
    -------
    ndarray, shape (N, n_sensors), bool
        ``[i, j]`` true when a window acting on sensor j holds ``start <= t_i < end``.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    faulty = np.zeros((t_ns.size, n_sensors), dtype=bool)
    for window in windows:
        active = t_ns >= window.start_ns
        if window.end_ns is not None:
            active &= t_ns < window.end_ns
        faulty[np.ix_(active, np.asarray(window.sensors, dtype=np.intp))] = True
    return faulty


def rising_edges(alarm: np.ndarray) -> np.ndarray:
    """Indices where ``alarm`` (N,) bool goes from False to True (index 0 if it starts True)."""
    alarm = np.asarray(alarm, dtype=bool)
    if alarm.size == 0:
        return np.zeros(0, dtype=np.intp)
    previous = np.concatenate([[False], alarm[:-1]])
    return np.flatnonzero(alarm & ~previous)


def persistent(alarm: np.ndarray, persist: int) -> np.ndarray:
    """True where the alarm is on for at least ``persist`` consecutive samples starting here."""
    alarm = np.asarray(alarm, dtype=bool)
    if persist <= 1 or alarm.size == 0:
        return alarm.copy()
    counts = np.convolve(alarm.astype(np.int64), np.ones(persist, dtype=np.int64), "full")
    # counts[i + persist - 1] = number of alarms in alarm[i : i + persist]
    window = counts[persist - 1 : persist - 1 + alarm.size]
    return window == persist


def compute_metrics(
    t_ns: np.ndarray,
    alarm: np.ndarray,
    isolated: np.ndarray,
    faulty: np.ndarray,
    faults: Sequence[FaultWindow] = (),
    *,
    persist: int = 1,
    isolated_set: np.ndarray | None = None,
) -> Metrics:
    """Per-sample metrics of one detector on one sensor type.

    Parameters
    ----------
    t_ns : ndarray, shape (N,), int64
        Sample timestamps, ns.
    alarm : ndarray, shape (N,), bool
        Detector alarm per sample.
    isolated : ndarray, shape (N,), int
        Isolated sensor index per sample (negative: none / not isolable).
    faulty : ndarray, shape (N, n_s), bool
        Ground truth: sensor j has an active fault at sample i.
    faults : sequence of FaultWindow
        The faults of this sensor type, for delays and per-fault figures.
    persist : int
        Detection delay counts the first alarm that persists this many samples.
    isolated_set : ndarray, shape (N, n_s), bool, optional
        Every sensor the detector isolated at each sample (detectors that isolate several
        simultaneous faults). Per-fault isolation then asks whether the fault's own sensor
        is in the set; FIR still judges the primary ``isolated`` sensor.

    Returns
    -------
    Metrics
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    alarm = np.asarray(alarm, dtype=bool)
    isolated = np.asarray(isolated, dtype=np.int64)
    faulty = np.asarray(faulty, dtype=bool).reshape(len(t_ns), -1)
    n = int(t_ns.size)
    any_fault = np.asarray(faulty.any(axis=1), dtype=bool)
    fault_free = np.logical_not(any_fault)
    false_alarms = int(np.count_nonzero(alarm & fault_free))
    n_free = int(np.count_nonzero(fault_free))
    n_faulty = int(np.count_nonzero(any_fault))
    missed = int(np.count_nonzero(any_fault & ~alarm))
    detected = any_fault & alarm
    n_detected = int(np.count_nonzero(detected))
    has_iso = isolated >= 0
    safe_iso = np.where(has_iso, isolated, 0)
    correct_iso = has_iso & faulty[np.arange(n), np.clip(safe_iso, 0, max(faulty.shape[1] - 1, 0))]
    false_iso = int(np.count_nonzero(detected & has_iso & ~correct_iso))
    unisolated = int(np.count_nonzero(detected & ~has_iso))

    far = _ratio(false_alarms, n_free)
    mar = _ratio(missed, n_faulty)
    fir = _ratio(false_iso, n_detected)
    accuracy = None if far is None or mar is None else 1.0 - far - mar
    if n_free and n_faulty == 0:
        accuracy = None  # without faulty samples the paper's accuracy is not defined

    duration_s = float(t_ns[-1] - t_ns[0]) / NS_PER_S if n > 1 else 0.0
    if n > 1:
        duration_s += float(np.median(np.diff(t_ns))) / NS_PER_S  # count the last period
    edges = rising_edges(alarm)
    false_events = int(np.count_nonzero(fault_free[edges])) if edges.size else 0
    free_hours = n_free * (duration_s / n) / 3600.0 if n and duration_s > 0 else 0.0

    confirmed = persistent(alarm, persist)
    figures: list[FaultFigures] = []
    delays: list[float] = []
    recoveries: list[float] = []
    for fault in faults:
        in_fault = t_ns >= fault.start_ns
        if fault.end_ns is not None:
            in_fault &= t_ns < fault.end_ns
        idx = np.flatnonzero(in_fault)
        hits = idx[confirmed[idx]] if idx.size else idx
        delay = float(t_ns[hits[0]] - fault.start_ns) / NS_PER_S if hits.size else None
        recovery = None
        if fault.end_ns is not None and hits.size:
            after = np.flatnonzero((t_ns >= fault.end_ns) & ~alarm)
            if after.size:
                recovery = float(t_ns[after[0]] - fault.end_ns) / NS_PER_S
        det_idx = idx[alarm[idx]] if idx.size else idx
        if det_idx.size and isolated_set is not None:
            hit = np.asarray(isolated_set, dtype=bool)[
                np.ix_(det_idx, np.asarray(fault.sensors, dtype=np.intp))
            ]
            iso_ok = float(np.count_nonzero(hit.any(axis=1))) / det_idx.size
        elif det_idx.size:
            iso = isolated[det_idx]
            iso_ok = float(np.count_nonzero(np.isin(iso, fault.sensors))) / det_idx.size
        else:
            iso_ok = None
        figures.append(
            FaultFigures(
                fault_id=fault.fault_id,
                detected=delay is not None,
                detection_delay_s=delay,
                recovery_delay_s=recovery,
                isolated_correctly=iso_ok,
                faulty_samples=int(idx.size),
            )
        )
        if delay is not None:
            delays.append(delay)
        if recovery is not None:
            recoveries.append(recovery)

    return Metrics(
        samples=n,
        fault_free_samples=n_free,
        faulty_samples=n_faulty,
        false_alarms=false_alarms,
        missed=missed,
        detected_faulty=n_detected,
        false_isolations=false_iso,
        unisolated=unisolated,
        far=far,
        mar=mar,
        accuracy=accuracy,
        fir=fir,
        isolation_accuracy=None if fir is None else 1.0 - fir,
        detection_delay_s=float(np.mean(delays)) if delays else None,
        recovery_delay_s=float(np.mean(recoveries)) if recoveries else None,
        alarm_rate=_ratio(int(np.count_nonzero(alarm)), n),
        alarm_events=int(edges.size),
        false_alarm_events_per_hour=(false_events / free_hours) if free_hours > 0 else None,
        duration_s=duration_s,
        faults=figures,
    )


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
