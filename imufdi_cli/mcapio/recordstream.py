"""The records of an MCAP file, the base of :class:`~imufdi_cli.mcapio.source.McapSource`
(which turns the messages they hold into batches).

- the summary section (seekable files), read up front: schemas, channels, statistics,
  metadata and the chunk index, or a scan for the metadata when it is unusable;
- the data section as a stream of records in file order: bounded reads, a read-ahead
  buffer for small records, records nobody reads stepped over, and the resumption after a
  damaged record at the next chunk the summary knows;
- the registry of the Schema, Channel and Metadata records met.
"""

from __future__ import annotations

import bisect
import io
import struct
from collections.abc import Callable, Iterator
from typing import IO

import numpy as np

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.compression import crc32
from imufdi_cli.mcapio.limits import ReaderLimits
from imufdi_cli.mcapio.records import (
    MAGIC,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_METADATA,
    OP_METADATA_INDEX,
    OP_SCHEMA,
    ChannelInfo,
    SchemaInfo,
)
from imufdi_cli.mcapio.scan import (
    _Cursor,
    parse_channel,
    parse_metadata,
    parse_schema,
    scan_records,
)

_FOOTER_SIZE = 9 + 20
#: An entry of a ChunkIndex record's message index offsets: channel id, record offset.
_INDEX_ENTRY = np.dtype([("channel", "<u2"), ("offset", "<u8")])
_RECORD_HEAD = struct.Struct("<BQ")
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
#: Reads from the stream are done in pieces of at most this many bytes, so a record
#: length that no file could satisfy never becomes one huge allocation.
_READ_PIECE = 16 << 20
#: Problems listed per source; beyond them one line says more were met (a damaged file
#: can hold millions of bad records: their messages alone would fill the memory).
MAX_PROBLEMS = 100
#: Bytes read at a time while a zero-filled region is stepped over on the stream.
_ZERO_PIECE = 4 << 20
#: The "opcode" :meth:`RecordStream._next_record` gives a zero-filled region (reported).
_ZERO_RUN = -1


def _record_name(opcode: int) -> str:
    return _OPCODE_NAMES.get(opcode, f"opcode {opcode:#04x}")


