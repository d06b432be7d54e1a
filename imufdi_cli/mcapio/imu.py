"""IMU arrays in MCAP: the streaming, time-aligning array reader (docs/formats.md).

The per-channel codecs live in :mod:`~imufdi_cli.mcapio.imu_codec`, the writer in
:mod:`~imufdi_cli.mcapio.imu_writer` and the time alignment in
:mod:`~imufdi_cli.mcapio.align`; their public names are re-exported here.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import ArrayConfigError, McapInputError, UsageError
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio.align import AlignmentStats, _Aligner
from imufdi_cli.mcapio.imu_codec import (
    ARRAY_METADATA,
    IMU_TYPE_NAMES,
    MAG_TYPE_NAMES,
    NS_PER_S,
    FixedLayoutDecoder,
    ImuFields,
    _decode,
    decode_imu,
    decode_mag,
    imu_fields_of,
    is_imu_channel,
    is_mag_channel,
    natural_key,
    patch_imu,
    patch_mag,
    schema_name,
)
from imufdi_cli.mcapio.records import (
    ChannelInfo,
    MessageBatch,
)
from imufdi_cli.mcapio.source import McapSource

if TYPE_CHECKING:
    from imufdi_cli.mcapio.imu_writer import ImuArrayWriter, encode_messages, write_array

__all__ = [
    "ARRAY_METADATA",
    "IMU_TYPE_NAMES",
    "MAG_TYPE_NAMES",
    "AlignmentStats",
    "ImuArrayReader",
    "ImuArrayWriter",
    "ImuFields",
    "NoImuChannelError",
    "decode_imu",
    "decode_mag",
    "encode_messages",
    "imu_fields_of",
    "is_imu_channel",
    "is_mag_channel",
    "natural_key",
    "patch_imu",
    "patch_mag",
    "read_array",
    "schema_name",
    "write_array",
]

#: Re-exported names of the writer, imported on first use: reading commands (``info``,
#: ``detect``'s input) do not pay for compiling the writer (start-up, docs/performance.md).
_WRITER_NAMES = frozenset({"ImuArrayWriter", "encode_messages", "write_array"})


def __getattr__(name: str) -> Any:
    if name in _WRITER_NAMES:
        from imufdi_cli.mcapio import imu_writer

        value = getattr(imu_writer, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: Read-ahead when a reader starts (see ImuArrayReader._prefetch_setup).
_SETUP_MESSAGES = 8
_SETUP_BATCHES = 4096
_SETUP_BYTES = 64 << 20


class NoImuChannelError(McapInputError):
    """The log has no ``sensor_msgs/msg/Imu`` channel (or none of the requested topics)."""


# --- reader -----------------------------------------------------------------------------


class ImuArrayReader:
    """Streaming reader of an IMU array from any MCAP with ``sensor_msgs/msg/Imu`` channels.

    Parameters
    ----------
    source : path, ``"-"``, binary stream or McapSource
    topics : sequence of str, optional
        Imu topics to read, in array order (default: every Imu channel, sorted naturally).
        A channel whose type holds exactly one ``sensor_msgs/msg/Imu`` field (e.g. a
        driver's message with an ``imu`` field) counts as an Imu channel; ``"/topic:path"``
        picks the Imu field at ``path`` explicitly. Magnetometers are read from
        ``<namespace>/mag`` MagneticField topics when every selected IMU has one.
    strict : bool
        Raise McapInputError on a truncated or corrupt file instead of adding a warning.
    time_source : {"auto", "header", "log_time"}
        Stamp used for alignment and output: ``header.stamp``, the MCAP log time, or
        (``auto``) the header stamp unless the Imu has no header or its stamps are all
        zero, in which case the log time is used with a warning.
    block_size : int, optional
        Samples per block yielded by :meth:`blocks`, and the samples the aligner gathers
        before it resolves a block for :meth:`stream`. Default: ``block_samples(n)`` for
        the ``n`` IMU topics read, 4096 samples up to 16 IMUs and fewer above (the
        samples of a block, and so the memory of a run, scale with samples x IMUs).
    tolerance_ns : int, optional
        Stamps of different topics closer than this are the same sample (default: 30 % of
        the sample period).
    keep_raw_chunks : bool
        Open a path with :class:`McapSource` ``keep_raw_chunks`` (``source.raw_chunk(batch)``
        then gives the Chunk record of a batch :meth:`stream` yields, for verbatim copying).
    validate_crcs : bool
        Check the CRC-32 of every chunk's records (default; a chunk that fails is skipped
        with a warning, or raises with ``strict``), unless its zstd frame's content
        checksum already covers them (see :class:`McapSource`). False skips the check
        (benchmarks, or logs known to be intact); the zstd/lz4 frame checksums are still
        verified. Applies when the reader opens ``source`` itself; an open McapSource
        keeps its own setting.
    partial : bool
        Also produce the array samples where some IMUs have no sample, as long as at least
        half of them have one (default): the missing IMUs' values are NaN and the block's
        ``missing`` mask says which (a topic that stopped or slowed; ``detect`` tests the
        others). False: only samples where every topic has one.

    Attributes
    ----------
    array : ArrayConfig
        From the ``imufdi.array`` metadata when it matches the topics, else inferred
        (co-aligned, one IMU per topic, measured rate).
    imu_fields : dict
        Topic -> path of the Imu inside its messages (``""``: the messages are Imu).
    imu_types : dict
        Topic -> message type name.
    time_source : str
        ``"header"`` or ``"log_time"``, as resolved.
    """

    def __init__(
        self,
        source: str | Path | IO[bytes] | McapSource,
        *,
        topics: Sequence[str] | None = None,
        strict: bool = False,
        time_source: str = "auto",
        block_size: int | None = None,
        tolerance_ns: int | None = None,
        keep_raw_chunks: bool = False,
        validate_crcs: bool = True,
        partial: bool = True,
    ) -> None:
        if time_source not in ("auto", "header", "log_time"):
            raise UsageError(f"unknown time source {time_source!r}; valid: auto, header, log_time")
        if block_size is not None and block_size < 1:
            raise UsageError(f"block_size must be >= 1, got {block_size}")
        self.source = (
            source
            if isinstance(source, McapSource)
            else McapSource(
                source,
                strict=strict,
                keep_raw_chunks=keep_raw_chunks,
                validate_crcs=validate_crcs,
            )
        )
        self.time_source = time_source
        self.block_size = 4096 if block_size is None else block_size  # set below if None
        self.warnings = self.source.warnings
        self._batches = self.source.batches()
        self._prefetched: deque[MessageBatch] = deque()
        self._exhausted = False
        self._imu_like: dict[int, tuple[ChannelInfo, bool]] = {}
        self._topics_given = topics is not None
        self._prefetch_setup(topics)
        try:
            self._select_topics(topics)
        except Exception:
            self.source.push_back(list(self._prefetched))
            if not isinstance(source, McapSource):
                self.close()
            raise
        imu_channels = {t: self.source.channels[cid] for t, cid in self._topic_channel.items()}
        mag_channels = {c.topic: c for c in self.source.channels.values() if is_mag_channel(c)}
        mag_topics = [t.rsplit("/", 1)[0] + "/mag" for t in self.imu_topics]
        self.mag_topics = (
            mag_topics
            if all(t in mag_channels for t in mag_topics) and not any(self.imu_fields.values())
            else []
        )
        self._imu_channel = {imu_channels[t].id: k for k, t in enumerate(self.imu_topics)}
        self._mag_channel = (
            {mag_channels[t].id: k for k, t in enumerate(self.mag_topics)}
            if self.mag_topics
            else {}
        )
        self._known_channels = -1  # check for late Imu channels on the first batch
        self._late_topics: set[str] = set()
        #: (channel id, fields) of the first Imu topic's read-ahead messages, while set up
        self._setup_fields: tuple[int, list[ImuFields]] | None = None
        self._resolve_time_source()
        self.array = self._array_config()
        self._setup_fields = None
        if self.array.has("mag") and not self.mag_topics:
            self.warnings.append(
                "array config has magnetometers but not every IMU topic has a <ns>/mag topic;"
                " magnetometers are not read"
            )
        if block_size is None:
            self.block_size = block_samples(len(self.imu_topics))
        block_size = self.block_size
        period_ns = NS_PER_S / self.array.rate_hz
        tolerance = int(0.3 * period_ns) if tolerance_ns is None else int(tolerance_ns)
        names = list(self.imu_topics) + list(self.mag_topics)
        widths = [6] * len(self.imu_topics) + [3] * len(self.mag_topics)
        self._period_ns = period_ns
        self._partial = partial
        self._aligner = _Aligner(
            names,
            widths,
            tolerance,
            max_pending=max(8 * block_size, 65536),
            quorum=(len(self.imu_topics) + 1) // 2 if partial else None,
            n_imus=len(self.imu_topics),
        )
        self.stats = self._aligner.stats
        self._groups: list[tuple[np.ndarray, ChannelInfo, tuple[str, ...], str]] | None = None
        self._stream_of = np.zeros(0, np.int64)
        self._group_of = np.zeros(0, np.int64)
        #: Per decode group: its fixed-layout decoder (CDR groups).
        self._fixed: dict[int, FixedLayoutDecoder] = {}

    # --- setup helpers --------------------------------------------------------------------

    def _select_topics(self, topics: Sequence[str] | None) -> None:
        """Fill ``imu_topics``, ``imu_fields``, ``imu_types`` and the topic -> channel id map."""
        channels = list(self.source.channels.values())
        by_topic = {c.topic: c for c in channels}
        found = {c.topic: imu_fields_of(c) for c in channels}
        self.imu_fields: dict[str, str] = {}
        self._topic_channel: dict[str, int] = {}
        if topics is None:
            usable = sorted((t for t, f in found.items() if len(f) == 1), key=natural_key)
            if not usable:
                listed = sorted(
                    (f"{c.topic} ({schema_name(c) or 'no schema'})" for c in channels),
                    key=natural_key,
                )
                raise NoImuChannelError(
                    f"{self.source.name}: no sensor_msgs/msg/Imu channel (CDR or JSON), and no"
                    " message type holding exactly one Imu field; topics: "
                    + (", ".join(listed) or "none")
                    + (f"; {self.warnings[0]}" if self.warnings else "")
                )
            self.imu_topics = usable
            for topic in usable:
                self.imu_fields[topic] = found[topic][0]
                self._topic_channel[topic] = by_topic[topic].id
        else:
            self.imu_topics = []
            for spec in topics:
                topic, _, path = spec.partition(":")
                channel = by_topic.get(topic)
                if channel is None:
                    usable = [t for t, f in found.items() if f]
                    raise NoImuChannelError(
                        f"{self.source.name}: no Imu channel on topic {topic or '(none)'};"
                        " Imu topics: " + (", ".join(sorted(usable, key=natural_key)) or "none")
                    )
                fields = found[topic]
                kind = schema_name(channel) or "no schema"
                if path and path not in fields:
                    raise McapInputError(
                        f"topic {topic} ({kind}, {channel.message_encoding}) has no"
                        f" sensor_msgs/msg/Imu field {path!r}; Imu fields: "
                        + (", ".join(f or "(the message)" for f in fields) or "none")
                    )
                if not path and len(fields) != 1:
                    if fields:
                        raise McapInputError(
                            f"topic {topic} ({kind}) holds {len(fields)} sensor_msgs/msg/Imu"
                            f" fields ({', '.join(fields)}); choose one with --topic"
                            f" {topic}:{fields[0]}"
                        )
                    raise McapInputError(
                        f"topic {topic} has type {kind} ({channel.message_encoding}), which is"
                        " not sensor_msgs/msg/Imu and holds no Imu field (CDR)"
                    )
                if topic in self.imu_fields:
                    raise UsageError(f"topic {topic} is selected twice")
                self.imu_topics.append(topic)
                self.imu_fields[topic] = path or fields[0]
                self._topic_channel[topic] = channel.id
            if not self.imu_topics:
                raise UsageError("no topic selected")
        self.imu_types = {t: schema_name(by_topic[t]) for t in self.imu_topics}

    def _resolve_time_source(self) -> None:
        """``auto``: header stamps, unless the first Imu topic has none or they are all 0."""
        requested = self.time_source
        if requested == "log_time":
            return
        topic = self.imu_topics[0]
        fields = self._prefetched_fields(self._topic_channel[topic], topic)
        if not fields:
            self.time_source = "header"
            return
        has_stamp = all(f.has_stamp for f in fields)
        zero = has_stamp and all(not bool(np.any(f.t_ns)) for f in fields)
        if has_stamp and not zero:
            self.time_source = "header"
            return
        why = "has no header.stamp" if not has_stamp else "has header stamps that are all zero"
        if requested == "header":
            raise McapInputError(
                f"{topic} ({self.imu_types[topic]}) {why}; use --stamps log (MCAP log time)"
            )
        self.time_source = "log_time"
        self.warnings.append(f"{topic} ({self.imu_types[topic]}) {why}: using the log time")

    def _prefetch_setup(self, topics: Sequence[str] | None) -> None:
        """Read ahead until the IMU set and the rate are known.

        Without a summary (stdin, a truncated file) channels are only known as their records
        are met, so batches are read until every Imu channel met so far (or every requested
        topic) has at least ``_SETUP_MESSAGES`` messages, within ``_SETUP_BATCHES`` batches
        and ``_SETUP_BYTES`` of buffered data. An Imu channel first met later is reported
        (:meth:`_check_new_channels`), never silently dropped.
        """
        counts: dict[int, int] = {}
        buffered = 0
        wanted = {spec.partition(":")[0] for spec in topics} if topics is not None else None
        while not self._exhausted:
            if len(self._prefetched) >= _SETUP_BATCHES or buffered >= _SETUP_BYTES:
                break
            imu_ids = [
                c.id
                for c in list(self.source.channels.values())
                if (c.topic in wanted if wanted is not None else self._holds_one_imu(c))
            ]
            seen_topics = {self.source.channels[i].topic for i in imu_ids}
            ready = bool(imu_ids) and (wanted is None or wanted <= seen_topics)
            if ready and all(counts.get(i, 0) >= _SETUP_MESSAGES for i in imu_ids):
                break
            try:
                batch = next(self._batches)
            except StopIteration:
                self._exhausted = True
                break
            self._prefetched.append(batch)
            buffered += int(batch.data.nbytes)
            ids, n = np.unique(batch.channel_id, return_counts=True)
            for i, c in zip(ids.tolist(), n.tolist()):
                counts[i] = counts.get(i, 0) + c

    def _holds_one_imu(self, channel: ChannelInfo) -> bool:
        """The channel is read as an IMU by default (an Imu, or one Imu field); cached."""
        known = self._imu_like.get(channel.id)
        if known is None or known[0] is not channel:
            known = (channel, len(imu_fields_of(channel)) == 1)
            self._imu_like[channel.id] = known
        return known[1]

    def _check_new_channels(self) -> None:
        """Warn about Imu channels first met after the IMU set was fixed (not read)."""
        channels = self.source.channels
        if len(channels) == self._known_channels or self._topics_given:
            return
        self._known_channels = len(channels)
        selected = {self.source.channels[cid].topic for cid in self._imu_channel}
        for channel in list(channels.values()):
            if (
                self._holds_one_imu(channel)
                and channel.topic not in selected
                and channel.topic not in self._late_topics
            ):
                self._late_topics.add(channel.topic)
                self.warnings.append(
                    f"Imu topic {channel.topic} first appears after the IMU set was fixed from"
                    f" the first {_SETUP_MESSAGES} messages of each topic; it is not read"
                    " (select topics with --topic)"
                )

    def _array_config(self) -> ArrayConfig:
        m = len(self.imu_topics)
        meta = self.source.metadata.get(ARRAY_METADATA)
        if meta is not None and "json" in meta:
            try:
                array = ArrayConfig.from_json(meta["json"])
            except ArrayConfigError as err:
                self.warnings.append(
                    f"{err}; ignored: the array is inferred from the topics (co-aligned IMUs,"
                    " measured rate)"
                )
            else:
                if array.n_imus == m:
                    return array
                self.warnings.append(
                    f"imufdi.array metadata describes {array.n_imus} IMUs but {m} topics are"
                    " read; using an inferred co-aligned array"
                )
        rate = self._measured_rate()
        sensors = ["gyro", "accel"] + (["mag"] if self.mag_topics else [])
        return ArrayConfig.co_aligned(m, rate, sensors=sensors)

    def _prefetched_fields(self, cid: int, topic: str) -> list[ImuFields]:
        """Gyro and accel fields of channel ``cid`` (the Imu topic ``topic``) in each
        read-ahead batch holding some of its messages, decoded once for the time source
        and the rate (malformed messages are left out here, reported when the data are
        read)."""
        cached = self._setup_fields
        if cached is not None and cached[0] == cid:
            return cached[1]
        channel = self.source.channels[cid]
        fields = [
            _decode(
                sub, channel, ("gyro", "accel"), self.imu_fields[topic], np.ones(len(sub), bool)
            )
            for sub in (b.select(b.channel_id == cid) for b in self._prefetched)
            if len(sub)
        ]
        self._setup_fields = (cid, fields)
        return fields

    def _measured_rate(self) -> float:
        first = self.imu_topics[0]
        cid = next(i for i, k in self._imu_channel.items() if k == 0)
        stamps = [
            fields.t_ns if self.time_source == "header" else fields.log_time
            for fields in self._prefetched_fields(cid, first)
        ]
        t = np.sort(np.concatenate(stamps)) if stamps else np.zeros(0, np.int64)
        steps = np.diff(t)
        steps = steps[steps > 0]
        if steps.size == 0:
            self.warnings.append(f"cannot measure the sample rate of {first}; assuming 100 Hz")
            return 100.0
        rate = NS_PER_S / float(np.median(steps))
        return float(f"{rate:.6g}") if math.isfinite(rate) and rate > 0 else 100.0

    # --- reading ------------------------------------------------------------------------

    def _raw_batches(self) -> Iterator[MessageBatch]:
        while self._prefetched:
            yield self._prefetched.popleft()
        if not self._exhausted:
            yield from self._batches
            self._exhausted = True

    def _decode_groups(self) -> list[tuple[np.ndarray, ChannelInfo, tuple[str, ...], str]]:
        """Channels read together: CDR channels sharing a schema (and Imu field) are decoded
        in one pass (their layout is the same); JSON channels one by one."""
        groups: dict[Any, list[int]] = {}
        field_of = {self._topic_channel[t]: f for t, f in self.imu_fields.items()}
        for cid in list(self._imu_channel) + list(self._mag_channel):
            channel = self.source.channels[cid]
            kind = "imu" if cid in self._imu_channel else "mag"
            path = field_of.get(cid, "") if kind == "imu" else ""
            if channel.message_encoding == "cdr" and channel.schema is not None:
                key: Any = (kind, channel.schema.name, channel.schema.data, path)
            else:
                key = (kind, cid, path)
            groups.setdefault(key, []).append(cid)
        out: list[tuple[np.ndarray, ChannelInfo, tuple[str, ...], str]] = []
        for key, ids in groups.items():
            kinds: tuple[str, ...] = ("gyro", "accel") if key[0] == "imu" else ("mag",)
            out.append((np.array(ids, np.int64), self.source.channels[ids[0]], kinds, key[-1]))
        return out

    def _feed(self, batch: MessageBatch) -> None:
        self._check_new_channels()
        if len(batch) == 0:
            return
        if self._groups is None:
            self._groups = self._decode_groups()
            m = len(self.imu_topics)
            self._stream_of = np.full(65536, -1, np.int64)
            for cid, k in self._imu_channel.items():
                self._stream_of[cid] = k
            for cid, k in self._mag_channel.items():
                self._stream_of[cid] = m + k
            self._group_of = np.full(65536, -1, np.int64)
            for key, (ids, _, _, _) in enumerate(self._groups):
                self._group_of[ids] = key
        stream_of_message = self._stream_of[batch.channel_id]
        group_of_message = self._group_of[batch.channel_id]
        for key, (_, channel, kinds, path) in enumerate(self._groups):
            mask = group_of_message == key
            n_selected = int(np.count_nonzero(mask))
            if not n_selected:
                continue
            whole = n_selected == len(batch)
            selected = batch if whole else batch.select(mask)
            streams = stream_of_message if whole else stream_of_message[mask]
            fixed = self._fixed.get(key)
            if fixed is None and channel.message_encoding == "cdr":
                fixed = FixedLayoutDecoder(channel, kinds, path, len(self._aligner.names))
                self._fixed[key] = fixed
            quick = None if fixed is None else fixed.decode(selected, streams)
            if quick is not None:
                if len(self._groups) == 1 and self.source.payload_fields is None:
                    # the read-ahead thread (if any) reads these fields from now on
                    self.source.payload_fields = fixed.payload_fields()  # type: ignore[union-attr]
                stamps, joint = quick
                if self.time_source == "header" and stamps is not None:
                    self._aligner.add(streams, stamps, joint)
                else:
                    self._aligner.add(streams, selected.log_time.astype(np.int64), joint)
                continue
            valid = np.ones(len(selected), bool)
            fields = _decode(selected, channel, kinds, path, valid, contiguous=False)
            if not bool(valid.all()):
                # one problem per topic (the group's channels share a schema, not a topic)
                bad = np.bincount(streams[~valid], minlength=len(self._aligner.names))
                streams = streams[valid]
                for stream in np.flatnonzero(bad).tolist():
                    self.source._problem(
                        f"{int(bad[stream])} malformed {schema_name(channel)} message(s) on"
                        f" {self._aligner.names[stream]} skipped (fields past the message end"
                        " or not decodable)"
                    )
            t = fields.t_ns if self.time_source == "header" else fields.log_time
            if kinds == ("mag",):
                values = fields.mag
            else:
                values = np.concatenate([fields.gyro, fields.accel], axis=1)  # type: ignore[list-item]
            self._aligner.add(streams, t, values)  # type: ignore[arg-type]

    def _block(
        self, t_ns: np.ndarray, values: list[np.ndarray], joint: np.ndarray | None = None
    ) -> ImuBlock:
        """The block of aligned samples: stamps (n,) and per-stream values (n, 6 or 3);
        ``joint`` (n, S, 6), when given, holds the same values (``values[s]`` is
        ``joint[:, s, :width]``) and is copied one component at a time (numpy copies
        (n, m) planes much faster than stacking m (n, 3) pieces)."""
        m = len(self.imu_topics)
        n = t_ns.shape[0]

        def planes(streams: slice, first: int) -> np.ndarray:
            """joint[:, streams, first:first + 3] copied to a new (n, q, 3) array, one
            component at a time: as 1-D strided copies when the streams are all of
            joint's (no magnetometers), since numpy copies a (n, q) plane of a 3-D array
            several times slower than the same values as one flat strided run."""
            assert joint is not None
            part = joint[:, streams]
            out = np.empty((n, part.shape[1], 3))
            if part.shape[1] == joint.shape[1] and joint.flags.c_contiguous:
                flat_in = joint.reshape(-1, joint.shape[2])
                flat_out = out.reshape(-1, 3)
                for axis in range(3):
                    flat_out[:, axis] = flat_in[:, first + axis]
            else:
                for axis in range(3):
                    out[:, :, axis] = part[:, :, first + axis]
            return out

        def stacked(columns: slice) -> np.ndarray:  # (n, m, 3), one copy
            if not m:
                return np.zeros((n, 0, 3))
            if joint is not None:
                return planes(slice(0, m), columns.start)
            return np.stack([v[:, columns] for v in values[:m]], axis=1)

        mag = None
        if self.mag_topics and self.array.has("mag"):
            if joint is not None:
                mag = planes(slice(m, None), 0)
            else:
                mag = np.stack(values[m:], axis=1)
        present = self._aligner.last_present
        return ImuBlock(
            t_ns=t_ns,
            gyro=stacked(slice(0, 3)) if self.array.has("gyro") else None,
            accel=stacked(slice(3, 6)) if self.array.has("accel") else None,
            mag=mag,
            missing=None if present is None or present.shape[0] != n else ~present[:, :m],
        )

    def stream(self) -> Iterator[tuple[MessageBatch, ImuBlock]]:
        """Each raw batch (all channels, for pass-through copying) with the aligned samples
        completed by it (possibly none); a final (empty batch, rest) pair at the end."""
        for batch in self._raw_batches():
            self._feed(batch)
            # Resolve in large groups: per-call numpy overhead is paid per block, not per chunk.
            if self._aligner.min_pending() >= self.block_size:
                t_ns, values = self._aligner.resolve(final=False)
                yield batch, self._block(t_ns, values, self._aligner.last_joint)
            else:
                yield batch, self._block(*self._aligner.empty())
        t_ns, values = self._aligner.resolve(final=True)
        self.warnings.extend(self._aligner.missing_report(self._period_ns, produced=self._partial))
        if t_ns.shape[0]:
            yield MessageBatch.empty(), self._block(t_ns, values, self._aligner.last_joint)

    def blocks(self) -> Iterator[ImuBlock]:
        """Aligned array samples in blocks of ``block_size`` (the last may be shorter)."""
        yield from recut((block for _, block in self.stream()), self.block_size)

    def close(self) -> None:
        self.source.close()

    def __enter__(self) -> ImuArrayReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


#: array samples x IMUs in a default block: 4096 samples of 16 IMUs
BLOCK_VALUES = 4096 * 16


def block_samples(n_imus: int) -> int:
    """The default samples per block for ``n_imus`` IMUs: 4096 up to 16 IMUs, then
    ``BLOCK_VALUES / n_imus`` (at least 256), so that a block holds about as many values
    whatever the array's size and a run's memory does not grow with the IMU count beyond
    the per-IMU state."""
    return int(min(4096, max(256, BLOCK_VALUES // max(n_imus, 1))))


def recut(blocks: Iterable[ImuBlock], block_size: int) -> Iterator[ImuBlock]:
    """The samples of ``blocks`` in blocks of exactly ``block_size`` (the last may be
    shorter), as :func:`imufdi_cli.log.rechunk` cuts them, copying only the samples of a
    block that straddles two input blocks (the others are views of the input blocks;
    ``rechunk`` copies every sample once more). Memory stays bounded by the input blocks
    and ``block_size``."""
    rest: ImuBlock | None = None
    for block in blocks:
        n = len(block)
        if n == 0:
            continue
        start = 0
        if rest is not None:
            need = block_size - len(rest)
            if n < need:
                rest = ImuBlock.concatenate([rest, block])
                continue
            yield ImuBlock.concatenate([rest, block.slice(0, need)])
            rest, start = None, need
        while n - start >= block_size:
            yield block.slice(start, start + block_size)
            start += block_size
        if start < n:
            rest = block.slice(start, n)
    if rest is not None:
        yield rest


def read_array(source: str | Path | IO[bytes], **kw: Any) -> tuple[ArrayConfig, ImuBlock]:
    """Read a whole log into memory: (array config, all aligned samples). Only the samples
    every IMU has, unless ``partial=True`` (then also those with some IMUs missing, their
    values NaN and flagged in the block's ``missing``, as ``detect`` reads them)."""
    kw.setdefault("partial", False)
    with ImuArrayReader(source, **kw) as reader:
        blocks = [b for _, b in reader.stream() if len(b)]
        if not blocks:
            return reader.array, reader._block(
                np.zeros(0, np.int64), [np.zeros((0, w)) for w in reader._aligner.widths]
            )
        return reader.array, ImuBlock.concatenate(blocks)
