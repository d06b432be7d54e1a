"""``imufdi inject``: copy an MCAP log with faults injected into its IMU messages, plus
ground truth (part of :mod:`imufdi_cli.faults`).
"""

from __future__ import annotations

import io
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import FaultSpecError
from imufdi_cli.faults.injector import FaultInjector
from imufdi_cli.faults.models import METADATA_NAME, TRUTH_TOPIC, Fault
from imufdi_cli.faults.spec import load_fault_file, parse_fault_spec
from imufdi_cli.progress import LogTimeProgress, ProgressCallback


@dataclass
class InjectResult:
    """What :func:`inject_file` did.

    Attributes
    ----------
    output : str
        Path written (``"-"`` for stdout).
    seed : int
    faults : list of Fault
        Faults injected by this run (with their ids).
    previous_faults : list of Fault
        Faults already recorded in the input.
    t0_ns : int
        Log start (first IMU sample stamp), ns.
    duration_s : float
        Last minus first IMU sample stamp, s.
    imu_topics : list of str
        IMU topics in IMU index order.
    warnings : list of str
        Reader warnings (e.g. log time used for Imu messages without header stamps).
    messages : int
        Messages copied (all channels, input only).
    messages_patched : int
        IMU/magnetometer messages whose values were rewritten.
    truth_messages : int
        Messages added to ``/imufdi/truth``.
    warnings : list of str
        Problems the reader met in the input (e.g. a corrupt chunk skipped: its messages
        are not in the output).
    """

    output: str
    seed: int
    faults: list[Fault]
    previous_faults: list[Fault]
    t0_ns: int
    duration_s: float
    imu_topics: list[str]
    messages: int = 0
    messages_patched: int = 0
    truth_messages: int = 0
    warnings: list[str] = field(default_factory=list)


def _same_file(a: str, b: str) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def inject_file(
    source: str | Path,
    output: str | Path,
    faults_specs: Sequence[str],
    fault_files: Sequence[str | Path],
    *,
    seed: int,
    compression: str = "zstd",
    topics: Sequence[str] | None = None,
    time_source: str = "auto",
    progress: ProgressCallback | None = None,
) -> InjectResult:
    """Copy an MCAP log with faults injected into its IMU messages, plus ground truth.

    Every channel, message and metadata record of the input is copied; IMU (and
    magnetometer) messages of faulted sensors are patched in place (all other bytes
    identical). Adds the ``/imufdi/truth`` channel (``imufdi_msgs/msg/FaultEvent``, CDR, one
    message per fault start/end; the JSON truth and alarm events of an older imufdi are
    re-encoded as FaultEvent / FdiEvent)
    and the ``imufdi.faults`` metadata record (seed, faults in SI, earlier runs under
    ``previous``). All specs are validated against the array and the log duration before
    anything is written; on failure no output file is left.

    Parameters
    ----------
    source : str or Path
        Input MCAP, or ``"-"`` for stdin (buffered in memory: the log is read twice).
    output : str or Path
        Output MCAP, or ``"-"`` for stdout. Must not be the input.
    faults_specs : sequence of str
        Specs in the ``MODEL:SENSOR,key=value,...`` grammar.
    fault_files : sequence of path
        TOML files of ``[[fault]]`` tables.
    seed : int
        Seed of the random fault models.
    compression : {"zstd", "lz4", "none"}
        Chunk compression of the output.
    topics : sequence of str, optional
        Imu topics in IMU order (``/topic:field`` for an Imu inside a larger message), as
        :class:`~imufdi_cli.mcapio.ImuArrayReader` takes them; default all.
    time_source : {"auto", "header", "log_time"}
        Stamps the fault times refer to (see :class:`~imufdi_cli.mcapio.ImuArrayReader`).
    progress : callable, optional
        ``progress(done, total)`` in seconds of log time, both passes counted
        (:mod:`imufdi_cli.progress`).

    Raises
    ------
    FaultSpecError
        No fault given, or a bad spec (exit code 2).
    McapInputError
        Unreadable input or no IMU channel (exit code 3).
    """
    from imufdi_cli.errors import UsageError

    if not faults_specs and not fault_files:
        raise FaultSpecError("inject needs at least one --fault SPEC or --faults FILE")
    source_name, output_name = str(source), str(output)
    if output_name != "-" and source_name != "-" and _same_file(source_name, output_name):
        raise UsageError(f"output {output_name} is the input file; inputs are never modified")
    open_input = _input_opener(source_name)
    layout = _read_layout(open_input, topics, time_source)
    scan = _scan_log(open_input, layout, source_name, progress)
    # Validate every spec before writing anything.
    faults = [parse_fault_spec(spec, layout.array) for spec in faults_specs]
    for path in fault_files:
        faults += load_fault_file(path, layout.array)
    duration_s = (scan.last_ns - scan.first_ns) * 1e-9
    injector = FaultInjector(
        faults,
        layout.array,
        seed=seed,
        t0_ns=scan.first_ns,
        log_duration_s=duration_s,
        previous_metadata=scan.metadata.get(METADATA_NAME),
    )
    _check_streams(injector, scan, layout)
    result = InjectResult(
        output=output_name,
        seed=injector.seed,
        faults=injector.faults,
        previous_faults=[
            Fault.from_dict(item) for run in injector.previous_runs for item in run["faults"]
        ],
        t0_ns=scan.first_ns,
        duration_s=duration_s,
        imu_topics=layout.imu_topics,
        warnings=layout.warnings,
    )
    _copy_with_faults(open_input, output, compression, layout, scan, injector, result)
    return result


