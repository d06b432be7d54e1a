"""Streaming MCAP reader: records in file order, batches of whole chunks.

Records inside a decompressed chunk are located in bulk: a few records are walked one by
one, the repeating pattern of record lengths (e.g. 16 IMU channels interleaved) is found,
and the whole run of the pattern is checked with numpy at once. Message headers are then
read with one strided gather. Memory is bounded by one chunk.
"""

from __future__ import annotations

import bisect
import io
import os
import struct
import sys
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.compression import (
    crc32,
    decompress,
    decompress_into,
    frame_checksummed,
)
from imufdi_cli.mcapio.limits import ReaderLimits
from imufdi_cli.mcapio.records import (
    MAGIC,
    MESSAGE_FIXED_CONTENT,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_METADATA,
    OP_METADATA_INDEX,
    OP_SCHEMA,
    ChannelInfo,
    MessageBatch,
    RawChunk,
    SchemaInfo,
    gather_bytes,
)
from imufdi_cli.mcapio.scan import (
    RecordPattern,
    _Cursor,
    _PendingMessages,
    parse_channel,
    parse_metadata,
    parse_schema,
    scan_records,
)

if TYPE_CHECKING:  # the read-ahead pool is imported when first used (start-up time)
    from concurrent.futures import Future, ThreadPoolExecutor

__all__ = ["McapSource", "parse_channel", "parse_metadata", "parse_schema", "scan_records"]

_MESSAGE_FIELDS = np.dtype(
    [("channel_id", "<u2"), ("sequence", "<u4"), ("log_time", "<u8"), ("publish_time", "<u8")]
)
_FOOTER_SIZE = 9 + 20
#: Chunk record fields before the compression name: start/end time, uncompressed size,
#: CRC, and the compression name's length.
_CHUNK_HEAD = struct.Struct("<QQQII")
_RECORD_HEAD = struct.Struct("<BQ")
#: Chunks of at most this many record bytes are walked in Python (numpy costs more there).
_SMALL_CHUNK = 4096
#: Read-ahead of the data section; larger records are read straight from the stream.
_READ_AHEAD = 256 << 10
#: Records of at least this many bytes are read into a buffer of their own (no joins).
_READ_DIRECT = 64 << 10


_OPCODE_NAMES = {
    0x01: "Header",
    0x02: "Footer",
    0x03: "Schema",
    0x04: "Channel",
    0x05: "Message",
    0x06: "Chunk",
    0x07: "MessageIndex",
    0x08: "ChunkIndex",
    0x09: "Attachment",
    0x0A: "AttachmentIndex",
    0x0B: "Statistics",
    0x0C: "Metadata",
    0x0D: "MetadataIndex",
    0x0E: "SummaryOffset",
    0x0F: "DataEnd",
}
#: Records read into memory (the others are skipped without being held).
_HELD = (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_METADATA)
#: Records the data section may hold that the reader neither keeps nor checks (Header,
#: MessageIndex, ChunkIndex, Attachment, AttachmentIndex, Statistics, MetadataIndex,
#: SummaryOffset): skipped without being handed on.
_IGNORED = frozenset((0x01, 0x07, 0x08, 0x09, 0x0A, 0x0B, 0x0D, 0x0E))
#: Records a chunk may hold.
_IN_CHUNK = frozenset((OP_SCHEMA, OP_CHANNEL, OP_MESSAGE))
#: Batches whose raw chunks are remembered for McapSource.raw_chunks (older ones are
#: forgotten and their messages re-encoded); each holds its ~4 MiB buffer until asked for.
_RAW_CHUNKS_KEPT = 8
#: Reads from the stream are done in pieces of at most this many bytes, so a record
#: length that no file could satisfy never becomes one huge allocation.
_READ_PIECE = 16 << 20
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


def _record_name(opcode: int) -> str:
    return _OPCODE_NAMES.get(opcode, f"opcode {opcode:#04x}")


