"""Streaming MCAP reader: records in file order, batches of whole chunks.

Records inside a decompressed chunk are located in bulk: a few records are walked one by
one, the repeating pattern of record lengths (e.g. 16 IMU channels interleaved) is found,
and the whole run of the pattern is checked with numpy at once. Message headers are then
read with one strided gather. Memory is bounded by one chunk.

The parts: the file's records (summary section, data-section record stream, schema and
channel registry) in :mod:`~imufdi_cli.mcapio.recordstream`, the base of
:class:`McapSource`; a Chunk record's unpacking (limit, decompression, CRC) in
:mod:`~imufdi_cli.mcapio.compression`; the record scan and message headers in
:mod:`~imufdi_cli.mcapio.scan`; the worker-thread read-ahead in
:mod:`~imufdi_cli.mcapio.readahead` (imported only when used). This module opens the
source and assembles the message batches.
"""

from __future__ import annotations

import os
import sys
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.compression import (
    _CHUNK_HEAD,
    _SMALL_CHUNK,
    _unpack_chunk,
)
from imufdi_cli.mcapio.limits import ReaderLimits
from imufdi_cli.mcapio.records import (
    MAGIC,
    MESSAGE_FIXED_CONTENT,
    OP_CHANNEL,
    OP_CHUNK,
    OP_FOOTER,
    OP_MESSAGE,
    OP_METADATA,
    OP_SCHEMA,
    ChannelInfo,
    MessageBatch,
    RawChunk,
    SchemaInfo,
)
from imufdi_cli.mcapio.recordstream import _RECORD_HEAD, RecordStream
from imufdi_cli.mcapio.scan import (
    Digest,
    PayloadFields,
    RecordPattern,
    _PendingMessages,
    chunk_digest,
    message_batch,
    parse_channel,
    parse_metadata,
    parse_schema,
    scan_records,
)

if TYPE_CHECKING:  # the read-ahead pool is imported when first used (start-up time)
    from concurrent.futures import ThreadPoolExecutor

    from imufdi_cli.mcapio.readahead import _Ahead

__all__ = ["McapSource", "parse_channel", "parse_metadata", "parse_schema", "scan_records"]

#: Records a chunk may hold.
_IN_CHUNK = frozenset((OP_SCHEMA, OP_CHANNEL, OP_MESSAGE))
#: Batches whose raw chunks are remembered for McapSource.raw_chunks (older ones are
#: forgotten and their messages re-encoded); each holds its ~4 MiB buffer until asked for.
_RAW_CHUNKS_KEPT = 8


