"""The bulk MCAP writer.

:class:`McapWriter` builds Message records for many messages at once with numpy (one
structured header array, one payload copy), so writing cost does not involve per-message
Python work. Fixed-size records built by the caller (:meth:`McapWriter.add_records`) go
into chunks without further copies; records a :class:`RecordSource` can build
(:meth:`McapWriter.add_record_source`, used by the IMU writer) are built straight into the
chunk buffer on a worker thread. Each chunk is assembled, checksummed, compressed and
given its MessageIndex records on worker threads (numpy copies, zstandard, lz4 and the
CRC-32 release the GIL) while the caller goes on, and written in order, so the output is
the same bytes as a serial write.
"""

from __future__ import annotations

import io
import os
import struct
import sys
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np

from imufdi_cli.errors import McapInputError, OutputError, UsageError
from imufdi_cli.mcapio.compression import compress, crc32
from imufdi_cli.mcapio.records import (
    COMPRESSIONS,
    MAGIC,
    MESSAGE_HEADER_SIZE,
    OP_CHANNEL,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE_INDEX,
    OP_METADATA,
    OP_METADATA_INDEX,
    OP_SCHEMA,
    OP_STATISTICS,
    OP_SUMMARY_OFFSET,
    ChannelInfo,
    MessageBatch,
    RawChunk,
    SchemaInfo,
    _bytes32,
    _record,
    _string,
    _string_map,
    build_message_records,
    channel_record,
    schema_record,
)


@dataclass
class _ChunkIndexEntry:
    start_time: int
    end_time: int
    chunk_offset: int
    chunk_length: int
    message_index_offsets: dict[int, int]
    message_index_length: int
    compression: str
    compressed_size: int
    uncompressed_size: int


@dataclass
class _RecordPart:
    """Ready Message records of one size: row i of ``records`` (N, R) is message i."""

    records: np.ndarray
    channel_id: np.ndarray
    log_time: np.ndarray

    def __len__(self) -> int:
        return int(self.records.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.records.shape[0] * self.records.shape[1])


class RecordSource(Protocol):
    """Fixed-size Message records that are built when their chunk is assembled (on a
    worker thread): :meth:`McapWriter.add_record_source`.

    ``fill`` must only read data the source owns (copies taken when it was made), since
    it runs after the call that queued it has returned.

    A source may also offer ``template_rows`` and ``fill_changing``
    (:class:`TemplatedSource`):
    then the worker thread keeps a buffer whose rows already hold the template's constant
    bytes, and only the bytes that change are written per chunk.
    """

    @property
    def record_size(self) -> int:
        """Bytes per record (header included)."""
        ...

    def __len__(self) -> int:
        """Number of records."""
        ...

    def fill(self, out: np.ndarray, start: int, stop: int) -> None:
        """Write records ``start..stop-1`` into ``out``, shape (stop - start, record_size),
        uint8, C-contiguous."""
        ...


class TemplatedSource(RecordSource, Protocol):
    """A :class:`RecordSource` whose record ``k`` is row ``k % P`` of ``template_rows``
    (P, R) except in bytes that ``fill_changing`` writes.

    ``template_rows`` must be the same array object (never modified) for every source
    sharing those constant bytes: a worker thread's primed buffer is reused while it is.
    """

    @property
    def template_rows(self) -> np.ndarray:
        """(P, record_size) uint8: the constant bytes of records with ``k % P == row``."""
        ...

    def fill_changing(self, out: np.ndarray, start: int, stop: int) -> None:
        """As ``fill``, into rows ``out`` whose row ``i`` already holds template row
        ``(start + i) % P``: every byte not written keeps its template value."""
        ...


@dataclass
class _SourcePart:
    """Records ``start..stop-1`` of a :class:`RecordSource`, built on a worker thread."""

    source: RecordSource
    start: int
    stop: int
    channel_id: np.ndarray
    log_time: np.ndarray

    def __len__(self) -> int:
        return self.stop - self.start

    @property
    def nbytes(self) -> int:
        return (self.stop - self.start) * int(self.source.record_size)


@dataclass
class _SerialPart:
    """Message records serialised by the caller's thread (variable sizes)."""

    records: np.ndarray  # (B,) uint8
    offsets: np.ndarray  # (N,) int64, start of each record in ``records``
    channel_id: np.ndarray
    log_time: np.ndarray

    @property
    def nbytes(self) -> int:
        return int(self.records.shape[0])


_ChunkPart = _RecordPart | _SourcePart | _SerialPart


