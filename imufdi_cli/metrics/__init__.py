"""Detection and isolation metrics from ground truth and alarms (docs/metrics.md).

All figures are per sample and per sensor type, with the definitions of Li et al.
(Micromachines 17(3):374, 2026), Table 4, measured out of sample (docs/metrics.md):

- FAR = alarms on fault-free samples / fault-free samples, outside the calibration window
  (``far_calibration``: the same inside it, where the detector was fitted)
- MAR = faulty samples without alarm / faulty samples (outside the calibration window)
- detection rate = 1 - MAR; detection accuracy = 1 - FAR - MAR (Table 4: 100 - 4.98 -
  26.58 = 68.44 %)
- FIR = detected faulty samples isolated to a sensor that is not faulty / detected faulty
  samples; isolation accuracy = 1 - FIR
- detection delay = decision time of the sample completing the first run of ``persist``
  consecutive alarms inside the fault - onset
- isolation delay = decision time of the first alarm inside the fault isolated to one of
  the fault's sensors - onset
- decision latency = mean over samples of (decision time - sample time)
- false alarm events per hour = those events / the tested, fault-free time (gaps excluded:
  :mod:`imufdi_cli.tested_time`)
- false alarm episodes per hour = episodes (the joining rule of the episode builder:
  :class:`~imufdi_cli.sweep.AlarmEpisodes`) that start on a fault-free, scored sample
  outside the calibration window / the fault-free tested time
  (:func:`~imufdi_cli.tested_time.fault_free_tested_hours`), with its exact Poisson 95 %
  upper bound; the mean
  time between false alarms is its inverse
- recovery delay = decision time of the first sample r at or after the fault end from
  which the alarms stop for good - fault end: at least ``persist`` quiet samples from r,
  and no alarm within ``merge_gap_s`` (0.1 s) of r — an alarm that comes back that soon
  is the same alarm episode flickering; one that comes back later is a new episode (and
  a false alarm). Only rows before the next onset on the same sensor type count.

:class:`MetricsAccumulator` computes them in one streaming pass (memory independent of the
log length); :func:`compute_metrics` is the one-call form. A figure whose denominator is
empty (no faulty samples, no detections, a fault never detected) is ``None`` —
"undefined" — never 0.
"""

from imufdi_cli.metrics.accumulator import (
    AMPLITUDE_POINTS,
    MetricsAccumulator,
    compute_metrics,
)
from imufdi_cli.metrics.figures import (
    METRIC_NAMES,
    AmplitudeFigure,
    FaultFigures,
    FaultWindow,
    Metrics,
    mean_metrics,
)
from imufdi_cli.metrics.rows import (
    NS_PER_S,
    apply_budget_match,
    budget_figures,
    episode_rate,
    faulty_matrix,
    judged_isolation,
    persistent,
    rising_edges,
)
from imufdi_cli.tested_time import SamplePeriod, fault_free_tested_hours

__all__ = [
    "AMPLITUDE_POINTS",
    "METRIC_NAMES",
    "NS_PER_S",
    "AmplitudeFigure",
    "FaultFigures",
    "FaultWindow",
    "Metrics",
    "MetricsAccumulator",
    "SamplePeriod",
    "apply_budget_match",
    "budget_figures",
    "compute_metrics",
    "episode_rate",
    "fault_free_tested_hours",
    "faulty_matrix",
    "judged_isolation",
    "mean_metrics",
    "persistent",
    "rising_edges",
]
