"""The tested, fault-free time: the denominator of every per-hour false-alarm figure.

``imufdi report``'s false alarm events per hour (:mod:`imufdi_cli.metrics`) and its false
episodes per hour (:mod:`imufdi_cli.report`) divide by one figure, computed here:
scored fault-free rows outside the calibration window times the sample period. A gap in
the log, where nothing was tested, adds no time (docs/metrics.md).
"""

from __future__ import annotations

import numpy as np

NS_PER_S = 1_000_000_000


def fault_free_tested_hours(fault_free_samples: int, sample_period_s: float | None) -> float:
    """The tested, fault-free time, in hours: the denominator of every per-hour false
    alarm figure (``false_alarm_events_per_hour``, the episodes' ``false_episodes_per_hour``).

    Parameters
    ----------
    fault_free_samples : int
        Status rows that were tested and scored without an active fault, outside the
        calibration window (:attr:`Metrics.fault_free_samples`; rows ``detect`` excluded
        as clipped, invalid or held are not among them, rows tested with an IMU missing
        are).
    sample_period_s : float or None
        The time one row stands for, s (:attr:`Metrics.sample_period_s`, the median
        interval between rows: :class:`SamplePeriod`). None or <= 0: no time.

    Returns
    -------
    float
        ``fault_free_samples * sample_period_s / 3600``. A gap in the log (no rows: nothing
        was tested) adds nothing, so a 3-hour gap in a 20 s log changes no rate; the
        first-to-last span would count it as 3 hours of testing without an alarm.
    """
    if not sample_period_s or sample_period_s <= 0 or fault_free_samples <= 0:
        return 0.0
    return fault_free_samples * float(sample_period_s) / 3600.0


class SamplePeriod:
    """The sample period of a stream of row times: the median of the first
    :attr:`INTERVALS` positive intervals between consecutive rows (streamed; a gap, a
    dropped row or a few irregular stamps do not move a median)."""

    INTERVALS = 1024

    def __init__(self) -> None:
        self._last: int | None = None
        self._steps: list[np.ndarray] = []
        self._count = 0

    def add(self, t_ns: np.ndarray) -> None:
        """Feed the next rows' times (ns, increasing)."""
        if self._count >= self.INTERVALS or t_ns.size == 0:
            if t_ns.size:
                self._last = int(t_ns[-1])
            return
        t = np.asarray(t_ns, dtype=np.int64)
        if self._last is not None:
            t = np.concatenate([[self._last], t])
        steps = np.diff(t)
        steps = steps[steps > 0][: self.INTERVALS - self._count]
        self._steps.append(steps)
        self._count += int(steps.size)
        self._last = int(t[-1])

    @property
    def seconds(self) -> float | None:
        """The period, s (None before two rows with different times)."""
        if self._count == 0:
            return None
        return float(np.median(np.concatenate(self._steps))) / NS_PER_S
