"""Streaming MCAP reader: records in file order, one :class:`MessageBatch` per chunk.

Records inside a decompressed chunk are located in bulk: a few records are walked one by
one, the repeating pattern of record lengths (e.g. 16 IMU channels interleaved) is found,
and the whole run of the pattern is checked with numpy at once. Message headers are then
read with one strided gather. Memory is bounded by one chunk.
"""

from __future__ import annotations

import io
import os
import struct
import sys
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from imufdi_cli.errors import McapInputError
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
    SchemaInfo,
    decompress,
    gather_bytes,
)

_MESSAGE_FIELDS = np.dtype(
    [("channel_id", "<u2"), ("sequence", "<u4"), ("log_time", "<u8"), ("publish_time", "<u8")]
)
_FOOTER_SIZE = 9 + 20
#: Un-chunked messages are grouped into batches of at most this many.
_LOOSE_BATCH = 4096


class _Cursor:
    """Reads little-endian MCAP primitives from a bytes object."""

    def __init__(self, raw: bytes | memoryview, where: str) -> None:
        self.raw = raw
        self.pos = 0
        self.where = where

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.raw):
            raise McapInputError(f"malformed {self.where} record (field past its end)")
        out = bytes(self.raw[self.pos : self.pos + n])
        self.pos += n
        return out

    def u16(self) -> int:
        return int(struct.unpack("<H", self.take(2))[0])

    def u32(self) -> int:
        return int(struct.unpack("<I", self.take(4))[0])

    def u64(self) -> int:
        return int(struct.unpack("<Q", self.take(8))[0])

    def string(self) -> str:
        raw = self.take(self.u32())
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise McapInputError(f"malformed {self.where} record (string is not UTF-8)") from err

    def bytes32(self) -> bytes:
        return self.take(self.u32())

    def string_map(self) -> dict[str, str]:
        end = self.u32() + self.pos
        out: dict[str, str] = {}
        while self.pos < end:
            key = self.string()
            out[key] = self.string()
        return out


def parse_schema(content: bytes) -> SchemaInfo:
    cur = _Cursor(content, "Schema")
    schema_id = cur.u16()
    name = cur.string()
    encoding = cur.string()
    return SchemaInfo(schema_id, name, encoding, cur.bytes32())


def parse_channel(content: bytes) -> tuple[int, int, str, str, dict[str, str]]:
    cur = _Cursor(content, "Channel")
    channel_id = cur.u16()
    schema_id = cur.u16()
    topic = cur.string()
    encoding = cur.string()
    return channel_id, schema_id, topic, encoding, cur.string_map()


def parse_metadata(content: bytes) -> tuple[str, dict[str, str]]:
    cur = _Cursor(content, "Metadata")
    name = cur.string()
    return name, cur.string_map()