class RecordStream:
    """Reads the records of an MCAP file's data section in file order from ``_stream``
    (set up, with the attributes below, by :class:`~imufdi_cli.mcapio.source.McapSource`).

    Problems (a cut or corrupt record) are warnings, or :class:`McapInputError` with
    ``strict``; while reading ahead (``_deferred`` is a list) they are held there and
    reported in file order by the read-ahead (:mod:`~imufdi_cli.mcapio.readahead`).
    """

    name: str
    strict: bool
    limits: ReaderLimits
    warnings: list[str]
    _stream: IO[bytes]
    _seekable: bool
    _file_size: int | None
    _ahead: bytes
    _ahead_pos: int
    _chunk_starts: list[int]
    #: The channel ids of each chunk, by its offset, from the summary's ChunkIndex records
    #: (their message index offsets; empty when a writer indexed none).
    _chunk_channels: dict[int, np.ndarray]
    #: Offsets of chunks to step over without decompressing them (:meth:`skip_chunks_without`).
    _skipped_chunks: frozenset[int] = frozenset()
    #: Per chunk offset, from its ChunkIndex record: the Chunk record's length and the
    #: length of the MessageIndex records right after it, where the two agree with the
    #: index's message index offsets (a skipped chunk and its indexes are stepped over in
    #: one seek: :meth:`_step_over`).
    _chunk_spans: dict[int, tuple[int, int]]
    _deferred: list[tuple[bool, str]] | None
    channels: dict[int, ChannelInfo]
    schemas: dict[int, SchemaInfo]
    metadata: dict[str, dict[str, str]]
    summary_channel_counts: dict[int, int] | None
    summary_message_count: int | None
    summary_time_range: tuple[int, int] | None
    _pending_channels: dict[int, tuple[int, str, str, dict[str, str]]]
    _known_size: int

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

    def _problem(self, message: str) -> None:
        if self._deferred is not None:  # reading ahead: reported when the reader gets there
            self._deferred.append((True, message))
            return
        if self.strict:
            raise McapInputError(f"{self.name}: {message}")
        problems = self._problems = getattr(self, "_problems", 0) + 1
        if problems < MAX_PROBLEMS:
            self.warnings.append(message)
        elif problems == MAX_PROBLEMS:
            self.warnings.append(
                f"{message}; further problems of this file are not listed (more than"
                f" {MAX_PROBLEMS}: a badly damaged file, see --strict)"
            )

    def _zero_run(self, take: bool) -> int:
        """Skip the zero bytes from the current position: through the data section's
        read-ahead buffer (``take``) or on the stream; returns how many were skipped.

        A zero-filled region (a file preallocated and not fully written, a disk image)
        reads as 9-byte records of opcode 0x00 and length 0: millions of them in a few
        MB. No MCAP record has opcode 0x00, so the whole run is stepped over at once."""
        skipped = 0
        while True:
            if take:
                if self._ahead_pos >= len(self._ahead):
                    self._ahead, self._ahead_pos = self._read_exact(_READ_AHEAD), 0
                buffer, start = self._ahead, self._ahead_pos
            else:
                buffer, start = self._read_exact(_ZERO_PIECE), 0
            if len(buffer) <= start:
                return skipped
            rest = np.frombuffer(buffer, np.uint8, offset=start)
            if not rest.any():
                skipped += len(buffer) - start
                if take:
                    self._ahead_pos = len(buffer)
                continue
            end = start + int(np.argmax(rest != 0))  # the first byte that is not zero
            skipped += end - start
            if take:
                self._ahead_pos = end
            else:
                self._stream.seek(end - len(buffer), io.SEEK_CUR)
            return skipped

    # --- records met ---------------------------------------------------------------------

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
            if opcode == 0 and length == 0:  # a zero-filled region: stepped over at once
                position += 9 + self._zero_run(take=False)
                continue
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
            self._chunk_channels = {}
            self._chunk_spans = {}
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
        self._chunk_channels = {}
        self._chunk_spans = {}
        for start, opcode, length in zip(starts.tolist(), opcodes.tolist(), lengths.tolist()):
            content = raw[start + 9 : start + 9 + length]
            if opcode == OP_SCHEMA:
                self._add_schema(parse_schema(content))
            elif opcode == OP_CHANNEL:
                self._add_channel(content)
            elif opcode == OP_METADATA_INDEX:
                offset, record_length = struct.unpack("<QQ", content[:16])
                metadata_offsets.append((int(offset), int(record_length)))
            elif opcode == 0x08:  # ChunkIndex: where each chunk starts, its channels
                (chunk_start,) = struct.unpack_from("<Q", content, 16)
                chunk_starts.append(int(chunk_start))
                (map_bytes,) = struct.unpack_from("<I", content, 32)
                if map_bytes % 10 or 36 + map_bytes > len(content):
                    raise McapInputError(
                        f"malformed ChunkIndex record of the chunk at byte {chunk_start}"
                    )
                entries = np.frombuffer(content, _INDEX_ENTRY, map_bytes // 10, 36)
                self._chunk_channels[int(chunk_start)] = entries["channel"].astype(np.int64)
                self._note_span(content, int(chunk_start), map_bytes, entries["offset"])
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

    def _note_span(
        self, content: bytes, chunk_start: int, map_bytes: int, index_offsets: np.ndarray
    ) -> None:
        """Remember the bytes of a chunk and of its MessageIndex records (a ChunkIndex
        record's ``chunk_length`` and ``message_index_length``) when the index's message
        index offsets all lie in that span right after the chunk (else nothing: such a
        chunk is stepped over record by record)."""
        if len(content) < 36 + map_bytes + 8:
            return
        (chunk_length,) = struct.unpack_from("<Q", content, 24)
        (index_length,) = struct.unpack_from("<Q", content, 36 + map_bytes)
        end = chunk_start + chunk_length
        if chunk_length < 9 or not index_offsets.size:
            return
        if int(index_offsets.min()) != end or int(index_offsets.max()) + 9 > end + index_length:
            return
        self._chunk_spans[chunk_start] = (int(chunk_length), int(index_length))

    # --- data section --------------------------------------------------------------------

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
        if opcode == 0 and length == 0:
            zeros = 9 + self._zero_run(take=True)
            self._problem(
                f"{zeros} zero bytes at byte {position} skipped (a zero-filled region: a file"
                " not completely written?)"
            )
            return _ZERO_RUN, zeros - 9, None
        if self._file_size is not None and length > self._file_size - position - 9:
            remaining = max(self._file_size - position - 9, 0)
            self._problem(
                f"corrupt or truncated MCAP: {_record_name(opcode)} record at byte {position}"
                f" claims {length} bytes but {remaining} remain"
            )
            return None
        if opcode not in _HELD or (opcode == OP_CHUNK and position in self._skipped_chunks):
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

    def _step_over(self, position: int, chunk_length: int, index_length: int) -> int:
        """Step over a skipped chunk at ``position`` and the MessageIndex records after it
        (``chunk_length`` and ``index_length`` bytes, from the summary's chunk index) without
        reading them: only the chunk's record head is read (9 bytes, not a read-ahead
        buffer) and checked against the index. Returns the bytes stepped over, or 0 when
        the head does not match or the span runs past the end of the file (the record is
        then read as any other)."""
        if self._file_size is None or position + chunk_length + index_length > self._file_size:
            return 0
        available = len(self._ahead) - self._ahead_pos
        if available >= 9:
            head = self._ahead[self._ahead_pos : self._ahead_pos + 9]
        else:
            head = self._ahead[self._ahead_pos :] + self._read_exact(9 - available)
            self._ahead, self._ahead_pos = head, 0
        if len(head) < 9:
            return 0
        opcode, length = _RECORD_HEAD.unpack(head)
        if opcode != OP_CHUNK or 9 + length != chunk_length:
            return 0
        total = chunk_length + index_length
        if self._discard(total) != total:  # the file is as long as the summary said
            return 0
        return total

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

    def skip_chunks_without(self, wanted: Callable[[ChannelInfo], bool]) -> int:
        """Step over, undecompressed, every chunk that holds no channel for which
        ``wanted`` is true, as the summary's chunk index says (the ``mcap`` package's
        indexed reader filters topics the same way); their messages are never yielded.
        Chunks the index does not list, or lists without channels (a writer that wrote no
        message indexes), and chunks with a channel the summary does not declare are read.
        Call before reading; without a usable summary nothing is skipped. Returns how many
        chunks will be skipped."""
        chunk_channels = getattr(self, "_chunk_channels", None) or {}
        read = np.ones(1 << 16, bool)  # channel ids not declared: read
        for cid, channel in self.channels.items():
            read[cid] = bool(wanted(channel))
        skipped = frozenset(
            offset for offset, ids in chunk_channels.items() if ids.size and not read[ids].any()
        )
        self._skipped_chunks = skipped
        return len(skipped)

    def _records(self) -> Iterator[tuple[int, int, bytes | None, int]]:
        """The data section's records in file order: (opcode, content length, content or
        None if skipped, byte offset); after a damaged record, reading resumes at the next
        chunk the summary knows. Ends after a DataEnd or Footer record."""
        self._ahead, self._ahead_pos = b"", 0
        position = len(MAGIC)
        spans = getattr(self, "_chunk_spans", None) if self._skipped_chunks else None
        while True:
            if spans and position in self._skipped_chunks and position in spans:
                stepped = self._step_over(position, *spans[position])
                if stepped:
                    yield OP_CHUNK, spans[position][0] - 9, None, position
                    position += stepped
                    continue
            record = self._next_record(position)
            if record is None:
                resume = self._resume_after(position)
                if resume is None:
                    return
                position = resume
                continue
            opcode, length, content = record
            if opcode == _ZERO_RUN:
                position += 9 + length
                continue
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


def _error_text(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return text or type(err).__name__
