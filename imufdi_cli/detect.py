"""``imufdi detect``: run detectors over a log and write the annotated MCAP (docs/formats.md).

One streaming pass: every input message is copied to the output as raw bytes (a whole
input chunk of messages only is written as it is, without recompression: docs/formats.md);
the aligned IMU samples go through each detector; per-sample status messages (fixed-layout
CDR, encoded in bulk) go to ``/imufdi/<detector>/<type>``, alarm start/end events
(``imufdi_msgs/msg/FdiEvent``, CDR, encoded in bulk per block) to ``/imufdi/events``, and
each detector's parameters and calibration to the ``imufdi.detect.<name>`` metadata record.
Ground truth on the JSON channel of an older imufdi is re-encoded as FaultEvent. Memory is
bounded by the block size and the calibration window, not by the log length.
"""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np

from imufdi_cli._version import __version__
from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors import make_detectors
from imufdi_cli.detectors.base import DetectionBlock, Detector
from imufdi_cli.errors import (
    CalibrationError,
    DetectorConfigError,
    FlightLogError,
)
from imufdi_cli.fclog.streams import rate_problem
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio import (
    ChannelInfo,
    ImuArrayReader,
    McapSource,
    McapWriter,
    MessageBatch,
    register_status_channel,
)
from imufdi_cli.mcapio.events import (
    EVENTS_TOPIC,
    TRUTH_TOPIC,
    decode_events,
    encode_episode_events,
    encode_fault_events,
    encode_fdi_events,
    is_event_channel,
    register_events_channel,
    register_truth_channel,
)
from imufdi_cli.mcapio.passthrough import ChannelCopier, keep_fdi_events
from imufdi_cli.mcapio.status import register_scores_channel, scores_records, status_records
from imufdi_cli.progress import LogTimeProgress, ProgressCallback
from imufdi_cli.units import window_from_log_start
from imufdi_cli.validity import Conditioner

if TYPE_CHECKING:
    from imufdi_cli.episodes import EpisodeBuilder

NS_PER_S = 1_000_000_000
DEFAULT_CALIBRATION = (0.0, 2.0)
#: Per sensor type, (clipped, invalid) masks of shape (N, m, 3) (imufdi_cli.validity).
Flags = dict[str, tuple[np.ndarray, np.ndarray]]


def with_budget(
    detectors: Iterable[tuple[str, Mapping[str, Any]]], false_alarms: float | None
) -> list[tuple[str, dict[str, Any]]]:
    """Detector specs with the false-alarm budget ``false_alarms`` (episodes per second) set
    on every detector that does not set its own ``false_alarms`` parameter.

    Raises DetectorConfigError for a negative budget or a detector that cannot decide
    under one."""
    from imufdi_cli.detectors import detector_class

    specs = [(name, dict(params)) for name, params in detectors]
    if false_alarms is None:
        return specs
    if not (false_alarms >= 0 and np.isfinite(false_alarms)):
        raise DetectorConfigError(
            f"--false-alarms must be a rate >= 0 such as 1/h, got {false_alarms!r}"
        )
    for name, params in specs:
        if "false_alarms" not in detector_class(name).PARAMS:
            raise DetectorConfigError(
                f"detector {name!r} has no false-alarm budget (its parameters:"
                f" {', '.join(sorted(detector_class(name).PARAMS))})"
            )
        params.setdefault("false_alarms", false_alarms)
    return specs


#: Above this many expected false alarm episodes an hour on a channel, detect warns.
NOISY_EPISODES_PER_HOUR = 60.0


