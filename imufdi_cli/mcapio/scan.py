"""Parsing of MCAP records in bulk: Schema/Channel/Metadata contents, the record scan of a
decompressed chunk (repeating patterns checked with numpy), the batching of pending
message records, and their headers read into a :class:`MessageBatch`. Used by :class:`~imufdi_cli.mcapio.source.McapSource`."""

from __future__ import annotations

import struct

import numpy as np

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.records import (
    MESSAGE_FIXED_CONTENT,
    MessageBatch,
    SchemaInfo,
    gather_bytes,
)

_MESSAGE_FIELDS = np.dtype(
    [("channel_id", "<u2"), ("sequence", "<u4"), ("log_time", "<u8"), ("publish_time", "<u8")]
)
#: Record header: opcode u8, content length u64 LE.
_RECORD_HEAD = struct.Struct("<BQ")
#: Bytes of records checked at once by scan_records' vectorised pattern test.
_SCAN_BLOCK = 4 << 20
#: Messages (whole chunks, or un-chunked) are joined into batches of about this size: the
#: numpy work per batch (record scan, CDR decoding, alignment) is then paid per ~4 MiB,
#: about 20 % less reader CPU than 1 MiB batches on 16-IMU logs of 1 MiB chunks.
_BATCH_MESSAGES = 16384
_BATCH_BYTES = 4 << 20


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


