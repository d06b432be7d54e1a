"""The streaming pass of ``imufdi report``: :func:`build_report` reads the status channels
and the explained episodes of an annotated MCAP once, with memory independent of the log
length, and returns a :class:`~imufdi_cli.report.model.Report`."""

from __future__ import annotations

import json
from typing import Any, BinaryIO

import numpy as np

from imufdi_cli.errors import McapInputError, UsageError
from imufdi_cli.metrics import FaultWindow, MetricsAccumulator, faulty_matrix
from imufdi_cli.progress import LogTimeProgress, ProgressCallback
from imufdi_cli.report.model import Report, ReportEntry
from imufdi_cli.report.truth import Truth, calibration_windows, truth_windows

#: Samples per channel kept for ``--plot``.
PLOT_POINTS = 20_000


class _Series:
    """Peak-preserving decimated copy of a status channel for plots (bounded memory).

    The rows are cut into buckets of ``stride`` consecutive samples (bucket ``b`` holds the
    samples ``b * stride`` to ``(b + 1) * stride - 1`` of the channel); each bucket keeps
    one row, the one with the largest ``statistic`` (NaN counts as lowest; the first such
    row on ties; the first row of the bucket when there is no statistic), with its own
    time, threshold, isolation and scores, and with ``alarm`` the OR of the bucket's
    alarms. So however long the log, neither an alarm nor a peak of the statistic
    disappears from the figure (an evenly strided copy dropped one-sample spikes of the
    statistic: 8 of 20 on a 10-min log). When more than ``2 * PLOT_POINTS`` rows are kept
    the stride doubles and each pair of buckets merges the same way.
    """

    def __init__(self) -> None:
        self.stride = 1
        self.seen = 0
        self.parts: list[dict[str, np.ndarray]] = []
        self.buckets: list[np.ndarray] = []  # bucket index of each kept row, per part
        self.kept = 0

    def add(self, rows: dict[str, np.ndarray]) -> None:
        n = int(rows["t_ns"].size)
        if n == 0:
            return
        bucket = (self.seen + np.arange(n, dtype=np.int64)) // self.stride
        self.seen += n
        if self.parts and self.buckets[-1][-1] == bucket[0]:
            # the last kept row's bucket was still open: reduce it with the new rows
            last = {k: v[-1:] for k, v in self.parts[-1].items()}
            self.parts[-1] = {k: v[:-1] for k, v in self.parts[-1].items()}
            self.buckets[-1] = self.buckets[-1][:-1]
            self.kept -= 1
            rows = {k: np.concatenate([last[k], np.asarray(rows[k])]) for k in rows}
            bucket = np.concatenate([bucket[:1], bucket])
        part, kept_buckets = _bucket_peaks(rows, bucket)
        self.parts.append(part)
        self.buckets.append(kept_buckets)
        self.kept += int(kept_buckets.size)
        if self.kept > 2 * PLOT_POINTS:
            whole = self.arrays()
            self.stride *= 2
            part, kept_buckets = _bucket_peaks(whole, np.concatenate(self.buckets) // 2)
            self.parts, self.buckets = [part], [kept_buckets]
            self.kept = int(kept_buckets.size)

    def arrays(self) -> dict[str, np.ndarray]:
        keys = self.parts[0].keys() if self.parts else ()
        return {k: np.concatenate([p[k] for p in self.parts]) for k in keys}


def _bucket_peaks(
    rows: dict[str, np.ndarray], bucket: np.ndarray
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """One row per run of equal ``bucket`` values: the row of the largest statistic (NaN
    lowest, first on ties; the first row without a statistic), ``alarm`` OR-ed over the run.

    Parameters
    ----------
    rows : dict of ndarray, each of shape (n, ...)
        Status rows in time order.
    bucket : ndarray of int64, shape (n,)
        Non-decreasing bucket index of each row.

    Returns
    -------
    kept rows (dict of ndarray, shape (m, ...)) and their bucket indices (shape (m,))
    """
    n = bucket.size
    starts = np.flatnonzero(np.concatenate([[True], bucket[1:] != bucket[:-1]]))
    if "statistic" in rows:
        stat = np.asarray(rows["statistic"], np.float64).reshape(n, -1).max(axis=1)
        key = np.where(np.isnan(stat), -np.inf, stat)
        run = np.repeat(np.arange(starts.size), np.diff(np.append(starts, n)))
        hits = np.flatnonzero(key == np.maximum.reduceat(key, starts)[run])
        pick = hits[np.concatenate([[True], run[hits[1:]] != run[hits[:-1]]])]
    else:
        pick = starts
    part = {k: np.asarray(v)[pick] for k, v in rows.items()}
    if "alarm" in rows:
        part["alarm"] = np.logical_or.reduceat(np.asarray(rows["alarm"], bool), starts)
    return part, bucket[starts]


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
            # only the chunks of the status and event channels are read (the IMU chunks,
            # most of the file, are stepped over by the summary's chunk index)
            status = iter_status(src, others=episodes.batch, others_wanted=episodes.wants)
            for detector, sensor_type, ids, rows in status:
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
        episode_spans=episodes.spans,
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
            amplitudes=rows["amplitudes"],
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
        from imufdi_cli.episodes.scoring import EpisodeMatcher

        self.calibration = calibration
        self.pending: list[tuple[Any, dict[str, Any]]] = []
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
        self.matcher = EpisodeMatcher(self.faults)
        self.listed: list[dict[str, Any]] = []
        self.tallies: dict[tuple[str, str], Any] = {}
        self.counts: dict[tuple[str, str], int] = {}
        self.spans: dict[tuple[str, str], list[tuple[int, int]]] = {}

    @staticmethod
    def wants(channel: Any) -> bool:
        """Whether :meth:`batch` reads anything from ``channel`` (the episode events)."""
        from imufdi_cli.mcapio.events import EVENTS_TOPIC, is_event_channel

        return bool(channel.topic == EVENTS_TOPIC and is_event_channel(channel))

    def batch(self, batch: Any, channel: Any) -> None:
        """Match, count and list the episodes of one batch of ``/imufdi/events``; only
        the listed ones have their explanation's JSON parsed
        (:class:`~imufdi_cli.mcapio.events.EpisodeEvent`)."""
        from imufdi_cli.mcapio.events import EVENTS_TOPIC, decode_episode_events, is_event_channel

        if channel.topic != EVENTS_TOPIC or not is_event_channel(channel):
            return
        found = decode_episode_events(batch, channel)
        if self.has_truth:
            match = self.matcher.match
            self._take([(e, match(*e.match_fields())) for e in found])
        else:
            self._take([(e, {"match": None}) for e in found])

    def _take(self, items: list[tuple[Any, dict[str, Any]]]) -> None:
        """Count and list episodes (:class:`~imufdi_cli.mcapio.events.EpisodeEvent`,
        with their matches) inside --start/--end; those of a channel whose first status
        row has not been read yet wait for it."""
        from imufdi_cli.episodes import EpisodeTally

        if self.pending:
            items, self.pending = self.pending + items, []
        for episode, match in items:
            key = (episode.detector, episode.sensor_type)
            if self.window is not None and key not in self.origins:
                self.pending.append((episode, match))
                continue
            if not self._inside(key, episode.start_ns):
                continue
            tally = self.tallies.get(key)
            if tally is None:
                tally = self.tallies[key] = EpisodeTally()
            window = self.calibration.get(episode.detector)
            if window is not None and episode.start_ns < window[1]:
                # inside the calibration window: in sample, listed but never scored
                match = {**match, "match": "calibration"}
                tally.calibration += 1
            elif self.has_truth:
                tally.add(match)
            else:
                tally.episodes += 1
            self.counts[key] = self.counts.get(key, 0) + 1
            self.spans.setdefault(key, []).append((int(episode.start_ns), int(episode.end_ns)))
            if self.counts[key] <= EPISODES_LISTED:
                self.listed.append({**episode.explanation(), **match})

    def _inside(self, key: tuple[str, str], start_ns: int) -> bool:
        """Whether an episode starting at ``start_ns`` is inside --start/--end."""
        origin = self.origins.get(key)
        if self.window is None or origin is None:
            return True
        from imufdi_cli.units import window_from_log_start

        start_s, end_s = window_from_log_start(self.window, origin)
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
    return MetricsAccumulator(
        len(ids), windows, calibration_ns=calibration, persist=persist, sensor_ids=ids
    )
