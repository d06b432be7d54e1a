"""Parsing of MCAP records in bulk: Schema/Channel/Metadata contents, the record scan of a
decompressed chunk (repeating patterns checked with numpy), the batching of pending
message records, and their headers read into a :class:`MessageBatch`. Used by :class:`~imufdi_cli.mcapio.source.McapSource`."""

from __future__ import annotations

import struct
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

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
#: The same as a numpy record (packed, 9 bytes), for strided views of record heads.
_HEAD = np.dtype([("opcode", "u1"), ("length", "<u8")])
#: Bytes of records checked at once by scan_records' vectorised pattern test.
_SCAN_BLOCK = 4 << 20
#: Records scan_records walks one by one before it looks for a repeating pattern; while
#: the records it meets repeat none, it walks twice as many each time, up to the most.
_PROBE = 32
_PROBE_MAX = 256
#: A repeating run at the end of a walk without pattern at least this long starts the
#: next walk (scan_records).
_REGULAR_RUN = 8
#: Messages (whole chunks, or un-chunked) are joined into batches of about this size: the
#: numpy work per batch (record scan, CDR decoding, alignment) is then paid per ~4 MiB,
#: about 20 % less reader CPU than 1 MiB batches on 16-IMU logs of 1 MiB chunks.
_BATCH_MESSAGES = 16384
_BATCH_BYTES = 4 << 20
#: Size of a new batch buffer: a batch ends after the chunk that takes it past
#: _BATCH_BYTES, so most batches fit without growing it.
_BATCH_CAPACITY = _BATCH_BYTES + (2 << 20)


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
    # records walked one by one since the last pattern run, made into one part at once
    loose: list[tuple[int, int, int]] = []

    def flush_loose() -> None:
        if loose:
            parts.append(
                (
                    np.array([w[0] for w in loose], np.int64),
                    np.array([w[1] for w in loose], np.uint8),
                    np.array([w[2] for w in loose], np.int64),
                )
            )
            loose.clear()

    buf = np.ascontiguousarray(buf, dtype=np.uint8)
    unpack = _RECORD_HEAD.unpack_from  # a record head without numpy scalar indexing

    pos = 0
    probe = _PROBE
    while pos + 9 <= size:
        # Walk a few records one by one.
        walked: list[tuple[int, int, int]] = []
        p = pos
        while p + 9 <= size and len(walked) < probe:
            opcode, length = unpack(buf, p)  # type: ignore[arg-type]
            if p + 9 + length > size or opcode not in allowed:
                break
            walked.append((p, opcode, length))
            p += 9 + length
        if not walked:
            break
        if pos == 0 and len(walked) < probe:
            # A small buffer, walked whole: no pattern search, no second gather.
            loose.extend(walked)
            flush_loose()
            return (*parts[0], p)
        # Find the shortest repeating pattern of (opcode, length) in the walked records
        # (a period p repeats the first record at p: only those are tried).
        keys = [(op, ln) for _, op, ln in walked]
        period = 0
        for candidate in range(1, len(keys) // 2 + 1):
            if keys[candidate] == keys[0] and all(
                keys[i] == keys[i % candidate] for i in range(len(keys))
            ):
                period = candidate
                break
        n_good = 0
        if period and len(walked) == probe:
            offsets = [w[0] - pos for w in walked[:period]]
            stride = sum(9 + ln for _, ln in keys[:period])
            n_periods = min((size - pos) // stride, max(1, _SCAN_BLOCK // stride))
            # the heads of each record of the period in every repetition, read in place
            # through a strided view of (opcode, length) pairs
            good = np.ones(n_periods, bool)
            for offset, (op, ln) in zip(offsets, keys[:period]):
                heads = np.ndarray(
                    (n_periods,), _HEAD, buffer=buf, offset=pos + offset, strides=(stride,)
                )
                good &= (heads["opcode"] == op) & (heads["length"] == ln)
            n_good = int(np.argmin(good)) if not bool(good.all()) else n_periods
        if n_good == 0:
            # No pattern here (records of varied lengths): keep them, and start the next
            # walk where a regular run begins at the end of this one, if one does (its
            # pattern is then found at once).
            cut = _regular_tail(keys) if p < size else len(walked)
            loose.extend(walked[:cut])
            pos = walked[cut][0] if cut < len(walked) else p
            probe = _PROBE if cut < len(walked) else min(2 * probe, _PROBE_MAX)
            continue
        flush_loose()
        pattern_offsets = np.array(offsets, dtype=np.int64)
        starts = pos + stride * np.arange(n_good, dtype=np.int64)[:, None] + pattern_offsets
        parts.append(
            (
                starts.reshape(-1),
                np.tile(np.array([op for op, _ in keys[:period]], dtype=np.uint8), n_good),
                np.tile(np.array([ln for _, ln in keys[:period]], dtype=np.int64), n_good),
            )
        )
        pos = pos + n_good * stride
        probe = _PROBE
    flush_loose()
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


def _regular_tail(keys: list[tuple[int, int]]) -> int:
    """Where the run at the end of ``keys`` that repeats with a period of at most 4
    records begins, when it holds at least ``_REGULAR_RUN`` records and something else
    comes before it; else ``len(keys)``."""
    n = len(keys)
    best = n
    for period in range(1, 5):
        i = n - 1
        while i >= period and keys[i] == keys[i - period]:
            i -= 1
        begin = i - period + 1  # keys[begin:] repeat with this period
        if 0 < begin < best and n - begin >= _REGULAR_RUN:
            best = begin
    return best


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
        #: The one content length of every record of the period, or -1 (then each record
        #: of the period is checked through a view of its own).
        self.uniform = self.lengths[0] if len(set(self.lengths)) == 1 else -1
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
        if self.uniform >= 0:
            return self._match_uniform(buf, phase)
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

    def _match_uniform(
        self, buf: np.ndarray, phase: int
    ) -> tuple[np.ndarray, np.ndarray, int] | None:
        """:meth:`match` when every record of the period has the same length: the chunk
        is then ``size / (9 + length)`` records whatever the phase, and all their heads are
        checked through two strided views (the general check makes two per record of the
        period; same answer: a phase fits exactly when the first one does)."""
        length = self.uniform
        record = 9 + length
        n, rest = divmod(buf.shape[0], record)
        if rest or not _uniform_heads(buf, record, n, length):
            return None
        return self.uniform_run(n, phase)

    def uniform_run(self, n: int, phase: int) -> tuple[np.ndarray, np.ndarray, int]:
        """What :meth:`match` returns for a chunk of ``n`` Message records of this
        pattern's one length (their heads already checked, e.g. by
        :func:`uniform_message_heads` on the read-ahead thread)."""
        record = 9 + self.uniform
        starts = np.arange(9, n * record, record, dtype=np.int64)
        return starts, np.full(n, self.uniform, np.int64), (phase + n) % self.period


def _uniform_heads(buf: np.ndarray, record: int, count: int, length: int) -> bool:
    """Whether the ``count`` records of ``record`` bytes from the start of ``buf`` all have
    a Message record's head (opcode 0x05, content length ``length``): the 8 bytes at each
    record start (opcode and the length's 7 low bytes) and the length's high byte, through
    typed strided views copied once (``length`` < 2**56: the high byte is 0)."""
    low = np.ndarray((count,), "<u8", buf, 0, (record,))
    high = np.ndarray((count,), np.uint8, buf, 8, (record,))
    head = 0x05 | (length << 8)
    return np.count_nonzero(low.copy() != head) == 0 and np.count_nonzero(high.copy()) == 0


#: Message header fields of a run of Message records, as :func:`message_batch` reads
#: them: channel_id (uint16), sequence (uint32), log_time, publish_time (int64).
Heads = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class PayloadFields:
    """Payload fields the read-ahead thread reads from every message of a chunk of
    uniform Message records whose payloads are ``length`` bytes long: the first 16 bytes
    (as (n, 4) little-endian uint32 words) and float64 values at payload ``offsets``
    (each (n,), side by side as an (n, len(offsets)) array). Set by the Imu reader on its
    source once it knows the layout (:class:`~imufdi_cli.mcapio.imu_codec.FixedLayoutDecoder`),
    which then takes them instead of reading the payloads itself."""

    length: int
    offsets: tuple[int, ...]

    def read(self, buf: np.ndarray, length: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(words (n, 4) ``<u4``, values (n, k) float64) of the records of ``buf``, whole
        Message records of content ``length`` (checked by the caller); None when their
        payloads are not ``self.length`` long."""
        if length - MESSAGE_FIXED_CONTENT != self.length or self.length < 16:
            return None
        record = 9 + length
        n = buf.shape[0] // record
        first = 9 + MESSAGE_FIXED_CONTENT
        words = np.ndarray((n,), "V16", buf, first, (record,)).copy().view("<u4").reshape(-1, 4)
        values = np.empty((n, len(self.offsets)))

        def column(offset: int, dtype: str) -> np.ndarray:
            return np.ndarray((n,), dtype, buf, first + offset, (record,))

        fill_float_columns(values, column, self.offsets)
        return words, values


#: float64 values can be copied as raw little-endian bytes (CDR's, as the reader reads them)
_LITTLE_ENDIAN_HOST = sys.byteorder == "little"


def fill_float_columns(
    values: np.ndarray, column: Callable[[int, str], np.ndarray], offsets: Sequence[int]
) -> None:
    """``values[:, k]`` = the little-endian float64 at payload offset ``offsets[k]`` of
    every message, where ``column(offset, dtype)`` gives those (N,) values as ``dtype``
    (a strided view, or a gather); ``values`` is a C-contiguous (N, len(offsets)) float64
    array. Three columns k, k+1, k+2 (k a multiple of 3) read from consecutive offsets (a
    vector's x, y, z) are copied as one 24-byte element per message: the same bytes, about
    2.7x faster than three 8-byte strided copies (docs/performance.md,
    "Reading"). Other columns are copied to a contiguous array first: numpy copies unaligned
    strided values to a strided column several times slower than to a contiguous one."""
    k = 0
    triples = values.view("V24") if _LITTLE_ENDIAN_HOST and values.shape[1] % 3 == 0 else None
    while k < len(offsets):
        at = offsets[k]
        if (
            triples is not None
            and k % 3 == 0
            and k + 2 < len(offsets)
            and offsets[k + 1] == at + 8
            and offsets[k + 2] == at + 16
        ):
            triples[:, k // 3] = column(at, "V24")
            k += 3
        else:
            values[:, k] = column(at, "<f8").copy()
            k += 1


#: What was read of a chunk right after its decompression: its message heads, and the
#: payload fields asked for (their spec, words, values) or None
Digest = tuple[Heads, "tuple[PayloadFields, np.ndarray, np.ndarray] | None"]


def chunk_digest(buf: np.ndarray, length: int, fields: PayloadFields | None) -> Digest | None:
    """The message heads (:func:`uniform_message_heads`) and the payload ``fields`` of a
    chunk ``buf`` made only of whole Message records of content ``length``, else None. Read
    right after the chunk is decompressed (on the read-ahead thread, or in line while the
    chunk is still in the CPU's cache: 4-10 % less reader CPU than reading the same fields
    per 4 MiB batch)."""
    heads = uniform_message_heads(buf, length)
    if heads is None:
        return None
    read = None if fields is None else fields.read(buf, length)
    if fields is None or read is None:
        return heads, None
    return heads, (fields, *read)


def uniform_message_heads(buf: np.ndarray, length: int) -> Heads | None:
    """The header fields of the Message records of a chunk ``buf`` (uint8, contiguous)
    when it holds only whole Message records of content length ``length`` (what
    :meth:`RecordPattern.match` accepts for a period of records of that one length), else
    None. The read-ahead thread reads them while the caller decodes earlier chunks; the
    values are those :func:`message_batch` reads from the same records."""
    record = 9 + length
    n, rest = divmod(buf.shape[0], record)
    if (
        n == 0
        or rest
        or length < MESSAGE_FIXED_CONTENT
        or not _uniform_heads(buf, record, n, length)
    ):
        return None

    def field(name: str, dtype: type) -> np.ndarray:
        code, at = _MESSAGE_FIELDS.fields[name][:2]  # type: ignore[index]
        return np.ndarray((n,), code, buf, 9 + at, (record,)).astype(dtype)

    return (
        field("channel_id", np.uint16),
        field("sequence", np.uint32),
        field("log_time", np.int64),
        field("publish_time", np.int64),
    )


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
        #: The read-ahead buffer that ``buffer`` is a view of (from ``base`` on), or None
        #: when ``buffer`` is this object's own; nothing is written into such a buffer here.
        self.owner: np.ndarray | None = None
        self.base = 0
        self.n_parts = 0
        self.starts: list[np.ndarray] = []
        self.lengths: list[np.ndarray] = []
        self.loose_starts: list[int] = []
        self.loose_lengths: list[int] = []
        #: What the read-ahead thread read of every part (message heads, payload fields),
        #: while all parts have it; None once a part has not.
        self.digests: list[Digest] | None = []
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
        if self.buffer is None or end > self.buffer.shape[0] or self.owner is not None:
            # (a read-ahead buffer is never written here: the worker may be filling the
            # region after the pending bytes; they are copied to a buffer of our own)
            capacity = max(end, _BATCH_CAPACITY)
            if self.buffer is not None and self.owner is None:
                capacity = max(capacity, 2 * self.buffer.shape[0])
            grown = np.empty(capacity, np.uint8)  # pages are touched only when written
            if self.buffer is not None:
                grown[: self.n_bytes] = self.buffer[: self.n_bytes]
            self.buffer = grown
            self.owner = None
        return memoryview(self.buffer)[self.n_bytes : end]  # type: ignore[arg-type]

    def adopt(self, buffer: np.ndarray, offset: int, n: int) -> bool:
        """Whether ``n`` bytes decompressed by the read-ahead worker at ``offset`` of
        ``buffer`` already lie right after the pending bytes (nothing pending: the pending
        buffer becomes a view of ``buffer`` from ``offset`` on), to be counted by
        :meth:`add_chunk` without a copy; else they must be copied to :meth:`slot`."""
        if self.n_bytes == 0 and not self.loose_starts:
            self.buffer = buffer[offset:]
            self.owner, self.base = buffer, offset
            return n <= self.buffer.shape[0]
        return (
            self.owner is buffer
            and self.base + self.n_bytes == offset
            and self.n_bytes + n <= self.buffer.shape[0]  # type: ignore[union-attr]
        )

    def add_loose(self, content: bytes, position: int) -> None:
        self.digests = None
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
        digest: Digest | None = None,
    ) -> None:
        """Count a chunk's ``size`` record bytes, already written at :meth:`slot`; starts
        and lengths of its Message records' contents relative to the chunk; ``digest``:
        what the read-ahead thread read of them."""
        if digest is None or self.digests is None:
            self.digests = None
        else:
            self.digests.append(digest)
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

    def take(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, Digest | None]:
        """(buffer, content starts, content lengths, what the read-ahead thread read of
        them when it read every part (payload fields only when all have the same), else
        None) of everything pending; empties it."""
        self._close_loose()
        buf = np.zeros(0, np.uint8) if self.buffer is None else self.buffer[: self.n_bytes]
        starts = self.starts[0] if len(self.starts) == 1 else np.concatenate(self.starts)
        lengths = self.lengths[0] if len(self.lengths) == 1 else np.concatenate(self.lengths)
        digest = _join_digests(self.digests) if self.digests else None
        self.__init__()  # type: ignore[misc]
        return buf, starts, lengths, digest


def _join_digests(parts: list[Digest]) -> Digest:
    """The digests of consecutive parts as one."""
    if len(parts) == 1:
        return parts[0]
    heads: Heads = tuple(  # type: ignore[assignment]
        np.concatenate([part[0][k] for part in parts]) for k in range(4)
    )
    fields = [part[1] for part in parts]
    first = fields[0]
    if first is None or any(f is None or f[0] != first[0] for f in fields):
        return heads, None
    return heads, (
        first[0],
        np.concatenate([f[1] for f in fields]),  # type: ignore[index]
        np.concatenate([f[2] for f in fields]),  # type: ignore[index]
    )


def message_batch(
    buf: np.ndarray,
    content_starts: np.ndarray,
    content_lengths: np.ndarray,
    heads: Heads | None = None,
) -> MessageBatch:
    """The Message records whose contents start at ``content_starts`` (shape (n,), each of
    at least ``MESSAGE_FIXED_CONTENT`` bytes) in ``buf`` (uint8): their header fields read
    at once (a strided view when evenly spaced, else one gather; or ``heads``, when they
    were read already); payloads stay in ``buf``."""
    if heads is not None:
        channel_id, sequence, log_time, publish_time = heads
        return MessageBatch(
            channel_id=channel_id,
            sequence=sequence,
            log_time=log_time,
            publish_time=publish_time,
            data=buf,
            offset=content_starts + MESSAGE_FIXED_CONTENT,
            length=content_lengths - MESSAGE_FIXED_CONTENT,
        )
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
