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

from imufdi_cli.mcapio.compression import _declared_size, _unpack_chunk, _Unpacked
from imufdi_cli.mcapio.records import OP_CHUNK

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

#: A chunk being unpacked on the worker thread, and the process id that asked for it (a
#: forked child never gets the answer: it unpacks the chunk itself)
_Ahead = tuple["Future[_Unpacked]", int]
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
                        job = source._worker().submit(
                            _unpack_chunk,
                            item[2],
                            source.limits.max_chunk_bytes,
                            source.validate_crcs,
                            None,
                            not source.strict,
                        )
                        future = (job, os.getpid())
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