class McapSource:
    """Low-level streaming reader over an MCAP file, path, ``"-"`` (stdin) or binary stream.

    Attributes
    ----------
    channels : dict
        Channel id -> ChannelInfo, filled as records are met (always before a message of
        that channel is yielded; up front from the summary when the source is seekable).
    metadata : dict
        Metadata record name -> string map. For seekable sources all of them are read before
        the first batch.
    warnings : list of str
        Problems met while reading (e.g. a truncated file), when ``strict`` is False. Each is
        one line naming the byte offset and the cause.
    limits : ReaderLimits
        Caps on declared sizes (default: :meth:`ReaderLimits.from_env`).

    Reading never trusts a declared size: record lengths are checked against the rest of
    the file and the record limit before anything is read, chunks against the chunk limit
    before they are decompressed, and decompression stops at the declared size. A corrupt
    or truncated file is read up to the problem (a bad chunk is skipped) with a warning; with
    ``strict`` every such problem raises :class:`McapInputError` instead.

    With ``read_ahead``, chunks of at least 64 KiB of records are decompressed and
    CRC-checked on one worker thread, up to four chunks ahead of the one being decoded
    (zstd, lz4 and the CRC release the GIL); results, warnings and errors come in file
    order as without it. It is off by default: on the shared 2-core build machine it cost
    5-20 % more CPU and gained no wall time (docs/performance.md); it can only help where a
    core is free, and moves at most the decompression (~15 % of reading) off the caller.

    Chunk records are verified when ``validate_crcs`` is true (the default): by the
    chunk's CRC-32, except that a zstd chunk whose frame carries a content checksum over
    exactly the declared records (imufdi's writer adds one) is already verified by zstd
    while it is decompressed, and its CRC-32 is then checked only with ``strict`` (a
    mismatch there means a wrong CRC field over intact records). With zlib-ng (a
    dependency) the CRC-32 costs about 0.07-0.1 ms per MiB of records, 5-8 % of reading;
    with zlib's (the fallback) about 0.4 ms per MiB, as much as the zstd decompression.

    A rosbag2 directory (or its ``metadata.yaml``) gives a
    :class:`~imufdi_cli.mcapio.bagdir.BagDirSource`: its split files read as one log.
    """

    #: Problems met while reading ahead, replayed in file order (see _prefetched); class
    #: defaults so that subclasses with their own __init__ (BagDirSource) have them too.
    _deferred: list[tuple[bool, str]] | None = None
    _pool: ThreadPoolExecutor | None = None
    _pool_pid = -1
    _pattern: RecordPattern | None = None
    _phase = 0

    def __new__(cls, source: Any = None, *args: Any, **kwargs: Any) -> McapSource:
        if (
            cls is McapSource
            and isinstance(source, (str, os.PathLike))
            and source != "-"
            # only these can be a bag directory (bagdir.is_bag_dir): a plain file does
            # not import the module (start-up time)
            and (os.path.isdir(source) or os.path.basename(source) == "metadata.yaml")
        ):
            from imufdi_cli.mcapio.bagdir import BagDirSource, is_bag_dir

            if is_bag_dir(source):
                return super().__new__(BagDirSource)
        return super().__new__(cls)

    def __init__(
        self,
        source: str | os.PathLike[str] | IO[bytes],
        *,
        strict: bool = False,
        validate_crcs: bool | None = True,
        limits: ReaderLimits | None = None,
        keep_raw_chunks: bool = False,
        read_ahead: bool = False,
    ) -> None:
        self.strict = strict
        #: Decompress and CRC-check chunks of >= _THREAD_CHUNK bytes on a worker thread.
        self.read_ahead = read_ahead
        #: Remember the Chunk record of each batch that is exactly one whole chunk, for
        #: :meth:`raw_chunk` (detect copies such chunks without recompressing them).
        self.keep_raw_chunks = keep_raw_chunks
        self._raw_chunks: deque[tuple[MessageBatch, list[ChunkRun]]] = deque(
            maxlen=_RAW_CHUNKS_KEPT
        )
        self._chunk_clean = False
        #: The record pattern of the last chunk scanned in full, and where the records
        #: after the last chunk stand in it (chunks that continue it are checked at once).
        self._pattern = None
        self._phase = 0
        self._deferred = None
        self._pool = None
        self.validate_crcs = validate_crcs is not False  # None (unset) also checks them
        self.limits = limits if limits is not None else ReaderLimits.from_env()
        self.channels: dict[int, ChannelInfo] = {}
        self.schemas: dict[int, SchemaInfo] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.warnings: list[str] = []
        self.summary_channel_counts: dict[int, int] | None = None
        self.summary_message_count: int | None = None
        self.summary_time_range: tuple[int, int] | None = None
        self._owns = False
        self._file_size: int | None = None
        self._known = np.zeros(1 << 16, bool)
        self._known_size = 0
        self._ahead = b""  # read-ahead buffer of the data section, and the position in it
        self._ahead_pos = 0
        #: Chunk offsets from the summary's ChunkIndex records (seekable files): where
        #: reading resumes after a damaged record.
        self._chunk_starts: list[int] = []
        self._pending_channels: dict[int, tuple[int, str, str, dict[str, str]]] = {}
        if isinstance(source, (str, os.PathLike)) and os.fspath(source) == "-":
            self.name = "<stdin>"
            self._stream: IO[bytes] = sys.stdin.buffer
        elif isinstance(source, (str, os.PathLike)):
            self.name = os.fspath(source)
            path = Path(source)
            if path.is_dir():
                raise McapInputError(
                    f"{path} is a directory, not an MCAP file (nor a rosbag2 directory with"
                    " metadata.yaml)"
                )
            try:
                self._stream = open(path, "rb")
            except FileNotFoundError as err:
                raise McapInputError(f"no such file: {path}") from err
            except OSError as err:
                raise McapInputError(f"cannot open {path}: {err.strerror}") from err
            self._owns = True
        else:
            self.name = getattr(source, "name", "<stream>")
            self._stream = source
        try:
            magic = self._read_exact(len(MAGIC))
        except BaseException:
            self.close()
            raise
        if magic != MAGIC:
            self.close()
            raise McapInputError(f"{self.name} is not an MCAP file (bad magic bytes)")
        self._seekable = self._is_seekable()
        self._iterator: Iterator[MessageBatch] | None = None
        self._pushback: list[MessageBatch] = []
        if self._seekable:
            try:
                self._read_summary()
            except BaseException:
                self.close()
                raise
            self._stream.seek(len(MAGIC))

    # --- plumbing ------------------------------------------------------------------------

    def _is_seekable(self) -> bool:
        try:
            return bool(self._stream.seekable())
        except (AttributeError, OSError, ValueError):
            return False

    def _read_exact(self, n: int) -> bytes:
        """Up to ``n`` bytes (fewer only at the end of the stream), read in bounded pieces."""
        if n <= 0:
            return b""
        chunks = []
        remaining = n
        while remaining > 0:
            part = self._stream.read(min(remaining, _READ_PIECE))
            if not part:
                break
            chunks.append(part)
            remaining -= len(part)
        return chunks[0] if len(chunks) == 1 else b"".join(chunks)

    def _skip(self, n: int) -> int:
        """Skip ``n`` bytes; returns how many were skipped (fewer at the end of the stream)."""
        if self._seekable:
            here = self._stream.tell()
            end = here + n if self._file_size is None else min(here + n, self._file_size)
            self._stream.seek(end)
            return end - here
        skipped = 0
        while skipped < n:
            part = self._stream.read(min(n - skipped, _READ_PIECE))
            if not part:
                break
            skipped += len(part)
        return skipped

    def close(self) -> None:
        pool = self._pool
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
        if self._owns:
            self._stream.close()
            self._owns = False

    def __enter__(self) -> McapSource:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _problem(self, message: str) -> None:
        if self._deferred is not None:  # reading ahead: reported when the reader gets there
            self._deferred.append((True, message))
            return
        if self.strict:
            raise McapInputError(f"{self.name}: {message}")
        self.warnings.append(message)

    def _add_schema(self, schema: SchemaInfo) -> None:
        self.schemas[schema.id] = schema
        # A channel may have arrived before its schema (allowed in chunks): resolve it now.
        for channel_id, (schema_id, topic, enc, meta) in list(self._pending_channels.items()):
            if schema_id == schema.id:
                self.channels[channel_id] = ChannelInfo(channel_id, topic, enc, meta, schema)
                del self._pending_channels[channel_id]

    def _add_channel(self, content: bytes) -> None:
        channel_id, schema_id, topic, encoding, meta = parse_channel(content)
        if schema_id != 0 and schema_id not in self.schemas:
            self._pending_channels[channel_id] = (schema_id, topic, encoding, meta)
            return
        self.channels[channel_id] = ChannelInfo(
            channel_id, topic, encoding, meta, self.schemas.get(schema_id)
        )

    def _add_record(self, opcode: int, content: bytes, position: int) -> None:
        """Register a Schema, Channel or Metadata record; a malformed one is a problem."""
        try:
            if opcode == OP_SCHEMA:
                self._add_schema(parse_schema(content))
            elif opcode == OP_CHANNEL:
                self._add_channel(content)
            elif opcode == OP_METADATA:
                name, values = parse_metadata(content)
                self.metadata[name] = values
        except McapInputError as err:
            self._problem(f"{_record_name(opcode)} record at byte {position} skipped: {err}")

    # --- summary (seekable sources) -------------------------------------------------------

    def _read_summary(self) -> None:
        stream = self._stream
        try:
            file_size = stream.seek(0, io.SEEK_END)
        except OSError:
            self._seekable = False
            return
        self._file_size = file_size
        summary_start = -1
        summary_end = file_size - len(MAGIC) - _FOOTER_SIZE
        summary_crc = 0
        if file_size >= len(MAGIC) * 2 + _FOOTER_SIZE:
            stream.seek(summary_end)
            tail = self._read_exact(_FOOTER_SIZE + len(MAGIC))
            if tail[-len(MAGIC) :] == MAGIC and tail[0] == OP_FOOTER:
                summary_start = int(struct.unpack("<Q", tail[9:17])[0])
                summary_crc = int(struct.unpack("<I", tail[25:29])[0])
                if summary_start != 0 and not len(MAGIC) < summary_start <= summary_end:
                    self._problem(
                        f"footer points at a summary section at byte {summary_start}, outside"
                        f" the file ({file_size} bytes); reading without it"
                    )
                    summary_start = -1
        if summary_start > 0:
            stream.seek(summary_start)
            raw = self._read_exact(summary_end - summary_start)
            if summary_crc != 0 and crc32(tail[:25], crc32(raw)) != summary_crc:
                self._problem("summary section CRC mismatch; reading without it")
            elif self._use_summary(raw, summary_start):
                return
            # Else: an unreadable summary, or a metadata index that does not point at
            # metadata records (written by imufdi <= 0.1.0 while chunks were still being
            # compressed): scan for the metadata instead.
        # No usable footer/summary (e.g. a truncated file): scan the top-level records for
        # metadata without decompressing chunks.
        stream.seek(len(MAGIC))
        position = len(MAGIC)
        while True:
            head = self._read_exact(9)
            if len(head) < 9:
                break
            opcode = head[0]
            length = int(struct.unpack("<Q", head[1:9])[0])
            if length > file_size - position - 9 or opcode in (OP_DATA_END, OP_FOOTER):
                break
            if opcode == OP_METADATA and length <= self.limits.max_record_bytes:
                self._add_record(opcode, self._read_exact(length), position)
            else:
                stream.seek(length, io.SEEK_CUR)
            position += 9 + length

    def _use_summary(self, raw: bytes, summary_start: int) -> bool:
        """Read channels, statistics and metadata through the summary; False if it is
        unusable or its metadata index is stale (the metadata are then found by a scan)."""
        saved = (dict(self.schemas), dict(self.channels), dict(self._pending_channels))
        try:
            metadata_offsets = self._parse_summary(raw)
        except (McapInputError, struct.error, ValueError) as err:
            self.schemas, self.channels, self._pending_channels = saved
            self._known_size = -1
            self._chunk_starts = []
            self.summary_channel_counts = None
            self.summary_message_count = None
            self.summary_time_range = None
            self._problem(
                f"summary section at byte {summary_start} unreadable ({_error_text(err)});"
                " reading without it"
            )
            return False
        assert self._file_size is not None
        stale = False
        for offset, length in metadata_offsets:
            if (
                offset < len(MAGIC)
                or length < 9
                or offset + length > self._file_size
                or length > self.limits.max_record_bytes
            ):
                stale = True
                continue
            self._stream.seek(offset)
            record = self._read_exact(length)
            if record[0] == OP_METADATA:
                self._add_record(OP_METADATA, record[9:], offset)
            else:
                stale = True
        return not stale

    def _parse_summary(self, raw: bytes) -> list[tuple[int, int]]:
        buf = np.frombuffer(raw, dtype=np.uint8)
        starts, opcodes, lengths, end = scan_records(buf)
        if end != buf.shape[0]:
            raise McapInputError(f"malformed record at byte {end} of the summary")
        metadata_offsets = []
        chunk_starts: list[int] = []
        for start, opcode, length in zip(starts.tolist(), opcodes.tolist(), lengths.tolist()):
            content = raw[start + 9 : start + 9 + length]
            if opcode == OP_SCHEMA:
                self._add_schema(parse_schema(content))
            elif opcode == OP_CHANNEL:
                self._add_channel(content)
            elif opcode == OP_METADATA_INDEX:
                offset, record_length = struct.unpack("<QQ", content[:16])
                metadata_offsets.append((int(offset), int(record_length)))
            elif opcode == 0x08:  # ChunkIndex: where each chunk starts
                (chunk_start,) = struct.unpack_from("<Q", content, 16)
                chunk_starts.append(int(chunk_start))
            elif opcode == 0x0B:  # Statistics
                cur = _Cursor(content, "Statistics")
                self.summary_message_count = cur.u64()
                cur.take(2 + 4 * 4)
                self.summary_time_range = (cur.u64(), cur.u64())
                end = cur.u32() + cur.pos
                counts = {}
                while cur.pos < end:
                    cid = cur.u16()
                    counts[cid] = cur.u64()
                self.summary_channel_counts = counts
        self._chunk_starts = sorted(chunk_starts)
        return metadata_offsets

    # --- data ------------------------------------------------------------------------------

    def batches(self) -> Iterator[MessageBatch]:
        """Message batches in file order: whole chunks (and un-chunked messages) joined into
        batches of about 4 MiB.

        The file is read once: calling this again continues where the last iteration
        stopped (batches handed back with :meth:`push_back` come first).
        """
        if self._iterator is None:
            self._iterator = self._read_batches()
        return self._with_pushback(self._iterator)

    def raw_chunks(self, batch: MessageBatch) -> list[ChunkRun] | None:
        """Where ``batch``'s messages came from, in order, when the source was opened with
        ``keep_raw_chunks`` (else None): runs of (Chunk record holding exactly those
        messages and no other record, or None; message count; byte offset of the chunk's
        records in ``batch.data``). Only the last ``_RAW_CHUNKS_KEPT`` batches are
        remembered, each until it is asked for once; ``batch`` must be the object
        :meth:`batches` yielded."""
        kept = getattr(self, "_raw_chunks", None)  # a BagDirSource keeps none
        if not kept:
            return None
        for index, (held, runs) in enumerate(kept):
            if held is batch:
                del kept[index]  # asked once: the batch and its chunks are not held longer
                return runs
        return None

    def push_back(self, batches: list[MessageBatch]) -> None:
        """Hand batches back so that the next :meth:`batches` iteration yields them first."""
        self._pushback[:0] = batches

    def _with_pushback(self, iterator: Iterator[MessageBatch]) -> Iterator[MessageBatch]:
        while self._pushback:
            yield self._pushback.pop(0)
        for batch in iterator:
            yield batch
            while self._pushback:
                yield self._pushback.pop(0)

    def _take(self, n: int) -> bytes:
        """Up to ``n`` bytes of the data section (fewer only at the end of the stream),
        through a read-ahead buffer: small records cost no stream call each."""
        available = len(self._ahead) - self._ahead_pos
        if n <= available:
            start = self._ahead_pos
            self._ahead_pos += n
            return self._ahead[start : start + n]
        if n >= _READ_DIRECT and (self._file_size is not None or n <= _READ_PIECE):
            # a large record (a chunk): what the read-ahead buffer holds of it, then the
            # rest read straight into place (one copy; the size was checked against the
            # rest of the file, or is small enough to allocate up front)
            out = bytearray(n)
            out[:available] = memoryview(self._ahead)[self._ahead_pos :]
            self._ahead, self._ahead_pos = b"", 0
            got = available + self._read_into(memoryview(out)[available:])
            return out if got == n else out[:got]  # type: ignore[return-value]
        rest = self._ahead[self._ahead_pos :]
        self._ahead, self._ahead_pos = b"", 0
        if n > _READ_AHEAD:
            return rest + self._read_exact(n - len(rest))
        self._ahead = rest + self._read_exact(_READ_AHEAD - len(rest))
        return self._take(min(n, len(self._ahead)))

    def _read_into(self, view: memoryview) -> int:
        """Fill ``view`` from the stream (fewer bytes only at its end); returns how many
        were read."""
        readinto = getattr(self._stream, "readinto", None)
        filled = 0
        while filled < len(view):
            if readinto is not None:
                got = readinto(view[filled : filled + _READ_PIECE])
            else:
                part = self._stream.read(min(len(view) - filled, _READ_PIECE))
                view[filled : filled + len(part)] = part
                got = len(part)
            if not got:
                break
            filled += got
        return filled

    def _discard(self, n: int) -> int:
        """Skip ``n`` bytes of the data section; returns how many were skipped."""
        available = len(self._ahead) - self._ahead_pos
        if n <= available:
            self._ahead_pos += n
            return n
        self._ahead, self._ahead_pos = b"", 0
        return available + self._skip(n - available)

    def _next_record(self, position: int) -> tuple[int, int, bytes | None] | None:
        """The record at ``position``: (opcode, content length, content or None if skipped),
        or None at the end of the data (after reporting why)."""
        head = self._take(9)
        if len(head) < 9:
            if head:
                self._problem(f"truncated MCAP: record header cut at byte {position}")
            else:
                self._problem(f"truncated MCAP: file ends at byte {position} without a footer")
            return None
        opcode, length = _RECORD_HEAD.unpack(head)
        if self._file_size is not None and length > self._file_size - position - 9:
            remaining = max(self._file_size - position - 9, 0)
            self._problem(
                f"corrupt or truncated MCAP: {_record_name(opcode)} record at byte {position}"
                f" claims {length} bytes but {remaining} remain"
            )
            return None
        if opcode not in _HELD:
            skipped = self._discard(length)
            if skipped < length:
                self._problem(
                    f"truncated MCAP: {_record_name(opcode)} record at byte {position} is cut"
                    f" after {skipped} of {length} bytes; read up to the cut"
                )
                return None
            return opcode, length, None
        if length > self.limits.max_record_bytes:
            self._problem(
                f"corrupt MCAP: {_record_name(opcode)} record at byte {position} claims"
                f" {length} bytes, over the limit of {self.limits.max_record_bytes}"
                " (IMUFDI_MAX_RECORD_BYTES)"
            )
            return None
        content = self._take(length)
        if len(content) < length:
            self._problem(
                f"truncated MCAP: {_record_name(opcode)} record at byte {position} is cut"
                f" after {len(content)} of {length} bytes; read up to the cut"
            )
            return None
        return opcode, length, content

    def _resume_after(self, position: int) -> int | None:
        """After a damaged record at ``position``: the next chunk the summary's chunk index
        knows (seekable files with a usable summary), positioned to read; else None."""
        if self._file_size is None or not self._chunk_starts:
            return None
        index = bisect.bisect_right(self._chunk_starts, position)
        if index == len(self._chunk_starts):
            return None
        resume = self._chunk_starts[index]
        if resume >= self._file_size:
            return None
        self._ahead, self._ahead_pos = b"", 0
        self._stream.seek(resume)
        message = f"resumed reading at the chunk at byte {resume} (from the summary's chunk index)"
        if self._deferred is not None:
            self._deferred.append((False, message))
        else:
            self.warnings.append(message)
        return resume

    def _records(self) -> Iterator[tuple[int, int, bytes | None, int]]:
        """The data section's records in file order: (opcode, content length, content or
        None if skipped, byte offset); after a damaged record, reading resumes at the next
        chunk the summary knows. Ends after a DataEnd or Footer record."""
        self._ahead, self._ahead_pos = b"", 0
        position = len(MAGIC)
        while True:
            record = self._next_record(position)
            if record is None:
                resume = self._resume_after(position)
                if resume is None:
                    return
                position = resume
                continue
            opcode, length, content = record
            if content is not None or opcode not in _IGNORED:
                yield opcode, length, content, position
            position += 9 + length
            if opcode in (OP_FOOTER, OP_DATA_END):
                return
            # Records nobody reads (the MessageIndex records after every chunk) that lie
            # whole in the read-ahead buffer are stepped over here, a few hundred ns each.
            ahead, at = self._ahead, self._ahead_pos
            end = len(ahead)
            limit = None if self._file_size is None else self._file_size - 9
            while at + 9 <= end:
                opcode, length = _RECORD_HEAD.unpack_from(ahead, at)
                if (
                    opcode not in _IGNORED
                    or at + 9 + length > end
                    or (limit is not None and length > limit - position)
                ):
                    break
                at += 9 + length
                position += 9 + length
            self._ahead_pos = at

    def _prefetched(
        self,
    ) -> Iterator[tuple[tuple[int, int, bytes | None, int], _Ahead | None]]:
        """:meth:`_records`, with large chunks decompressed and CRC-checked on a worker
        thread up to ``_PREFETCH_CHUNKS`` chunks ahead: each record comes with the future of
        its chunk's records and the id of the process that asked for it (or None). Problems met while reading ahead are held and
        reported (or raised, with ``strict``) when the record they precede is handed out,
        so warnings, errors and batches come in the same order as without read-ahead."""
        records = self._records()
        if not self.read_ahead:  # nothing is read ahead: records as they come
            for record in records:
                yield record, None
            return
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
                    self._deferred = notes
                    try:
                        item = next(records, None)
                    finally:
                        self._deferred = None
                    future: _Ahead | None = None
                    size = 0
                    if item is None:
                        exhausted = True
                    elif item[0] == OP_CHUNK and item[2] is not None:
                        size = _declared_size(item[2])
                        if size >= _THREAD_CHUNK and self.read_ahead:
                            job = self._worker().submit(
                                _unpack_chunk,
                                item[2],
                                self.limits.max_chunk_bytes,
                                self.validate_crcs,
                                None,
                                not self.strict,
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
                        self._problem(message)
                    else:
                        self.warnings.append(message)
                if item is None:
                    return
                yield item, future
        finally:
            for _, _, future, _ in queue:
                if future is not None:
                    future[0].cancel()

    def _worker(self) -> ThreadPoolExecutor:
        """The read-ahead thread's executor, made on first use (and anew in a forked child
        process, where the parent's thread does not exist)."""
        if self._pool is None or self._pool_pid != os.getpid():
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(1, thread_name_prefix="imufdi-chunks")
            self._pool_pid = os.getpid()
        return self._pool

    def _read_batches(self) -> Iterator[MessageBatch]:
        pending = _PendingMessages()
        runs: list[ChunkRun] = []  # where the pending messages come from (keep_raw_chunks)
        for (opcode, length, content, here), future in self._prefetched():
            if opcode == OP_MESSAGE:
                assert content is not None
                if self.keep_raw_chunks:
                    runs.append((None, 1, pending.n_bytes))
                pending.add_loose(content, here)
            elif opcode == OP_CHUNK:
                assert content is not None
                part = self._chunk_part(content, here, future, pending)
                if part is not None:
                    if self.keep_raw_chunks:
                        raw = _raw_chunk(content) if self._chunk_clean else None
                        runs.append((raw, len(part[1]), pending.n_bytes))
                    pending.add_chunk(*part, here)
            elif opcode in (OP_SCHEMA, OP_CHANNEL, OP_METADATA):
                # Not a message: the pending messages before it stay in the current batch,
                # so the channels of a file that declares each just before its first message
                # are all known when the batch is handed out.
                assert content is not None
                self._add_record(opcode, content, here)
            elif opcode == OP_FOOTER:
                if length != 20:
                    self._problem(f"malformed Footer record at byte {here}")
            elif opcode == 0 or 0x10 <= opcode < 0x80:
                # Not an MCAP v0 record (0x80-0xFF are private records, skipped silently).
                self._problem(f"record with unknown opcode {opcode:#04x} at byte {here} skipped")
            if pending.full():
                batch = self._flush(pending)
                self._note_runs(batch, runs)
                runs = []
                if len(batch):
                    yield batch
        batch = self._flush(pending)
        self._note_runs(batch, runs)
        if len(batch):
            yield batch

    def _note_runs(self, batch: MessageBatch, runs: list[ChunkRun]) -> None:
        """Remember where a batch's messages came from, when every one is accounted for
        (none was dropped as malformed or of an unknown channel) and a chunk is whole."""
        if sum(count for _, count, _ in runs) == len(batch) and any(r for r, _, _ in runs):
            self._raw_chunks.append((batch, runs))

    def _flush(self, pending: _PendingMessages) -> MessageBatch:
        """One batch of the pending messages (small chunks and loose messages are joined,
        so the cost per batch is paid per 4 MiB, not per chunk)."""
        if not pending.n_parts:
            return MessageBatch.empty()
        where = pending.where()
        buf, starts, lengths = pending.take()
        return self._messages_from(buf, starts, lengths, where)

    def _messages_from(
        self,
        buf: np.ndarray,
        content_starts: np.ndarray,
        content_lengths: np.ndarray,
        where: str,
    ) -> MessageBatch:
        bad = content_lengths < MESSAGE_FIXED_CONTENT
        if bool(bad.any()):
            self._problem(f"{where}: {int(bad.sum())} malformed Message record(s) skipped")
            content_starts = content_starts[~bad]
            content_lengths = content_lengths[~bad]
        step = _even_step(content_starts)
        if step and int(content_starts[-1]) + MESSAGE_FIXED_CONTENT <= buf.shape[0]:
            # evenly spaced records: each field through a typed strided view, copied once
            # (a 22-byte element gather costs several times more)
            n, first = content_starts.shape[0], int(content_starts[0])

            def field(name: str, dtype: type) -> np.ndarray:
                code, at = _MESSAGE_FIELDS.fields[name][:2]  # type: ignore[index]
                view = np.ndarray((n,), code, buf, first + at, (step,))
                return view.astype(dtype)

        else:
            fields = (
                gather_bytes(buf, content_starts, MESSAGE_FIXED_CONTENT)
                .reshape(-1)
                .view(_MESSAGE_FIELDS)
            )

            def field(name: str, dtype: type) -> np.ndarray:
                return fields[name].astype(dtype)

        batch = MessageBatch(
            channel_id=field("channel_id", np.uint16),
            sequence=field("sequence", np.uint32),
            log_time=field("log_time", np.int64),
            publish_time=field("publish_time", np.int64),
            data=buf,
            offset=content_starts + MESSAGE_FIXED_CONTENT,
            length=content_lengths - MESSAGE_FIXED_CONTENT,
        )
        known = self._known_lookup()[batch.channel_id]
        if not bool(known.all()):
            missing = sorted(set(np.unique(batch.channel_id[~known]).tolist()))
            shown = ", ".join(str(c) for c in missing[:8]) + (" ..." if len(missing) > 8 else "")
            self._problem(
                f"{where}: {int((~known).sum())} message(s) on unknown channel id(s) {shown}"
                " skipped"
            )
            batch = batch.select(known)
        return batch

    def _known_lookup(self) -> np.ndarray:
        """Boolean table over all 65536 channel ids: is the channel known."""
        if self._known_size != len(self.channels):
            self._known = np.zeros(1 << 16, bool)
            self._known[np.fromiter(self.channels, dtype=np.int64)] = True
            self._known_size = len(self.channels)
        return self._known

    def _chunk_records(
        self,
        content: bytes,
        chunk_offset: int,
        future: _Ahead | None = None,
        slot: Callable[[int], memoryview] | None = None,
    ) -> bytes | memoryview | None:
        """The decompressed, CRC-checked records of a Chunk record (None if unusable):
        large zstd chunks decompressed into ``slot(size)`` (the batch buffer), others as
        bytes; ``future``: the same, computed ahead on the worker thread."""
        if future is not None and future[1] == os.getpid():
            raw, error = future[0].result()
        else:  # in line (also in a forked child: the parent's worker never answers there)
            raw, error = _unpack_chunk(
                content, self.limits.max_chunk_bytes, self.validate_crcs, slot, not self.strict
            )
        if raw is None:
            self._problem(f"chunk at byte {chunk_offset} skipped: {error}")
        return raw

    def _chunk_part(
        self,
        content: bytes,
        chunk_offset: int,
        future: _Ahead | None,
        pending: _PendingMessages,
    ) -> tuple[int, np.ndarray | list[int], np.ndarray | list[int]] | None:
        """A chunk's records placed after the pending ones (``pending.slot``, to be counted
        by ``pending.add_chunk``): their size, and the content starts and lengths of its
        Message records (its Schema and Channel records are registered); None if the
        chunk is unusable."""
        self._chunk_clean = False
        raw = self._chunk_records(content, chunk_offset, future, pending.slot)
        if raw is None:
            return None
        size = len(raw)
        if isinstance(raw, bytes):  # not decompressed in place: copied there
            pending.slot(size)[:] = raw
        if size <= _SMALL_CHUNK:
            assert isinstance(raw, bytes)
            return (size, *self._small_chunk_part(raw, chunk_offset))
        buf = np.frombuffer(raw, dtype=np.uint8)
        found = None if self._pattern is None else self._pattern.match(buf, self._phase)
        if found is not None:  # whole Message records only: the chunk is clean
            content_starts, lengths, self._phase = found
            self._chunk_clean = True
            return size, content_starts, lengths
        starts, opcodes, lengths, end = scan_records(buf, _IN_CHUNK)
        pattern = RecordPattern.learn(opcodes, lengths, buf.shape[0]) if end == size else None
        if pattern is not None:
            self._pattern = pattern
            self._phase = pattern.phase_after(0, lengths.shape[0])
        is_message = opcodes == OP_MESSAGE
        # only Message records, all of them well formed: the chunk can be copied verbatim
        self._chunk_clean = end == buf.shape[0] and bool(is_message.all())
        if end != buf.shape[0]:
            self._problem(
                f"chunk at byte {chunk_offset}: malformed record at byte {end} of its"
                f" {buf.shape[0]} record bytes; the {int(np.count_nonzero(is_message))}"
                " message(s) before it kept"
            )
        if not bool(is_message.all()):
            # Schema/Channel records inside the chunk must be known before its messages.
            for index in np.flatnonzero(~is_message).tolist():
                start = int(starts[index]) + 9
                body = bytes(raw[start : start + int(lengths[index])])
                self._add_record(int(opcodes[index]), body, chunk_offset)
            starts = starts[is_message]
            lengths = lengths[is_message]
        return size, starts + 9, lengths

    def _small_chunk_part(self, raw: bytes, chunk_offset: int) -> tuple[list[int], list[int]]:
        """:meth:`_chunk_part` for a chunk of a few records: walked in Python, no numpy."""
        starts: list[int] = []
        lengths: list[int] = []
        position = 0
        size = len(raw)
        while position + 9 <= size:
            opcode, length = _RECORD_HEAD.unpack_from(raw, position)
            if position + 9 + length > size or opcode not in _IN_CHUNK:
                break
            if opcode == OP_MESSAGE:
                starts.append(position + 9)
                lengths.append(length)
            else:
                self._add_record(opcode, raw[position + 9 : position + 9 + length], chunk_offset)
            position += 9 + length
        if position != size:
            self._problem(
                f"chunk at byte {chunk_offset}: malformed record at byte {position} of its"
                f" {size} record bytes; the {len(starts)} message(s) before it kept"
            )
        return starts, lengths


#: (chunk copied verbatim or None, message count, byte offset of its records in the batch)
ChunkRun = tuple[RawChunk | None, int, int]

#: (records, "") of a usable chunk, or (None, why it is not)
_Unpacked = tuple[bytes | memoryview | None, str]
#: A chunk being unpacked on the worker thread, and the process id that asked for it (a
#: forked child never gets the answer: it unpacks the chunk itself)
_Ahead = tuple["Future[_Unpacked]", int]


def _even_step(starts: np.ndarray) -> int:
    """The constant positive distance between consecutive ``starts`` (at least two), or 0
    when they are not evenly spaced."""
    n = starts.shape[0]
    if n < 2:
        return 0
    first = int(starts[0])
    step = int(starts[1]) - first
    if step <= 0 or int(starts[-1]) != first + (n - 1) * step:
        return 0
    if n > 2 and np.count_nonzero(np.diff(starts) != step):
        return 0
    return step


def _declared_size(content: bytes) -> int:
    """The uncompressed size a Chunk record's content declares (0 if it is too short)."""
    if len(content) < _CHUNK_HEAD.size:
        return 0
    return int(_CHUNK_HEAD.unpack_from(content)[2])


def _unpack_chunk(
    content: bytes,
    max_chunk_bytes: int,
    validate_crcs: bool,
    slot: Callable[[int], memoryview] | None = None,
    trust_frame_checksum: bool = False,
) -> _Unpacked:
    """A Chunk record's records, decompressed and (with ``validate_crcs``) CRC-checked, or
    why the chunk is unusable. A zstd chunk of more than ``_SMALL_CHUNK`` bytes is
    decompressed into ``slot(size)`` when given (no allocation, no later copy). Touches
    no reader state (runs on the worker thread, without ``slot``). With
    ``trust_frame_checksum`` the CRC-32 is skipped when the zstd frame's content checksum
    already verified every record byte (:func:`~imufdi_cli.mcapio.compression.frame_checksummed`)."""
    try:
        if len(content) < _CHUNK_HEAD.size + 8:
            raise McapInputError("malformed Chunk record (shorter than its fields)")
        _, _, uncompressed_size, crc, name_length = _CHUNK_HEAD.unpack_from(content)
        records_at = _CHUNK_HEAD.size + name_length + 8
        if records_at > len(content):
            raise McapInputError("malformed Chunk record (compression name past its end)")
        compression = content[_CHUNK_HEAD.size : records_at - 8].decode("utf-8", "replace")
        (records_length,) = struct.unpack_from("<Q", content, records_at - 8)
        if records_length != len(content) - records_at:
            raise McapInputError(
                f"records length {records_length} does not match the record"
                f" ({len(content) - records_at} bytes left)"
            )
        if uncompressed_size > max_chunk_bytes:
            raise McapInputError(
                f"declares {uncompressed_size} uncompressed bytes, over the limit of"
                f" {max_chunk_bytes} (IMUFDI_MAX_CHUNK_BYTES)"
            )
        data = memoryview(content)[records_at:]
        framed = (
            validate_crcs
            and trust_frame_checksum
            and frame_checksummed(data, compression, uncompressed_size)
        )
        raw: bytes | memoryview
        if slot is not None and compression == "zstd" and uncompressed_size > _SMALL_CHUNK:
            raw = slot(uncompressed_size)
            decompress_into(data, compression, raw)
        else:
            raw = decompress(data, compression, uncompressed_size)
    except McapInputError as err:
        return None, str(err)
    if validate_crcs and crc != 0 and not framed:
        actual = crc32(raw)
        if actual != crc:
            return None, (f"CRC mismatch (records CRC-32 {actual:#010x}, chunk says {crc:#010x})")
    return raw, ""


def _raw_chunk(content: bytes) -> RawChunk:
    """A :class:`RawChunk` of a Chunk record's content (already checked by the reader)."""
    start_time, end_time, uncompressed_size, _, name_length = _CHUNK_HEAD.unpack_from(content)
    records_at = _CHUNK_HEAD.size + name_length + 8
    compression = content[_CHUNK_HEAD.size : records_at - 8].decode("utf-8", "replace")
    return RawChunk(
        content=content,
        start_time=int(start_time),
        end_time=int(end_time),
        uncompressed_size=int(uncompressed_size),
        compressed_size=len(content) - records_at,
        compression=compression,
    )


def _error_text(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text or type(err).__name__


def iter_topic(
    source: str | os.PathLike[str] | IO[bytes] | McapSource, topic: str
) -> Iterator[tuple[ChannelInfo, MessageBatch]]:
    """The messages on ``topic``, one ``(channel, batch)`` per channel of each batch read,
    in file order. A path or stream is opened here and closed when the iteration ends; an
    open :class:`McapSource` is left open."""
    own = not isinstance(source, McapSource)
    src = source if isinstance(source, McapSource) else McapSource(source)
    try:
        for batch in src.batches():
            for cid, part in batch.by_channel():
                channel = src.channels[cid]
                if channel.topic == topic:
                    yield channel, part
    finally:
        if own:
            src.close()