def _input_opener(source_name: str) -> Callable[[], Any]:
    """A function giving the input afresh for each pass (stdin is buffered in memory)."""
    if source_name != "-":
        return lambda: source_name
    buffered = io.BytesIO(sys.stdin.buffer.read())

    def rewound() -> io.BytesIO:
        buffered.seek(0)
        return buffered

    return rewound


@dataclass
class _Layout:
    """The array and the topic -> IMU index rule, exactly as the reader sees them."""

    array: ArrayConfig
    imu_topics: list[str]
    imu_fields: dict[str, str]  # topic -> path of the Imu inside its messages
    mag_topics: list[str]
    use_log_time: bool
    warnings: list[str]


def _read_layout(
    open_input: Callable[[], Any], topics: Sequence[str] | None, time_source: str
) -> _Layout:
    from imufdi_cli import mcapio

    with mcapio.ImuArrayReader(open_input(), topics=topics, time_source=time_source) as reader:
        array = reader.array
        return _Layout(
            array=array,
            imu_topics=list(reader.imu_topics),
            imu_fields=dict(reader.imu_fields),
            mag_topics=list(reader.mag_topics) if array.has("mag") else [],
            use_log_time=reader.time_source == "log_time",
            warnings=list(reader.warnings),
        )


@dataclass
class _Scan:
    """Pass 1: channels, metadata, the IMU time span (and truth on older JSON channels)."""

    first_ns: int
    last_ns: int
    channels: dict[int, Any]
    metadata: dict[str, dict[str, str]]
    imu_channels: dict[int, int]  # channel id -> IMU index
    mag_channels: dict[int, int]
    legacy_truth: list[dict[str, Any]]
    legacy_alarms: list[tuple[int, dict[str, Any]]]
    #: progress through both passes (over the log's time range)
    tracker: LogTimeProgress = field(default_factory=lambda: LogTimeProgress(None, None))


def _scan_log(
    open_input: Callable[[], Any],
    layout: _Layout,
    source_name: str,
    progress: ProgressCallback | None = None,
) -> _Scan:
    from imufdi_cli import mcapio
    from imufdi_cli.errors import McapInputError
    from imufdi_cli.mcapio.events import decode_events, is_event_channel

    first_ns: int | None = None
    last_ns: int | None = None
    legacy_truth: list[dict[str, Any]] = []
    legacy_alarms: list[tuple[int, dict[str, Any]]] = []
    with mcapio.McapSource(open_input()) as reader:
        tracker = LogTimeProgress(progress, reader.summary_time_range, passes=2)
        for batch in reader.batches():
            tracker.batch(batch)
            for cid, sub in batch.by_channel():
                channel = reader.channels[cid]
                if channel.message_encoding == "json" and is_event_channel(channel):
                    if channel.topic == TRUTH_TOPIC:
                        legacy_truth += decode_events(sub, channel)
                    else:
                        legacy_alarms += zip(sub.log_time.tolist(), decode_events(sub, channel))
            span = _imu_span(batch, reader.channels, layout)
            if span is not None:
                first_ns = span[0] if first_ns is None else min(first_ns, span[0])
                last_ns = span[1] if last_ns is None else max(last_ns, span[1])
        channels = dict(reader.channels)
        metadata = {name: dict(values) for name, values in reader.metadata.items()}
    if first_ns is None or last_ns is None:
        raise McapInputError(f"{source_name}: no sensor_msgs/msg/Imu messages to inject into")
    imu_index = {topic: k for k, topic in enumerate(layout.imu_topics)}
    mag_index = {topic: k for k, topic in enumerate(layout.mag_topics)}
    return _Scan(
        first_ns=first_ns,
        last_ns=last_ns,
        channels=channels,
        metadata=metadata,
        imu_channels={
            cid: imu_index[ch.topic]
            for cid, ch in channels.items()
            if _is_imu_source(ch, layout.imu_fields)
        },
        mag_channels={
            cid: mag_index[ch.topic]
            for cid, ch in channels.items()
            if ch.topic in mag_index and mcapio.is_mag_channel(ch)
        },
        legacy_truth=legacy_truth,
        legacy_alarms=legacy_alarms,
        tracker=tracker,
    )