def scan_records(
    buf: np.ndarray, allowed: frozenset[int] = frozenset(range(0x01, 0x10))
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Locate the records in a buffer of concatenated MCAP records.

    Parameters
    ----------
    buf : ndarray, uint8
    allowed : set of int
        Opcodes that may occur; the scan stops at any other (default: every MCAP opcode).

    Returns
    -------
    starts, opcodes, lengths : ndarray, shape (R,)
        Record start offsets, opcodes and content lengths.
    end : int
        Offset after the last complete record (``< len(buf)`` if the buffer is cut or
        holds a record with an opcode not allowed).

    Runs of a repeating record pattern are checked with numpy in blocks of at most
    ``_SCAN_BLOCK`` bytes, so the work memory is bounded whatever the buffer holds.
    """
    size = buf.shape[0]
    # (starts, opcodes, lengths) of each run found; a pattern run's heads were all
    # checked, so its opcodes and lengths are the pattern's, repeated
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def walked_part(walked: list[tuple[int, int, int]]) -> tuple[np.ndarray, ...]:
        return (
            np.array([w[0] for w in walked], np.int64),
            np.array([w[1] for w in walked], np.uint8),
            np.array([w[2] for w in walked], np.int64),
        )

    buf = np.ascontiguousarray(buf, dtype=np.uint8)
    unpack = _RECORD_HEAD.unpack_from  # a record head without numpy scalar indexing

    def head_of(at: int) -> tuple[int, int]:
        return unpack(buf, at)  # type: ignore[arg-type,no-any-return]

    pos = 0
    probe = 32
    while pos + 9 <= size:
        # Walk a few records one by one.
        walked: list[tuple[int, int, int]] = []
        p = pos
        while p + 9 <= size and len(walked) < probe:
            opcode, length = head_of(p)
            if p + 9 + length > size or opcode not in allowed:
                break
            walked.append((p, opcode, length))
            p += 9 + length
        if not walked:
            break
        if pos == 0 and len(walked) < probe:
            # A small buffer, walked whole: no pattern search, no second gather.
            starts, opcodes, lengths = walked_part(walked)
            return starts, opcodes, lengths, p
        # Find the shortest repeating pattern of (opcode, length) in the walked records.
        keys = [(op, ln) for _, op, ln in walked]
        period = 0
        for candidate in range(1, len(keys) // 2 + 1):
            if all(keys[i] == keys[i % candidate] for i in range(len(keys))):
                period = candidate
                break
        if period == 0 or len(walked) < probe:
            parts.append(walked_part(walked))  # type: ignore[arg-type]
            pos = p
            continue
        pattern_offsets = np.array([w[0] - pos for w in walked[:period]], dtype=np.int64)
        stride = sum(9 + ln for _, ln in keys[:period])
        n_periods = min((size - pos) // stride, max(1, _SCAN_BLOCK // stride))
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
            parts.append(walked_part(walked))  # type: ignore[arg-type]
            pos = p
            continue
        parts.append(
            (
                candidates[:n_good].reshape(-1),
                np.tile(expected_ops, n_good),
                np.tile(expected_len.astype(np.int64), n_good),
            )
        )
        pos = pos + n_good * stride
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.int64), 0
    if len(parts) == 1:
        return (*parts[0], pos)
    return (
        np.concatenate([part[0] for part in parts]),
        np.concatenate([part[1] for part in parts]),
        np.concatenate([part[2] for part in parts]),
        pos,
    )


class RecordPattern:
    """The repeating run of Message records a chunk was found to hold (e.g. one record
    of each of 16 IMU channels), remembered across chunks: a later chunk that continues
    it is checked in one vectorised pass (:meth:`match`) instead of being scanned anew.

    Parameters
    ----------
    lengths : sequence of int
        Content lengths of the P Message records of one period, in file order.
    """

    def __init__(self, lengths: list[int]) -> None:
        self.lengths = [int(n) for n in lengths]
        self.period = len(self.lengths)
        self.stride = sum(9 + n for n in self.lengths)
        self._rotations: dict[int, tuple[np.ndarray, np.ndarray, dict[int, int]]] = {}

    @classmethod
    def learn(cls, opcodes: np.ndarray, lengths: np.ndarray, size: int) -> RecordPattern | None:
        """The shortest period of a chunk made only of Message records (``opcodes``,
        ``lengths`` of all its records, ``size`` its record bytes), when the whole chunk
        follows it and holds at least two periods; else None."""
        n = lengths.shape[0]
        if n < 2 or not bool((opcodes == 0x05).all()):
            return None
        head = lengths[: min(n, 64)].tolist()
        for period in range(1, len(head) // 2 + 1):
            if all(head[i] == head[i % period] for i in range(len(head))):
                break
        else:
            return None
        reps = -(-n // period)
        if not bool((np.tile(lengths[:period], reps)[:n] == lengths).all()):
            return None
        pattern = cls(lengths[:period].tolist())
        return pattern if int(lengths.sum()) + 9 * n == size else None

    def phase_after(self, phase: int, n_records: int) -> int:
        return (phase + n_records) % self.period

    def _rotation(self, phase: int) -> tuple[np.ndarray, np.ndarray, dict[int, int]]:
        """(record offsets in a period, their content lengths, {bytes of the first j
        records: j}) of the pattern started at ``phase``."""
        known = self._rotations.get(phase)
        if known is None:
            lengths = np.array(self.lengths[phase:] + self.lengths[:phase], np.int64)
            cumulative = np.zeros(self.period + 1, np.int64)
            np.cumsum(lengths + 9, out=cumulative[1:])
            ends = {int(c): j for j, c in enumerate(cumulative[:-1].tolist())}
            known = (cumulative[:-1], lengths, ends)
            self._rotations[phase] = known
        return known

    def match(self, buf: np.ndarray, phase: int) -> tuple[np.ndarray, np.ndarray, int] | None:
        """The records of a chunk ``buf`` (uint8, contiguous) when they are whole Message
        records continuing this pattern from ``phase`` (tried first) or another phase whose
        record length fits the first record: (content starts, content lengths, the phase
        after the chunk), what :func:`scan_records` finds (its starts + 9, its lengths,
        opcodes all 0x05); None when the chunk does not follow the pattern (it is then
        scanned in full). Every record head (opcode and length) is checked, through one
        strided view per record of the period (no gather)."""
        size = buf.shape[0]
        if size < 9 or buf[0] != 0x05:
            return None
        first = int(buf[1:9].view("<u8")[0])
        phases = [phase] + [p for p in range(self.period) if p != phase]
        for start in phases:
            if self.lengths[start] != first:
                continue
            offsets, lengths, cumulative = self._rotation(start)
            n_full, rest = divmod(size, self.stride)
            tail = cumulative.get(rest)
            if tail is None:
                continue
            if not all(
                _heads_are(buf, offset, self.stride, n_full + (j < tail), length)
                for j, (offset, length) in enumerate(zip(offsets.tolist(), lengths.tolist()))
            ):
                continue
            rows = self.stride * np.arange(n_full, dtype=np.int64)
            starts = (rows[:, None] + (offsets + 9)).reshape(-1)
            record_lengths = (
                np.full(n_full, lengths[0]) if self.period == 1 else np.tile(lengths, n_full)
            )
            if tail:
                body = n_full * self.stride
                starts = np.concatenate([starts, body + 9 + offsets[:tail]])
                record_lengths = np.concatenate([record_lengths, lengths[:tail]])
            return starts, record_lengths, (start + starts.shape[0]) % self.period
        return None


def _heads_are(buf: np.ndarray, first: int, stride: int, count: int, length: int) -> bool:
    """Whether the ``count`` record heads at ``first``, ``first + stride``, ... of ``buf``
    are all a Message record's (opcode 0x05) with content length ``length`` (typed strided
    views, copied once: comparing unaligned views in place is several times slower)."""
    if count == 0:
        return True
    opcodes = np.ndarray((count,), np.uint8, buf, first, (stride,))
    lengths = np.ndarray((count,), "<u8", buf, first + 1, (stride,))
    return (
        np.count_nonzero(opcodes.copy() != 0x05) == 0
        and np.count_nonzero(lengths.copy() != length) == 0
    )


class _PendingMessages:
    """Message records waiting to become one batch: whole chunks' records and loose
    (un-chunked) Message records, in file order, in one buffer (chunks are decompressed
    straight into it: :meth:`slot`), handed out without joining."""

    def __init__(self) -> None:
        self.buffer: np.ndarray | None = None
        self.n_parts = 0
        self.starts: list[np.ndarray] = []
        self.lengths: list[np.ndarray] = []
        self.loose_starts: list[int] = []
        self.loose_lengths: list[int] = []
        self.n_bytes = 0
        self.n_messages = 0
        self.first_byte = -1
        self.last_byte = -1

    def _note(self, position: int, n_bytes: int, n_messages: int) -> None:
        if self.first_byte < 0:
            self.first_byte = position
        self.last_byte = position
        self.n_bytes += n_bytes
        self.n_messages += n_messages

    def _close_loose(self) -> None:
        if self.loose_starts:
            self.starts.append(np.array(self.loose_starts, np.int64))
            self.lengths.append(np.array(self.loose_lengths, np.int64))
            self.loose_starts, self.loose_lengths = [], []

    def slot(self, n: int) -> memoryview:
        """Writable room for ``n`` bytes after the pending ones (not counted until
        :meth:`add_chunk`); the buffer grows by copying only when a part does not fit."""
        end = self.n_bytes + n
        if self.buffer is None or end > self.buffer.shape[0]:
            capacity = max(end, _BATCH_BYTES + (2 << 20))
            if self.buffer is not None:
                capacity = max(capacity, 2 * self.buffer.shape[0])
            grown = np.empty(capacity, np.uint8)  # pages are touched only when written
            if self.buffer is not None:
                grown[: self.n_bytes] = self.buffer[: self.n_bytes]
            self.buffer = grown
        return memoryview(self.buffer)[self.n_bytes : end]  # type: ignore[arg-type]

    def add_loose(self, content: bytes, position: int) -> None:
        self.slot(len(content))[:] = content
        self.loose_starts.append(self.n_bytes)
        self.loose_lengths.append(len(content))
        self.n_parts += 1
        self._note(position, len(content), 1)

    def add_chunk(
        self,
        size: int,
        starts: np.ndarray | list[int],
        lengths: np.ndarray | list[int],
        position: int,
    ) -> None:
        """Count a chunk's ``size`` record bytes, already written at :meth:`slot`; starts
        and lengths of its Message records' contents relative to the chunk."""
        if isinstance(starts, list):  # a small chunk: kept in lists like loose messages
            shift = self.n_bytes
            self.loose_starts.extend(start + shift for start in starts)
            self.loose_lengths.extend(lengths)
        else:
            self._close_loose()
            self.starts.append(starts + self.n_bytes)
            self.lengths.append(np.asarray(lengths))
        self.n_parts += 1
        self._note(position, size, len(starts))

    def full(self) -> bool:
        return self.n_bytes >= _BATCH_BYTES or self.n_messages >= _BATCH_MESSAGES

    def where(self) -> str:
        if self.first_byte == self.last_byte:
            return f"record at byte {self.first_byte}"
        return f"records at bytes {self.first_byte}-{self.last_byte}"

    def take(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(buffer, content starts, content lengths) of everything pending; empties it."""
        self._close_loose()
        buf = np.zeros(0, np.uint8) if self.buffer is None else self.buffer[: self.n_bytes]
        starts = self.starts[0] if len(self.starts) == 1 else np.concatenate(self.starts)
        lengths = self.lengths[0] if len(self.lengths) == 1 else np.concatenate(self.lengths)
        self.__init__()  # type: ignore[misc]
        return buf, starts, lengths


def message_batch(
    buf: np.ndarray, content_starts: np.ndarray, content_lengths: np.ndarray
) -> MessageBatch:
    """The Message records whose contents start at ``content_starts`` (shape (n,), each of
    at least ``MESSAGE_FIXED_CONTENT`` bytes) in ``buf`` (uint8): their header fields read
    at once (a strided view when evenly spaced, else one gather); payloads stay in ``buf``."""
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

    return MessageBatch(
        channel_id=field("channel_id", np.uint16),
        sequence=field("sequence", np.uint32),
        log_time=field("log_time", np.int64),
        publish_time=field("publish_time", np.int64),
        data=buf,
        offset=content_starts + MESSAGE_FIXED_CONTENT,
        length=content_lengths - MESSAGE_FIXED_CONTENT,
    )


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
