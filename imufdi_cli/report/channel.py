"""The scoring of one status channel (a detector on a sensor type), shared by ``imufdi
report`` and campaigns: the same rows excluded (:func:`~imufdi_cli.validity.select_rows`),
the same truth windows, accumulators, false alarm episodes, matched figures and reference
delays, whether the rows come from an annotated MCAP (:mod:`imufdi_cli.report.scan`) or
straight from the detection core (:mod:`imufdi_cli.campaign.run`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from imufdi_cli.metrics import FaultWindow, Metrics, MetricsAccumulator
from imufdi_cli.report.truth import Truth

#: The episodes' joining rule (imufdi_cli.episodes.builder.EpisodeBuilder's defaults):
#: alarms across at most this much quiet time are one run ...
MERGE_GAP_S = 0.1
#: ... and runs isolating the same sensor this close are one episode.
JOIN_GAP_S = 1.0


def fault_windows(truth: Truth | None, ids: Sequence[str]) -> list[FaultWindow]:
    """The faults of ``truth`` acting on sensors of one channel (every faulty sensor among
    ``ids``), with their sensors as column indices."""
    if truth is None:
        return []
    return [
        FaultWindow(
            w.fault_id,
            tuple(ids.index(s) for s in w.sensors),
            w.start_ns,
            w.end_ns,
            w.model,
            w.size,
        )
        for w in truth.windows
        if all(s in ids for s in w.sensors)
    ]


def rows_of_block(t_ns: np.ndarray, decided_ns: np.ndarray, out: Any) -> dict[str, np.ndarray]:
    """A detector's output rows (a :class:`~imufdi_cli.detectors.base.DetectionBlock`) as a
    status reader returns them (:func:`~imufdi_cli.mcapio.status.iter_status`): the fields
    the scoring reads, with the types and the per-sensor sets the status messages carry."""
    return {
        "t_ns": np.asarray(t_ns, np.int64),
        "decided_ns": np.asarray(decided_ns, np.int64),
        "statistic": np.asarray(out.statistic, np.float64),
        "threshold": np.asarray(out.threshold, np.float64),
        "alarm": np.asarray(out.alarm, bool),
        "isolated": np.asarray(out.isolated).astype(np.int32),
        "scores": np.asarray(out.scores, np.float64).reshape(len(out), -1),
        "isolated_set": out.isolation_set(),
        "amplitudes": out.amplitude_set(),
    }


class ChannelScore:
    """Streaming figures of one detector on one sensor type.

    Feed the status rows in time order with :meth:`add`; :meth:`metrics` gives the
    figures. Rows ``detect`` marked clipped or invalid (in the record's ``validity``) and
    rows outside ``window`` are counted and left out of every figure, as the report does.

    Parameters
    ----------
    detector, sensor_type : str
    ids : list of str
        The channel's sensor ids.
    truth : Truth or None
    calibration_ns : (start_ns, end_ns) or None
    record : dict or None
        The detector's ``imufdi.detect.<name>`` record (``t0_ns``, ``validity``,
        ``detector_metadata``); a campaign passes the same fields, kept current.
    window : (start_s, end_s or None), optional
        ``report --start/--end``.
    persist : int
    rate_hz : float, optional
        The array's sample rate: the joining rule of the false alarm episodes and the
        reference delays need it (None: those figures are undefined).
    keep_series : bool
        Keep the kept rows' series for ``--plot`` (:class:`~imufdi_cli.report.scan._Series`).
    budget_levels : bool
        Count the false episodes at every level of the matched budget (what
        ``match_budget`` and the budget curve need; a report without ``--match-budget``
        leaves them out).
    """

    def __init__(
        self,
        detector: str,
        sensor_type: str,
        ids: list[str],
        *,
        truth: Truth | None,
        calibration_ns: tuple[int, int] | None,
        record: dict[str, Any] | None,
        window: tuple[float, float | None] | None = None,
        persist: int = 1,
        rate_hz: float | None = None,
        keep_series: bool = False,
        budget_levels: bool = True,
    ) -> None:
        from imufdi_cli.sweep import episode_gap_rows

        self.detector = detector
        self.sensor_type = sensor_type
        self.ids = ids
        self.truth = truth
        self.record = record
        self.window = window
        self.rate_hz = rate_hz if rate_hz and rate_hz > 0 else None
        gaps = (
            None
            if self.rate_hz is None
            else episode_gap_rows(self.rate_hz, MERGE_GAP_S, JOIN_GAP_S)
        )
        self.accumulator = MetricsAccumulator(
            len(ids),
            fault_windows(truth, ids),
            calibration_ns=calibration_ns,
            persist=persist,
            sensor_ids=ids,
            episode_gaps=gaps,
            budget_levels=budget_levels,
        )
        self.validity = {"clipped": 0, "invalid": 0, "excluded": 0, "missing": 0}
        self.origin_ns: int | None = None  # the first status row's time
        self.last_ns: int | None = None  # the last scored row's time
        self.all_decided = True
        self.series: Any = None
        if keep_series:
            from imufdi_cli.report.scan import _Series

            self.series = _Series()

    def add(self, rows: Mapping[str, np.ndarray], origin_ns: int | None = None) -> None:
        """Score the next status rows (the fields of
        :func:`~imufdi_cli.mcapio.status.iter_status`); ``origin_ns``: time zero of the
        window when the record has no ``t0_ns`` (default: the channel's first row)."""
        from imufdi_cli.validity import select_rows

        t_ns = rows["t_ns"]
        if self.origin_ns is None and t_ns.size:
            self.origin_ns = int(t_ns[0])
        origin = origin_ns if origin_ns is not None else self.origin_ns
        selection = select_rows(
            t_ns, self.record, self.sensor_type, self.window, origin_ns=origin or 0
        )
        self.validity["clipped"] += selection.clipped
        self.validity["invalid"] += selection.invalid
        self.validity["excluded"] += selection.excluded
        self.validity["missing"] += selection.missing
        self.all_decided &= "decided_ns" in rows
        keep = selection.keep
        kept = np.flatnonzero(keep)
        if kept.size:
            self.last_ns = int(t_ns[kept[-1]])
        self.accumulator.update(
            t_ns,
            rows["alarm"],
            rows["isolated"],
            decided_ns=rows.get("decided_ns"),
            isolated_set=rows["isolated_set"],
            statistic=rows["statistic"],
            threshold=rows["threshold"],
            scores=rows.get("scores"),
            amplitudes=rows.get("amplitudes"),
            scored=keep,
            amplitude=rows.get("amplitude"),
            best_score=rows.get("best_score"),
        )
        if self.series is not None:
            from imufdi_cli.report.scan import SERIES_FIELDS

            everything = bool(keep.all())
            self.series.add({k: rows[k] if everything else rows[k][keep] for k in SERIES_FIELDS})

    def metrics(
        self,
        match_far: float | None = None,
        match_budget: float | None = None,
    ) -> tuple[Metrics, list[str]]:
        """The figures, with the matched FAR (``match_far``, a rate in (0, 1)) and the
        matched budget (``match_budget``, false episodes per hour) when asked for; and the
        notes of what could not be matched. Without truth the truth-based figures are
        None, and every alarm episode counts as false (a log taken as fault-free)."""
        acc = self.accumulator
        metrics = acc.result()
        notes: list[str] = []
        label = f"{self.detector}.{self.sensor_type}"
        has_truth = self.truth is not None
        if match_far is not None and has_truth:
            note = acc.matched(metrics, match_far)
            if note:
                notes.append(f"{label} at FAR {match_far:g}: {note}")
        if match_budget is not None:
            from imufdi_cli.sweep import format_rate

            note = acc.matched_budget(metrics, match_budget)
            if note:
                notes.append(f"{label} at budget {format_rate(match_budget)}: {note}")
        if metrics.false_episodes is None and self.rate_hz is None:
            notes.append(
                f"{label}: no sample rate recorded (imufdi.array): false alarm episodes undefined"
            )
        reference_delays(metrics, acc.windows, self.budget_metadata(), self.ids, self.rate_hz)
        if not has_truth:
            metrics.far = metrics.mar = metrics.accuracy = None
            metrics.fir = metrics.isolation_accuracy = None
            metrics.false_alarm_events_per_hour = metrics.far_calibration = None
            metrics.mar_at_budget = metrics.fir_at_budget = None
            metrics.detection_delay_s_at_budget = metrics.isolation_delay_s_at_budget = None
        return metrics, notes

    def budget_metadata(self) -> tuple[dict[str, Any], list[str]] | None:
        """The detector's ``types.<type>.budget`` metadata (when it decided under a
        false-alarm budget) and the sensor ids its per-sensor entries follow."""
        record = self.record or {}
        meta = record.get("detector_metadata")
        types = meta.get("types") if isinstance(meta, Mapping) else None
        entry = types.get(self.sensor_type) if isinstance(types, Mapping) else None
        budget = entry.get("budget") if isinstance(entry, Mapping) else None
        if not isinstance(budget, Mapping):
            return None
        ids = entry.get("sensor_ids") if isinstance(entry, Mapping) else None
        return dict(budget), list(ids) if isinstance(ids, list) else list(self.ids)


def reference_delays(
    metrics: Metrics,
    windows: Sequence[FaultWindow],
    budget: tuple[dict[str, Any], list[str]] | None,
    ids: Sequence[str],
    rate_hz: float | None,
) -> None:
    """Fill each fault's ``reference_delay_s`` (the optimal sequential test's delay for its
    size, Lorden 1971: :func:`~imufdi_cli.maths.sequential.lorden_delay_samples` for a
    step, :func:`~imufdi_cli.maths.sequential.lorden_drift_samples` for a drift) and
    ``delay_ratio`` (detection delay / reference), and their means in ``metrics``.

    The reference is the test that knows the fault's size, at the detector's false-alarm
    budget (an average run length of ``rate_hz x 3600 / budget`` samples between false
    alarms) over the bank's hypotheses, for the evidence of the fault's most sensitive
    faulty sensor (``sensitivity``: z units per SI unit, whitened parity noise and the
    long-run factor included), whose fault-free noise has the outliers the detector
    measured on its calibration window (``outlier_share``, ``outlier_size``: Lorden's
    information of a step in that noise, :func:`~imufdi_cli.maths.sequential.step_information`;
    Gaussian when the channel has none). None without a budget, for other fault models, or without
    the fault's size."""
    if budget is None or not rate_hz:
        return
    from imufdi_cli.maths.sequential import lorden_delay_samples, lorden_drift_samples

    meta, sensor_ids = budget
    try:
        per_hour = float(meta["false_alarms_per_hour"])
        hypotheses = int(meta["hypotheses"])
        sensitivity = [float(g) for g in meta["sensitivity"]]
        # the evidence's outliers (written since the reference counts them; a status
        # channel without them is taken as Gaussian, the reference it was reported with)
        contamination = float(meta.get("outlier_share") or 0.0)
        outlier = float(meta.get("outlier_size") or 0.0)
    except (KeyError, TypeError, ValueError):
        return
    if not per_hour > 0 or hypotheses < 1:
        return
    run_length = rate_hz * 3600.0 / per_hour
    references: list[float] = []
    ratios: list[float] = []
    for figure, window in zip(metrics.faults, windows):
        if window.model not in ("step", "drift") or not window.size:
            continue
        gains = [
            sensitivity[sensor_ids.index(ids[j])]
            for j in window.sensors
            if ids[j] in sensor_ids and sensor_ids.index(ids[j]) < len(sensitivity)
        ]
        gain = max(gains, default=0.0)
        if not gain > 0:
            continue
        size = abs(float(window.size)) * gain
        if window.model == "step":
            samples = lorden_delay_samples(
                size * size, run_length, hypotheses, contamination, outlier
            )
        else:
            samples = lorden_drift_samples(
                size / rate_hz, run_length, hypotheses, contamination, outlier
            )
        if not math.isfinite(samples):
            continue
        figure.reference_delay_s = samples / rate_hz
        references.append(figure.reference_delay_s)
        if figure.detection_delay_s is not None and figure.reference_delay_s > 0:
            figure.delay_ratio = figure.detection_delay_s / figure.reference_delay_s
            ratios.append(figure.delay_ratio)
    metrics.reference_delay_s = float(np.mean(references)) if references else None
    metrics.delay_ratio = float(np.mean(ratios)) if ratios else None
