"""MCAP record layer: message batches, schema/channel descriptions, record serialisation.

The MCAP format (https://mcap.dev/spec) is a magic, a Header record, a data section of
Schema, Channel, Metadata and Chunk records (each chunk holds Message records, followed by
one MessageIndex record per channel), a DataEnd record, a summary section (Schema, Channel,
Statistics, ChunkIndex, MetadataIndex, SummaryOffset records), a Footer and the magic again.
Every record is ``opcode u8 | length u64 LE | content``.

Chunk compression is in :mod:`~imufdi_cli.mcapio.compression`, the bulk writer in
:mod:`~imufdi_cli.mcapio.writer` (``McapWriter``, ``compress`` and ``decompress`` are still
importable from here).
"""

from __future__ import annotations

import itertools
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_ATTACHMENT = 0x09
OP_ATTACHMENT_INDEX = 0x0A
OP_STATISTICS = 0x0B
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F

#: Message record header: opcode, record length, channel id, sequence, log time, publish time.
MESSAGE_HEADER_DTYPE = np.dtype(
    [
        ("opcode", "u1"),
        ("record_length", "<u8"),
        ("channel_id", "<u2"),
        ("sequence", "<u4"),
        ("log_time", "<u8"),
        ("publish_time", "<u8"),
    ]
)
MESSAGE_HEADER_SIZE = MESSAGE_HEADER_DTYPE.itemsize  # 31 bytes
#: Bytes of a Message record's content before its payload.
MESSAGE_FIXED_CONTENT = MESSAGE_HEADER_SIZE - 9  # 22 bytes

COMPRESSIONS = ("zstd", "lz4", "none")


# --- batches of raw messages ------------------------------------------------------------


def gather_bytes(data: np.ndarray, positions: np.ndarray, n_bytes: int) -> np.ndarray:
    """Bytes ``data[p : p + n_bytes]`` for every p in ``positions``, shape (N, n_bytes), uint8.

    Uses a strided view (one copy, no index array) when positions are evenly spaced, which
    is the case for fixed-size messages interleaved regularly in a chunk; otherwise one
    ``V<n_bytes>`` element per position out of a sliding view (one memcpy per row).
    """
    positions = np.asarray(positions, dtype=np.int64)
    n = positions.shape[0]
    if n == 0:
        return np.zeros((0, n_bytes), dtype=np.uint8)
    first = int(positions[0])
    if n > 1:
        step = _even_step(data, positions, n_bytes)
        if step is not None:
            if data.flags.c_contiguous and n_bytes > 0:
                # one n_bytes-wide void element per row: numpy copies each with one memcpy
                # (a uint8 (n, n_bytes) strided copy goes byte by byte, 10-50x slower)
                rows = np.ndarray(
                    (n,), dtype=f"V{n_bytes}", buffer=data, offset=first, strides=(step,)
                )
                return rows.copy().view(np.uint8).reshape(n, n_bytes)
            view = np.lib.stride_tricks.as_strided(
                data[first:], shape=(n, n_bytes), strides=(step, 1), writeable=False
            )
            return np.array(view, copy=True)
    if data.flags.c_contiguous and 0 < n_bytes <= data.shape[0] and data.dtype == np.uint8:
        # A sliding (B - n_bytes + 1,) view of n_bytes-wide void elements, one per byte
        # offset: fancy indexing it copies each row with one memcpy, about 10x faster than
        # an (N, n_bytes) index array (positions past the end still raise IndexError).
        if int(positions.min()) >= 0:
            windows = np.ndarray(
                (data.shape[0] - n_bytes + 1,), dtype=f"V{n_bytes}", buffer=data, strides=(1,)
            )
            return windows[positions].view(np.uint8).reshape(n, n_bytes)
    index = positions[:, None] + np.arange(n_bytes, dtype=np.int64)[None, :]
    return data[index]


def _even_step(data: np.ndarray, positions: np.ndarray, n_bytes: int) -> int | None:
    """The constant step of ``positions`` (N >= 2, int64) when they are evenly spaced,
    increasing and every ``n_bytes`` from each lies inside ``data``; else None."""
    n = positions.shape[0]
    first = int(positions[0])
    step = int(positions[1] - positions[0])
    last = int(positions[-1])
    if (
        step > 0
        and last == first + (n - 1) * step
        and last + n_bytes <= data.shape[0]
        and first >= 0
        and (n == 2 or bool(np.all(np.diff(positions) == step)))
    ):
        return step
    return None


