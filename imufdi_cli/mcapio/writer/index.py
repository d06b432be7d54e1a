"""The writer's index records: MessageIndex records of a chunk, the ChunkIndex entry noted
for each chunk written, and the summary section (Schema, Channel, Statistics, ChunkIndex,
MetadataIndex, SummaryOffset records) with the Footer that ends the file."""

from __future__ import annotations

import struct
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from imufdi_cli.mcapio.compression import crc32
from imufdi_cli.mcapio.records import (
    OP_CHANNEL,
    OP_CHUNK_INDEX,
    OP_FOOTER,
    OP_MESSAGE_INDEX,
    OP_METADATA_INDEX,
    OP_SCHEMA,
    OP_STATISTICS,
    OP_SUMMARY_OFFSET,
    ChannelInfo,
    SchemaInfo,
    _bytes32,
    _record,
    _string,
    channel_record,
    schema_record,
)


@dataclass
class _ChunkIndexEntry:
    start_time: int
    end_time: int
    chunk_offset: int
    chunk_length: int
    message_index_offsets: dict[int, int]
    message_index_length: int
    compression: str
    compressed_size: int
    uncompressed_size: int


#: The fixed part of a MessageIndex record: opcode, record length, channel id, bytes of
#: entries (each entry: log time u64, record offset u64).
_MESSAGE_INDEX_HEAD = np.dtype(
    {
        "names": ["opcode", "record_length", "channel_id", "entries_length"],
        "formats": ["u1", "<u8", "<u2", "<u4"],
        "offsets": [0, 1, 9, 11],
        "itemsize": 15,
    }
)


def message_index_records(
    channel_ids: np.ndarray, log_time: np.ndarray, record_offsets: np.ndarray
) -> tuple[bytes, dict[int, int], dict[int, int]]:
    """The MessageIndex records of one chunk: one per channel, channels in increasing
    order, entries (log time, record offset) sorted by log time (ties in chunk order).

    Parameters
    ----------
    channel_ids : ndarray, shape (N,), unsigned
    log_time : ndarray, shape (N,), int64, ns
    record_offsets : ndarray, shape (N,), int64
        Offset of each message's record in the chunk's uncompressed records.

    Returns
    -------
    records : bytes
    offsets : dict
        Channel id -> offset of its MessageIndex record in ``records``.
    counts : dict
        Channel id -> number of its messages in the chunk.

    What depends on the channel ids alone (their sort, the record heads, the offsets) is
    kept for the last sequences met (:func:`_index_layout`): an array logger's chunks
    repeat a few, and a chunk then costs two gathers and a join.
    """
    channel_ids = np.asarray(channel_ids)
    log_time = np.asarray(log_time, np.int64)
    n = int(channel_ids.shape[0])
    layout = _index_layout(channel_ids)
    if n < 2 or bool(np.all(log_time[1:] >= log_time[:-1])):
        # already in time order: a stable sort by channel is the (channel, time) sort
        order = layout.order
    else:
        order = np.lexsort((log_time, channel_ids))
    entries = np.empty((n, 2), "<u8")
    entries[:, 0] = log_time[order]
    entries[:, 1] = np.asarray(record_offsets, np.int64)[order]
    bodies = entries.view(np.uint8).reshape(-1).data
    pieces: list[bytes | memoryview] = []
    for head, (start, stop) in zip(layout.heads, layout.bounds):
        pieces.append(head)
        pieces.append(bodies[start:stop])
    return b"".join(pieces), dict(layout.offsets), dict(layout.counts)


@dataclass(frozen=True)
class _IndexLayout:
    """What the MessageIndex records of a chunk owe to its channel ids alone."""

    #: (N,) the stable sort of the channel ids: the (channel, time) order of a chunk in
    #: time order
    order: np.ndarray
    #: the 15-byte head of each channel's record, channels in increasing order
    heads: list[bytes]
    #: byte range of each channel's entries in the (N, 2) entries sorted by channel
    bounds: list[tuple[int, int]]
    offsets: dict[int, int]
    counts: dict[int, int]


#: Per thread: the layouts of the last channel id sequences met (an array logger's chunks
#: repeat a few: one per phase of the sample at which a chunk starts, and the last one).
_LAYOUTS = threading.local()
_LAYOUTS_KEPT = 40


