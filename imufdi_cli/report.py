"""``imufdi report``: metrics of an annotated log, renderers and CI gates.

:func:`build_report` reads the detector status channels and the ground truth of an
annotated MCAP and computes the metrics of DESIGN.md §7 per detector and sensor type.
Renderers turn a :class:`Report` into JSON, Markdown (the layout of Li et al. Table 4), CSV
and JUnit XML; :func:`parse_gate` / :func:`evaluate_gates` implement ``--fail-if``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import operator
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, BinaryIO
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from imufdi_cli.errors import GateError, McapInputError, UsageError
from imufdi_cli.jsonout import dumps as json_dumps
from imufdi_cli.metrics import (
    METRIC_NAMES,
    FaultWindow,
    Metrics,
    MetricsAccumulator,
    faulty_matrix,
)
from imufdi_cli.progress import LogTimeProgress, ProgressCallback

# --- building --------------------------------------------------------------------------


@dataclass
class ReportEntry:
    """Metrics of one detector on one sensor type.

    The series (``t_ns`` ... ``faulty``) are only kept for ``--plot`` (``keep_series``), at
    most :data:`PLOT_POINTS` samples per channel (evenly decimated); otherwise empty.
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
    #: explained alarm episodes (the first EPISODES_LISTED of each detector and type, each
    #: with its ``match`` to the truth), docs/episodes.md
    episodes: list[dict[str, Any]] = field(default_factory=list)
    #: per ``detector.type``: EpisodeTally figures, plus ``listed`` and ``omitted``
    episode_scores: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: per detector: its ``imufdi.detect.<name>`` record (parameters, what its statistic
    #: and scores are), when the log has one
    records: dict[str, dict[str, Any]] = field(default_factory=dict)

    def entry(self, detector: str, sensor_type: str) -> ReportEntry | None:
        for item in self.entries:
            if item.detector == detector and item.sensor_type == sensor_type:
                return item
        return None


@dataclass(frozen=True)
class TruthWindow:
    """An injected fault with absolute times, as recorded in ``imufdi.faults``."""

    fault_id: str
    sensors: tuple[str, ...]
    start_ns: int
    end_ns: int | None


@dataclass
class Truth:
    windows: list[TruthWindow]
    descriptions: list[dict[str, Any]]


def truth_windows(metadata: dict[str, dict[str, str]]) -> Truth | None:
    """Ground truth of a log from its ``imufdi.faults`` record (None when there is none).

    Each injection run records its log start ``t0_ns``; fault times are relative to it.
    """
    from imufdi_cli.errors import TruthError
    from imufdi_cli.faults import METADATA_NAME, Fault

    record_meta = metadata.get(METADATA_NAME)
    if record_meta is None:
        return None
    try:
        record = json.loads(record_meta["json"])
        runs = [*record.get("previous", []), record]
        windows = []
        descriptions = []
        for run in runs:
            t0 = int(run["t0_ns"])
            for item in run.get("faults", []):
                fault = Fault.from_dict(item)
                end = None if fault.until_ns is None else t0 + fault.until_ns
                windows.append(TruthWindow(fault.id, tuple(fault.sensors), t0 + fault.at_ns, end))
                descriptions.append(fault.to_dict())
    except (KeyError, TypeError, ValueError) as err:
        raise TruthError(f"{METADATA_NAME} metadata is malformed ({err})") from err
    return Truth(windows=windows, descriptions=descriptions)


def calibration_windows(
    metadata: dict[str, dict[str, str]],
) -> dict[str, tuple[int, int] | None]:
    """Detector name -> calibration window ``(start_ns, end_ns)`` from the
    ``imufdi.detect.<name>`` records; a detector absent from the result recorded none
    (a log from an imufdi before the window was recorded)."""
    out: dict[str, tuple[int, int] | None] = {}
    for name, data in metadata.items():
        if not name.startswith("imufdi.detect."):
            continue
        try:
            record = json.loads(data.get("json", "{}"))
        except ValueError:
            continue
        if not isinstance(record, dict) or "calibration_window_ns" not in record:
            continue
        window = record["calibration_window_ns"]
        detector = name.removeprefix("imufdi.detect.")
        if window is None:
            out[detector] = None
        else:
            try:
                out[detector] = (int(window[0]), int(window[1]))
            except (TypeError, ValueError, IndexError) as err:
                raise McapInputError(
                    f"{name}: calibration_window_ns is malformed ({window!r})"
                ) from err
    return out


#: Samples per channel kept for ``--plot``.
PLOT_POINTS = 20_000


class _Series:
    """Evenly decimated copy of a status channel for plots (bounded memory).

    Every ``stride``-th sample is kept; its ``alarm`` is the OR of the alarms since the
    previous kept sample, so that no alarm disappears from the plot however long the log.
    """

    def __init__(self) -> None:
        self.stride = 1
        self.seen = 0
        self.parts: list[dict[str, np.ndarray]] = []
        self.kept = 0
        self.pending_alarm = False  # an alarm after the last kept sample

    def add(self, rows: dict[str, np.ndarray]) -> None:
        n = int(rows["t_ns"].size)
        first = (-self.seen) % self.stride
        pick = np.arange(first, n, self.stride)
        self.seen += n
        alarm = np.asarray(rows["alarm"], bool) if "alarm" in rows else None
        if pick.size:
            part = {k: v[pick] for k, v in rows.items()}
            if alarm is not None:
                count = np.concatenate([[0], np.cumsum(alarm)])  # alarms in rows[:i]
                ends = pick + 1
                starts = np.concatenate([[0], ends[:-1]])
                part["alarm"] = (count[ends] - count[starts]) > 0
                part["alarm"][0] |= self.pending_alarm
                self.pending_alarm = bool(alarm[pick[-1] + 1 :].any())
            self.parts.append(part)
            self.kept += int(pick.size)
        elif alarm is not None:
            self.pending_alarm |= bool(alarm.any())
        if self.kept > 2 * PLOT_POINTS:
            whole = self.arrays()
            keep = slice(0, None, 2)
            halved = {k: v[keep] for k, v in whole.items()}
            if "alarm" in whole:  # kept sample 2j also covers the dropped 2j - 1
                merged = whole["alarm"][0::2].copy()
                odd = whole["alarm"][1::2]
                merged[1 : odd.size + 1] |= odd[: merged.size - 1]
                if odd.size == merged.size:  # the last sample was dropped
                    self.pending_alarm |= bool(odd[-1])
                halved["alarm"] = merged
            self.parts = [halved]
            self.kept = int(self.parts[0]["t_ns"].size)
            self.stride *= 2

    def arrays(self) -> dict[str, np.ndarray]:
        keys = self.parts[0].keys() if self.parts else ()
        return {k: np.concatenate([p[k] for p in self.parts]) for k in keys}


def _open_seekable(source: str | BinaryIO) -> tuple[Any, bool]:
    """A seekable binary stream of ``source`` (stdin and pipes are spooled to a temporary
    file, so that the metadata at the end of the file is known before the first message).
    Returns the stream and whether the caller must close it."""
    import shutil
    import sys
    import tempfile

    if isinstance(source, str) and source != "-":
        return source, False
    stream = sys.stdin.buffer if source == "-" else source
    assert not isinstance(stream, str)
    try:
        if stream.seekable():
            return stream, False
    except (AttributeError, OSError, ValueError):
        pass
    spool = tempfile.TemporaryFile()
    shutil.copyfileobj(stream, spool, 1 << 20)
    spool.seek(0)
    return spool, True


def build_report(
    source: str | BinaryIO,
    *,
    persist: int = 1,
    match_far: float | None = None,
    keep_series: bool = False,
    keep_roc: bool = False,
    window: tuple[float, float | None] | None = None,
    progress: ProgressCallback | None = None,
) -> Report:
    """Compute the report of an annotated log in one streaming pass.

    Parameters
    ----------
    source : path, ``"-"`` or binary stream
        An MCAP written by ``imufdi detect`` (stdin is spooled to a temporary file).
    persist : int
        Detection delays count the first run of this many alarms; recovery needs this many
        quiet samples after the last alarm (docs/metrics.md).
    match_far : float, optional
        Target FAR in (0, 1) for the matched-FAR figures (``mar_at_far``, ...).
    keep_series : bool
        Keep (decimated) status series for :func:`imufdi_cli.plots.plot_report`.
    keep_roc : bool
        Keep the swept curve of each entry (``ReportEntry.roc``) for :func:`to_roc_csv`.
    window : (start_s, end_s or None), optional
        Score only samples in this range (seconds from the log's first sample, as
        ``detect`` recorded it). Samples ``detect`` excluded as clipped or invalid are never
        scored (:func:`imufdi_cli.validity.select_rows`).
    progress : callable, optional
        ``progress(seconds done, log seconds or None)`` (:mod:`imufdi_cli.progress`).

    Memory does not depend on the log length (one chunk, fixed histograms), except for
    the bounded series of ``keep_series``.
    """
    from imufdi_cli.mcapio import McapSource, iter_status

    if match_far is not None and not 0.0 < match_far < 1.0:
        raise UsageError(f"--match-far must be in (0, 1), got {match_far:g}")
    name = source if isinstance(source, str) else "<stream>"
    name = "<stdin>" if name == "-" else name
    stream, close = _open_seekable(source)
    try:
        with McapSource(stream) as src:
            metadata = dict(src.metadata)  # seekable: read from the summary up front
            scan = _StatusScan(metadata, window, persist, keep_series)
            episodes = _EpisodeCollector(scan.truth, scan.windows_cal, window, scan.first_ns)
            tracker = LogTimeProgress(progress, getattr(src, "summary_time_range", None))
            for detector, sensor_type, ids, rows in iter_status(src, others=episodes.batch):
                if rows["t_ns"].size:
                    tracker.at(int(rows["t_ns"][-1]))
                scan.add(detector, sensor_type, ids, rows)
            problems = list(src.warnings)
    finally:
        if close:
            stream.close()
    if not scan.accumulators:
        raise McapInputError(
            f"{name}: no detector status channels (/imufdi/<detector>/<type>); "
            "run `imufdi detect` on the log first" + (f"; {problems[0]}" if problems else "")
        )
    notes = scan.notes(problems)
    entries = [scan.entry(key, match_far, keep_roc, notes) for key in sorted(scan.accumulators)]
    if match_far is not None and scan.truth is not None:
        notes.append(
            f"matched FAR {match_far:g}: the threshold of each detector's raw statistic is"
            " scaled (alarm when statistic >= scale x threshold, per sample); confirmation"
            " and persistence rules are not re-run (docs/metrics.md)"
        )
    episode_scores = episodes.scores(scan.fault_free_hours(entries))  # takes pending ones
    return Report(
        source=name,
        has_truth=scan.truth is not None,
        faults=[] if scan.truth is None else scan.truth.descriptions,
        entries=entries,
        notes=notes,
        t0_ns=min(scan.first_ns.values()) if scan.first_ns else 0,
        match_far=match_far,
        episode_scores=episode_scores,
        episodes=episodes.listed,
        records={d: r for d, r in scan.records.items() if r is not None},
    )


#: the status fields kept for plots (``keep_series``)
_SERIES_FIELDS = ("t_ns", "statistic", "threshold", "alarm", "isolated", "scores")


class _StatusScan:
    """What :func:`build_report`'s pass over the status channels gathers per
    ``(detector, sensor type)``: metric accumulators, sensor ids, first and last sample
    times, whether every row had a decision time, validity counts and plot series."""

    def __init__(
        self,
        metadata: dict[str, dict[str, str]],
        window: tuple[float, float | None] | None,
        persist: int,
        keep_series: bool,
    ) -> None:
        self.truth = truth_windows(metadata)
        self.windows_cal = calibration_windows(metadata)
        self.metadata = metadata
        self.window = window
        self.persist = persist
        self.keep_series = keep_series
        self.records = {d: _detect_record(metadata, d) for d in self.windows_cal}
        self.accumulators: dict[tuple[str, str], MetricsAccumulator] = {}
        self.ids_of: dict[tuple[str, str], list[str]] = {}
        self.series: dict[tuple[str, str], _Series] = {}
        #: shared with the episode collector, which reads the origins as they appear
        self.first_ns: dict[tuple[str, str], int] = {}
        self.all_decided: dict[tuple[str, str], bool] = {}
        self.last_ns: dict[tuple[str, str], int] = {}
        self.validity: dict[tuple[str, str], dict[str, int]] = {}

    def add(
        self, detector: str, sensor_type: str, ids: list[str], rows: dict[str, np.ndarray]
    ) -> None:
        """Score one batch of status rows of a channel (those ``detect`` marked clipped or
        invalid, and those outside the window, are counted and left out)."""
        from imufdi_cli.validity import select_rows

        key = (detector, sensor_type)
        if key not in self.first_ns and rows["t_ns"].size:
            origin = int(rows["t_ns"][0])
        else:
            origin = self.first_ns.get(key, 0)
        if detector not in self.records:
            self.records[detector] = _detect_record(self.metadata, detector)
        selection = select_rows(
            rows["t_ns"], self.records[detector], sensor_type, self.window, origin_ns=origin
        )
        counts = self.validity.setdefault(key, {"clipped": 0, "invalid": 0, "excluded": 0})
        counts["clipped"] += selection.clipped
        counts["invalid"] += selection.invalid
        counts["excluded"] += selection.excluded
        if not selection.keep.all():
            rows = {k: v[selection.keep] for k, v in rows.items()}
        acc = self.accumulators.get(key)
        if acc is None:
            acc = _accumulator(self.truth, ids, self.windows_cal.get(detector), self.persist)
            self.accumulators[key] = acc
            self.ids_of[key] = ids
            self.first_ns[key] = origin
            self.all_decided[key] = True
            if self.keep_series:
                self.series[key] = _Series()
        self.all_decided[key] &= "decided_ns" in rows
        if rows["t_ns"].size:
            self.last_ns[key] = int(rows["t_ns"][-1])
        acc.update(
            rows["t_ns"],
            rows["alarm"],
            rows["isolated"],
            decided_ns=rows.get("decided_ns"),
            isolated_set=rows["isolated_set"],
            statistic=rows["statistic"],
            threshold=rows["threshold"],
            scores=rows["scores"],
        )
        if self.keep_series:
            self.series[key].add({k: rows[k] for k in _SERIES_FIELDS})

    def notes(self, problems: list[str]) -> list[str]:
        """What the reader must know about the whole log: input damage, missing truth,
        older logs, samples not scored."""
        # a damaged log is reported on what could be read, and says so
        notes = [f"input: {problem}" for problem in problems]
        if self.truth is None:
            notes.append(
                "no ground truth in this log (inject faults with `imufdi inject`): "
                "FAR, MAR, FIR and delays need truth; alarm statistics only"
            )
        old = sorted({d for d, _ in self.accumulators if d not in self.windows_cal})
        if old:
            notes.append(
                f"{', '.join(old)}: no calibration window recorded (log from an older imufdi):"
                " FAR and alarm rate count every sample, including the in-sample calibration"
            )
        undecided = sorted({d for (d, _), ok in self.all_decided.items() if not ok})
        if undecided:
            notes.append(
                f"{', '.join(undecided)}: status without decision times (older imufdi): delays"
                " are at sample time"
            )
        for (detector, sensor_type), counts in sorted(self.validity.items()):
            if counts["excluded"]:
                notes.append(
                    f"{detector}.{sensor_type}: {counts['excluded']} samples not scored"
                    f" ({counts['clipped']} clipped, {counts['invalid']} invalid in the range)"
                )
        return notes

    def entry(
        self,
        key: tuple[str, str],
        match_far: float | None,
        keep_roc: bool,
        notes: list[str],
    ) -> ReportEntry:
        """The finished :class:`ReportEntry` of one channel (a matched-FAR problem is
        appended to ``notes``); without truth the truth-based metrics are None."""
        detector, sensor_type = key
        has_truth = self.truth is not None
        acc = self.accumulators[key]
        metrics = acc.result()
        roc = None
        if match_far is not None and has_truth:
            note = acc.matched(metrics, match_far)
            if note:
                notes.append(f"{detector}.{sensor_type} at FAR {match_far:g}: {note}")
        if keep_roc and has_truth and acc.sweep is not None and acc.sweep.sweepable:
            roc = acc.sweep.curve()
        if not has_truth:
            metrics.far = metrics.mar = metrics.accuracy = None
            metrics.fir = metrics.isolation_accuracy = None
            metrics.false_alarm_events_per_hour = metrics.far_calibration = None
        arrays = self.series[key].arrays() if key in self.series else {}
        n_s = len(self.ids_of[key])
        t_ns = arrays.get("t_ns", np.zeros(0, np.int64))
        return ReportEntry(
            detector=detector,
            sensor_type=sensor_type,
            sensor_ids=self.ids_of[key],
            metrics=metrics,
            t_ns=t_ns,
            statistic=arrays.get("statistic", np.zeros(0)),
            threshold=arrays.get("threshold", np.zeros(0)),
            alarm=arrays.get("alarm", np.zeros(0, bool)),
            scores=arrays.get("scores", np.zeros((0, n_s))),
            faulty=faulty_matrix(t_ns, acc.windows, n_s),
            isolated=arrays.get("isolated", np.zeros(0, np.int64)),
            roc=roc,
            validity=self.validity.get(key, {}),
        )

    def fault_free_hours(self, entries: list[ReportEntry]) -> dict[tuple[str, str], float]:
        """Hours of each channel's log span, times its fault-free share when there is
        truth (the denominator of the episode rates)."""
        hours = {}
        for entry in entries:
            key, metrics = (entry.detector, entry.sensor_type), entry.metrics
            span_h = (self.last_ns.get(key, 0) - self.first_ns[key]) * 1e-9 / 3600
            share = metrics.fault_free_samples / metrics.samples if metrics.samples else 0.0
            hours[key] = span_h * (share if self.truth is not None else 1.0)
        return hours


def _detect_record(metadata: dict[str, dict[str, str]], detector: str) -> dict[str, Any] | None:
    """The decoded ``imufdi.detect.<detector>`` record, or None."""
    try:
        record = json.loads(metadata[f"imufdi.detect.{detector}"]["json"])
    except (KeyError, TypeError, ValueError):
        return None
    return record if isinstance(record, dict) else None


#: episodes listed per detector and sensor type (all are counted)
EPISODES_LISTED = 200


class _EpisodeCollector:
    """Explained episodes from the ``/imufdi/events`` channel, matched to the truth as
    they stream by; keeps the first EPISODES_LISTED per detector and type."""

    def __init__(
        self,
        truth: Truth | None,
        calibration: dict[str, tuple[int, int] | None],
        window: tuple[float, float | None] | None = None,
        origins: dict[tuple[str, str], int] | None = None,
    ) -> None:
        self.calibration = calibration
        self.pending: list[tuple[dict[str, Any], dict[str, Any]]] = []
        self.window = window  # --start/--end, seconds from each channel's first sample
        self.origins = origins if origins is not None else {}
        self.faults = (
            []
            if truth is None
            else [
                {**d, "start_ns": w.start_ns, "end_ns": w.end_ns}
                for w, d in zip(truth.windows, truth.descriptions)
            ]
        )
        self.has_truth = truth is not None
        self.listed: list[dict[str, Any]] = []
        self.tallies: dict[tuple[str, str], Any] = {}
        self.counts: dict[tuple[str, str], int] = {}

    def batch(self, batch: Any, channel: Any) -> None:
        from imufdi_cli.episodes import match_episodes
        from imufdi_cli.mcapio.events import EVENTS_TOPIC, decode_events, is_event_channel

        if channel.topic != EVENTS_TOPIC or not is_event_channel(channel):
            return
        found = [e["episode"] for e in decode_events(batch, channel) if "episode" in e]
        matches = (
            match_episodes(found, self.faults)
            if self.has_truth
            else [{"match": None} for _ in found]
        )
        self._take(list(zip(found, matches)))

    def _take(self, items: list[tuple[dict[str, Any], dict[str, Any]]]) -> None:
        """Count and list episodes (with their matches) inside --start/--end; those of a
        channel whose first status row has not been read yet wait for it."""
        from imufdi_cli.episodes import EpisodeTally

        if self.pending:
            items, self.pending = self.pending + items, []
        for episode, match in items:
            key = (episode["detector"], episode["sensor_type"])
            if self.window is not None and key not in self.origins:
                self.pending.append((episode, match))
                continue
            if not self._inside(key, episode["start_ns"]):
                continue
            tally = self.tallies.setdefault(key, EpisodeTally())
            window = self.calibration.get(episode["detector"])
            if window is not None and episode["start_ns"] < window[1]:
                # inside the calibration window: in sample, listed but never scored
                match = {**match, "match": "calibration"}
                tally.calibration += 1
            elif self.has_truth:
                tally.add(match)
            else:
                tally.episodes += 1
            self.counts[key] = self.counts.get(key, 0) + 1
            if self.counts[key] <= EPISODES_LISTED:
                self.listed.append({**episode, **match})

    def _inside(self, key: tuple[str, str], start_ns: int) -> bool:
        """Whether an episode starting at ``start_ns`` is inside --start/--end."""
        origin = self.origins.get(key)
        if self.window is None or origin is None:
            return True
        start_s, end_s = self.window
        rel = (start_ns - origin) * 1e-9
        return rel >= start_s and (end_s is None or rel < end_s)

    def scores(self, hours: dict[tuple[str, str], float]) -> dict[str, dict[str, Any]]:
        if self.pending:  # read before their channel's first status row: windowed now
            pending, self.pending = self.pending, []
            self._take(pending)
        if self.pending:  # channels without status rows: no origin, nothing to window
            self.window, pending, self.pending = None, self.pending, []
            self._take(pending)
        out = {}
        for key, tally in sorted(self.tallies.items()):
            result = tally.result(hours.get(key) if self.has_truth else None)
            if not self.has_truth:
                span = hours.get(key)
                result = {
                    "episodes": tally.episodes,
                    "episodes_per_hour": tally.episodes / span if span else None,
                }
            result["listed"] = min(self.counts[key], EPISODES_LISTED)
            result["omitted"] = max(0, self.counts[key] - EPISODES_LISTED)
            out[f"{key[0]}.{key[1]}"] = result
        return out


def _accumulator(
    truth: Truth | None,
    ids: list[str],
    calibration: tuple[int, int] | None,
    persist: int,
) -> MetricsAccumulator:
    windows: list[FaultWindow] = []
    if truth is not None:
        windows = [
            FaultWindow(w.fault_id, tuple(ids.index(s) for s in w.sensors), w.start_ns, w.end_ns)
            for w in truth.windows
            if all(s in ids for s in w.sensors)
        ]
    return MetricsAccumulator(len(ids), windows, calibration_ns=calibration, persist=persist)


def parse_far(text: str) -> float:
    """``"1%"``, ``"0.01"`` -> 0.01; UsageError (exit 2) outside (0, 1) or malformed."""
    raw = text.strip()
    try:
        value = float(raw[:-1]) / 100.0 if raw.endswith("%") else float(raw)
    except ValueError:
        raise UsageError(f"--match-far {text!r} is not a rate (e.g. 1% or 0.01)") from None
    if not (0.0 < value < 1.0) or math.isnan(value):
        raise UsageError(f"--match-far {text!r} must be in (0, 1) (e.g. 1% or 0.01)")
    return value


# --- gates -----------------------------------------------------------------------------

OPERATORS: dict[str, Callable[[float, float], bool]] = {
    ">": operator.gt,
    ">=": operator.ge,
    "<": operator.lt,
    "<=": operator.le,
    "==": operator.eq,
    "!=": operator.ne,
}
_GATE = re.compile(
    r"^\s*([A-Za-z0-9_*-]+)\.([A-Za-z*]+)\.([A-Za-z_]+)\s*(>=|<=|==|!=|>|<)\s*"
    r"([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(%?)\s*$"
)


@dataclass(frozen=True)
class Gate:
    """``DETECTOR.TYPE.METRIC OP VALUE``: fails when the comparison is true."""

    text: str
    detector: str
    sensor_type: str
    metric: str
    op: str
    value: float


@dataclass
class GateResult:
    gate: Gate
    target: str  # "glt.gyro"
    actual: float | None
    failed: bool
    message: str


def parse_gate(text: str, known_detectors: Iterable[str]) -> Gate:
    """Parse a ``--fail-if`` expression (e.g. ``glt.gyro.far > 0.01`` or ``*.accel.mar >= 5%``).

    Raises GateError (exit 2) naming what is wrong and the valid choices.
    """
    match = _GATE.match(text)
    if match is None:
        raise GateError(
            f"--fail-if {text!r} is not of the form DETECTOR.TYPE.METRIC OP NUMBER "
            "(e.g. 'glt.gyro.far > 0.01'; OP one of > >= < <= == !=)"
        )
    detector, sensor_type, metric, op, number, percent = match.groups()
    known = sorted(known_detectors)
    if detector != "*" and detector not in known:
        raise GateError(
            f"--fail-if {text!r}: unknown detector {detector!r}; valid: {', '.join(known)}, *"
        )
    if sensor_type not in ("gyro", "accel", "mag", "*"):
        raise GateError(
            f"--fail-if {text!r}: unknown sensor type {sensor_type!r}; valid: gyro, accel, mag, *"
        )
    if metric not in METRIC_NAMES:
        raise GateError(
            f"--fail-if {text!r}: unknown metric {metric!r}; valid: {', '.join(METRIC_NAMES)}"
        )
    value = float(number) / (100.0 if percent else 1.0)
    return Gate(text.strip(), detector, sensor_type, metric, op, value)


def evaluate_gates(report: Report, gates: Sequence[Gate]) -> list[GateResult]:
    """Evaluate gates; a gate naming results absent from the log raises GateError.

    A gate whose metric is undefined on this log (e.g. MAR without faulty samples) fails:
    a CI gate must not pass on a figure that could not be computed.
    """
    results = []
    for gate in gates:
        matched = [
            e
            for e in report.entries
            if gate.detector in ("*", e.detector) and gate.sensor_type in ("*", e.sensor_type)
        ]
        if not matched:
            present = ", ".join(f"{e.detector}.{e.sensor_type}" for e in report.entries)
            raise GateError(
                f"--fail-if {gate.text!r}: no results for {gate.detector}.{gate.sensor_type} "
                f"in this log (present: {present or 'none'})"
            )
        for entry in matched:
            actual = entry.metrics.value(gate.metric)
            target = f"{entry.detector}.{entry.sensor_type}.{gate.metric}"
            if actual is None:
                results.append(
                    GateResult(gate, target, None, True, f"{target} is undefined on this log")
                )
                continue
            failed = OPERATORS[gate.op](actual, gate.value)
            verdict = "FAILED" if failed else "passed"
            results.append(
                GateResult(
                    gate,
                    target,
                    actual,
                    failed,
                    f"{verdict}: {target} = {actual:.6g} (fail if {gate.op} {gate.value:g})",
                )
            )
    return results


# --- renderers -------------------------------------------------------------------------

#: Columns of the tables: (metric, header, scale, format)
TABLE_COLUMNS: list[tuple[str, str, float, str]] = [
    ("far", "FAR %", 100.0, "{:.2f}"),
    ("mar", "MAR %", 100.0, "{:.2f}"),
    ("accuracy", "Accuracy %", 100.0, "{:.2f}"),
    ("fir", "FIR %", 100.0, "{:.2f}"),
    ("detection_delay_s", "Delay s", 1.0, "{:.3f}"),
    ("isolation_delay_s", "Iso delay s", 1.0, "{:.3f}"),
    ("decision_latency_s", "Latency s", 1.0, "{:.3f}"),
    ("recovery_delay_s", "Recovery s", 1.0, "{:.3f}"),
    ("far_calibration", "FAR cal %", 100.0, "{:.2f}"),
    ("alarm_rate", "Alarm %", 100.0, "{:.2f}"),
    ("alarm_events", "Events", 1.0, "{:.0f}"),
]
#: Extra columns with --match-far.
MATCHED_COLUMNS: list[tuple[str, str, float, str]] = [
    ("mar_at_far", "MAR@FAR %", 100.0, "{:.2f}"),
    ("fir_at_far", "FIR@FAR %", 100.0, "{:.2f}"),
    ("detection_delay_at_far_s", "Delay@FAR s", 1.0, "{:.3f}"),
    ("threshold_scale_at_far", "Scale@FAR", 1.0, "{:.3g}"),
]


#: Columns the terminal table leaves out (they stay in Markdown, CSV, JSON and JUnit).
CONSOLE_OMITS = {"far_calibration", "alarm_rate"}


def table_columns(report: Report, *, console: bool = False) -> list[tuple[str, str, float, str]]:
    """The columns of this report's tables (matched-FAR columns with ``--match-far``;
    ``console``: the narrower terminal table)."""
    columns = TABLE_COLUMNS + (MATCHED_COLUMNS if report.match_far is not None else [])
    return [c for c in columns if not (console and c[0] in CONSOLE_OMITS)]


def format_value(value: float | None, scale: float = 1.0, fmt: str = "{:.4g}") -> str:
    """Format a figure for tables; undefined values read ``undefined``."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "undefined"
    return fmt.format(value * scale)


def table_rows(report: Report, *, console: bool = False) -> list[list[str]]:
    """Rows (detector, type, columns of :func:`table_columns`) as strings."""
    columns = table_columns(report, console=console)
    return [
        [e.detector, e.sensor_type]
        + [format_value(e.metrics.value(m), s, f) for m, _, s, f in columns]
        for e in report.entries
    ]


def to_json(report: Report, gate_results: Sequence[GateResult] = ()) -> str:
    data = {
        "source": report.source,
        "has_truth": report.has_truth,
        "match_far": report.match_far,
        "faults": report.faults,
        "results": [
            {
                "detector": e.detector,
                "sensor_type": e.sensor_type,
                **e.metrics.to_dict(),
                **e.validity,
            }
            for e in report.entries
        ],
        "gates": [
            {
                "gate": r.gate.text,
                "target": r.target,
                "actual": r.actual,
                "failed": r.failed,
            }
            for r in gate_results
        ],
        "notes": report.notes,
        "episodes": report.episodes,
        "episode_scores": report.episode_scores,
    }
    return json_dumps(data)


def to_markdown(report: Report, gate_results: Sequence[GateResult] = ()) -> str:
    header = ["Detector", "Sensor"] + [h for _, h, _, _ in table_columns(report)]
    lines = [
        f"# imufdi report: `{report.source}`",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(report)]
    if report.faults:
        lines += ["", "## Injected faults", ""]
        lines += [f"- `{f.get('spec', f.get('id', '?'))}`" for f in report.faults]
    per_fault = [(e, f) for e in report.entries for f in e.metrics.faults]
    if per_fault:
        lines += [
            "",
            "## Per fault",
            "",
            "| Fault | Detector | Sensor | Detected | Delay s | Iso delay s | Recovery s"
            " | Isolated to it % |",
            "|---|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {f.fault_id} | {e.detector} | {e.sensor_type} | {'yes' if f.detected else 'no'} | "
            f"{format_value(f.detection_delay_s, 1.0, '{:.3f}')} | "
            f"{format_value(f.isolation_delay_s, 1.0, '{:.3f}')} | "
            f"{format_value(f.recovery_delay_s, 1.0, '{:.3f}')} | "
            f"{format_value(f.isolated_correctly, 100.0, '{:.1f}')} |"
            for e, f in per_fault
        ]
    lines += _episodes_markdown(report)
    if gate_results:
        lines += ["", "## Gates", ""]
        lines += [f"- {'❌' if r.failed else '✅'} {r.message}" for r in gate_results]
    if report.notes:
        lines += [""] + [f"> {note}" for note in report.notes]
    return "\n".join(lines) + "\n"


# --- episodes ---------------------------------------------------------------------------

#: display unit of an episode's size: (sensor type, size name) -> (scale from SI, unit)
_SIZE_UNITS = {
    ("gyro", "amp"): (180.0 / math.pi, "deg/s"),
    ("gyro", "rate"): (180.0 / math.pi, "deg/s^2"),
    ("gyro", "value"): (180.0 / math.pi, "deg/s"),
    ("accel", "amp"): (1.0, "m/s^2"),
    ("accel", "rate"): (1.0, "m/s^3"),
    ("accel", "value"): (1.0, "m/s^2"),
    ("mag", "amp"): (1e6, "uT"),
    ("mag", "rate"): (1e6, "uT/s"),
    ("mag", "value"): (1e6, "uT"),
}


def format_size(episode: dict[str, Any]) -> str:
    """``0.91 deg/s [0.88, 0.94]``: the best fit's size and interval in display units."""
    fits = episode.get("fits") or []
    if not fits or fits[0].get("model") in (None, "none"):
        return "-"
    fit = fits[0]
    name = fit.get("size_name", "")
    if name == "factor":
        scale, unit = 1.0, "x"
    else:
        scale, unit = _SIZE_UNITS.get((episode["sensor_type"], name), (1.0, "SI"))

    def num(value: float | None) -> str:
        return "?" if value is None else f"{value * scale:.3g}"

    if fit.get("model") == "stuck":
        return f"at {num(fit.get('size'))} {unit}"
    return f"{num(fit.get('size'))} {unit} [{num(fit.get('low'))}, {num(fit.get('high'))}]"


EPISODE_COLUMNS = [
    "detector",
    "sensor_type",
    "start_s",
    "duration_s",
    "decided_start_s",
    "sensor",
    "fault_class",
    "size",
    "runner_up_class",
    "peak_ratio",
    "runner_up_sensor",
    "runner_up_share",
    "alarms",
    "match",
    "fault_id",
]


def episode_rows(report: Report) -> list[dict[str, Any]]:
    """One flat row per listed episode (times in seconds from the log's first sample)."""
    rows = []
    for e in report.episodes:
        fits = e.get("fits") or []
        rows.append(
            {
                "detector": e["detector"],
                "sensor_type": e["sensor_type"],
                "start_s": (e["start_ns"] - report.t0_ns) * 1e-9,
                "duration_s": e.get("duration_s"),
                "decided_start_s": (e["decided_start_ns"] - report.t0_ns) * 1e-9,
                "sensor": (e.get("sensors") or [None])[0],
                "fault_class": e.get("fault_class"),
                "size": format_size(e),
                "runner_up_class": fits[1]["model"] if len(fits) > 1 else None,
                "peak_ratio": e.get("peak_ratio"),
                "runner_up_sensor": e.get("runner_up"),
                "runner_up_share": e.get("runner_up_share"),
                "alarms": e.get("alarms"),
                "match": e.get("match"),
                "fault_id": e.get("fault_id"),
            }
        )
    return rows


def to_episodes_csv(report: Report) -> str:
    """The listed episodes, one CSV row each (:data:`EPISODE_COLUMNS`)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(EPISODE_COLUMNS)
    for row in episode_rows(report):
        writer.writerow(["" if row[k] is None else row[k] for k in EPISODE_COLUMNS])
    return out.getvalue()


def _episodes_markdown(report: Report) -> list[str]:
    if not report.episode_scores:
        return []
    lines = ["", "## Alarm episodes", ""]
    if report.has_truth:
        lines += [
            "| Detector | Sensor | Episodes | Matched | False | False / h | Class right %"
            " | 90 % interval covers % |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for key, score in report.episode_scores.items():
            detector, sensor_type = key.split(".", 1)
            lines.append(
                f"| {detector} | {sensor_type} | {score['episodes']} | {score['matched']} | "
                f"{score['false']} | {format_value(score['false_episodes_per_hour'], 1, '{:.3g}')} | "
                f"{format_value(score['class_accuracy'], 100.0, '{:.1f}')} | "
                f"{format_value(score['coverage'], 100.0, '{:.1f}')} |"
            )
    lines += [
        "",
        "| Detector | Sensor | Start s | Duration s | Isolated | Class | Size [90 % interval]"
        " | Runner-up class | Peak stat/threshold | Match |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in episode_rows(report):
        lines.append(
            f"| {row['detector']} | {row['sensor_type']} | {row['start_s']:.3f} | "
            f"{format_value(row['duration_s'], 1.0, '{:.3f}')} | {row['sensor'] or '-'} | "
            f"{row['fault_class'] or '-'} | {row['size']} | {row['runner_up_class'] or '-'} | "
            f"{format_value(row['peak_ratio'], 1.0, '{:.3g}')} | "
            f"{row['match'] or '-'}{' ' + row['fault_id'] if row['fault_id'] else ''} |"
        )
    omitted = sum(s.get("omitted", 0) for s in report.episode_scores.values())
    if omitted:
        lines += ["", f"> {omitted} more episodes counted but not listed"]
    return lines


CSV_FIELDS = [
    "detector",
    "sensor_type",
    "samples",
    "fault_free_samples",
    "faulty_samples",
    "calibration_samples",
    "far",
    "far_calibration",
    "mar",
    "detection_rate",
    "accuracy",
    "fir",
    "isolation_accuracy",
    "detection_delay_s",
    "isolation_delay_s",
    "decision_latency_s",
    "recovery_delay_s",
    "rate_after_first_detection",
    "alarm_rate",
    "alarm_events",
    "false_alarm_events_per_hour",
    "target_far",
    "mar_at_far",
    "fir_at_far",
    "detection_delay_at_far_s",
    "threshold_scale_at_far",
]


def to_csv(report: Report) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_FIELDS)
    for e in report.entries:
        data = {"detector": e.detector, "sensor_type": e.sensor_type, **e.metrics.to_dict()}
        writer.writerow(["" if data[k] is None else data[k] for k in CSV_FIELDS])
    return out.getvalue()


def to_junit(report: Report, gate_results: Sequence[GateResult] = ()) -> str:
    """JUnit XML: one test case per gate (or per detector/type when no gates are given)."""
    cases = []
    if gate_results:
        for r in gate_results:
            body = (
                f"<failure message={quoteattr(r.message)}>{escape(r.message)}</failure>"
                if r.failed
                else ""
            )
            cases.append(
                f'  <testcase classname="imufdi.gates" name={quoteattr(r.target + " " + r.gate.op + " " + format(r.gate.value, "g"))}>{body}</testcase>'
            )
    else:
        for e in report.entries:
            summary = ", ".join(
                f"{h}={format_value(e.metrics.value(m), s, f)}"
                for m, h, s, f in table_columns(report)
            )
            cases.append(
                f'  <testcase classname="imufdi.{escape(e.detector)}" name="{escape(e.sensor_type)}">'
                f"<system-out>{escape(summary)}</system-out></testcase>"
            )
    failures = sum(r.failed for r in gate_results)
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<testsuite name="imufdi" tests="{len(cases)}" failures="{failures}" errors="0">\n'
        + "\n".join(cases)
        + "\n</testsuite>\n"
    )


ROC_FIELDS = [
    "detector",
    "sensor_type",
    "threshold_scale",
    "far",
    "mar",
    "fir",
    "detection_delay_s",
]


def to_roc_csv(report: Report) -> str:
    """The swept curves (``--roc``): one row per histogram edge where FAR or MAR changes
    (plus the first and last edge), per detector and sensor type; empty cells are undefined."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(ROC_FIELDS)
    for e in report.entries:
        if e.roc is None:
            continue
        far, mar = e.roc["far"], e.roc["mar"]
        change = np.ones(far.size, dtype=bool)
        change[1:-1] = (np.diff(np.nan_to_num(far, nan=-1.0))[:-1] != 0) | (
            np.diff(np.nan_to_num(mar, nan=-1.0))[:-1] != 0
        )
        for k in np.flatnonzero(change).tolist():
            row = [e.detector, e.sensor_type, f"{10 ** e.roc['log10_scale'][k]:.6g}"]
            for name in ("far", "mar", "fir", "detection_delay_s"):
                v = float(e.roc[name][k])
                row.append("" if math.isnan(v) else f"{v:.6g}")
            writer.writerow(row)
    return out.getvalue()