class McapSource(RecordStream):
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
    (zstd, lz4 and the CRC release the GIL), straight into the buffers the caller's
    batches use; when the records of the chunks before were all Message records of one
    length (an IMU array's), the worker also checks every record head and reads the
    message heads and the payload fields the Imu reader asked for
    (:attr:`payload_fields`). Results, warnings and errors come in file order and are the
    same as without it. It moves about half of the CPU of reading off the calling thread
    and adds 5-15 % in all, but the two threads share the GIL, and on the 2-core
    build machine it gained no wall time that could be told from the load's noise
    (docs/performance.md): the default (``None``) is off, unless the environment variable
    ``IMUFDI_READ_AHEAD=1`` turns it on for every source.

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
    #: a message log time beyond int64 was reported (once per source)
    _time_warned = False
    #: Payload fields the read-ahead thread reads from chunks of uniform Message records
    #: (set by the Imu reader once it knows their layout; None: only the message heads).
    payload_fields: PayloadFields | None = None

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
        read_ahead: bool | None = None,
    ) -> None:
        self.strict = strict
        #: Decompress and CRC-check chunks of >= readahead._THREAD_CHUNK bytes on a worker
        #: thread (None until the file is open: see _auto_read_ahead).
        self.read_ahead = bool(read_ahead)
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
        self._chunk_channels: dict[int, np.ndarray] = {}
        self._chunk_spans: dict[int, tuple[int, int]] = {}
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
        if read_ahead is None:
            self.read_ahead = _default_read_ahead()

    # --- plumbing ------------------------------------------------------------------------

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

    def _prefetched(
        self,
    ) -> Iterator[tuple[tuple[int, int, bytes | None, int], _Ahead | None]]:
        """:meth:`_records`, each with the future of its chunk's records on the worker
        thread (or None): see :func:`~imufdi_cli.mcapio.readahead.read_ahead`."""
        records = self._records()
        if not self.read_ahead:  # nothing is read ahead: records as they come
            for record in records:
                yield record, None
            return
        from imufdi_cli.mcapio.readahead import read_ahead

        yield from read_ahead(self, records)

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
                if content is None:  # stepped over (skip_chunks_without)
                    continue
                part = self._chunk_part(content, here, future, pending)
                if part is not None:
                    if self.keep_raw_chunks:
                        raw = _raw_chunk(content) if self._chunk_clean else None
                        runs.append((raw, len(part[1]), pending.n_bytes))
                    pending.add_chunk(part[0], part[1], part[2], here, part[3])
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
        buf, starts, lengths, digest = pending.take()
        batch = self._messages_from(buf, starts, lengths, where, digest)
        return batch

    def _messages_from(
        self,
        buf: np.ndarray,
        content_starts: np.ndarray,
        content_lengths: np.ndarray,
        where: str,
        digest: Digest | None = None,
    ) -> MessageBatch:
        bad = content_lengths < MESSAGE_FIXED_CONTENT
        if bool(bad.any()):
            self._problem(f"{where}: {int(bad.sum())} malformed Message record(s) skipped")
            content_starts = content_starts[~bad]
            content_lengths = content_lengths[~bad]
            digest = None
        batch = message_batch(
            buf, content_starts, content_lengths, None if digest is None else digest[0]
        )
        if digest is not None and digest[1] is not None:
            # the payload fields read ahead, for the Imu decoder (a selection drops them)
            batch.payload_fields = digest[1]  # type: ignore[attr-defined]
        known = self._known_lookup()[batch.channel_id]
        if not bool(known.all()):
            missing = sorted(set(np.unique(batch.channel_id[~known]).tolist()))
            shown = ", ".join(str(c) for c in missing[:8]) + (" ..." if len(missing) > 8 else "")
            self._problem(
                f"{where}: {int((~known).sum())} message(s) on unknown channel id(s) {shown}"
                " skipped"
            )
            batch = batch.select(known)
        if not self._time_warned and len(batch) and int(batch.log_time.min()) < 0:
            self._time_warned = True  # once: the first such message names the problem
            first = int(np.flatnonzero(batch.log_time < 0)[0])
            channel = self.channels.get(int(batch.channel_id[first]))
            topic = channel.topic if channel is not None else "an unknown channel"
            self._problem(
                f"{where}: a message log time beyond 2^63 ns ({topic}:"
                f" {int(batch.log_time[first]) + (1 << 64)} ns); imufdi's time base is int64"
                " nanoseconds: detect and inject refuse this log (exit 3)"
            )
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
        pending: _PendingMessages | None = None,
    ) -> tuple[bytes | memoryview | None, Digest | None]:
        """The decompressed, CRC-checked records of a Chunk record (None if unusable),
        and what the read-ahead thread read of them (else None):
        large zstd chunks decompressed into ``pending.slot(size)`` (the batch buffer),
        others as bytes; ``future``: the same, computed ahead on the worker thread (into a
        read-ahead buffer, used in place when it follows the pending records, else copied
        to the slot)."""
        heads: Digest | None = None
        if future is not None and future[1] == os.getpid():
            raw, error, heads = future[0].result()
            place = future[2]
            if raw is not None and place is not None and not isinstance(raw, bytes):
                buffer, offset = place
                if pending is None:
                    raw = bytes(raw)
                elif not pending.adopt(buffer, offset, len(raw)):
                    target = pending.slot(len(raw))
                    target[:] = raw
                    raw = target
        else:  # in line (also in a forked child: the parent's worker never answers there)
            raw, error = _unpack_chunk(
                content,
                self.limits.max_chunk_bytes,
                self.validate_crcs,
                None if pending is None else pending.slot,
                not self.strict,
            )
            pattern = self._pattern
            if (
                raw is not None
                and pattern is not None
                and pattern.uniform >= 0
                and len(raw) > _SMALL_CHUNK
            ):
                # heads and fields read while the chunk is still in the cache
                heads = chunk_digest(
                    np.frombuffer(raw, np.uint8), pattern.uniform, self.payload_fields
                )
        if raw is None:
            self._problem(f"chunk at byte {chunk_offset} skipped: {error}")
        return raw, heads

    def _chunk_part(
        self,
        content: bytes,
        chunk_offset: int,
        future: _Ahead | None,
        pending: _PendingMessages,
    ) -> tuple[int, np.ndarray | list[int], np.ndarray | list[int], Digest | None] | None:
        """A chunk's records placed after the pending ones (``pending.slot``, to be counted
        by ``pending.add_chunk``): their size, the content starts and lengths of its
        Message records (its Schema and Channel records are registered), and their
        message heads when the read-ahead thread read them; None if the chunk is
        unusable."""
        self._chunk_clean = False
        raw, heads = self._chunk_records(content, chunk_offset, future, pending)
        if raw is None:
            return None
        size = len(raw)
        if isinstance(raw, bytes):  # not decompressed in place: copied there
            pending.slot(size)[:] = raw
        if size <= _SMALL_CHUNK:
            assert isinstance(raw, bytes)
            return (size, *self._small_chunk_part(raw, chunk_offset), None)
        buf = np.frombuffer(raw, dtype=np.uint8)
        pattern = self._pattern
        found: tuple[np.ndarray, np.ndarray, int] | None
        if heads is not None and pattern is not None and pattern.uniform >= 0:
            # read ahead as whole records of one length: the pattern's if it is the same
            n = heads[0][0].shape[0]
            if n * (9 + pattern.uniform) == size:
                found = pattern.uniform_run(n, self._phase)
            else:
                found, heads = pattern.match(buf, self._phase), None
        else:
            found = None if pattern is None else pattern.match(buf, self._phase)
            heads = None
        if found is not None:  # whole Message records only: the chunk is clean
            content_starts, lengths, self._phase = found
            self._chunk_clean = True
            return size, content_starts, lengths, heads
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
        return size, starts + 9, lengths, None

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


def _default_read_ahead() -> bool:
    """The default of ``read_ahead``: off, unless the environment variable
    ``IMUFDI_READ_AHEAD`` is ``1`` (then every source reads ahead; e.g. for long logs on a
    machine with a free core). Off by default because the two threads share the GIL: on
    the 2-core build machine the read-ahead reader took about as much wall time as the
    in-line one and more CPU (docs/performance.md, "Reading")."""
    return os.environ.get("IMUFDI_READ_AHEAD", "").strip() == "1"


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