@dataclass
class _BuiltChunk:
    """What a worker thread made of a chunk's parts."""

    payload: bytes  # compressed records
    crc: int  # CRC-32 of the uncompressed records
    uncompressed_size: int


@dataclass
class _ChunkKeys:
    """What the caller's thread makes of a chunk's parts while a worker builds it."""

    start_time: int
    end_time: int
    #: the chunk's MessageIndex records, one per channel, and each one's offset in them
    index_records: bytes
    index_offsets: dict[int, int]
    channel_counts: dict[int, int]
    message_count: int


@dataclass
class _ChunkJob:
    """A chunk being built on a worker thread, and its index made by the caller."""

    future: Future[_BuiltChunk]
    keys: _ChunkKeys


#: The fixed part of a MessageIndex record: opcode, record length, channel id, bytes of
#: entries (each entry: log time u64, record offset u64).
_MESSAGE_INDEX_HEAD = np.dtype(
    {
        "names": ["opcode", "record_length", "channel_id", "entries_length"],
        "formats": ["u1", "<u8", "<u2", "<u4"],
        "offsets": [0, 1, 9, 11],
        "itemsize": 15,
    }
)


def message_index_records(
    channel_ids: np.ndarray, log_time: np.ndarray, record_offsets: np.ndarray
) -> tuple[bytes, dict[int, int], dict[int, int]]:
    """The MessageIndex records of one chunk: one per channel, channels in increasing
    order, entries (log time, record offset) sorted by log time (ties in chunk order).

    Parameters
    ----------
    channel_ids : ndarray, shape (N,), unsigned
    log_time : ndarray, shape (N,), int64, ns
    record_offsets : ndarray, shape (N,), int64
        Offset of each message's record in the chunk's uncompressed records.

    Returns
    -------
    records : bytes
    offsets : dict
        Channel id -> offset of its MessageIndex record in ``records``.
    counts : dict
        Channel id -> number of its messages in the chunk.
    """
    channel_ids = np.asarray(channel_ids)
    log_time = np.asarray(log_time, np.int64)
    n = int(channel_ids.shape[0])
    if n < 2 or bool(np.all(log_time[1:] >= log_time[:-1])):
        # already in time order: a stable sort by channel is the (channel, time) sort
        order = np.argsort(channel_ids, kind="stable")
    else:
        order = np.lexsort((log_time, channel_ids))
    per_channel = np.bincount(channel_ids.astype(np.intp))
    present = np.flatnonzero(per_channel)
    sizes = per_channel[present].astype(np.int64)
    firsts = np.zeros(present.shape[0], np.int64)
    np.cumsum(sizes[:-1], out=firsts[1:])
    head = np.empty(present.shape[0], _MESSAGE_INDEX_HEAD)
    head["opcode"] = OP_MESSAGE_INDEX
    head["record_length"] = 2 + 4 + 16 * sizes
    head["channel_id"] = present
    head["entries_length"] = 16 * sizes
    entries = np.empty((n, 2), "<u8")
    entries[:, 0] = log_time[order]
    entries[:, 1] = record_offsets[order]
    heads = head.view(np.uint8).data
    bodies = entries.view(np.uint8).reshape(-1).data
    pieces = []
    for g, (first, size) in enumerate(zip(firsts.tolist(), sizes.tolist())):
        pieces.append(heads[15 * g : 15 * g + 15])
        pieces.append(bodies[16 * first : 16 * (first + size)])
    starts = 15 * np.arange(present.shape[0], dtype=np.int64) + 16 * firsts
    ids = present.tolist()
    return (
        b"".join(pieces),
        dict(zip(ids, starts.tolist())),
        dict(zip(ids, sizes.tolist())),
    )


#: Per worker thread: a reusable buffer for chunk records (no fresh pages to fault in
#: and zero for every chunk), and one whose rows hold a template's constant bytes.
_THREAD = threading.local()


def _thread_buffer(size: int) -> np.ndarray:
    """(size,) uint8 scratch of the calling thread, reused from chunk to chunk (its
    contents are garbage; nothing built from it may keep a reference)."""
    buffer: np.ndarray | None = getattr(_THREAD, "buffer", None)
    if buffer is None or buffer.shape[0] < size:
        buffer = np.empty(size, np.uint8)
        _THREAD.buffer = buffer
    return buffer[:size]