def _imu_span(batch: Any, channels: Mapping[int, Any], layout: _Layout) -> tuple[int, int] | None:
    """First and last IMU stamp of a batch (the time source the faults refer to), or None."""
    from imufdi_cli import mcapio

    # one bulk decode per schema: channels sharing a schema share a codec
    groups: dict[tuple[Any, str, str], list[int]] = {}
    for cid in np.unique(batch.channel_id).tolist():
        channel = channels[cid]
        if _is_imu_source(channel, layout.imu_fields):
            key = (channel.schema, channel.message_encoding, layout.imu_fields[channel.topic])
            groups.setdefault(key, []).append(cid)
    span: tuple[int, int] | None = None
    for (_, _, imu_path), cids in groups.items():
        part = batch.select(np.flatnonzero(np.isin(batch.channel_id, cids)))
        decoded = mcapio.decode_imu(part, channels[cids[0]], imu_path)
        stamps = decoded.log_time if layout.use_log_time else decoded.t_ns
        if stamps.size:
            low, high = int(stamps.min()), int(stamps.max())
            span = (low, high) if span is None else (min(span[0], low), max(span[1], high))
    return span


def _check_streams(injector: FaultInjector, scan: _Scan, layout: _Layout) -> None:
    """Every faulted stream must exist in the log and be patchable (CDR) before writing."""
    from imufdi_cli.errors import McapInputError

    streams = {(k, t): cid for cid, k in scan.imu_channels.items() for t in ("gyro", "accel")}
    streams.update({(k, "mag"): cid for cid, k in scan.mag_channels.items()})
    for fault in injector.faults:
        cid = streams.get((fault.imu, fault.sensor_type))
        if cid is None:
            raise FaultSpecError(
                f"fault {fault.spec!r}: the log has no {fault.sensor_type} topic for "
                f"imu{fault.imu}; IMU topics: {', '.join(layout.imu_topics)}"
            )
        channel = scan.channels[cid]
        if channel.message_encoding != "cdr":
            raise McapInputError(
                f"fault {fault.spec!r}: {channel.topic} is "
                f"{channel.message_encoding!r}-encoded; only CDR messages can be patched"
            )


def _copy_with_faults(
    open_input: Callable[[], Any],
    output: str | Path,
    compression: str,
    layout: _Layout,
    scan: _Scan,
    injector: FaultInjector,
    result: InjectResult,
) -> None:
    """Pass 2: copy, patching the faulted IMU messages; adds truth and metadata."""
    from imufdi_cli import mcapio
    from imufdi_cli.mcapio.events import is_event_channel

    channels = scan.channels
    with (
        mcapio.McapSource(open_input()) as reader,
        mcapio.McapWriter(output, compression=compression) as writer,
    ):
        # JSON event channels of an older imufdi are re-encoded as FaultEvent / FdiEvent
        legacy_ids = [
            cid
            for cid, ch in channels.items()
            if ch.message_encoding == "json" and is_event_channel(ch)
        ]
        writer.copy_channels({c: ch for c, ch in channels.items() if c not in legacy_ids})
        for name, values in scan.metadata.items():
            if name != METADATA_NAME:
                writer.add_metadata(name, values)
        if "imufdi.array" not in scan.metadata:
            writer.add_metadata("imufdi.array", {"json": layout.array.to_json()})
        writer.add_metadata(METADATA_NAME, injector.metadata())
        result.truth_messages += _write_events(writer, scan, injector)
        scan.tracker.next_pass()
        for batch in reader.batches():
            scan.tracker.batch(batch)
            if legacy_ids:
                batch = batch.select(~np.isin(batch.channel_id, legacy_ids))
            result.messages += len(batch)
            patched, count = _patch_batch(
                batch,
                channels,
                scan.imu_channels,
                scan.mag_channels,
                injector,
                imu_fields=layout.imu_fields,
                use_log_time=layout.use_log_time,
            )
            result.messages_patched += count
            writer.add_batch(patched)
        # the layout pass's warnings (array, stamps) and this pass's, each once
        result.warnings = list(dict.fromkeys([*layout.warnings, *reader.warnings]))


