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
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import IO

from imufdi_cli.errors import OutputError
from imufdi_cli.mcapio.records import ChannelInfo, MessageBatch, SchemaInfo
from imufdi_cli.mcapio.writer.index import _ChunkIndexEntry
from imufdi_cli.mcapio.writer.parts import _ChunkJob, _RecordPart, _SourcePart


class _Output:
    """The output stream of a writer and its temporary file."""

    # the output (this class)
    _stream: IO[bytes]
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
    _chunk_index: list[_ChunkIndexEntry]
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
            self._owns_stream = True
        else:
            self._stream = output
        self._position = 0

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

    def _commit_output(self) -> None:
        """Close (or flush) the stream and rename the temporary file into place."""
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

    def _discard_output(self) -> None:
        """Close the stream and remove the temporary file (nothing is left behind)."""
        if self._owns_stream:
            try:
                self._stream.close()
            except OSError:
                pass
        if self._temp_path is not None:
            from imufdi_cli.fileio import discard_temp

            discard_temp(self._temp_path)
