"""Where the writer's bytes go: stdout, a caller's stream, or a path written to a temporary
file in the same directory and renamed into place only when the file is complete.

:class:`_Output` is the first of the classes :class:`~imufdi_cli.mcapio.writer.McapWriter`
is assembled from (output, then messages and chunks, then the file's records and summary):
the attributes they share are annotated here once.
"""

from __future__ import annotations

import io
import os
import sys
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import IO

from imufdi_cli.errors import OutputError
from imufdi_cli.mcapio.records import ChannelInfo, MessageBatch, SchemaInfo
from imufdi_cli.mcapio.writer.parts import _ChunkJob, _RecordPart, _SourcePart

#: A file output's bytes go through a thread of their own (:class:`_WriteBehind`) from
#: the first write of at least this size on (a chunk): small files never start one.
WRITE_BEHIND_FROM = 64 << 10
#: Pieces handed to one write of the write-behind thread (one ``writev`` system call).
_PIECES_PER_WRITE = 64


class _WriteBehind:
    """Writes a file output's bytes on a thread of their own, in call order, so that the
    kernel's copy into the page cache (and a stall there) does not hold up the caller's
    thread; the write releases the GIL, so the copy runs beside the caller's work.

    At most ``limit`` bytes wait (memory stays flat). The thread is woken only once
    ``wake`` bytes wait (or at :meth:`finish`), and then writes everything queued: one
    wake-up per megabyte or so instead of one per call, so the caller's thread is not
    asked for the GIL after every chunk, index and header piece it queues (each such
    hand-off costs the caller up to the switch interval; docs/performance.md, "Writing"). The first error of a write is kept: nothing after it is written,
    and the next :meth:`write` and :meth:`finish` raise it.

    Parameters
    ----------
    write : callable
        ``write(pieces)``: writes a list of bytes objects, in order (the output's
        :meth:`_Output._stream_write_many`).
    limit : int
        Bytes queued at most before :meth:`write` waits.
    wake : int
        Bytes queued before the thread is woken (below ``limit``).
    """

    def __init__(
        self,
        write: Callable[[list[bytes]], object],
        limit: int = 4 << 20,
        wake: int = 1 << 20,
    ) -> None:
        self._sink = write
        self._limit = limit
        self._wake = min(wake, limit)
        self._queue: deque[bytes] = deque()
        self._queued = 0
        self._error: BaseException | None = None
        self._closing = False
        self._cancelled = False
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="mcap-write", daemon=True)
        self._thread.start()

    def write(self, data: bytes) -> None:
        """Queue ``data`` (a bytes object: it must not change afterwards)."""
        with self._cond:
            while self._queued >= self._limit and self._error is None:
                self._cond.wait()
            if self._error is not None:
                raise self._error
            self._queue.append(data)
            self._queued += len(data)
            if self._queued >= self._wake:
                self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closing and (self._queued < self._wake or not self._queue):
                    self._cond.wait()
                if not self._queue:
                    return
                batch = list(self._queue)  # everything queued, written in order below
                self._queue.clear()
            # a few pieces at a time (each write releases the GIL), so that room is made
            # for a waiting caller before the whole batch is written
            for first in range(0, len(batch), _PIECES_PER_WRITE):
                pieces = batch[first : first + _PIECES_PER_WRITE]
                try:
                    self._sink(pieces)
                except BaseException as err:  # kept for the caller's thread
                    with self._cond:
                        self._error = err
                        self._queue.clear()
                        self._queued = 0
                        self._cond.notify_all()
                    return
                with self._cond:
                    if self._cancelled:
                        return  # the rest of the batch is dropped too
                    self._queued -= sum(len(piece) for piece in pieces)
                    if self._queued < self._limit:
                        self._cond.notify_all()  # a caller waiting for room (or finish)

    def finish(self) -> None:
        """Wait until everything queued is written; raise the first write error."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join()
        if self._error is not None:
            raise self._error

    def cancel(self) -> None:
        """Drop what is queued, wait for the write under way, ignore errors."""
        with self._cond:
            self._queue.clear()
            self._queued = 0
            self._closing = True
            self._cancelled = True
            self._cond.notify_all()
        self._thread.join()


class _Output:
    """The output stream of a writer and its temporary file."""

    # the output (this class)
    _stream: IO[bytes]
    #: the file this writer opened (a temporary file) and its descriptor, else None
    _file: IO[bytes] | None
    _fd: int | None
    _behind: _WriteBehind | None
    _final_path: Path | None
    _temp_path: Path | None
    _owns_stream: bool
    _position: int
    # the file's records (McapWriter)
    compression: str
    chunk_size: int
    _data_crc: int
    _closed: bool
    schemas: dict[int, SchemaInfo]
    channels: dict[int, ChannelInfo]
    _channel_schema: dict[int, int]
    _metadata_index: list[tuple[int, int, str]]
    # messages and chunks (_ChunkQueue)
    #: the ChunkIndex record of every chunk written, in file order
    _chunk_index: list[bytes]
    _pending: list[MessageBatch | _RecordPart | _SourcePart]
    #: each queued part's channel ids, found when first needed (add_raw_chunk)
    _pending_ids: list[set[int] | None]
    _pending_bytes: int
    _in_flight: deque[_ChunkJob]
    _executor: ThreadPoolExecutor | None
    _message_count: int
    _channel_counts: dict[int, int]
    _start_time: int | None
    _end_time: int | None

    def _open_output(self, output: str | os.PathLike[str] | IO[bytes]) -> None:
        """Open ``output``: ``"-"`` is stdout, a path a temporary file beside it (a special
        file such as /dev/null or a FIFO is written in place), anything else a stream."""
        self._final_path = None
        self._temp_path = None
        self._owns_stream = False
        self._behind = None
        self._file = None
        self._fd = None
        if isinstance(output, (str, os.PathLike)) and os.fspath(output) == "-":
            self._stream = sys.stdout.buffer
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
                self._file, self._fd = self._stream, fd  # (the write-behind thread's writev)
            self._owns_stream = True
        else:
            self._stream = output
        self._position = 0

    def _write_now(self, raw: bytes | memoryview) -> None:
        """Write ``raw`` at the end of the output (a file's through :class:`_WriteBehind`
        from its first chunk on)."""
        # The data section CRC is optional (0 = not computed, as the mcap package writes).
        size = len(raw)
        try:
            if self._behind is None and self._temp_path is not None and size >= WRITE_BEHIND_FROM:
                self._behind = _WriteBehind(self._stream_write_many)
            if self._behind is not None:
                self._behind.write(raw if isinstance(raw, bytes) else bytes(raw))
            else:
                self._stream.write(raw)
        except OSError as err:
            self._write_failed(err)
        self._position += size

    def _stream_write_many(self, pieces: list[bytes]) -> None:
        """Write ``pieces`` in order (the write-behind thread). To the file this writer
        opened: its buffer flushed, then one ``os.writev`` of the pieces (no copy into the
        buffer, which would hold the GIL for each byte copied, and one system call);
        to any other stream (``self._stream`` replaced), one ``write`` per piece."""
        stream = self._stream
        fd = self._fd
        if fd is None or stream is not self._file:
            for piece in pieces:
                stream.write(piece)
            return
        stream.flush()  # (empty once the first pieces have gone this way)
        views = [memoryview(piece) for piece in pieces if len(piece)]
        while views:
            written = os.writev(fd, views)
            # a short write: drop what went out, write the rest
            while views and written >= len(views[0]):
                written -= len(views[0])
                views.pop(0)
            if views and written:
                views[0] = views[0][written:]

    def _write_failed(self, err: OSError) -> None:
        """A file output that cannot be written (ENOSPC, EFBIG, EIO) is an OutputError
        naming it; stream errors (a closed pipe) pass through unchanged."""
        if not self._owns_stream:
            raise err
        raise OutputError(
            f"cannot write {self._final_path}: {err.strerror or err}; nothing was written"
        ) from err

    def _commit_output(self) -> None:
        """Close (or flush) the stream and rename the temporary file into place."""
        # The last buffered bytes reach the file here: a flush/close error (ENOSPC,
        # EFBIG) must remove the temporary file like any other failure.
        behind = self._behind
        if behind is not None:
            # kept until its thread has ended: an interrupt while waiting for it leaves it
            # to _discard_output to cancel
            try:
                behind.finish()
            except OSError as err:
                self._behind = None
                self._write_failed(err)
            self._behind = None
        if self._owns_stream:
            try:
                self._stream.close()
            except OSError as err:
                self._write_failed(err)
        else:
            self._stream.flush()
        if self._temp_path is not None and self._final_path is not None:
            os.replace(self._temp_path, self._final_path)

    def _discard_output(self) -> None:
        """Close the stream and remove the temporary file (nothing is left behind)."""
        if self._behind is not None:
            behind, self._behind = self._behind, None
            behind.cancel()
        if self._owns_stream:
            try:
                self._stream.close()
            except OSError:
                pass
        if self._temp_path is not None:
            from imufdi_cli.fileio import discard_temp

            discard_temp(self._temp_path)
