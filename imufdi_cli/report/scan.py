"""The streaming pass of ``imufdi report``: :func:`build_report` reads the status channels
and the explained episodes of an annotated MCAP once, with memory independent of the log
length, and returns a :class:`~imufdi_cli.report.model.Report`."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any, BinaryIO

import numpy as np

from imufdi_cli.errors import McapInputError, UsageError
from imufdi_cli.metrics import faulty_matrix
from imufdi_cli.progress import LogTimeProgress, ProgressCallback
from imufdi_cli.report.channel import ChannelScore
from imufdi_cli.report.model import Report, ReportEntry
from imufdi_cli.report.truth import Truth, calibration_windows, truth_windows

#: the detector name of variance-drop episodes (imufdi_cli.episodes.variance_drop, not
#: imported here: the episodes package is loaded only when episodes are read)
VARIANCE_DROP = "variance-drop"

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
    match_budget: float | None = None,
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
    match_budget : float, optional
        Target false alarm episodes per hour (> 0) for the matched-budget figures
        (``mar_at_budget``, ...).
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
    if match_budget is not None and not (0.0 < match_budget < float("inf")):
        raise UsageError(f"--match-budget must be a rate > 0 such as 1/h, got {match_budget!r}")
    name = source if isinstance(source, str) else "<stream>"
    name = "<stdin>" if name == "-" else name
    stream, close = _open_seekable(source)
    try:
        with McapSource(stream) as src:
            metadata = dict(src.metadata)  # seekable: read from the summary up front
            scan = _StatusScan(metadata, window, persist, keep_series, match_budget is not None)
            episodes = _EpisodeCollector(scan.truth, scan.windows_cal, window, scan.origin_ns)
            tracker = LogTimeProgress(progress, getattr(src, "summary_time_range", None))
            # only the chunks of the status and event channels are read (the IMU chunks,
            # most of the file, are stepped over by the summary's chunk index)
            status = iter_status(
                src,
                others=episodes.batch,
                others_wanted=episodes.wants,
                amplitude_columns=False,
                score_columns=keep_series,  # (the plots draw the scores)
            )
            for detector, sensor_type, ids, rows in status:
                if rows["t_ns"].size:
                    tracker.at(int(rows["t_ns"][-1]))
                scan.add(detector, sensor_type, ids, rows)
            problems = list(src.warnings)
    finally:
        if close:
            stream.close()
    if not scan.scores:
        raise McapInputError(
            f"{name}: no detector status channels (/imufdi/<detector>/<type>); "
            "run `imufdi detect` on the log first" + (f"; {problems[0]}" if problems else "")
        )
    notes = scan.notes(problems)
    entries = [
        scan.entry(key, match_far, match_budget, keep_roc, notes) for key in sorted(scan.scores)
    ]
    if match_far is not None and scan.truth is not None:
        notes.append(
            f"matched FAR {match_far:g}: the threshold of each detector's raw statistic is"
            " scaled (alarm when statistic >= scale x threshold, per sample); confirmation"
            " and persistence rules are not re-run (docs/metrics.md)"
        )
    if match_budget is not None:
        from imufdi_cli.sweep import format_rate

        notes.append(
            f"matched budget {format_rate(match_budget)}: the threshold of each detector's"
            " raw statistic is scaled until the false alarm episodes per fault-free tested"
            " hour fall to the target; a sequential test's restarts stay those of its own"
            " threshold (docs/metrics.md)"
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
        match_budget=match_budget,
        episode_scores=episode_scores,
        episodes=episodes.listed,
        episode_spans=episodes.spans,
        records={d: r for d, r in scan.records.items() if r is not None},
    )


#: the status fields kept for plots (``keep_series``)
SERIES_FIELDS = ("t_ns", "statistic", "threshold", "alarm", "isolated", "scores")


class _StatusScan:
    """What :func:`build_report`'s pass over the status channels gathers: one
    :class:`~imufdi_cli.report.channel.ChannelScore` per ``(detector, sensor type)``."""

    def __init__(
        self,
        metadata: dict[str, dict[str, str]],
        window: tuple[float, float | None] | None,
        persist: int,
        keep_series: bool,
        budget_levels: bool = False,
    ) -> None:
        self.truth = truth_windows(metadata)
        self.budget_levels = budget_levels
        self.windows_cal = calibration_windows(metadata)
        self.metadata = metadata
        self.window = window
        self.persist = persist
        self.keep_series = keep_series
        self.records = {d: _detect_record(metadata, d) for d in self.windows_cal}
        self.scores: dict[tuple[str, str], ChannelScore] = {}
        #: shared with the episode collector, which reads the origins as they appear
        self.first_ns: dict[tuple[str, str], int] = {}

    def add(
        self, detector: str, sensor_type: str, ids: list[str], rows: dict[str, np.ndarray]
    ) -> None:
        """Score one batch of status rows of a channel (those ``detect`` marked clipped or
        invalid, and those outside the window, are counted and left out)."""
        key = (detector, sensor_type)
        if detector not in self.records:
            self.records[detector] = _detect_record(self.metadata, detector)
        score = self.scores.get(key)
        if score is None:
            record = self.records[detector]
            score = self.scores[key] = ChannelScore(
                detector,
                sensor_type,
                ids,
                truth=self.truth,
                calibration_ns=self.windows_cal.get(detector),
                record=record,
                window=self.window,
                persist=self.persist,
                rate_hz=_rate_hz(self.metadata, record),
                keep_series=self.keep_series,
                budget_levels=self.budget_levels,
            )
        if key not in self.first_ns and rows["t_ns"].size:
            self.first_ns[key] = int(rows["t_ns"][0])
        score.add(rows, origin_ns=self.origin_ns(detector, sensor_type))

    def notes(self, problems: list[str]) -> list[str]:
        """What the reader must know about the whole log: input damage, missing truth,
        older logs, samples not scored."""
        # a damaged log is reported on what could be read, and says so
        notes = [f"input: {problem}" for problem in problems]
        if self.truth is None:
            notes.append(
                "no ground truth in this log (inject faults with `imufdi inject`): "
                "FAR, MAR, FIR and delays need truth; alarm statistics only, and every"
                " alarm episode counts as false (the log taken as fault-free)"
            )
        old = sorted({d for d, _ in self.scores if d not in self.windows_cal})
        if old:
            notes.append(
                f"{', '.join(old)}: no calibration window recorded (log from an older imufdi):"
                " FAR and alarm rate count every sample, including the in-sample calibration"
            )
        undecided = sorted({d for (d, _), sc in self.scores.items() if not sc.all_decided})
        if undecided:
            notes.append(
                f"{', '.join(undecided)}: status without decision times (older imufdi): delays"
                " are at sample time"
            )
        for (detector, sensor_type), score in sorted(self.scores.items()):
            counts = score.validity
            if counts["excluded"]:
                notes.append(
                    f"{detector}.{sensor_type}: {counts['excluded']} samples not scored"
                    f" ({counts['clipped']} clipped, {counts['invalid']} invalid in the range)"
                )
            if counts.get("missing"):
                notes.append(
                    f"{detector}.{sensor_type}: {counts['missing']} samples tested with an IMU"
                    " missing (its sensors replaced by the others' consensus) and scored"
                )
        return notes

    def entry(
        self,
        key: tuple[str, str],
        match_far: float | None,
        match_budget: float | None,
        keep_roc: bool,
        notes: list[str],
    ) -> ReportEntry:
        """The finished :class:`ReportEntry` of one channel (a matched-FAR or budget
        problem is appended to ``notes``); without truth the truth-based metrics are None."""
        detector, sensor_type = key
        score = self.scores[key]
        acc = score.accumulator
        metrics, problems = score.metrics(match_far, match_budget)
        notes.extend(problems)
        roc = None
        has_truth = self.truth is not None
        if keep_roc and has_truth and acc.sweep is not None and acc.sweep.sweepable:
            roc = acc.sweep.curve()
        arrays = score.series.arrays() if score.series is not None else {}
        n_s = len(score.ids)
        t_ns = arrays.get("t_ns", np.zeros(0, np.int64))
        return ReportEntry(
            detector=detector,
            sensor_type=sensor_type,
            sensor_ids=score.ids,
            metrics=metrics,
            t_ns=t_ns,
            statistic=arrays.get("statistic", np.zeros(0)),
            threshold=arrays.get("threshold", np.zeros(0)),
            alarm=arrays.get("alarm", np.zeros(0, bool)),
            scores=arrays.get("scores", np.zeros((0, n_s))),
            faulty=faulty_matrix(t_ns, acc.windows, n_s),
            isolated=arrays.get("isolated", np.zeros(0, np.int64)),
            roc=roc,
            validity=dict(score.validity),
        )

    def fault_free_hours(self, entries: list[ReportEntry]) -> dict[tuple[str, str], float]:
        """The tested, fault-free hours of each channel, the denominator of its episode
        rates: the same as its alarm events' (:func:`imufdi_cli.metrics.fault_free_tested_hours`:
        scored fault-free rows outside the calibration window times the sample period,
        gaps excluded). Episodes of a type that no status channel carries (variance-drop,
        run by ``detect`` beside the detectors) take the largest of that type."""
        hours: dict[tuple[str, str], float] = {}
        for entry in entries:
            hours[(entry.detector, entry.sensor_type)] = entry.metrics.fault_free_hours
        for entry in entries:
            key = (VARIANCE_DROP, entry.sensor_type)
            hours[key] = max(hours.get(key, 0.0), entry.metrics.fault_free_hours)
        return hours

    def origin_ns(self, detector: str, sensor_type: str) -> int | None:
        """Time zero of ``--start/--end`` for one channel: the log's first sample as
        ``detect`` recorded it (``t0_ns``), else the channel's first status row. Episodes
        of a channel without status rows (variance-drop, run beside the detectors; a type
        a detector does not test) take the first that exists of: the detector's record,
        any detector's record (one detect run: one log start), the detector's earliest
        status row, the earliest status row of all. None while nothing is known. The one
        origin of the rows (:func:`imufdi_cli.validity.select_rows`) and of the episodes.
        """
        record = self.records.get(detector)
        if record is None and detector in self.windows_cal:
            record = self.records[detector] = _detect_record(self.metadata, detector)
        if record is not None and isinstance(record.get("t0_ns"), int):
            return int(record["t0_ns"])
        if (detector, sensor_type) in self.first_ns:
            return self.first_ns[(detector, sensor_type)]
        recorded = [r.get("t0_ns") for r in self.records.values() if r is not None]
        known = [int(t) for t in recorded if isinstance(t, int)]
        if known:
            return min(known)
        mine = [t for (d, _), t in self.first_ns.items() if d == detector]
        if mine or self.first_ns:
            return min(mine or self.first_ns.values())
        return None


def _rate_hz(metadata: dict[str, dict[str, str]], record: dict[str, Any] | None) -> float | None:
    """The sample rate of the array the detector tested with: ``detect --array``'s (in its
    record), else the log's ``imufdi.array``; None when neither says."""
    array = (record or {}).get("array")
    if not isinstance(array, dict):
        try:
            array = json.loads(metadata["imufdi.array"]["json"])
        except (KeyError, TypeError, ValueError):
            return None
    rate = array.get("rate_hz") if isinstance(array, dict) else None
    try:
        value = float(rate)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return value if value > 0 else None


