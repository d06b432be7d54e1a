"""``imufdi detect``: run detectors over a log and write the annotated MCAP (docs/formats.md).

One streaming pass: every input message is copied to the output as raw bytes (a whole
input chunk of messages only is written as it is, without recompression: docs/formats.md);
the aligned IMU samples go through the detection core (:class:`~imufdi_cli.engine.Engine`:
conditioning, calibration window, detectors, decision times, episodes), whose sink here
writes the results: per-sample status messages (fixed-layout
CDR, encoded in bulk) go to ``/imufdi/<detector>/<type>``, alarm start/end events
(``imufdi_msgs/msg/FdiEvent``, CDR, encoded in bulk per block) to ``/imufdi/events``, and
each detector's parameters and calibration to the ``imufdi.detect.<name>`` metadata record.
Ground truth on the JSON channel of an older imufdi is re-encoded as FaultEvent. Memory is
bounded by the block size and the calibration window, not by the log length.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import numpy as np

from imufdi_cli._version import __version__
from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors import make_detectors
from imufdi_cli.detectors.base import DetectionBlock, Detector
from imufdi_cli.engine import (
    DEFAULT_CALIBRATION,
    NOISY_EPISODES_PER_HOUR,
    Engine,
    Track,
    calibration_window_ns,
    decision_positions,
    level_warning,
    lookahead_of,
    with_budget,
)
from imufdi_cli.errors import FlightLogError
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
from imufdi_cli.validity import Conditioner

NS_PER_S = 1_000_000_000
#: re-exported: what the detection core defines, under the names callers know
__all__ = [
    "DEFAULT_CALIBRATION",
    "NOISY_EPISODES_PER_HOUR",
    "DetectResult",
    "TypeSummary",
    "calibration_window_ns",
    "decision_positions",
    "detect_file",
    "level_warning",
    "lookahead_of",
    "with_budget",
]


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


def _events(
    alarm_on: dict[str, bool],
    detector: str,
    sensor_ids: list[str],
    channel_id: int,
    sensor_type: str,
    t_ns: np.ndarray,
    out: DetectionBlock,
) -> tuple[MessageBatch, int]:
    """Alarm start/end events of a block (the alarm state carried across blocks in
    ``alarm_on``, per sensor type), encoded in bulk; also the number of alarm starts."""
    alarm = np.asarray(out.alarm, dtype=bool)
    before = alarm_on.get(sensor_type, False)
    previous = np.concatenate([[before], alarm[:-1]])
    changes = np.flatnonzero(alarm != previous)
    if alarm.size:
        alarm_on[sensor_type] = bool(alarm[-1])
    amplitude = np.asarray(out.amplitude, np.float64)[changes]
    batch = encode_fdi_events(
        channel_id,
        np.asarray(t_ns, np.int64)[changes],
        detector=detector,
        sensor_type=sensor_type,
        sensor_ids=sensor_ids,
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
    """One streaming detect pass: input messages copied, blocks through the detection
    core (:class:`~imufdi_cli.engine.Engine`), its rows and episodes written as status
    channels, alarm events and episode events (this class is the engine's sink)."""

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
        self.engine = Engine(
            instances,
            array,
            conditioner,
            self,
            calibrate=calibrate,
            window=window,
            explain=explain,
            imu_topics=reader.imu_topics,
        )
        self.warnings: list[str] = []
        self.named_scores = named_scores
        # per detector: status channel, alarm state and summary of each sensor type
        self.channels: dict[str, dict[str, int]] = {det.name: {} for det in instances}
        #: per detector: the named-scores channel of each sensor type
        self.score_channels: dict[str, dict[str, int]] = {det.name: {} for det in instances}
        self.alarm_on: dict[str, dict[str, bool]] = {det.name: {} for det in instances}
        self.summary: dict[str, dict[str, TypeSummary]] = {det.name: {} for det in instances}
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
        """An aligned block, to the detection core."""
        self.engine.add_block(block)

    # --- writing results (the engine's sink) ------------------------------------------

    def rows(
        self,
        track: Track,
        sensor_type: str,
        t_ns: np.ndarray,
        decided_ns: np.ndarray,
        out: DetectionBlock,
    ) -> None:
        """Status messages and alarm events of one sensor type's rows."""
        writer, array, name = self.writer, self.array, track.name
        channels = self.channels[name]
        if sensor_type not in channels:
            ids = array.sensor_ids(sensor_type)
            channels[sensor_type] = register_status_channel(writer, name, sensor_type, ids)
            if ids and self.named_scores:  # the scores under the sensors' names (viewers)
                self.score_channels[name][sensor_type] = register_scores_channel(
                    writer, name, sensor_type, ids
                )
            self.summary[name][sensor_type] = TypeSummary()
        channel = channels[sensor_type]
        # whole records from a template (the bytes encode_status + add_batch make)
        writer.add_records(
            status_records(channel, t_ns, out, decided_ns), np.full(len(t_ns), channel), t_ns
        )
        named = self.score_channels[name].get(sensor_type)
        if named is not None:
            writer.add_records(
                scores_records(named, t_ns, out.scores), np.full(len(t_ns), named), t_ns
            )
        summary = self.summary[name][sensor_type]
        summary.samples += len(out)
        summary.alarms += int(np.count_nonzero(out.alarm))
        ids = array.sensor_ids(sensor_type)
        iso = out.isolated[out.alarm & (out.isolated >= 0)]
        for index, count in zip(*np.unique(iso, return_counts=True)):
            sid = ids[int(index)]
            summary.isolated[sid] = summary.isolated.get(sid, 0) + int(count)
        events, starts = _events(
            self.alarm_on[name], name, ids, self.events_channel, sensor_type, t_ns, out
        )
        summary.events += starts
        writer.add_batch(events)

    def episodes(self, track: Track, episodes: Sequence[Any]) -> None:
        """Explained episodes, as ``episode`` events."""
        self.writer.add_batch(
            encode_episode_events(self.events_channel, [e.to_dict() for e in episodes])
        )
        for episode in (e for e in episodes if e.detector == track.name):
            counts = self.summary[track.name][episode.sensor_type].episodes
            label = episode.fault_class or "unexplained"
            counts[label] = counts.get(label, 0) + 1

    def finish(self, strict: bool) -> None:
        """Finish the pass (:meth:`Engine.finish`), say what the alarms say about the
        detectors' levels, and write the metadata records."""
        engine = self.engine
        engine.finish(strict)
        windowed = engine.test_start_s > 0 or engine.test_end_s is not None
        if windowed and engine.n_samples == 0 and engine.t_first is not None:
            end = "end" if engine.test_end_s is None else f"{engine.test_end_s:.6g} s"
            engine.warnings.append(
                f"--start/--end holds no sample: the window is {engine.test_start_s:.6g} s to"
                f" {end} from the log start, the log spans 0 to"
                f" {(engine.t_last - engine.t_first) / NS_PER_S:.6g} s (from"
                f" {_utc(engine.t_first)}); nothing was tested"
            )
        # a log with injected faults alarms more by design: report measures its FAR on truth
        if "imufdi.faults" not in self.reader.source.metadata:
            for track in engine.tracks:
                engine.warnings.extend(
                    observed_level_warnings(
                        track.detector, self.summary[track.name], self.array.rate_hz
                    )
                )
        self._write_metadata()

    def _write_metadata(self) -> None:
        """``imufdi.detect.<name>`` per detector, then the input's other metadata records."""
        log_array = self.reader.array
        engine = self.engine
        window_ns = engine.calibration_window()
        for track in engine.tracks:
            record = {
                "detector": track.detector.name,
                "version": __version__,
                "calibration_s": [engine.cal_start_s, engine.cal_end_s],
                "calibration_window_ns": window_ns,
                "calibration_samples": engine.cal_samples,
                "lookahead_samples": track.lookahead,
                "detector_metadata": track.detector.metadata(),
                "t0_ns": engine.t_first,
                "window_s": [engine.test_start_s, engine.test_end_s],
                "array_source": "log" if self.array is log_array else "--array",
                "validity": self.conditioner.metadata(),
            }
            if self.array is not log_array:
                record["array"] = self.array.to_dict()
            self.writer.add_metadata(
                f"imufdi.detect.{track.detector.name}",
                {"json": json.dumps(record, default=_json_default)},
            )
        names = {t.detector.name for t in engine.tracks}
        for name, data in self.reader.source.metadata.items():
            if not name.startswith("imufdi.detect."):
                self.writer.add_metadata(name, data)
            elif name.removeprefix("imufdi.detect.") not in names:
                self.writer.add_metadata(name, data)
        if "imufdi.array" not in self.reader.source.metadata:
            self.writer.add_metadata("imufdi.array", {"json": self.array.to_json()})

    def result(self, output: str) -> DetectResult:
        engine = self.engine
        t_first = engine.t_first
        return DetectResult(
            output=output,
            samples=engine.n_samples,
            duration_s=(engine.t_last - t_first) / NS_PER_S if t_first is not None else 0.0,
            calibration_s=(
                engine.cal_start_s,
                engine.cal_end_s if engine.cal_end_s is not None else float("nan"),
            ),
            calibration_samples=engine.cal_samples,
            array=self.array,
            summaries={t.name: self.summary[t.name] for t in engine.tracks},
            alignment=self.reader.stats,
            warnings=list(self.reader.warnings) + self.warnings + engine.warnings,
            validity={s: c.to_dict() for s, c in self.conditioner.counts.items()},
        )


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