def _write_events(writer: Any, scan: _Scan, injector: FaultInjector) -> int:
    """Truth events (earlier ones kept) and re-encoded legacy alarms; new truth messages."""
    from imufdi_cli.mcapio.events import (
        encode_fault_events,
        encode_fdi_event_dicts,
        is_event_channel,
        register_events_channel,
        register_truth_channel,
    )

    truth_ids = [
        cid
        for cid, ch in scan.channels.items()
        if ch.topic == TRUTH_TOPIC and ch.message_encoding == "cdr" and is_event_channel(ch)
    ]
    truth_channel = truth_ids[0] if truth_ids else register_truth_channel(writer)
    events = scan.legacy_truth + injector.truth_events()
    writer.add_batch(encode_fault_events(truth_channel, events))
    if scan.legacy_alarms:
        writer.add_batch(
            encode_fdi_event_dicts(
                register_events_channel(writer),
                [t for t, _ in scan.legacy_alarms],
                [e for _, e in scan.legacy_alarms],
            )
        )
    return len(events) - len(scan.legacy_truth)


def _is_imu_source(channel: Any, imu_fields: Mapping[str, str]) -> bool:
    """The channel carries the Imu of one of the array's topics (at that topic's field)."""
    from imufdi_cli.mcapio.imu import imu_fields_of

    path = imu_fields.get(channel.topic)
    return path is not None and path in imu_fields_of(channel)


def _patch_batch(
    batch: Any,
    channels: Mapping[int, Any],
    imu_channels: Mapping[int, int],
    mag_channels: Mapping[int, int],
    injector: FaultInjector,
    *,
    imu_fields: Mapping[str, str] | None = None,
    use_log_time: bool = False,
) -> tuple[Any, int]:
    """The batch with faulted IMU/magnetometer messages rewritten, in the original order.

    ``imu_fields``: topic -> path of the Imu inside its messages; ``use_log_time``: fault
    times refer to the log time instead of the header stamps."""
    from imufdi_cli import mcapio

    pieces: list[Any] = []
    positions: list[np.ndarray] = []
    patched = 0
    for channel_id, where in batch.channel_indices():
        imu = imu_channels.get(channel_id, mag_channels.get(channel_id))
        if imu is None:
            continue
        is_mag = channel_id in mag_channels
        types = ("mag",) if is_mag else ("gyro", "accel")
        if not any(injector.affects(imu, t) for t in types):
            continue
        part = batch.select(where)
        channel = channels[channel_id]
        path = "" if is_mag else (imu_fields or {}).get(channel.topic, "")
        if is_mag:
            fields = mcapio.decode_mag(part, channel)
        else:
            fields = mcapio.decode_imu(part, channel, path)
        stamps = fields.log_time if use_log_time else fields.t_ns
        new_values: dict[str, np.ndarray] = {}
        for sensor_type in types:
            decoded = getattr(fields, sensor_type)
            if decoded is None or not injector.affects(imu, sensor_type):
                continue
            new_values[sensor_type] = injector.apply(imu, sensor_type, stamps, decoded)
        if not new_values:
            continue
        if is_mag:
            pieces.append(mcapio.patch_mag(part, channel, mag=new_values["mag"]))
        else:
            pieces.append(mcapio.patch_imu(part, channel, field=path, **new_values))
        positions.append(where)
        patched += len(where)
    if not pieces:
        return batch, 0
    untouched = np.ones(len(batch), dtype=bool)
    for where in positions:
        untouched[where] = False
    rest = np.flatnonzero(untouched)
    if rest.size:
        pieces.append(batch.select(rest))
        positions.append(rest)
    joined = mcapio.MessageBatch.concatenate(pieces)
    order = np.argsort(np.concatenate(positions), kind="stable")
    return joined.select(order), patched