def scan_records(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Locate the records in a buffer of concatenated MCAP records.

    Returns
    -------
    starts, opcodes, lengths : ndarray, shape (R,)
        Record start offsets, opcodes and content lengths.
    end : int
        Offset after the last complete record (``< len(buf)`` if the buffer is cut).
    """
    size = buf.shape[0]
    starts: list[np.ndarray] = []
    pos = 0
    probe = 32
    while pos + 9 <= size:
        # Walk a few records one by one.
        walked: list[tuple[int, int, int]] = []
        p = pos
        while p + 9 <= size and len(walked) < probe:
            opcode = int(buf[p])
            length = int(buf[p + 1 : p + 9].view("<u8")[0])
            if p + 9 + length > size:
                break
            walked.append((p, opcode, length))
            p += 9 + length
        if not walked:
            break
        # Find the shortest repeating pattern of (opcode, length) in the walked records.
        keys = [(op, ln) for _, op, ln in walked]
        period = 0
        for candidate in range(1, len(keys) // 2 + 1):
            if all(keys[i] == keys[i % candidate] for i in range(len(keys))):
                period = candidate
                break
        if period == 0 or len(walked) < probe:
            starts.append(np.array([w[0] for w in walked], dtype=np.int64))
            pos = p
            continue
        pattern_offsets = np.array([w[0] - pos for w in walked[:period]], dtype=np.int64)
        stride = sum(9 + ln for _, ln in keys[:period])
        n_periods = (size - pos) // stride
        candidates = pos + stride * np.arange(n_periods, dtype=np.int64)[:, None] + pattern_offsets
        heads = gather_bytes(buf, candidates.reshape(-1), 9)
        expected_ops = np.array([op for op, _ in keys[:period]], dtype=np.uint8)
        expected_len = np.array([ln for _, ln in keys[:period]], dtype=np.uint64)
        ok = (heads[:, 0].reshape(n_periods, period) == expected_ops) & (
            heads[:, 1:].copy().view("<u8").reshape(n_periods, period) == expected_len
        )
        good = ok.all(axis=1)
        n_good = int(np.argmin(good)) if not bool(good.all()) else n_periods
        if n_good == 0:
            starts.append(np.array([w[0] for w in walked], dtype=np.int64))
            pos = p
            continue
        starts.append(candidates[:n_good].reshape(-1))
        pos = pos + n_good * stride
    all_starts = np.concatenate(starts) if starts else np.zeros(0, np.int64)
    if all_starts.size == 0:
        return all_starts, np.zeros(0, np.uint8), np.zeros(0, np.int64), 0
    heads = gather_bytes(buf, all_starts, 9)
    opcodes = heads[:, 0].copy()
    lengths = heads[:, 1:].copy().view("<u8").reshape(-1).astype(np.int64)
    return all_starts, opcodes, lengths, pos


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
        Problems met while reading (e.g. a truncated file), when ``strict`` is False.

    Chunk CRCs are checked when ``validate_crcs`` is true (default: when ``strict``).
    A rosbag2 directory (or its ``metadata.yaml``) gives a
    :class:`~imufdi_cli.mcapio.bagdir.BagDirSource`: its split files read as one log.
    """

    def __new__(cls, source: Any = None, *args: Any, **kwargs: Any) -> McapSource:
        if cls is McapSource and isinstance(source, (str, os.PathLike)) and source != "-":
            from imufdi_cli.mcapio.bagdir import BagDirSource, is_bag_dir

            if is_bag_dir(source):
                return super().__new__(BagDirSource)
        return super().__new__(cls)

    def __init__(
        self,
        source: str | os.PathLike[str] | IO[bytes],
        *,
        strict: bool = False,
        validate_crcs: bool | None = None,
    ) -> None:
        self.strict = strict
        self.validate_crcs = strict if validate_crcs is None else validate_crcs
        self.channels: dict[int, ChannelInfo] = {}
        self.schemas: dict[int, SchemaInfo] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.warnings: list[str] = []
        self.summary_channel_counts: dict[int, int] | None = None
        self.summary_message_count: int | None = None
        self.summary_time_range: tuple[int, int] | None = None
        self._owns = False
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
            finally:
                self._stream.seek(len(MAGIC))

    # --- plumbing ------------------------------------------------------------------------

    def _is_seekable(self) -> bool:
        try:
            return bool(self._stream.seekable())
        except (AttributeError, OSError, ValueError):
            return False

    def _read_exact(self, n: int) -> bytes:
        chunks = []
        remaining = n
        while remaining > 0:
            part = self._stream.read(remaining)
            if not part:
                break
            chunks.append(part)
            remaining -= len(part)
        return b"".join(chunks)

    def close(self) -> None:
        if self._owns:
            self._stream.close()
            self._owns = False

    def __enter__(self) -> McapSource:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _problem(self, message: str) -> None:
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

    # --- summary (seekable sources) -------------------------------------------------------

    def _read_summary(self) -> None:
        stream = self._stream
        try:
            file_size = stream.seek(0, io.SEEK_END)
        except OSError:
            return
        summary_start = 0
        if file_size >= len(MAGIC) * 2 + _FOOTER_SIZE:
            stream.seek(file_size - len(MAGIC) - _FOOTER_SIZE)
            tail = self._read_exact(_FOOTER_SIZE + len(MAGIC))
            if tail[-len(MAGIC) :] == MAGIC and tail[0] == OP_FOOTER:
                summary_start = int(struct.unpack("<Q", tail[9:17])[0])
            else:
                summary_start = -1
        else:
            summary_start = -1
        if summary_start > 0:
            stream.seek(summary_start)
            raw = self._read_exact(file_size - len(MAGIC) - _FOOTER_SIZE - summary_start)
            metadata_offsets = self._parse_summary(raw)
            stale = False
            for offset, length in metadata_offsets:
                stream.seek(offset)
                record = self._read_exact(length)
                if len(record) == length and record[0] == OP_METADATA:
                    name, values = parse_metadata(record[9:])
                    self.metadata[name] = values
                else:
                    stale = True
            if not stale:
                return
            # A metadata index that does not point at metadata records (written by
            # imufdi <= 0.1.0 while chunks were still being compressed): scan instead.
        # No footer/summary (e.g. a truncated file): scan the top-level records for
        # metadata without decompressing chunks.
        stream.seek(len(MAGIC))
        position = len(MAGIC)
        while True:
            head = self._read_exact(9)
            if len(head) < 9:
                break
            opcode = head[0]
            length = int(struct.unpack("<Q", head[1:9])[0])
            if position + 9 + length > file_size:
                break
            if opcode == OP_METADATA:
                name, values = parse_metadata(self._read_exact(length))
                self.metadata[name] = values
            elif opcode in (OP_DATA_END, OP_FOOTER):
                break
            else:
                stream.seek(length, io.SEEK_CUR)
            position += 9 + length

    def _parse_summary(self, raw: bytes) -> list[tuple[int, int]]:
        buf = np.frombuffer(raw, dtype=np.uint8)
        starts, opcodes, lengths, _ = scan_records(buf)
        metadata_offsets = []
        for start, opcode, length in zip(starts.tolist(), opcodes.tolist(), lengths.tolist()):
            content = raw[start + 9 : start + 9 + length]
            if opcode == OP_SCHEMA:
                self._add_schema(parse_schema(content))
            elif opcode == OP_CHANNEL:
                self._add_channel(content)
            elif opcode == OP_METADATA_INDEX:
                offset, record_length = struct.unpack("<QQ", content[:16])
                metadata_offsets.append((int(offset), int(record_length)))
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
        return metadata_offsets

    # --- data ------------------------------------------------------------------------------

    def batches(self) -> Iterator[MessageBatch]:
        """Message batches in file order: one per chunk; un-chunked messages are grouped.

        The file is read once: calling this again continues where the last iteration
        stopped (batches handed back with :meth:`push_back` come first).
        """
        if self._iterator is None:
            self._iterator = self._read_batches()
        return self._with_pushback(self._iterator)

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

    def _read_batches(self) -> Iterator[MessageBatch]:
        loose: list[tuple[bytes, int]] = []
        position = len(MAGIC)
        while True:
            head = self._read_exact(9)
            if not head:
                self._problem(f"truncated MCAP: file ends at byte {position} without a footer")
                break
            if len(head) < 9:
                self._problem(f"truncated MCAP: record header cut at byte {position}")
                break
            opcode = head[0]
            length = int(struct.unpack("<Q", head[1:9])[0])
            if opcode == OP_FOOTER and length == 20:
                break
            if length > (1 << 40):
                self._problem(f"corrupt MCAP: record at byte {position} claims {length} bytes")
                break
            content = self._read_exact(length)
            if len(content) < length:
                self._problem(
                    f"truncated MCAP: record (opcode {opcode:#04x}) at byte {position} is cut"
                    f" after {len(content)} of {length} bytes; read up to the cut"
                )
                break
            position += 9 + length
            if opcode == OP_MESSAGE:
                loose.append((content, position - length))
                if len(loose) >= _LOOSE_BATCH:
                    yield self._loose_batch(loose)
                    loose = []
                continue
            if loose:
                yield self._loose_batch(loose)
                loose = []
            if opcode == OP_CHUNK:
                batch = self._chunk_batch(content, position - 9 - length)
                if batch is not None and len(batch):
                    yield batch
            elif opcode == OP_SCHEMA:
                self._add_schema(parse_schema(content))
            elif opcode == OP_CHANNEL:
                self._add_channel(content)
            elif opcode == OP_METADATA:
                name, values = parse_metadata(content)
                self.metadata[name] = values
            elif opcode == OP_DATA_END:
                break
        if loose:
            yield self._loose_batch(loose)

    def _loose_batch(self, loose: list[tuple[bytes, int]]) -> MessageBatch:
        joined = b"".join(content for content, _ in loose)
        buf = np.frombuffer(joined, dtype=np.uint8)
        lengths = np.array([len(content) for content, _ in loose], dtype=np.int64)
        starts = np.zeros(len(loose), np.int64)
        np.cumsum(lengths[:-1], out=starts[1:])
        return self._messages_from(buf, starts, lengths)

    def _messages_from(
        self, buf: np.ndarray, content_starts: np.ndarray, content_lengths: np.ndarray
    ) -> MessageBatch:
        bad = content_lengths < MESSAGE_FIXED_CONTENT
        if bool(bad.any()):
            self._problem(f"{int(bad.sum())} malformed Message record(s) skipped")
            content_starts = content_starts[~bad]
            content_lengths = content_lengths[~bad]
        fields = (
            gather_bytes(buf, content_starts, MESSAGE_FIXED_CONTENT)
            .reshape(-1)
            .view(_MESSAGE_FIELDS)
        )
        batch = MessageBatch(
            channel_id=fields["channel_id"].astype(np.uint16),
            sequence=fields["sequence"].astype(np.uint32),
            log_time=fields["log_time"].astype(np.int64),
            publish_time=fields["publish_time"].astype(np.int64),
            data=buf,
            offset=content_starts + MESSAGE_FIXED_CONTENT,
            length=content_lengths - MESSAGE_FIXED_CONTENT,
        )
        known = np.isin(batch.channel_id, np.fromiter(self.channels, dtype=np.int64))
        if not bool(known.all()):
            missing = sorted(set(np.unique(batch.channel_id[~known]).tolist()))
            self._problem(f"messages on unknown channel id(s) {missing} skipped")
            batch = batch.select(known)
        return batch

    def _chunk_batch(self, content: bytes, chunk_offset: int) -> MessageBatch | None:
        try:
            cur = _Cursor(content, "Chunk")
            cur.take(16)
            uncompressed_size = cur.u64()
            crc = cur.u32()
            compression = cur.string()
            records_length = cur.u64()
            payload = memoryview(content)[cur.pos : cur.pos + records_length]
            if len(payload) < records_length:
                raise McapInputError("records past the end of the chunk")
            raw = decompress(bytes(payload), compression, uncompressed_size)
        except McapInputError as err:
            self._problem(f"chunk at byte {chunk_offset} skipped: {err}")
            return None
        if self.validate_crcs and crc != 0 and zlib.crc32(raw) != crc:
            self._problem(f"chunk at byte {chunk_offset} skipped: CRC mismatch")
            return None
        buf = np.frombuffer(raw, dtype=np.uint8)
        starts, opcodes, lengths, end = scan_records(buf)
        if end != buf.shape[0]:
            self._problem(f"chunk at byte {chunk_offset}: malformed records after byte {end}")
        is_message = opcodes == OP_MESSAGE
        if not bool(is_message.all()):
            # Schema/Channel records inside the chunk must be known before its messages.
            for index in np.flatnonzero(~is_message).tolist():
                start = int(starts[index]) + 9
                body = raw[start : start + int(lengths[index])]
                if opcodes[index] == OP_SCHEMA:
                    self._add_schema(parse_schema(body))
                elif opcodes[index] == OP_CHANNEL:
                    self._add_channel(body)
            starts = starts[is_message]
            lengths = lengths[is_message]
        return self._messages_from(buf, starts + 9, lengths)
