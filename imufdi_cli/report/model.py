"""The :class:`Report` of an annotated log and its :class:`ReportEntry` per detector and
sensor type (what :func:`~imufdi_cli.report.scan.build_report` returns, what the gates and
renderers read)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imufdi_cli.metrics import Metrics


@dataclass
class ReportEntry:
    """Metrics of one detector on one sensor type.

    The series (``t_ns`` ... ``faulty``) are only kept for ``--plot`` (``keep_series``), at
    most 2 x :data:`PLOT_POINTS` samples per channel (each the peak of the statistic in its
    bucket of samples, with the bucket's alarms OR-ed; ``scan._Series``); otherwise empty.
    """

    detector: str
    sensor_type: str
    sensor_ids: list[str]
    metrics: Metrics
    t_ns: np.ndarray = field(repr=False)
    statistic: np.ndarray = field(repr=False)
    threshold: np.ndarray = field(repr=False)
    alarm: np.ndarray = field(repr=False)
    scores: np.ndarray = field(repr=False)
    faulty: np.ndarray = field(repr=False)
    roc: dict[str, np.ndarray] | None = field(default=None, repr=False)
    validity: dict[str, int] = field(default_factory=dict)  # clipped, invalid, excluded
    #: isolated sensor index per kept sample (-1: none), for ``--plot``
    isolated: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)


@dataclass
class Report:
    """Everything ``imufdi report`` shows."""

    source: str
    has_truth: bool
    faults: list[dict[str, Any]]
    entries: list[ReportEntry]
    notes: list[str]
    t0_ns: int
    match_far: float | None = None
    #: target of the matched-budget figures, false episodes per hour (``--match-budget``)
    match_budget: float | None = None
    #: explained alarm episodes (the first EPISODES_LISTED of each detector and type, each
    #: with its ``match`` to the truth), docs/episodes.md
    episodes: list[dict[str, Any]] = field(default_factory=list)
    #: per ``detector.type``: EpisodeTally figures, plus ``listed`` and ``omitted``
    episode_scores: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: per (detector, type): (start_ns, end_ns) of every episode counted (listed or not),
    #: for the figures (16 bytes an episode)
    episode_spans: dict[tuple[str, str], list[tuple[int, int]]] = field(default_factory=dict)
    #: per detector: its ``imufdi.detect.<name>`` record (parameters, what its statistic
    #: and scores are), when the log has one
    records: dict[str, dict[str, Any]] = field(default_factory=dict)

    def entry(self, detector: str, sensor_type: str) -> ReportEntry | None:
        for item in self.entries:
            if item.detector == detector and item.sensor_type == sensor_type:
                return item
        return None