def level_warning(detector: Any, rate_hz: float) -> str | None:
    """A one-line warning when a detector's settings should raise more than
    :data:`NOISY_EPISODES_PER_HOUR` false alarm episodes an hour on each of its channels
    of a fault-free log at ``rate_hz`` (the per-sample tests at their ``alpha``: about
    ``alpha^persistence`` of the samples start one), naming ``--false-alarms``; None when
    it should not, or when the detector's rate cannot be told from its settings."""
    budget = float(getattr(detector, "false_alarms", 0.0) or 0.0)
    alpha = getattr(detector, "alpha", None)
    if budget > 0 or alpha is None or not rate_hz > 0:
        return None
    persistence = max(1, int(getattr(detector, "persistence", 1) or 1))
    per_hour = float(alpha) ** persistence * rate_hz * 3600.0
    if per_hour <= NOISY_EPISODES_PER_HOUR:
        return None
    return (
        f"{detector.name}: the per-sample test at alpha={float(alpha):g} should raise about"
        f" {per_hour:,.0f} false alarm episodes an hour on each channel at {rate_hz:g} Hz;"
        " for recorded data and CI give a budget, e.g. --false-alarms 1/h (docs/guide.md)"
    )


#: A channel alarming more than this many times its level (alpha, or the budget) warns.
LEVEL_EXCESS = 10.0


def observed_level_warnings(
    detector: Any, summaries: Mapping[str, Any], rate_hz: float
) -> list[str]:
    """One line per status channel whose alarms over the whole tested log exceed
    :data:`LEVEL_EXCESS` times what the detector's settings allow: under a budget, the
    alarm episodes per hour (at least 5 of them); per sample, the share of alarmed
    samples against ``alpha`` (over at least 1,000 samples). Faults in the log raise it
    legitimately, so the line says both causes; a detector whose noise model does not
    hold on this log (motion, orientation-dependent noise) never alarms silently. detect
    asks only for logs without injected faults (``imufdi.faults``)."""
    budget = float(getattr(detector, "false_alarms", 0.0) or 0.0)
    alpha = getattr(detector, "alpha", None)
    notes = []
    for sensor_type, summary in summaries.items():
        if not summary.samples or not rate_hz > 0:
            continue
        hours = summary.samples / rate_hz / 3600.0
        if budget > 0:
            per_hour = summary.events / hours
            if summary.events >= 5 and per_hour > LEVEL_EXCESS * budget * 3600.0:
                notes.append(
                    f"{detector.name}.{sensor_type}: {summary.events} alarm episodes in"
                    f" {hours * 60:.3g} min ({per_hour:,.0f}/h) against a budget of"
                    f" {budget * 3600:g}/h: faults in the log, or noise this detector does"
                    " not model here (motion, orientation); see docs/guide.md"
                )
        elif alpha is not None and summary.samples >= 1000:
            share = summary.alarms / summary.samples
            if share > LEVEL_EXCESS * float(alpha):
                notes.append(
                    f"{detector.name}.{sensor_type}: alarms on {100 * share:.3g} % of the tested"
                    f" samples, {share / float(alpha):.0f} times its level alpha={float(alpha):g}:"
                    " faults in the log, or noise this detector does not model here (motion,"
                    " orientation); see docs/guide.md"
                )
    return notes


@dataclass
class TypeSummary:
    """What one detector said about one sensor type over the whole log."""

    samples: int = 0
    alarms: int = 0
    events: int = 0
    isolated: dict[str, int] = field(default_factory=dict)  # sensor id -> alarm samples
    episodes: dict[str, int] = field(default_factory=dict)  # fault class -> episodes


@dataclass
class DetectResult:
    """Summary of a detect run (the annotated log itself is the main output)."""

    output: str
    samples: int
    duration_s: float
    calibration_s: tuple[float, float]
    calibration_samples: int
    array: ArrayConfig
    summaries: dict[str, dict[str, TypeSummary]]
    alignment: Any
    warnings: list[str]
    validity: dict[str, Any] = field(default_factory=dict)  # per type: clipped, invalid, ...


def lookahead_of(detector: Any) -> int | None:
    """A detector's declared ``lookahead_samples`` (None when it declares none)."""
    value = getattr(detector, "lookahead_samples", None)
    return None if value is None else int(value)