def _detect_record(metadata: dict[str, dict[str, str]], detector: str) -> dict[str, Any] | None:
    """The ``imufdi.detect.<detector>`` record checked against its schema, or None when
    the log has none (McapInputError when it is malformed: :mod:`imufdi_cli.metadata`)."""
    from imufdi_cli.metadata import detect_record

    return detect_record(metadata, detector)


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
        origin: Callable[[str, str], int | None] | None = None,
    ) -> None:
        from imufdi_cli.episodes.scoring import EpisodeMatcher

        self.calibration = calibration
        # variance-drop episodes come from the detect run of the detectors: its window
        shared = [w for _, w in sorted(calibration.items()) if w is not None]
        if shared and VARIANCE_DROP not in calibration:
            self.calibration = {**calibration, VARIANCE_DROP: shared[0]}
        self.pending: list[tuple[Any, dict[str, Any]]] = []
        self.window = window  # --start/--end, seconds from the time origin of each channel
        self.origin = origin if origin is not None else (lambda detector, sensor_type: None)
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
            origin = None if self.window is None else self.origin(*key)
            if self.window is not None and origin is None:
                self.pending.append((episode, match))
                continue
            if origin is not None and not self._inside(origin, episode.start_ns):
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

    def _inside(self, origin: int, start_ns: int) -> bool:
        """Whether an episode starting at ``start_ns`` is inside --start/--end (seconds
        from ``origin``)."""
        if self.window is None:
            return True
        from imufdi_cli.units import window_from_log_start

        start_s, end_s = window_from_log_start(self.window, origin)
        rel = (start_ns - origin) * 1e-9
        return rel >= start_s and (end_s is None or rel < end_s)

    def scores(self, hours: dict[tuple[str, str], float]) -> dict[str, dict[str, Any]]:
        if self.pending:  # read before their channel's first status row: windowed now
            pending, self.pending = self.pending, []
            self._take(pending)
        if self.pending:  # no time origin at all (no status rows, no record): not scored
            self.pending = []
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
