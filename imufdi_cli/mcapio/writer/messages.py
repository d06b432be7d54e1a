"""Messages into chunks: :class:`_ChunkQueue` checks and queues messages (batches, ready
records, record sources) until a chunk fills, hands each chunk to a worker thread
(:mod:`~imufdi_cli.mcapio.writer.chunks`), and writes the built chunks with their
MessageIndex records in call order; input chunks can be copied verbatim
(:meth:`_ChunkQueue.add_raw_chunk`). The counts kept here make the Statistics record.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np

from imufdi_cli.errors import McapInputError, UsageError
from imufdi_cli.mcapio.records import (
    MESSAGE_HEADER_SIZE,
    OP_CHUNK,
    MessageBatch,
    RawChunk,
    _string,
    build_message_records,
)
from imufdi_cli.mcapio.writer import chunks
from imufdi_cli.mcapio.writer.chunks import _build_chunk, _chunk_keys
from imufdi_cli.mcapio.writer.index import (
    _chunk_index_record,
    _ChunkIndexEntry,
    message_index_records,
)
from imufdi_cli.mcapio.writer.output import _Output
from imufdi_cli.mcapio.writer.parts import (
    RecordSource,
    _ChunkJob,
    _ChunkKeys,
    _ChunkPart,
    _RecordPart,
    _SerialPart,
    _SourcePart,
)


class _ChunkQueue(_Output):
    """Queued messages, the chunks being built on worker threads, and the counts of the
    messages written."""

    def _write(self, raw: bytes | memoryview) -> None:
        """Write after every chunk still being compressed (records stay in call order)."""
        if self._in_flight:
            self._drain(0)
        self._write_now(raw)

    def _shutdown_executor(self) -> None:
        self._in_flight.clear()
        if self._executor is not None:
            try:
                self._executor.shutdown(wait=True, cancel_futures=True)
            finally:
                self._executor = None
                chunks.fast_switching_off()

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
            self._pending_ids.append(None)
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
            self._pending_ids.append(None)
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
        self._pending_ids = []
        self._pending_bytes = 0
        if self._executor is None:
            self._executor = ThreadPoolExecutor(
                max_workers=chunks.COMPRESS_THREADS, thread_name_prefix="mcap-chunk"
            )
            chunks.fast_switching_on()
        future = self._executor.submit(_build_chunk, parts, self.compression)
        # the index is made here while a worker builds the chunk
        self._in_flight.append(_ChunkJob(future, _chunk_keys(parts)))
        self._drain(chunks.MAX_CHUNKS_IN_FLIGHT)

    def _drain(self, keep: int) -> None:
        """Write built chunks, oldest first, until at most ``keep`` are in flight."""
        while len(self._in_flight) > keep:
            self._write_chunk(self._in_flight.popleft())

    def _write_chunk(self, job: _ChunkJob) -> None:
        """Write a chunk (built on a worker thread, or an input chunk copied verbatim), its
        MessageIndex records, and note its ChunkIndex."""
        keys = job.keys
        chunk_offset = self._position
        raw = job.raw
        if raw is None:
            assert job.future is not None
            built = job.future.result()
            compression = self.compression
            compressed_size, uncompressed_size = len(built.payload), built.uncompressed_size
            start_time, end_time = keys.start_time, keys.end_time
            content = (
                struct.pack("<QQQI", start_time, end_time, uncompressed_size, built.crc)
                + _string(compression)
                + struct.pack("<Q", compressed_size)
            )
            self._write_now(struct.pack("<BQ", OP_CHUNK, len(content) + compressed_size) + content)
            self._write_now(built.payload)
        else:
            compression = raw.compression
            compressed_size, uncompressed_size = raw.compressed_size, raw.uncompressed_size
            start_time, end_time = raw.start_time, raw.end_time  # as the input's record says
            self._write_now(struct.pack("<BQ", OP_CHUNK, len(raw.content)))
            self._write_now(raw.content)
        chunk_length = self._position - chunk_offset
        index_start = self._position
        self._write_now(keys.index_records)
        self._chunk_index.append(  # the record (a few hundred bytes) kept, not the entry
            _chunk_index_record(
                _ChunkIndexEntry(
                    start_time,
                    end_time,
                    chunk_offset,
                    chunk_length,
                    {cid: index_start + at for cid, at in keys.index_offsets.items()},
                    len(keys.index_records),
                    compression,
                    compressed_size,
                    uncompressed_size,
                )
            )
        )
        self._count(keys.channel_counts, keys.message_count, keys.start_time, keys.end_time)

    def add_raw_chunk(self, chunk: RawChunk, batch: MessageBatch, records_at: int = 0) -> None:
        """Write an input Chunk record verbatim (no recompression) with its MessageIndex
        records; ``batch`` is exactly its messages (as read from it: payload offsets into
        ``batch.data``, where the chunk's records start at byte ``records_at``; channel ids
        already registered here with the same ids).

        Messages queued before of the same channels are written first, so every channel
        stays in time order in the file. The chunk joins the chunks being built on worker
        threads, in call order: it is written after them without waiting for them here.
        """
        n = len(batch)
        if n == 0:
            return
        ids = np.flatnonzero(
            np.bincount(batch.channel_id.astype(np.intp))
        ).tolist()  # (a few ids: set operations in Python)
        unknown = [cid for cid in ids if cid not in self.channels]
        if unknown:
            raise UsageError(f"messages for unregistered channel id {int(unknown[0])}")
        self._check_log_time(batch.channel_id, batch.log_time)
        if self._pending and not self._queued_channels().isdisjoint(ids):
            self._flush_chunk()
        log_time = np.asarray(batch.log_time, np.int64)
        record_offsets = np.asarray(batch.offset, np.int64) - MESSAGE_HEADER_SIZE - records_at
        records, offsets, channel_counts = message_index_records(
            batch.channel_id, log_time, record_offsets
        )
        keys = _ChunkKeys(
            start_time=int(log_time.min()),
            end_time=int(log_time.max()),
            index_records=records,
            index_offsets=offsets,
            channel_counts=channel_counts,
            message_count=n,
        )
        if not isinstance(chunk.content, bytes):  # held until written: our own copy
            chunk = replace(chunk, content=bytes(chunk.content))
        self._in_flight.append(_ChunkJob(None, keys, raw=chunk))
        self._drain(chunks.MAX_CHUNKS_IN_FLIGHT)

    def _queued_channels(self) -> set[int]:
        """The channel ids of the messages queued for the next chunk (each part's ids
        found once, when first asked for)."""
        queued: set[int] = set()
        for k, part in enumerate(self._pending):
            ids = self._pending_ids[k]
            if ids is None:
                channel_id = part.channel_id
                low, high = int(channel_id.min()), int(channel_id.max())
                if low == high:
                    ids = {low}
                else:
                    ids = set(np.flatnonzero(np.bincount(channel_id.astype(np.intp))).tolist())
                self._pending_ids[k] = ids
            queued |= ids
        return queued

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