def _index_layout(channel_ids: np.ndarray) -> _IndexLayout:
    """The layout of the MessageIndex records of a chunk with these channel ids (N,),
    remembered for the next chunks with the same sequence."""
    key = (channel_ids.dtype.str, channel_ids.tobytes())
    cache: OrderedDict[tuple[str, bytes], _IndexLayout] | None = getattr(_LAYOUTS, "cache", None)
    if cache is None:
        cache = _LAYOUTS.cache = OrderedDict()
    layout = cache.get(key)
    if layout is not None:
        cache.move_to_end(key)
        return layout
    per_channel = np.bincount(channel_ids.astype(np.intp))
    present = np.flatnonzero(per_channel)
    sizes = per_channel[present].astype(np.int64)
    firsts = np.zeros(present.shape[0], np.int64)
    np.cumsum(sizes[:-1], out=firsts[1:])
    head = np.empty(present.shape[0], _MESSAGE_INDEX_HEAD)
    head["opcode"] = OP_MESSAGE_INDEX
    head["record_length"] = 2 + 4 + 16 * sizes
    head["channel_id"] = present
    head["entries_length"] = 16 * sizes
    raw = head.tobytes()
    starts = 15 * np.arange(present.shape[0], dtype=np.int64) + 16 * firsts
    ids = present.tolist()
    layout = _IndexLayout(
        order=np.argsort(channel_ids, kind="stable"),
        heads=[raw[15 * g : 15 * g + 15] for g in range(len(ids))],
        bounds=[
            (16 * first, 16 * (first + size))
            for first, size in zip(firsts.tolist(), sizes.tolist())
        ],
        offsets=dict(zip(ids, starts.tolist())),
        counts=dict(zip(ids, sizes.tolist())),
    )
    cache[key] = layout
    if len(cache) > _LAYOUTS_KEPT:
        cache.popitem(last=False)
    return layout


def _chunk_index_record(entry: _ChunkIndexEntry) -> bytes:
    """The ChunkIndex record of one chunk written."""
    pairs = sorted(entry.message_index_offsets.items())
    offsets = struct.pack("<" + "HQ" * len(pairs), *[value for pair in pairs for value in pair])
    return _record(
        OP_CHUNK_INDEX,
        struct.pack(
            "<QQQQ",
            entry.start_time,
            entry.end_time,
            entry.chunk_offset,
            entry.chunk_length,
        )
        + _bytes32(offsets)
        + struct.pack("<Q", entry.message_index_length)
        + _string(entry.compression)
        + struct.pack("<QQ", entry.compressed_size, entry.uncompressed_size),
    )


def _statistics_record(
    *,
    message_count: int,
    schema_count: int,
    channel_count: int,
    metadata_count: int,
    chunk_count: int,
    start_time: int | None,
    end_time: int | None,
    channel_counts: dict[int, int],
) -> bytes:
    """The Statistics record (no attachments; times 0 when no message was written)."""
    counts = b"".join(struct.pack("<HQ", cid, n) for cid, n in sorted(channel_counts.items()))
    statistics = struct.pack(
        "<QHIIIIQQ",
        message_count,
        schema_count,
        channel_count,
        0,
        metadata_count,
        chunk_count,
        start_time or 0,
        end_time or 0,
    ) + _bytes32(counts)
    return _record(OP_STATISTICS, statistics)


def summary_section(
    summary_start: int,
    *,
    schemas: dict[int, SchemaInfo],
    channels: dict[int, ChannelInfo],
    channel_schema: dict[int, int],
    chunk_index: list[bytes],
    metadata_index: list[tuple[int, int, str]],
    statistics: bytes,
) -> tuple[bytes, bytes]:
    """The summary section and the Footer record of a file whose summary starts at byte
    ``summary_start``.

    Parameters
    ----------
    summary_start : int
        Offset of the summary section in the file (just after the DataEnd record).
    schemas, channels : dict
        Id -> the schemas and channels registered (written in increasing id order).
    channel_schema : dict
        Channel id -> its schema id (0: none).
    chunk_index : list of bytes
        The ChunkIndex record of each chunk written (:func:`_chunk_index_record`), in
        file order.
    metadata_index : list of (offset, length, name)
        One entry per Metadata record written.
    statistics : bytes
        The Statistics record (:func:`_statistics_record`).

    Returns
    -------
    summary : bytes
        Schema, Channel, Statistics, ChunkIndex, MetadataIndex records (each group only if
        not empty), then one SummaryOffset record per group.
    footer : bytes
        The Footer record (summary start, summary offset start, CRC-32 of the summary and
        the footer's own fields).
    """
    groups: list[tuple[int, int, int]] = []
    parts: list[bytes] = []
    offset = summary_start

    def group(opcode: int, records: list[bytes]) -> None:
        nonlocal offset
        if not records:
            return
        body = b"".join(records)
        groups.append((opcode, offset, len(body)))
        parts.append(body)
        offset += len(body)

    group(OP_SCHEMA, [schema_record(s) for _, s in sorted(schemas.items())])
    group(
        OP_CHANNEL,
        [
            channel_record(c.id, channel_schema[c.id], c.topic, c.message_encoding, c.metadata)
            for _, c in sorted(channels.items())
        ],
    )
    group(OP_STATISTICS, [statistics])
    group(OP_CHUNK_INDEX, chunk_index)
    group(
        OP_METADATA_INDEX,
        [
            _record(OP_METADATA_INDEX, struct.pack("<QQ", off, length) + _string(name))
            for off, length, name in metadata_index
        ],
    )
    summary_offset_start = offset
    parts.append(
        b"".join(
            _record(OP_SUMMARY_OFFSET, struct.pack("<BQQ", op, start, length))
            for op, start, length in groups
        )
    )
    summary = b"".join(parts)
    footer_head = struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, summary_offset_start)
    summary_crc = crc32(footer_head, crc32(summary))
    return summary, footer_head + struct.pack("<I", summary_crc)