def byte_rows(data: np.ndarray, positions: np.ndarray, n_bytes: int) -> np.ndarray:
    """Bytes ``data[p : p + n_bytes]`` for every p in ``positions``, shape (N, n_bytes),
    uint8, like :func:`gather_bytes`, but a read-only strided view of ``data`` (no copy)
    when the positions are evenly spaced (the messages of one channel in a chunk that
    repeats a pattern of records). A view lives only as long as the bytes of ``data``
    stay as they are: copy what must outlive them."""
    positions = np.asarray(positions, dtype=np.int64)
    if (
        positions.shape[0] > 1
        and n_bytes > 0
        and data.dtype == np.uint8
        and data.flags.c_contiguous
        and _even_step(data, positions, n_bytes) is not None
    ):
        step = int(positions[1] - positions[0])
        return np.lib.stride_tricks.as_strided(
            data[int(positions[0]) :],
            shape=(positions.shape[0], n_bytes),
            strides=(step, 1),
            writeable=False,
        )
    return gather_bytes(data, positions, n_bytes)


@dataclass
class MessageBatch:
    """N raw MCAP messages whose payloads live in one byte buffer.

    Attributes
    ----------
    channel_id : ndarray, shape (N,), uint16
    sequence : ndarray, shape (N,), uint32
    log_time, publish_time : ndarray, shape (N,), int64
        Nanoseconds.
    data : ndarray, shape (B,), uint8
        Buffer holding the payloads (may hold other bytes too).
    offset, length : ndarray, shape (N,), int64
        Payload i is ``data[offset[i] : offset[i] + length[i]]``.
    """

    channel_id: np.ndarray
    sequence: np.ndarray
    log_time: np.ndarray
    publish_time: np.ndarray
    data: np.ndarray
    offset: np.ndarray
    length: np.ndarray

    def __len__(self) -> int:
        return int(self.channel_id.shape[0])

    @classmethod
    def empty(cls) -> MessageBatch:
        return cls(
            channel_id=np.zeros(0, np.uint16),
            sequence=np.zeros(0, np.uint32),
            log_time=np.zeros(0, np.int64),
            publish_time=np.zeros(0, np.int64),
            data=np.zeros(0, np.uint8),
            offset=np.zeros(0, np.int64),
            length=np.zeros(0, np.int64),
        )

    @classmethod
    def from_payloads(
        cls,
        channel_id: int | np.ndarray,
        log_time: np.ndarray,
        payloads: Sequence[bytes],
        *,
        publish_time: np.ndarray | None = None,
        sequence: np.ndarray | None = None,
    ) -> MessageBatch:
        """Batch from a list of payloads (joins them in one buffer)."""
        n = len(payloads)
        lengths = np.fromiter((len(p) for p in payloads), dtype=np.int64, count=n)
        offsets = np.zeros(n, np.int64)
        if n > 1:
            np.cumsum(lengths[:-1], out=offsets[1:])
        log = np.asarray(log_time, dtype=np.int64).reshape(n)
        return cls(
            channel_id=np.broadcast_to(np.asarray(channel_id, np.uint16), (n,)).copy(),
            sequence=(
                np.zeros(n, np.uint32) if sequence is None else np.asarray(sequence, np.uint32)
            ),
            log_time=log,
            publish_time=log.copy() if publish_time is None else np.asarray(publish_time, np.int64),
            data=np.frombuffer(b"".join(payloads), dtype=np.uint8),
            offset=offsets,
            length=lengths,
        )

    def payload(self, i: int) -> bytes:
        """Payload of message ``i`` as bytes."""
        start = int(self.offset[i])
        return self.data[start : start + int(self.length[i])].tobytes()

    def select(self, mask_or_indices: np.ndarray | Sequence[int] | slice) -> MessageBatch:
        """Subset of the messages (boolean mask, indices or slice); shares the buffer."""
        key = mask_or_indices
        if not isinstance(key, slice):
            key = np.asarray(key)
        return MessageBatch(
            channel_id=self.channel_id[key],
            sequence=self.sequence[key],
            log_time=self.log_time[key],
            publish_time=self.publish_time[key],
            data=self.data,
            offset=self.offset[key],
            length=self.length[key],
        )

    @staticmethod
    def concatenate(batches: list[MessageBatch]) -> MessageBatch:
        """Join batches in order (buffers are joined unless they are all the same object)."""
        batches = [b for b in batches if len(b)]
        if not batches:
            return MessageBatch.empty()
        if len(batches) == 1:
            return batches[0]
        same = all(b.data is batches[0].data for b in batches)
        if same:
            data = batches[0].data
            offsets = [b.offset for b in batches]
        else:
            starts = np.cumsum([0] + [b.data.shape[0] for b in batches[:-1]])
            data = np.concatenate([b.data for b in batches])
            offsets = [b.offset + int(s) for b, s in zip(batches, starts)]
        return MessageBatch(
            channel_id=np.concatenate([b.channel_id for b in batches]),
            sequence=np.concatenate([b.sequence for b in batches]),
            log_time=np.concatenate([b.log_time for b in batches]),
            publish_time=np.concatenate([b.publish_time for b in batches]),
            data=data,
            offset=np.concatenate(offsets),
            length=np.concatenate([b.length for b in batches]),
        )

    def channel_indices(self) -> list[tuple[int, np.ndarray]]:
        """``(channel id, indices)`` for each channel in the batch, ascending channel id;
        ``indices`` (int64, ascending) are the positions of that channel's messages.

        One stable sort of the channel ids (radix for uint16), not one mask per channel.
        """
        n = len(self)
        if n == 0:
            return []
        ids = self.channel_id
        first = ids[0]
        if bool(np.all(ids == first)):
            return [(int(first), np.arange(n, dtype=np.int64))]
        order = np.argsort(ids, kind="stable")
        ordered = ids[order]
        cuts = np.flatnonzero(ordered[1:] != ordered[:-1]) + 1
        bounds = [0, *cuts.tolist(), n]
        return [
            (int(ordered[a]), order[a:b].astype(np.int64, copy=False))
            for a, b in itertools.pairwise(bounds)
        ]

    def by_channel(self) -> list[tuple[int, MessageBatch]]:
        """``(channel id, that channel's messages in batch order)`` for each channel in the
        batch, ascending channel id (what ``np.unique(channel_id)`` and one ``select`` per
        id give); a batch of one channel is returned as it is, not copied."""
        groups = self.channel_indices()
        if len(groups) == 1:
            return [(groups[0][0], self)]
        return [(cid, self.select(index)) for cid, index in groups]

    def sorted_by_time(self) -> MessageBatch:
        """The same messages ordered by log time (stable)."""
        if len(self) < 2 or bool(np.all(np.diff(self.log_time) >= 0)):
            return self
        return self.select(np.argsort(self.log_time, kind="stable"))

    def payload_matrix(self) -> np.ndarray | None:
        """(N, L) uint8 copy of the payloads when they all have the same length L, else None."""
        if len(self) == 0:
            return np.zeros((0, 0), np.uint8)
        length = int(self.length[0])
        if not bool(np.all(self.length == length)):
            return None
        return gather_bytes(self.data, self.offset, length)


