"""Chunk building on worker threads: each chunk's records are assembled (into a
per-thread buffer, or one already primed with a template's constant bytes), checksummed
and compressed off the caller's thread, while the caller makes the chunk's MessageIndex
records (:func:`_chunk_keys`)."""

from __future__ import annotations

import sys
import threading

import numpy as np

from imufdi_cli.mcapio.compression import compress, crc32
from imufdi_cli.mcapio.writer.index import message_index_records
from imufdi_cli.mcapio.writer.parts import (
    _BuiltChunk,
    _ChunkKeys,
    _ChunkPart,
    _RecordPart,
    _SerialPart,
    _SourcePart,
)

#: Worker threads building chunks, and how many chunks may wait to be written.
COMPRESS_THREADS = 2
MAX_CHUNKS_IN_FLIGHT = 4
#: The interpreter's thread switch interval (s) while any writer's worker threads exist
#: (:func:`fast_switching_on`); None leaves it alone.
SWITCH_INTERVAL: float | None = 2e-4

_SWITCH_LOCK = threading.Lock()
#: Writers holding the short switch interval, and the interval they found (restored when
#: the last one lets go).
_switch_users = 0
_switch_saved: float | None = None


def fast_switching_on() -> None:
    """Shorten the interpreter's switch interval while a writer's worker threads run.

    A worker thread takes the GIL back after each C call that released it (the chunk's
    numpy copies, the CRC-32, the compression: about six per chunk). When the caller's
    thread is busy in Python (parsing a capture, running a detector) the worker waits for
    the switch interval before the caller is made to let go: 5 ms by default, longer than
    the 5 ms of CPU a 4 MiB chunk costs, so the workers run at a fraction of a core
    (docs/performance.md, "Writing": GIL hand-offs). At 0.2 ms they wait little; the caller's
    thread is asked to let go only when a worker is waiting. The interval is process-wide:
    it is set when the first writer starts its workers and restored (unless someone else
    changed it meanwhile) when the last one shuts them down. Pair every call with
    :func:`fast_switching_off`.
    """
    global _switch_users, _switch_saved
    with _SWITCH_LOCK:
        if _switch_users == 0:
            _switch_saved = None
            current = sys.getswitchinterval()
            if SWITCH_INTERVAL is not None and current > SWITCH_INTERVAL:
                _switch_saved = current
                sys.setswitchinterval(SWITCH_INTERVAL)
        _switch_users += 1


def fast_switching_off() -> None:
    """Let go of :func:`fast_switching_on` (the last writer restores the interval)."""
    global _switch_users, _switch_saved
    with _SWITCH_LOCK:
        _switch_users = max(0, _switch_users - 1)
        if _switch_users == 0 and _switch_saved is not None:
            if SWITCH_INTERVAL is None or abs(sys.getswitchinterval() - SWITCH_INTERVAL) < 1e-6:
                sys.setswitchinterval(_switch_saved)
            _switch_saved = None


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
