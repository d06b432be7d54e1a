"""What a chunk is made of: the record sources callers queue (:class:`RecordSource`,
:class:`TemplatedSource`), the parts the writer keeps until a chunk fills, and what the
worker threads and the caller's thread make of a chunk's parts."""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from imufdi_cli.mcapio.records import RawChunk


@dataclass
class _RecordPart:
    """Ready Message records of one size: row i of ``records`` (N, R) is message i."""

    records: np.ndarray
    channel_id: np.ndarray
    log_time: np.ndarray

    def __len__(self) -> int:
        return int(self.records.shape[0])

    @property
    def nbytes(self) -> int:
        return int(self.records.shape[0] * self.records.shape[1])


class RecordSource(Protocol):
    """Fixed-size Message records that are built when their chunk is assembled (on a
    worker thread): :meth:`McapWriter.add_record_source`.

    ``fill`` must only read data the source owns (copies taken when it was made), since
    it runs after the call that queued it has returned.

    A source may also offer ``template_rows`` and ``fill_changing``
    (:class:`TemplatedSource`):
    then the worker thread keeps a buffer whose rows already hold the template's constant
    bytes, and only the bytes that change are written per chunk.
    """

    @property
    def record_size(self) -> int:
        """Bytes per record (header included)."""
        ...

    def __len__(self) -> int:
        """Number of records."""
        ...

    def fill(self, out: np.ndarray, start: int, stop: int) -> None:
        """Write records ``start..stop-1`` into ``out``, shape (stop - start, record_size),
        uint8, C-contiguous."""
        ...


class TemplatedSource(RecordSource, Protocol):
    """A :class:`RecordSource` whose record ``k`` is row ``k % P`` of ``template_rows``
    (P, R) except in bytes that ``fill_changing`` writes.

    ``template_rows`` must be the same array object (never modified) for every source
    sharing those constant bytes: a worker thread's primed buffer is reused while it is.
    """

    @property
    def template_rows(self) -> np.ndarray:
        """(P, record_size) uint8: the constant bytes of records with ``k % P == row``."""
        ...

    def fill_changing(self, out: np.ndarray, start: int, stop: int) -> None:
        """As ``fill``, into rows ``out`` whose row ``i`` already holds template row
        ``(start + i) % P``: every byte not written keeps its template value."""
        ...


@dataclass
class _SourcePart:
    """Records ``start..stop-1`` of a :class:`RecordSource`, built on a worker thread."""

    source: RecordSource
    start: int
    stop: int
    channel_id: np.ndarray
    log_time: np.ndarray

    def __len__(self) -> int:
        return self.stop - self.start

    @property
    def nbytes(self) -> int:
        return (self.stop - self.start) * int(self.source.record_size)


@dataclass
class _SerialPart:
    """Message records serialised by the caller's thread (variable sizes)."""

    records: np.ndarray  # (B,) uint8
    offsets: np.ndarray  # (N,) int64, start of each record in ``records``
    channel_id: np.ndarray
    log_time: np.ndarray

    @property
    def nbytes(self) -> int:
        return int(self.records.shape[0])


_ChunkPart = _RecordPart | _SourcePart | _SerialPart


@dataclass
class _BuiltChunk:
    """What a worker thread made of a chunk's parts."""

    payload: bytes  # compressed records
    crc: int  # CRC-32 of the uncompressed records
    uncompressed_size: int


@dataclass
class _ChunkKeys:
    """What the caller's thread makes of a chunk's parts while a worker builds it."""

    start_time: int
    end_time: int
    #: the chunk's MessageIndex records, one per channel, and each one's offset in them
    index_records: bytes
    index_offsets: dict[int, int]
    channel_counts: dict[int, int]
    message_count: int


@dataclass
class _ChunkJob:
    """A chunk being built on a worker thread (``future``), or an input chunk copied
    verbatim (``raw``), and its index made by the caller; written in call order."""

    future: Future[_BuiltChunk] | None
    keys: _ChunkKeys
    raw: RawChunk | None = None