@dataclass(frozen=True)
class SchemaInfo:
    """An MCAP Schema record."""

    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class ChannelInfo:
    """An MCAP Channel record, with its schema (None for schema id 0)."""

    id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str] = field(default_factory=dict)
    schema: SchemaInfo | None = None


@dataclass(frozen=True)
class RawChunk:
    """An input Chunk record kept as read, for copying it verbatim (no recompression).

    Attributes
    ----------
    content : bytes
        The record's content (everything after opcode and length): times, sizes, CRC,
        compression name and the compressed records.
    start_time, end_time : int
        The chunk's message time range, ns (as the record says).
    uncompressed_size, compressed_size : int
        Bytes of its records before and after compression.
    compression : str
        ``"zstd"``, ``"lz4"`` or ``""`` (none).
    """

    content: bytes
    start_time: int
    end_time: int
    uncompressed_size: int
    compressed_size: int
    compression: str


# --- record serialisation helpers -------------------------------------------------------


def _string(text: str) -> bytes:
    raw = text.encode("utf-8")
    return struct.pack("<I", len(raw)) + raw


def _bytes32(raw: bytes) -> bytes:
    return struct.pack("<I", len(raw)) + raw


def _string_map(mapping: dict[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in sorted(mapping.items()))
    return _bytes32(body)


def _record(opcode: int, content: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(content)) + content


def schema_record(schema: SchemaInfo) -> bytes:
    return _record(
        OP_SCHEMA,
        struct.pack("<H", schema.id)
        + _string(schema.name)
        + _string(schema.encoding)
        + _bytes32(schema.data),
    )


def channel_record(channel_id: int, schema_id: int, topic: str, encoding: str, meta: dict) -> bytes:
    return _record(
        OP_CHANNEL,
        struct.pack("<HH", channel_id, schema_id)
        + _string(topic)
        + _string(encoding)
        + _string_map(meta),
    )


def message_headers(batch: MessageBatch) -> np.ndarray:
    """The fixed part of each message's record (opcode, record length, channel id,
    sequence, log and publish times), shape (N,), dtype ``MESSAGE_HEADER_DTYPE``."""
    header = np.empty(len(batch), dtype=MESSAGE_HEADER_DTYPE)
    header["opcode"] = OP_MESSAGE
    header["record_length"] = batch.length.astype(np.int64) + MESSAGE_FIXED_CONTENT
    header["channel_id"] = batch.channel_id
    header["sequence"] = batch.sequence
    header["log_time"] = batch.log_time.astype(np.uint64)
    header["publish_time"] = batch.publish_time.astype(np.uint64)
    return header


def build_message_records(batch: MessageBatch) -> tuple[np.ndarray, np.ndarray]:
    """Serialise a batch as consecutive Message records.

    Returns
    -------
    records : ndarray, shape (B,), uint8
    record_offsets : ndarray, shape (N,), int64
        Start of each record in ``records``.
    """
    n = len(batch)
    lengths = batch.length.astype(np.int64)
    header = message_headers(batch)
    header_bytes = header.view(np.uint8).reshape(n, MESSAGE_HEADER_SIZE)
    sizes = lengths + MESSAGE_HEADER_SIZE
    starts = np.zeros(n, np.int64)
    if n > 1:
        np.cumsum(sizes[:-1], out=starts[1:])
    total = int(sizes.sum()) if n else 0
    if n and bool(np.all(lengths == lengths[0])):
        length = int(lengths[0])
        out2d = np.empty((n, MESSAGE_HEADER_SIZE + length), dtype=np.uint8)
        out2d[:, :MESSAGE_HEADER_SIZE] = header_bytes
        out2d[:, MESSAGE_HEADER_SIZE:] = gather_bytes(batch.data, batch.offset, length)
        return out2d.reshape(-1), starts
    out = np.empty(total, dtype=np.uint8)
    if n == 0:
        return out, starts
    # Payloads of a few lengths (frame ids, statuses): per length L, one L-byte void element
    # per message copied from a sliding view of the source into one of the output (one
    # memcpy per record and part, no per-byte index arrays); the headers likewise.
    order = np.argsort(lengths, kind="stable")
    ordered = lengths[order]
    cuts = np.flatnonzero(ordered[1:] != ordered[:-1]) + 1
    if cuts.shape[0] + 1 > max(_FEW_LENGTHS, n // 16):
        return _join_message_records(batch, header, lengths, total), starts
    _copy_rows(out, starts, header.view(f"V{MESSAGE_HEADER_SIZE}"), MESSAGE_HEADER_SIZE)
    data = batch.data
    if not data.flags.c_contiguous or data.dtype != np.uint8:
        data = np.ascontiguousarray(data, dtype=np.uint8)
    bounds = [0, *cuts.tolist(), n]
    for a, b in itertools.pairwise(bounds):
        length = int(ordered[a])
        if length == 0:
            continue
        index = order[a:b]
        source = batch.offset[index]
        if int(source.min()) < 0 or int(source.max()) + length > data.shape[0]:
            raise IndexError("message payload outside the batch's buffer")
        rows = np.ndarray(
            (data.shape[0] - length + 1,), dtype=f"V{length}", buffer=data, strides=(1,)
        )[source]
        _copy_rows(out, starts[index] + MESSAGE_HEADER_SIZE, rows, length)
    return out, starts


#: Distinct payload lengths up to which a batch's records are copied per length (more, and
#: more than one per 16 messages: one ``bytearray.join`` of the records' parts).
_FEW_LENGTHS = 16


def _copy_rows(out: np.ndarray, at: np.ndarray, rows: np.ndarray, width: int) -> None:
    """Write the ``width``-byte void elements ``rows`` (shape (K,)) at byte offsets ``at``
    (shape (K,), int64) of the uint8 buffer ``out`` (the ranges do not overlap)."""
    windows = np.ndarray((out.shape[0] - width + 1,), dtype=f"V{width}", buffer=out, strides=(1,))
    windows[at] = rows


def _join_message_records(
    batch: MessageBatch, header: np.ndarray, lengths: np.ndarray, total: int
) -> np.ndarray:
    """Records of a batch of many payload lengths: header and payload of each message
    joined in order (one ``bytearray.join`` of memoryview slices), shape (total,), uint8."""
    heads = header.view(np.uint8).data.cast("B")
    data = np.ascontiguousarray(batch.data, dtype=np.uint8).data.cast("B")
    size = data.nbytes
    parts: list[memoryview] = []
    at = 0
    for start, length in zip(batch.offset.tolist(), lengths.tolist(), strict=True):
        if start < 0 or start + length > size:
            raise IndexError("message payload outside the batch's buffer")
        parts.append(heads[at : at + MESSAGE_HEADER_SIZE])
        parts.append(data[start : start + length])
        at += MESSAGE_HEADER_SIZE
    joined = bytearray().join(parts)
    assert len(joined) == total
    return np.frombuffer(joined, dtype=np.uint8)


def __getattr__(name: str) -> object:
    """``McapWriter``, ``compress``, ``decompress`` from their new modules (old import path;
    imported on first use, so this module imports neither)."""
    if name in ("compress", "decompress", "ZSTD_LEVEL"):
        from imufdi_cli.mcapio import compression

        return getattr(compression, name)
    if name in ("McapWriter", "COMPRESS_THREADS", "MAX_CHUNKS_IN_FLIGHT"):
        from imufdi_cli.mcapio import writer

        return getattr(writer, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
