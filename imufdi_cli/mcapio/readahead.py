"""Read-ahead of large chunks on a worker thread, for :class:`McapSource` opened with
``read_ahead`` (imported only then: start-up time).

Chunks of at least ``_THREAD_CHUNK`` record bytes are decompressed and CRC-checked on one
worker thread (zstd, lz4 and the CRC-32 release the GIL) while the caller decodes the chunks
before them; results, warnings and errors come in file order as without read-ahead.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from imufdi_cli.mcapio.compression import _declared_size, _unpack_chunk
from imufdi_cli.mcapio.records import OP_CHUNK
from imufdi_cli.mcapio.scan import (
    _BATCH_BYTES,
    _BATCH_CAPACITY,
    Digest,
    PayloadFields,
    chunk_digest,
)

if TYPE_CHECKING:
    from concurrent.futures import Future

    from imufdi_cli.mcapio.source import McapSource

#: Chunks declaring at least this many record bytes are decompressed (and CRC-checked) on
#: a worker thread ahead of their use (zstd, lz4 and the CRC-32 release the GIL), while the
#: caller decodes the chunks before them; smaller chunks are decompressed in line (a thread
#: hand-off costs more than they do).
_THREAD_CHUNK = 64 << 10
#: Read-ahead of that worker: at most this many chunks, and this many declared record
#: bytes, in flight (memory stays bounded by a few chunks).
_PREFETCH_CHUNKS = 4
_PREFETCH_BYTES = 64 << 20
_PREFETCH_RECORDS = 1024

#: A chunk being unpacked on the worker thread, the process id that asked for it (a
#: forked child never gets the answer: it unpacks the chunk itself), and where its records
#: are decompressed: (batch buffer, offset) or None (then they come as bytes of their own)
_Ahead = tuple["Future[_Read]", int, "tuple[np.ndarray, int] | None"]
#: What the worker hands back: the chunk's records or None, why not, and the message heads
#: of its records when they are whole Message records of the expected length
_Read = tuple["bytes | memoryview | None", str, "Digest | None"]
#: A data-section record: (opcode, content length, content or None if skipped, byte offset)
_Record = tuple[int, int, bytes | None, int]


def read_ahead(
    source: McapSource, records: Iterator[_Record]
) -> Iterator[tuple[_Record, _Ahead | None]]:
    """``records`` (the source's :meth:`~McapSource._records`), with large chunks
    decompressed and CRC-checked on ``source``'s worker thread up to ``_PREFETCH_CHUNKS``
    chunks ahead: each record comes with the future of its chunk's records and the id of
    the process that asked for it (or None). Problems met while reading ahead are held and
    reported (or raised, with ``strict``) when the record they precede is handed out, so
    warnings, errors and batches come in the same order as without read-ahead."""
    queue: deque[tuple[Any, list[tuple[bool, str]], _Ahead | None, int]] = deque()
    in_flight = 0  # chunks on the worker
    in_flight_bytes = 0
    exhausted = False
    places = _Places()
    try:
        while True:
            # read one record when there is none; more only while chunks are being
            # decompressed, to find the next ones (bounded in chunks, bytes, records)
            while not exhausted and (
                not queue
                or (
                    0 < in_flight < _PREFETCH_CHUNKS
                    and in_flight_bytes < _PREFETCH_BYTES
                    and len(queue) < _PREFETCH_RECORDS
                )
            ):
                notes: list[tuple[bool, str]] = []
                source._deferred = notes
                try:
                    item = next(records, None)
                finally:
                    source._deferred = None
                future: _Ahead | None = None
                size = 0
                if item is None:
                    exhausted = True
                elif item[0] == OP_CHUNK and item[2] is not None:
                    size = _declared_size(item[2])
                    if size >= _THREAD_CHUNK and source.read_ahead:
                        place = (
                            places.reserve(size) if size <= source.limits.max_chunk_bytes else None
                        )
                        pattern = source._pattern
                        job = source._worker().submit(
                            _unpack_ahead,
                            item[2],
                            source.limits.max_chunk_bytes,
                            source.validate_crcs,
                            None if place is None else _Slot(*place),
                            not source.strict,
                            -1 if pattern is None else pattern.uniform,
                            source.payload_fields,
                        )
                        future = (job, os.getpid(), place)
                        in_flight += 1
                        in_flight_bytes += size
                queue.append((item, notes, future, size))
            if not queue:
                return
            item, notes, future, size = queue.popleft()
            if future is not None:
                in_flight -= 1
                in_flight_bytes -= size
            for is_problem, message in notes:
                if is_problem:
                    source._problem(message)
                else:
                    source.warnings.append(message)
            if item is None:
                return
            yield item, future
    finally:
        for _, _, future, _ in queue:
            if future is not None:
                future[0].cancel()


class _Places:
    """Where the worker thread decompresses the chunks it reads ahead: one after another
    in batch buffers of the size the caller's batches have (a new one once
    ``_BATCH_BYTES`` are filled, as the caller's batches end), so that the caller can use
    the records where they are (:meth:`_PendingMessages.adopt
    <imufdi_cli.mcapio.scan._PendingMessages.adopt>`) instead of copying them. Regions
    are never handed out twice, and the caller never writes into these buffers."""

    def __init__(self) -> None:
        self.buffer: np.ndarray | None = None
        self.fill = 0

    def reserve(self, size: int) -> tuple[np.ndarray, int]:
        """(buffer, offset) of ``size`` bytes nobody else writes."""
        if (
            self.buffer is None
            or self.fill >= _BATCH_BYTES
            or self.fill + size > self.buffer.shape[0]
        ):
            # pages are touched (faulted in) by the worker thread as it writes them
            self.buffer = np.empty(max(_BATCH_CAPACITY, size), np.uint8)
            self.fill = 0
        place = (self.buffer, self.fill)
        self.fill += size
        return place


class _Slot:
    """The ``slot`` of :func:`~imufdi_cli.mcapio.compression._unpack_chunk` for a reserved
    region: a writable view of exactly the declared size."""

    def __init__(self, buffer: np.ndarray, offset: int) -> None:
        self.buffer = buffer
        self.offset = offset

    def __call__(self, n: int) -> memoryview:
        return memoryview(self.buffer)[self.offset : self.offset + n]  # type: ignore[arg-type]


def _unpack_ahead(
    content: bytes,
    max_chunk_bytes: int,
    validate_crcs: bool,
    slot: _Slot | None,
    trust_frame_checksum: bool,
    length: int,
    fields: PayloadFields | None,
) -> _Read:
    """:func:`~imufdi_cli.mcapio.compression._unpack_chunk` on the worker thread, and when
    the caller's record pattern is one of Message records of one content ``length`` (-1:
    none) and the chunk holds only such records, their message heads
    (:func:`~imufdi_cli.mcapio.scan.uniform_message_heads`: the caller then neither checks
    nor reads them) and the payload ``fields`` the caller asked for."""
    raw, error = _unpack_chunk(content, max_chunk_bytes, validate_crcs, slot, trust_frame_checksum)
    digest: Digest | None = None
    if raw is not None and length >= 0:
        digest = chunk_digest(np.frombuffer(raw, np.uint8), length, fields)
    return raw, error, digest