def _primed_rows(parts: list[_ChunkPart]) -> np.ndarray | None:
    """Rows (N, R) of the calling thread's primed buffer for a chunk made only of parts of
    :class:`TemplatedSource` objects sharing one template, positioned so that row ``i``
    holds template row ``(first record + i) % P``; None for any other chunk."""
    if not all(isinstance(part, _SourcePart) for part in parts):
        return None
    template = getattr(parts[0].source, "template_rows", None)  # type: ignore[union-attr]
    if template is None:
        return None
    period, size = template.shape
    phase = parts[0].start % period  # type: ignore[union-attr]
    at = phase
    for part in parts:
        assert isinstance(part, _SourcePart)
        if (
            getattr(part.source, "template_rows", None) is not template
            or part.start % period != at % period
        ):
            return None
        at += len(part)
    count = at - phase
    state = getattr(_THREAD, "primed", None)
    if state is None or state[0] is not template or state[1].shape[0] < at:
        samples = -(-(count + period) // period)  # room for any phase
        buffer = np.empty((samples, period, size), np.uint8)
        buffer[...] = template
        state = (template, buffer.reshape(samples * period, size))
        _THREAD.primed = state
    rows: np.ndarray = state[1][phase:at]
    return rows


def _build_chunk(parts: list[_ChunkPart], compression: str) -> _BuiltChunk:
    """Assemble a chunk's records from its parts, checksum and compress them (worker
    thread). The MessageIndex records are made by the caller meanwhile (:func:`_chunk_keys`):
    this thread needs the GIL only between its few large numpy copies and C calls.

    Every chunk carries the CRC-32 of its uncompressed records, whatever the compression,
    so that readers which check chunk CRCs (the ``mcap`` package, ``mcap doctor``, our own
    reader) verify our files end to end; zstd and lz4 frames also carry their own content
    checksum. The CRC-32 (zlib-ng's, else zlib's) releases the GIL on this worker thread.
    """
    total = sum(part.nbytes for part in parts)
    only = parts[0]
    in_place = False
    primed = _primed_rows(parts)
    if primed is not None:
        raw = primed.reshape(-1)  # the template's constant bytes are already there
    elif len(parts) == 1 and isinstance(only, (_RecordPart, _SerialPart)):
        if only.records.flags.c_contiguous:
            raw = only.records.reshape(-1)  # one part of ready records: compressed as they are
            in_place = True
    if primed is None and not in_place:
        raw = _thread_buffer(total)
    shift = 0
    for part in parts:
        size = part.nbytes
        if isinstance(part, _SourcePart):
            rows = raw[shift : shift + size].reshape(len(part), -1)
            if primed is not None:
                part.source.fill_changing(rows, part.start, part.stop)  # type: ignore[attr-defined]
            else:
                part.source.fill(rows, part.start, part.stop)
        elif not in_place:
            raw[shift : shift + size] = part.records.reshape(-1)
        shift += size
    view = raw.data
    return _BuiltChunk(
        payload=compress(view, compression), crc=crc32(view), uncompressed_size=total
    )


def _chunk_keys(parts: list[_ChunkPart]) -> _ChunkKeys:
    """Time range, MessageIndex records and counts of a chunk's parts (caller's thread)."""
    offset_parts = []
    shift = 0
    for part in parts:
        if isinstance(part, _SerialPart):
            offset_parts.append(part.offsets + shift)
        else:
            record_size = part.nbytes // len(part)
            offset_parts.append(np.arange(len(part), dtype=np.int64) * record_size + shift)
        shift += part.nbytes
    record_offsets = offset_parts[0] if len(offset_parts) == 1 else np.concatenate(offset_parts)
    channel_ids = np.concatenate([p.channel_id for p in parts])
    log_time = np.concatenate([p.log_time for p in parts])
    index_records, index_offsets, channel_counts = message_index_records(
        channel_ids, log_time, record_offsets
    )
    return _ChunkKeys(
        start_time=int(log_time.min()),
        end_time=int(log_time.max()),
        index_records=index_records,
        index_offsets=index_offsets,
        channel_counts=channel_counts,
        message_count=int(channel_ids.shape[0]),
    )


#: Worker threads building chunks, and how many chunks may wait to be written.
COMPRESS_THREADS = 2
MAX_CHUNKS_IN_FLIGHT = 4


class McapWriter:
    """Bulk MCAP writer (a context manager).

    Parameters
    ----------
    output : str, Path or binary stream
        ``"-"`` writes straight to stdout. A path is written to a temporary file in the same
        directory and renamed into place by :meth:`close`; if the ``with`` block raises,
        the temporary file is removed and nothing is left behind.
    compression : {"zstd", "lz4", "none"}
    chunk_size : int
        Uncompressed bytes of message records per chunk (approximate).
    profile : str
        The Header profile (``"ros2"`` for ROS 2 CDR messages).
    """

    def __init__(
        self,
        output: str | os.PathLike[str] | IO[bytes],
        *,
        compression: str = "zstd",
        chunk_size: int = 1 << 20,
        profile: str = "ros2",
    ) -> None:
        if compression not in COMPRESSIONS:
            raise UsageError(
                f"unknown MCAP compression {compression!r}; valid: {', '.join(COMPRESSIONS)}"
            )
        if chunk_size < 1:
            raise UsageError(f"chunk_size must be >= 1 byte, got {chunk_size}")
        self.compression = "" if compression == "none" else compression
        self.chunk_size = int(chunk_size)
        self._final_path: Path | None = None
        self._temp_path: Path | None = None
        self._owns_stream = False
        if isinstance(output, (str, os.PathLike)) and os.fspath(output) == "-":
            self._stream: IO[bytes] = sys.stdout.buffer
        elif isinstance(output, (str, os.PathLike)):
            from imufdi_cli.fileio import create_temp, is_special

            final = Path(output)
            self._final_path = final
            if is_special(final):  # /dev/null, a FIFO: written in place, never replaced
                self._stream = open(final, "wb", buffering=1 << 20)
            else:
                fd, temp = create_temp(final)  # the one output path (imufdi_cli.fileio)
                self._temp_path = temp
                self._stream = io.BufferedWriter(io.FileIO(fd, "wb"), buffer_size=1 << 20)
            self._owns_stream = True
        else:
            self._stream = output
        self._position = 0
        self._data_crc = 0
        self._closed = False
        self.schemas: dict[int, SchemaInfo] = {}
        self.channels: dict[int, ChannelInfo] = {}
        self._channel_schema: dict[int, int] = {}
        self._metadata_index: list[tuple[int, int, str]] = []
        self._chunk_index: list[_ChunkIndexEntry] = []
        self._pending: list[MessageBatch | _RecordPart | _SourcePart] = []
        self._pending_bytes = 0
        self._in_flight: deque[_ChunkJob] = deque()
        self._executor: ThreadPoolExecutor | None = None
        self._message_count = 0
        self._channel_counts: dict[int, int] = {}
        self._start_time: int | None = None
        self._end_time: int | None = None
        self._write(MAGIC)
        self._write(_record(OP_HEADER, _string(profile) + _string("imufdi")))

    # --- low level -------------------------------------------------------------------

    def _write(self, raw: bytes | memoryview) -> None:
        """Write after every chunk still being compressed (records stay in call order)."""
        if self._in_flight:
            self._drain(0)
        self._write_now(raw)

    def _write_now(self, raw: bytes | memoryview) -> None:
        # The data section CRC is optional (0 = not computed, as the mcap package writes).
        try:
            self._stream.write(raw)
        except OSError as err:
            self._write_failed(err)
        self._position += len(raw)

    def _write_failed(self, err: OSError) -> None:
        """A file output that cannot be written (ENOSPC, EFBIG, EIO) is an OutputError
        naming it; stream errors (a closed pipe) pass through unchanged."""
        if not self._owns_stream:
            raise err
        raise OutputError(
            f"cannot write {self._final_path}: {err.strerror or err}; nothing was written"
        ) from err

    def _shutdown_executor(self) -> None:
        self._in_flight.clear()
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # --- schemas, channels, metadata --------------------------------------------------

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Write a Schema record (or reuse an identical one); returns its id (>= 1)."""
        for schema in self.schemas.values():
            if (schema.name, schema.encoding, schema.data) == (name, encoding, bytes(data)):
                return schema.id
        schema_id = max(self.schemas, default=0) + 1
        self._add_schema(SchemaInfo(schema_id, name, encoding, bytes(data)))
        return schema_id

    def _add_schema(self, schema: SchemaInfo) -> None:
        self.schemas[schema.id] = schema
        self._write(schema_record(schema))

    def register_channel(
        self,
        topic: str,
        message_encoding: str,
        schema_id: int,
        metadata: dict[str, str] | None = None,
    ) -> int:
        """Write a Channel record; returns its id."""
        if schema_id != 0 and schema_id not in self.schemas:
            raise UsageError(f"schema id {schema_id} is not registered")
        channel_id = max(self.channels, default=-1) + 1
        self._add_channel(channel_id, topic, message_encoding, schema_id, metadata or {})
        return channel_id

    def _add_channel(
        self, channel_id: int, topic: str, encoding: str, schema_id: int, meta: dict[str, str]
    ) -> None:
        self.channels[channel_id] = ChannelInfo(
            channel_id, topic, encoding, dict(meta), self.schemas.get(schema_id)
        )
        self._channel_schema[channel_id] = schema_id
        self._write(channel_record(channel_id, schema_id, topic, encoding, meta))

    def copy_channels(self, channels: dict[int, ChannelInfo]) -> None:
        """Register channels (and their schemas) with the SAME ids, for raw pass-through."""
        for channel_id in sorted(channels):
            info = channels[channel_id]
            if channel_id in self.channels:
                raise UsageError(f"channel id {channel_id} ({info.topic}) is already registered")
            schema_id = 0
            if info.schema is not None:
                schema_id = info.schema.id
                existing = self.schemas.get(schema_id)
                if existing is None:
                    self._add_schema(info.schema)
                elif existing != info.schema:
                    raise UsageError(f"schema id {schema_id} is already used by another schema")
            self._add_channel(
                channel_id, info.topic, info.message_encoding, schema_id, dict(info.metadata)
            )

    def register_json_channel(self, topic: str, schema_name: str) -> int:
        """A JSON channel (``message_encoding="json"``) with a permissive jsonschema."""
        schema_id = self.register_schema(schema_name, "jsonschema", b'{"type": "object"}')
        return self.register_channel(topic, "json", schema_id)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Write a Metadata record (values must be strings)."""
        for key, value in data.items():
            if not isinstance(key, str) or not isinstance(value, str):
                raise UsageError(f"metadata {name!r}: keys and values must be strings")
        record = _record(OP_METADATA, _string(name) + _string_map(data))
        # Chunks still compressing on worker threads are written first: the index entry
        # must hold the position the record actually lands at.
        self._drain(0)
        self._metadata_index.append((self._position, len(record), name))
        self._write_now(record)

    # --- messages ----------------------------------------------------------------------

    def add_batch(self, batch: MessageBatch) -> None:
        """Queue messages (any channels, file order kept); chunks are written as they fill."""
        n = len(batch)
        if n == 0:
            return
        self._check_registered(batch.channel_id)
        self._check_log_time(batch.channel_id, batch.log_time)
        sizes = batch.length.astype(np.int64) + MESSAGE_HEADER_SIZE
        cumulative = np.cumsum(sizes)
        start = 0
        consumed = 0
        while start < n:
            room = self.chunk_size - self._pending_bytes
            # number of messages (at least one) that fit in the current chunk
            stop = int(np.searchsorted(cumulative, consumed + room, side="right"))
            stop = max(stop, start + 1)
            stop = min(stop, n)
            part = batch.select(slice(start, stop))
            self._pending.append(part)
            part_bytes = int(cumulative[stop - 1] - consumed)
            self._pending_bytes += part_bytes
            consumed = int(cumulative[stop - 1])
            start = stop
            if self._pending_bytes >= self.chunk_size:
                self._flush_chunk()

    def add_records(
        self, records: np.ndarray, channel_id: np.ndarray, log_time: np.ndarray
    ) -> None:
        """Queue ready Message records of one size, without copying them.

        Parameters
        ----------
        records : ndarray, shape (N, R), uint8, C-contiguous
            Row i is a whole Message record (opcode, length, channel id, sequence, log
            time, publish time, payload), as :func:`build_message_records` makes. The writer
            keeps a reference until the chunk is written: do not modify it afterwards.
        channel_id : ndarray, shape (N,)
            Channel of each record (must be registered; must match the records).
        log_time : ndarray, shape (N,), int64
            Log time of each record, ns (must match the records).
        """
        n = int(records.shape[0])
        if n == 0:
            return
        if records.ndim != 2 or records.dtype != np.uint8 or not records.flags.c_contiguous:
            raise UsageError("records must be a C-contiguous (N, R) uint8 array")
        channel_id, log_time = self._record_keys(n, channel_id, log_time)
        size = int(records.shape[1])
        self._queue_fixed(
            n,
            size,
            lambda start, stop: _RecordPart(
                records[start:stop], channel_id[start:stop], log_time[start:stop]
            ),
        )

    def add_record_source(
        self, source: RecordSource, channel_id: np.ndarray, log_time: np.ndarray
    ) -> None:
        """Queue records that ``source`` builds when their chunk is assembled, on a worker
        thread, straight into the chunk buffer (no copy, and the caller's thread free).

        Parameters
        ----------
        source : RecordSource
            N records of ``source.record_size`` bytes.
        channel_id : ndarray, shape (N,)
            Channel of each record (must be registered; must match the records).
        log_time : ndarray, shape (N,), int64
            Log time of each record, ns (must match the records).

        The output is the same bytes as :meth:`add_records` with the built records.
        """
        n = len(source)
        if n == 0:
            return
        size = int(source.record_size)
        channel_id, log_time = self._record_keys(n, channel_id, log_time)
        self._queue_fixed(
            n,
            size,
            lambda start, stop: _SourcePart(
                source, start, stop, channel_id[start:stop], log_time[start:stop]
            ),
        )

    def _record_keys(
        self, n: int, channel_id: np.ndarray, log_time: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``channel_id`` (N,) uint16 and ``log_time`` (N,) int64 of N queued records,
        checked: one per record, registered channels, log times as :meth:`_check_log_time`."""
        channel_id = np.asarray(channel_id, np.uint16)
        log_time = np.asarray(log_time, np.int64)
        if channel_id.shape != (n,) or log_time.shape != (n,):
            raise UsageError(f"need {n} channel ids and log times, one per record")
        self._check_registered(channel_id)
        self._check_log_time(channel_id, log_time)
        return channel_id, log_time

    def _queue_fixed(
        self, n: int, size: int, make_part: Callable[[int, int], _RecordPart | _SourcePart]
    ) -> None:
        """Queue ``n`` records of ``size`` bytes as parts that fill the current chunk."""
        start = 0
        while start < n:
            room = self.chunk_size - self._pending_bytes
            # enough records to fill the current chunk (at least one)
            stop = min(n, start + max(1, -(-room // size)))
            self._pending.append(make_part(start, stop))
            self._pending_bytes += (stop - start) * size
            start = stop
            if self._pending_bytes >= self.chunk_size:
                self._flush_chunk()

    def _check_registered(self, channel_id: np.ndarray) -> None:
        """Refuse messages of channels not registered (a lookup table, no sorting)."""
        channel_id = np.asarray(channel_id)
        if channel_id.size == 0:
            return
        known = np.zeros(max(self.channels, default=-1) + 1, dtype=bool)
        known[list(self.channels)] = True
        if int(channel_id.max()) < known.shape[0] and bool(known[channel_id].all()):
            return
        unknown = np.setdiff1d(np.unique(channel_id), list(self.channels))
        raise UsageError(f"messages for unregistered channel id {int(unknown[0])}")

    def _check_log_time(self, channel_id: np.ndarray, log_time: np.ndarray) -> None:
        """Refuse log times the file format and the int64 time base cannot hold.

        Times are int64 ns here; a u64 time >= 2^63 read from a file wraps to a negative
        value. Such a message is bad input data (exit 3), named by topic and value.
        """
        log_time = np.asarray(log_time)
        if log_time.size == 0 or int(log_time.min()) >= 0:
            return
        first = int(np.flatnonzero(log_time < 0)[0])
        value = int(log_time[first])
        channel = self.channels.get(int(channel_id[first]))
        topic = channel.topic if channel is not None else f"channel {int(channel_id[first])}"
        raise McapInputError(
            f"{topic}: message log_time {value + (1 << 64) if value < 0 else value} ns is"
            f" outside the supported range 0..{(1 << 63) - 1} ns"
        )

    def add_message(
        self,
        channel_id: int,
        log_time: int,
        data: bytes,
        publish_time: int | None = None,
        sequence: int = 0,
    ) -> None:
        """Queue one message."""
        self.add_batch(
            MessageBatch.from_payloads(
                channel_id,
                np.array([log_time], np.int64),
                [bytes(data)],
                publish_time=np.array([log_time if publish_time is None else publish_time]),
                sequence=np.array([sequence]),
            )
        )

    def add_json(self, channel_id: int, log_time: int, obj: Any) -> None:
        """Queue one JSON message (compact UTF-8)."""
        import json

        self.add_message(channel_id, log_time, json.dumps(obj, separators=(",", ":")).encode())

    def _flush_chunk(self) -> None:
        """Hand the queued messages to a worker thread that builds and compresses the chunk."""
        if not self._pending:
            return
        parts: list[_ChunkPart] = []
        for part in self._pending:
            if isinstance(part, MessageBatch):
                # serialised now: a batch's arrays may be reused by the caller afterwards
                records, offsets = build_message_records(part)
                parts.append(_SerialPart(records, offsets, part.channel_id, part.log_time))
            else:
                parts.append(part)
        self._pending = []
        self._pending_bytes = 0
        if self._executor is None:
            self._executor = ThreadPoolExecutor(
                max_workers=COMPRESS_THREADS, thread_name_prefix="mcap-chunk"
            )
        future = self._executor.submit(_build_chunk, parts, self.compression)
        # the index is made here while a worker builds the chunk
        self._in_flight.append(_ChunkJob(future, _chunk_keys(parts)))
        self._drain(MAX_CHUNKS_IN_FLIGHT)

    def _drain(self, keep: int) -> None:
        """Write built chunks, oldest first, until at most ``keep`` are in flight."""
        while len(self._in_flight) > keep:
            self._write_chunk(self._in_flight.popleft())

    def _write_chunk(self, job: _ChunkJob) -> None:
        """Write a built chunk, its MessageIndex records, and note its ChunkIndex."""
        built = job.future.result()
        keys = job.keys
        content = (
            struct.pack("<QQQI", keys.start_time, keys.end_time, built.uncompressed_size, built.crc)
            + _string(self.compression)
            + struct.pack("<Q", len(built.payload))
        )
        chunk_offset = self._position
        self._write_now(struct.pack("<BQ", OP_CHUNK, len(content) + len(built.payload)) + content)
        self._write_now(built.payload)
        chunk_length = self._position - chunk_offset
        index_start = self._position
        self._write_now(keys.index_records)
        self._chunk_index.append(
            _ChunkIndexEntry(
                keys.start_time,
                keys.end_time,
                chunk_offset,
                chunk_length,
                {cid: index_start + at for cid, at in keys.index_offsets.items()},
                len(keys.index_records),
                self.compression,
                len(built.payload),
                built.uncompressed_size,
            )
        )
        self._count(keys.channel_counts, keys.message_count, keys.start_time, keys.end_time)

    def _write_message_indexes(
        self, channel_ids: np.ndarray, log_time: np.ndarray, record_offsets: np.ndarray
    ) -> tuple[dict[int, int], int]:
        """One MessageIndex record per channel of a chunk just written, entries sorted by
        log time; returns the position of each channel's record and their total length."""
        records, offsets, _ = message_index_records(channel_ids, log_time, record_offsets)
        index_start = self._position
        self._write_now(records)
        return {cid: index_start + at for cid, at in offsets.items()}, len(records)

    def add_raw_chunk(self, chunk: RawChunk, batch: MessageBatch, records_at: int = 0) -> None:
        """Write an input Chunk record verbatim (no recompression) with its MessageIndex
        records; ``batch`` is exactly its messages (as read from it: payload offsets into
        ``batch.data``, where the chunk's records start at byte ``records_at``; channel ids
        already registered here with the same ids).

        Messages queued before of the same channels are written first, so every channel
        stays in time order in the file.
        """
        n = len(batch)
        if n == 0:
            return
        ids = np.unique(batch.channel_id).tolist()  # (a few ids: set operations in Python)
        unknown = [cid for cid in ids if cid not in self.channels]
        if unknown:
            raise UsageError(f"messages for unregistered channel id {int(unknown[0])}")
        self._check_log_time(batch.channel_id, batch.log_time)
        if self._pending:
            queued = {cid for p in self._pending for cid in np.unique(p.channel_id).tolist()}
            if not queued.isdisjoint(ids):
                self._flush_chunk()
        log_time = np.asarray(batch.log_time, np.int64)
        record_offsets = np.asarray(batch.offset, np.int64) - MESSAGE_HEADER_SIZE - records_at
        self._drain(0)  # chunks still compressing are written first, in call order
        chunk_offset = self._position
        self._write_now(struct.pack("<BQ", OP_CHUNK, len(chunk.content)))
        self._write_now(chunk.content)
        chunk_length = self._position - chunk_offset
        index_offsets, index_length = self._write_message_indexes(
            batch.channel_id, log_time, record_offsets
        )
        self._chunk_index.append(
            _ChunkIndexEntry(
                chunk.start_time,
                chunk.end_time,
                chunk_offset,
                chunk_length,
                index_offsets,
                index_length,
                chunk.compression,
                chunk.compressed_size,
                chunk.uncompressed_size,
            )
        )
        self._count_messages(batch.channel_id, int(log_time.min()), int(log_time.max()))

    def _count_messages(self, channel_ids: np.ndarray, start_time: int, end_time: int) -> None:
        """Statistics: messages per channel and the time range."""
        counts = np.bincount(channel_ids.astype(np.int64))
        present = np.flatnonzero(counts)
        self._count(
            dict(zip(present.tolist(), counts[present].tolist())),
            int(channel_ids.shape[0]),
            start_time,
            end_time,
        )

    def _count(
        self, channel_counts: dict[int, int], message_count: int, start_time: int, end_time: int
    ) -> None:
        for cid, count in channel_counts.items():
            self._channel_counts[cid] = self._channel_counts.get(cid, 0) + count
        self._message_count += message_count
        self._start_time = (
            start_time if self._start_time is None else min(self._start_time, start_time)
        )
        self._end_time = end_time if self._end_time is None else max(self._end_time, end_time)

    # --- finishing ---------------------------------------------------------------------

    def close(self) -> None:
        """Write the remaining chunk, DataEnd, summary and footer; rename into place."""
        if self._closed:
            return
        try:
            self._finish()
            # The last buffered bytes reach the file here: a flush/close error (ENOSPC,
            # EFBIG) must remove the temporary file like any other failure.
            if self._owns_stream:
                try:
                    self._stream.close()
                except OSError as err:
                    self._write_failed(err)
            else:
                self._stream.flush()
            if self._temp_path is not None and self._final_path is not None:
                os.replace(self._temp_path, self._final_path)
        except BaseException:
            self.abort()
            raise
        finally:
            self._shutdown_executor()
        self._closed = True

    def abort(self) -> None:
        """Stop writing and remove the temporary file (nothing is left behind)."""
        if self._closed:
            return
        self._closed = True
        self._shutdown_executor()
        if self._owns_stream:
            try:
                self._stream.close()
            except OSError:
                pass
        if self._temp_path is not None:
            from imufdi_cli.fileio import discard_temp

            discard_temp(self._temp_path)

    def _finish(self) -> None:
        self._flush_chunk()
        self._drain(0)
        self._write(_record(OP_DATA_END, struct.pack("<I", self._data_crc)))
        summary_start = self._position
        groups: list[tuple[int, int, int]] = []
        parts: list[bytes] = []
        offset = summary_start

        def group(opcode: int, records: list[bytes]) -> None:
            nonlocal offset
            if not records:
                return
            body = b"".join(records)
            groups.append((opcode, offset, len(body)))
            parts.append(body)
            offset += len(body)

        group(OP_SCHEMA, [schema_record(s) for _, s in sorted(self.schemas.items())])
        group(
            OP_CHANNEL,
            [
                channel_record(
                    c.id, self._channel_schema[c.id], c.topic, c.message_encoding, c.metadata
                )
                for _, c in sorted(self.channels.items())
            ],
        )
        counts = b"".join(
            struct.pack("<HQ", cid, n) for cid, n in sorted(self._channel_counts.items())
        )
        statistics = struct.pack(
            "<QHIIIIQQ",
            self._message_count,
            len(self.schemas),
            len(self.channels),
            0,
            len(self._metadata_index),
            len(self._chunk_index),
            self._start_time or 0,
            self._end_time or 0,
        ) + _bytes32(counts)
        group(OP_STATISTICS, [_record(OP_STATISTICS, statistics)])
        chunk_records = []
        for entry in self._chunk_index:
            offsets = b"".join(
                struct.pack("<HQ", cid, off)
                for cid, off in sorted(entry.message_index_offsets.items())
            )
            chunk_records.append(
                _record(
                    OP_CHUNK_INDEX,
                    struct.pack(
                        "<QQQQ",
                        entry.start_time,
                        entry.end_time,
                        entry.chunk_offset,
                        entry.chunk_length,
                    )
                    + _bytes32(offsets)
                    + struct.pack("<Q", entry.message_index_length)
                    + _string(entry.compression)
                    + struct.pack("<QQ", entry.compressed_size, entry.uncompressed_size),
                )
            )
        group(OP_CHUNK_INDEX, chunk_records)
        group(
            OP_METADATA_INDEX,
            [
                _record(OP_METADATA_INDEX, struct.pack("<QQ", off, length) + _string(name))
                for off, length, name in self._metadata_index
            ],
        )
        summary_offset_start = offset
        parts.append(
            b"".join(
                _record(OP_SUMMARY_OFFSET, struct.pack("<BQQ", op, start, length))
                for op, start, length in groups
            )
        )
        summary = b"".join(parts)
        footer_head = struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, summary_offset_start)
        summary_crc = crc32(footer_head, crc32(summary))
        self._write(summary)
        self._write(footer_head + struct.pack("<I", summary_crc))
        self._write(MAGIC)