def decision_positions(first_row: int, rows: int, passed: int, lookahead: int | None) -> np.ndarray:
    """Index of the input sample at whose arrival each output row's decision is available.

    Rows ``first_row .. first_row + rows - 1`` were returned by a ``process``/``flush``
    call after ``passed`` input samples had been passed to the detector. The decision on
    row i is available at the newest passed sample (index ``passed - 1``) — and, since the
    detector declares that it never waits for more than ``lookahead`` later samples, no
    later than sample ``i + lookahead``. The decision time is the timestamp of
    ``min(i + lookahead, passed - 1)``: the sample time for a causal detector whatever the
    block size, and a block-size independent bound for one that looks ahead. A detector
    that declares no look-ahead (``None``) is charged the newest passed sample.

    Returns
    -------
    ndarray, shape (rows,), int64
    """
    index = np.arange(first_row, first_row + rows, dtype=np.int64)
    newest = np.full(rows, passed - 1, dtype=np.int64)
    if lookahead is None:
        return newest
    return np.minimum(index + int(lookahead), newest)


class _Track:
    """Streaming bookkeeping for one detector: pending timestamps, alarm state, channels."""

    def __init__(self, detector: Detector, array: ArrayConfig) -> None:
        self.detector = detector
        self.array = array
        self.lookahead = lookahead_of(detector)
        self.pending: deque[np.ndarray] = deque()
        self.passed = 0  # input samples passed to the detector
        self.emitted = 0  # rows returned by it
        self.channels: dict[str, int] = {}
        self.score_channels: dict[str, int] = {}  # sensor type -> named-scores channel
        self.alarm_on: dict[str, bool] = {}
        self.summary: dict[str, TypeSummary] = {}
        self.episodes: dict[str, EpisodeBuilder] = {}  # sensor type -> builder

    def feed(self, t_ns: np.ndarray) -> None:
        """Record the timestamps of a block about to be passed to the detector."""
        self.pending.append(t_ns)
        self.passed += int(t_ns.size)

    def take_times(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Sample times and decision times (ns) of the next ``count`` rows, in order."""
        if count > self.passed - self.emitted:
            raise DetectorConfigError(
                f"detector {self.detector.name} returned {count} rows for"
                f" {self.passed - self.emitted} samples not yet reported"
            )
        positions = decision_positions(self.emitted, count, self.passed, self.lookahead)
        # every position lies in [emitted, passed): the pending timestamps hold them
        held = np.concatenate(list(self.pending)) if self.pending else np.zeros(0, np.int64)
        decided = held[positions - self.emitted] if count else np.zeros(0, np.int64)
        times = held[:count]
        rest = held[count:]
        self.pending.clear()
        if rest.size:
            self.pending.append(rest)
        self.emitted += count
        return times, decided


def _events(
    track: _Track, channel_id: int, sensor_type: str, t_ns: np.ndarray, out: DetectionBlock
) -> tuple[MessageBatch, int]:
    """Alarm start/end events of a block (state carried across blocks), encoded in bulk;
    also the number of alarm starts."""
    alarm = np.asarray(out.alarm, dtype=bool)
    before = track.alarm_on.get(sensor_type, False)
    previous = np.concatenate([[before], alarm[:-1]])
    changes = np.flatnonzero(alarm != previous)
    if alarm.size:
        track.alarm_on[sensor_type] = bool(alarm[-1])
    amplitude = np.asarray(out.amplitude, np.float64)[changes]
    batch = encode_fdi_events(
        channel_id,
        np.asarray(t_ns, np.int64)[changes],
        detector=track.detector.name,
        sensor_type=sensor_type,
        sensor_ids=track.array.sensor_ids(sensor_type),
        alarm=alarm[changes],
        isolated=np.asarray(out.isolated)[changes],
        amplitude=np.where(np.isfinite(amplitude), amplitude, np.nan),
        statistic=np.asarray(out.statistic, np.float64)[changes],
    )
    return batch, int(np.count_nonzero(alarm[changes]))


def detect_file(
    source: str | BinaryIO,
    output: str | BinaryIO,
    detectors: Sequence[tuple[str, Mapping[str, Any]]],
    *,
    calibrate: tuple[float, float | None] = DEFAULT_CALIBRATION,
    topics: Sequence[str] | None = None,
    strict: bool = False,
    compression: str = "zstd",
    array: ArrayConfig | None = None,
    window: tuple[float, float | None] | None = None,
    time_source: str = "auto",
    explain: bool = True,
    progress: ProgressCallback | None = None,
    read_ahead: bool | None = None,
    false_alarms: float | None = None,
    named_scores: bool = False,
) -> DetectResult:
    """Run detectors over a log and write the annotated MCAP.

    Parameters
    ----------
    source, output : path, ``"-"`` or binary stream
    detectors : sequence of (name, params)
        Detector names from ``DETECTORS`` and their parameters (strings or values).
    calibrate : (start_s, end_s or None)
        Fault-free calibration window, seconds from the first aligned sample.
    topics : sequence of str, optional
        Imu topics to use, in array order (default: all, natural order); ``/topic:field``
        for an Imu inside a larger message.
    time_source : {"auto", "header", "log_time"}
        Stamps to align on (see :class:`~imufdi_cli.mcapio.ImuArrayReader`).
    array : ArrayConfig, optional
        Geometry and chip calibration to test with, instead of the log's ``imufdi.array``
        (``detect --array``); its calibration replaces the log's (see
        :mod:`imufdi_cli.validity`).
    window : (start_s, end_s or None), optional
        Samples tested (seconds from the first aligned sample); the others get no status.
        The calibration window is taken from the whole log either way.
    explain : bool
        Write an explained ``episode`` event for every alarm episode (docs/episodes.md).
    named_scores : bool
        Also write each status channel's scores under the sensors' names, on
        ``/imufdi/<detector>/<type>/scores`` (docs/formats.md), for Foxglove and
        PlotJuggler.
    progress : callable, optional
        ``progress(seconds done, log seconds or None)`` (:mod:`imufdi_cli.progress`).
    false_alarms : float, optional
        False-alarm budget, episodes per second of fault-free data on each status channel
        (``--false-alarms 1/h`` is 1/3600): every detector whose parameters do not set
        ``false_alarms`` themselves decides under it (:func:`with_budget`). None: the
        detectors' own settings (by default the papers' per-sample tests).
    read_ahead : bool or None
        Decompress the input's large chunks on a worker thread ahead of their use
        (:class:`~imufdi_cli.mcapio.McapSource`); the output is the same either way.
        Default (None): the reader's default, off unless ``IMUFDI_READ_AHEAD=1``. Off,
        detect takes less CPU and (on two cores) less time: the worker thread and the
        main thread share the GIL, and the hand-offs cost the main thread about what the
        decompression it moves off (docs/performance.md, "Reading").

    Returns
    -------
    DetectResult
    """
    instances, notes = make_detectors(with_budget(detectors, false_alarms))
    # read in line by default: reading ahead on a worker thread costs more CPU and time
    # than it moves off this thread (GIL hand-offs; docs/performance.md)
    log = McapSource(source, strict=strict, keep_raw_chunks=True, read_ahead=read_ahead)
    try:
        reader = ImuArrayReader(log, topics=topics, strict=strict, time_source=time_source)
        too_sparse = rate_problem(log.metadata)
        if too_sparse is not None:
            raise FlightLogError(f"{log.name}: {too_sparse}")
        log_array = reader.array
        array = log_array if array is None else array.check_matches(log_array)
        with McapWriter(output, compression=compression) as writer:
            run = _DetectRun(
                reader,
                writer,
                instances,
                array,
                Conditioner(log_array, array),
                calibrate=calibrate,
                window=window if window is not None else (0.0, None),
                explain=explain,
                named_scores=named_scores,
            )
            run.warnings.extend(notes)  # e.g. a renamed detector parameter
            tracker = LogTimeProgress(progress, getattr(reader.source, "summary_time_range", None))
            for batch, block in reader.stream():
                run.copy_batch(batch)
                tracker.batch(batch)
                if len(block):
                    run.add_block(block)
            run.finish(strict)
    finally:
        log.close()  # (its read-ahead thread too, on every path)
    return run.result(output if isinstance(output, str) else "<stream>")


class _DetectRun:
    """One streaming detect pass: input messages copied, blocks calibrated on and tested,
    status and events written (the state :func:`detect_file` works through)."""

    def __init__(
        self,
        reader: ImuArrayReader,
        writer: McapWriter,
        instances: Sequence[Detector],
        array: ArrayConfig,
        conditioner: Conditioner,
        *,
        calibrate: tuple[float, float | None],
        window: tuple[float, float | None],
        explain: bool,
        named_scores: bool = False,
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.array = array
        self.conditioner = conditioner
        self.cal_start_s, self.cal_end_s = calibrate
        self.test_start_s, self.test_end_s = window
        self.explain = explain
        self.named_scores = named_scores
        self.tracks = [_Track(det, array) for det in instances]
        self.warnings: list[str] = []
        self.n_samples = 0
        self.t_first: int | None = None
        self.t_last = 0
        self.calibration: list[tuple[ImuBlock, Flags]] = []
        self.backlog: list[tuple[ImuBlock, Flags]] = []
        self.fitted = False
        self.cal_samples = 0
        self.rerun = {det.name for det in instances}
        self.copier = ChannelCopier(writer)
        self.dropped: set[int] = set()  # input channels replaced by this run's output
        self.legacy_truth: set[int] = set()  # JSON truth channels of an older imufdi
        self.truth_channel: int | None = None
        # The input channels known so far first, so they keep their ids (their chunks can
        # then be copied verbatim); this run's own channels take the next free ids.
        self._admit(set(reader.source.channels))
        self.events_channel = register_events_channel(writer)

    # --- copying the input ------------------------------------------------------------

    def copy_batch(self, batch: MessageBatch) -> None:
        """Copy a raw input batch, leaving out (or re-encoding) what this run replaces."""
        channels = self.reader.source.channels
        # the batch's channel ids (one bincount: no sort of its ~12,000 ids)
        self._admit(set(np.flatnonzero(np.bincount(batch.channel_id.astype(np.intp))).tolist()))
        if self.dropped:
            keep = ~np.isin(batch.channel_id, list(self.dropped))
            for cid in np.unique(batch.channel_id[~keep]).tolist():
                self._replace_dropped(batch, channels[cid])
            if not bool(keep.all()):
                batch = batch.select(keep)
        if not len(batch):
            return
        runs = self.reader.source.raw_chunks(batch) if self.copier.identity else None
        if runs is None:
            self.writer.add_batch(self.copier.remap(batch))
            return
        start = 0
        for raw, count, records_at in runs:
            part = batch.select(slice(start, start + count))
            if raw is not None and raw.compression == self.writer.compression:
                # the input chunk as it is: no record building, no recompression
                self.writer.add_raw_chunk(raw, part, records_at)
            else:
                self.writer.add_batch(part)
            start += count

    def _admit(self, ids: set[int]) -> None:
        """Input channels met for the first time: copied (same id where free), or dropped
        when this run replaces them (its detectors' status, the events, JSON truth)."""
        channels = self.reader.source.channels
        new = ids - self.copier.known - self.dropped
        for c in sorted(new):
            topic = channels[c].topic
            parts = topic.split("/")
            # a detector run again replaces its status channels and their named scores
            rerun = len(parts) in (4, 5) and parts[1] == "imufdi" and parts[2] in self.rerun
            if rerun and len(parts) == 5 and parts[4] != "scores":
                rerun = False
            if topic == EVENTS_TOPIC or rerun:
                self.dropped.add(c)
            elif topic == TRUTH_TOPIC and channels[c].message_encoding == "json":
                self.dropped.add(c)
                self.legacy_truth.add(c)
        self.copier.ensure(channels, new - self.dropped)

    def _replace_dropped(self, batch: MessageBatch, channel: ChannelInfo) -> None:
        """Events of detectors not run again are kept; JSON truth becomes FaultEvent."""
        if channel.topic == EVENTS_TOPIC and is_event_channel(channel):
            keep_fdi_events(self.writer, self.events_channel, batch, channel, self.rerun)
        elif channel.id in self.legacy_truth:
            if self.truth_channel is None:
                self.truth_channel = register_truth_channel(self.writer)
            old = decode_events(batch.select(batch.channel_id == channel.id), channel)
            self.writer.add_batch(encode_fault_events(self.truth_channel, old))

    # --- detecting --------------------------------------------------------------------

    def add_block(self, block: ImuBlock) -> None:
        """An aligned block: into the calibration window and backlog until the detectors
        are fitted, then straight through them."""
        if self.t_first is None:
            self.t_first = int(block.t_ns[0])
            # ISO 8601 / Unix times of --start/--end, now that the log start is known
            self.test_start_s, self.test_end_s = window_from_log_start(
                (self.test_start_s, self.test_end_s), self.t_first
            )
        self.t_last = int(block.t_ns[-1])
        block, flags = self.conditioner.prepare(block)
        rel = (block.t_ns - self.t_first) / NS_PER_S
        tested = rel >= self.test_start_s
        if self.test_end_s is not None:
            tested &= rel < self.test_end_s
        test_block, test_flags = block, flags
        if not tested.all():
            test_block, test_flags = block.mask(tested), _mask_flags(flags, tested)
        self.n_samples += len(test_block)
        if self.fitted:
            if len(test_block):
                self._process(test_block, test_flags)
            return
        cal_window = calibration_window_ns(
            self.t_first, self.t_last, self.cal_start_s, self.cal_end_s
        )
        assert cal_window is not None
        inside = block.t_ns >= cal_window[0]
        if self.cal_end_s is not None:
            inside &= block.t_ns < cal_window[1]
        if inside.any():
            self.calibration.append((block.mask(inside).copy(), _mask_flags(flags, inside)))
        if len(test_block):
            self.backlog.append((test_block.copy(), test_flags))
        if self.cal_end_s is not None and block.t_ns[-1] >= cal_window[1]:
            self._fit()

    def _process(self, block: ImuBlock, flags: Flags) -> None:
        block = self.conditioner.sanitize(block, flags)
        for track in self.tracks:
            track.feed(block.t_ns)
            note_flags = getattr(track.detector, "note_flags", None)
            if note_flags is not None:  # a detector that tests flagged samples itself
                note_flags(flags)
            for sensor_type, builder in track.episodes.items():
                triads = block.get(sensor_type)
                assert triads is not None  # builders exist only for types in the log
                builder.feed(self.array.select(triads, sensor_type))
            self._emit(track, track.detector.process(block))

    def _fit(self) -> None:
        whole = ImuBlock.concatenate(b for b, _ in self.calibration)
        whole_flags = _concat_flags([f for _, f in self.calibration])
        self.cal_samples = len(whole)
        if self.cal_samples == 0:
            end = "" if self.cal_end_s is None else f"{self.cal_end_s:g}s"
            raise CalibrationError(
                f"calibration window {self.cal_start_s:g}s:{end}"
                " holds no samples; choose one inside the log with --calibrate START:END"
            )
        self.conditioner.fit(whole, whole_flags)
        whole = self.conditioner.sanitize(whole, whole_flags, count=False)
        for track in self.tracks:
            track.detector.fit(whole, self.array)
            note = level_warning(track.detector, self.array.rate_hz)
            if note is not None:
                self.warnings.append(note)
        builders: dict[str, EpisodeBuilder] = {}
        if self.explain:
            # imported when used: --no-explain runs do not load (or compile) it
            from imufdi_cli.episodes import episode_builders

            builders = episode_builders(whole, self.array)
        for track in self.tracks:
            track.episodes = {t: b.for_detector(track.detector.name) for t, b in builders.items()}
        self.fitted = True
        self.calibration.clear()
        for pending, pending_flags in self.backlog:
            self._process(pending, pending_flags)
        self.backlog.clear()

    # --- writing results --------------------------------------------------------------

    def _emit(self, track: _Track, outputs: Mapping[str, DetectionBlock]) -> None:
        """Status, events and episodes of the rows a detector returned."""
        rows = {len(v) for v in outputs.values()}
        if not rows:
            return
        if len(rows) != 1:
            raise DetectorConfigError(
                f"detector {track.detector.name} returned blocks of different lengths"
            )
        t_ns, decided_ns = track.take_times(rows.pop())
        if t_ns.size == 0:
            return
        for sensor_type, out in outputs.items():
            self._emit_type(track, sensor_type, out, t_ns, decided_ns)
        for sensor_type in set(track.episodes) - set(outputs):
            del track.episodes[sensor_type]  # a type this detector does not test

    def _emit_type(
        self,
        track: _Track,
        sensor_type: str,
        out: DetectionBlock,
        t_ns: np.ndarray,
        decided_ns: np.ndarray,
    ) -> None:
        writer, array = self.writer, self.array
        if sensor_type not in track.channels:
            ids = array.sensor_ids(sensor_type)
            track.channels[sensor_type] = register_status_channel(
                writer, track.detector.name, sensor_type, ids
            )
            if ids and self.named_scores:  # the scores under the sensors' names (viewers)
                track.score_channels[sensor_type] = register_scores_channel(
                    writer, track.detector.name, sensor_type, ids
                )
            track.summary[sensor_type] = TypeSummary()
        channel = track.channels[sensor_type]
        # whole records from a template (the bytes encode_status + add_batch make)
        writer.add_records(
            status_records(channel, t_ns, out, decided_ns), np.full(len(t_ns), channel), t_ns
        )
        named = track.score_channels.get(sensor_type)
        if named is not None:
            writer.add_records(
                scores_records(named, t_ns, out.scores), np.full(len(t_ns), named), t_ns
            )
        summary = track.summary[sensor_type]
        summary.samples += len(out)
        summary.alarms += int(np.count_nonzero(out.alarm))
        ids = array.sensor_ids(sensor_type)
        iso = out.isolated[out.alarm & (out.isolated >= 0)]
        for index, count in zip(*np.unique(iso, return_counts=True)):
            sid = ids[int(index)]
            summary.isolated[sid] = summary.isolated.get(sid, 0) + int(count)
        events, starts = _events(track, self.events_channel, sensor_type, t_ns, out)
        summary.events += starts
        writer.add_batch(events)
        builder = track.episodes.get(sensor_type)
        if builder is not None:
            self._add_episodes(track, builder.rows(t_ns, decided_ns, out))

    def _add_episodes(self, track: _Track, episodes: Sequence[Any]) -> None:
        if not episodes:
            return
        explain = getattr(track.detector, "explain_episode", None)
        if explain is not None:  # a detector that knows what raised its episodes
            for episode in episodes:
                if episode.detector == track.detector.name:
                    episode.fits = explain(episode)
        self.writer.add_batch(
            encode_episode_events(self.events_channel, [e.to_dict() for e in episodes])
        )
        for episode in (e for e in episodes if e.detector == track.detector.name):
            counts = track.summary[episode.sensor_type].episodes
            label = episode.fault_class or "unexplained"
            counts[label] = counts.get(label, 0) + 1

    def finish(self, strict: bool) -> None:
        """Fit if the log ended inside the calibration window, flush the detectors, check
        their calibration, and write the metadata records."""
        if not self.fitted:
            if self.t_first is not None and self.cal_end_s is not None:
                self.warnings.append(
                    f"the log ({(self.t_last - self.t_first) / NS_PER_S:.3g} s) is shorter"
                    f" than the calibration window end ({self.cal_end_s:g} s); calibrated on"
                    " what there is"
                )
            self._fit()
        for track in self.tracks:
            self._emit(track, track.detector.flush())
            for builder in track.episodes.values():
                self._add_episodes(track, builder.finish())
            if track.pending and sum(p.size for p in track.pending):
                raise DetectorConfigError(
                    f"detector {track.detector.name} left samples without output"
                )
        windowed = self.test_start_s > 0 or self.test_end_s is not None
        if windowed and self.n_samples == 0 and self.t_first is not None:
            end = "end" if self.test_end_s is None else f"{self.test_end_s:.6g} s"
            self.warnings.append(
                f"--start/--end holds no sample: the window is {self.test_start_s:.6g} s to"
                f" {end} from the log start, the log spans 0 to"
                f" {(self.t_last - self.t_first) / NS_PER_S:.6g} s (from"
                f" {_utc(self.t_first)}); nothing was tested"
            )
        # a log with injected faults alarms more by design: report measures its FAR on truth
        if "imufdi.faults" not in self.reader.source.metadata:
            for track in self.tracks:
                self.warnings.extend(
                    observed_level_warnings(track.detector, track.summary, self.array.rate_hz)
                )
        for track in self.tracks:
            # A detector may judge its calibration window from what it processed (e.g.
            # pca-parity: motion beyond the calibrated range); --strict makes that fatal.
            judge = getattr(track.detector, "calibration_warnings", None)
            found = list(judge()) if judge is not None else []
            if strict and found:
                raise CalibrationError(f"{found[0]} (--strict)")
            self.warnings.extend(found)
        self._write_metadata()

    def _write_metadata(self) -> None:
        """``imufdi.detect.<name>`` per detector, then the input's other metadata records."""
        log_array = self.reader.array
        window_ns = calibration_window_ns(
            self.t_first, self.t_last, self.cal_start_s, self.cal_end_s
        )
        for track in self.tracks:
            record = {
                "detector": track.detector.name,
                "version": __version__,
                "calibration_s": [self.cal_start_s, self.cal_end_s],
                "calibration_window_ns": window_ns,
                "calibration_samples": self.cal_samples,
                "lookahead_samples": track.lookahead,
                "detector_metadata": track.detector.metadata(),
                "t0_ns": self.t_first,
                "window_s": [self.test_start_s, self.test_end_s],
                "array_source": "log" if self.array is log_array else "--array",
                "validity": self.conditioner.metadata(),
            }
            if self.array is not log_array:
                record["array"] = self.array.to_dict()
            self.writer.add_metadata(
                f"imufdi.detect.{track.detector.name}",
                {"json": json.dumps(record, default=_json_default)},
            )
        names = {t.detector.name for t in self.tracks}
        for name, data in self.reader.source.metadata.items():
            if not name.startswith("imufdi.detect."):
                self.writer.add_metadata(name, data)
            elif name.removeprefix("imufdi.detect.") not in names:
                self.writer.add_metadata(name, data)
        if "imufdi.array" not in self.reader.source.metadata:
            self.writer.add_metadata("imufdi.array", {"json": self.array.to_json()})

    def result(self, output: str) -> DetectResult:
        t_first = self.t_first
        return DetectResult(
            output=output,
            samples=self.n_samples,
            duration_s=(self.t_last - t_first) / NS_PER_S if t_first is not None else 0.0,
            calibration_s=(
                self.cal_start_s,
                self.cal_end_s if self.cal_end_s is not None else float("nan"),
            ),
            calibration_samples=self.cal_samples,
            array=self.array,
            summaries={t.detector.name: t.summary for t in self.tracks},
            alignment=self.reader.stats,
            warnings=list(self.reader.warnings) + self.warnings,
            validity={s: c.to_dict() for s, c in self.conditioner.counts.items()},
        )


def calibration_window_ns(
    t_first: int | None, t_last: int, start_s: float, end_s: float | None
) -> list[int] | None:
    """The calibration window as absolute ``[start_ns, end_ns)`` (None for an empty log).

    A sample at time t was in the window when ``start_ns <= t < end_ns``; an open end
    (``end_s`` None) ends after the last sample.
    """
    if t_first is None:
        return None
    start = t_first + round(start_s * NS_PER_S)
    end = t_last + 1 if end_s is None else t_first + round(end_s * NS_PER_S)
    return [start, end]


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _utc(t_ns: int) -> str:
    """``2023-11-14T22:13:20Z`` (ISO 8601 UTC, to the millisecond when not whole)."""
    from imufdi_cli.units import utc_iso

    return utc_iso(t_ns)


def _mask_flags(flags: Flags, keep: np.ndarray) -> Flags:
    return {s: (c[keep], i[keep]) for s, (c, i) in flags.items()}


def _concat_flags(parts: Sequence[Flags]) -> Flags:
    if not parts:
        return {}
    return {
        s: (
            np.concatenate([p[s][0] for p in parts]),
            np.concatenate([p[s][1] for p in parts]),
        )
        for s in parts[0]
    }
