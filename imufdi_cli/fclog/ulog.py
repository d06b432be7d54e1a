"""A streaming reader of PX4 ULog files (``.ulg``), vectorised per chunk.

The format (PX4 "ULog file format" specification) is self-describing: a 16-byte header
(magic ``ULog\\x01\\x12\\x35``, version, start time in µs), a definitions section (``F``
formats, ``I``/``M`` info, ``P``/``Q`` parameters, ``B`` flag bits) and a data section
(``A`` subscriptions, ``D`` data, ``O`` dropouts, ``S`` sync, ``L``/``C`` log strings,
``P`` parameter changes, ``R`` unsubscriptions). Every message is ``u16 size | u8 type |
size bytes``, little-endian.

:class:`ULogFile` parses the header and the definitions when opened, then
:meth:`ULogFile.read` streams the data section in chunks: one Python step per message
header (the size chain cannot be followed otherwise), then, per subscription wanted, one
gather of its payloads and one view as a numpy structured array with only the fields
asked for. Memory is bounded by the chunk size, whatever the log length.

Corruption (a header of unknown type, size 0, a data message of an unknown subscription
or of an impossible size) is counted and skipped: the reader resynchronises on the next
sync message (``S``, 8 magic bytes) when the log has them, else one byte further on, as
pyulog does. Appended data (``B`` flag bits, incompat bit 0): each stretch is read up to
its offset, then reading resumes at the offset.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, BinaryIO, Final

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from imufdi_cli.errors import FlightLogError

MAGIC: Final[bytes] = b"ULog\x01\x12\x35"
SYNC: Final[bytes] = b"\x2f\x73\x13\x20\x25\x0c\xbb\x12"
HEADER_SIZE: Final[int] = 16

#: ULog primitive type -> numpy dtype (little-endian)
PRIMITIVES: Final[dict[str, str]] = {
    "int8_t": "i1",
    "uint8_t": "u1",
    "int16_t": "<i2",
    "uint16_t": "<u2",
    "int32_t": "<i4",
    "uint32_t": "<u4",
    "int64_t": "<i8",
    "uint64_t": "<u8",
    "float": "<f4",
    "double": "<f8",
    "bool": "u1",
    "char": "S1",
}
_DATA_TYPES: Final[frozenset[int]] = frozenset(map(ord, "ADILMOPQRSC"))
#: largest message a PX4 logger writes is well under this (pyulog uses the same bound)
_MAX_MESSAGE: Final[int] = 10000


@dataclass(frozen=True)
class FormatField:
    """One field of a ``F`` format: ``type``, array length (0: scalar) and name."""

    type: str
    count: int
    name: str


@dataclass
class Subscription:
    """An ``A`` message: a topic instance logged under ``msg_id``."""

    msg_id: int
    name: str
    multi_id: int


@dataclass
class ULogCounts:
    """What the data section held besides the wanted data.

    Attributes
    ----------
    messages : int
        Messages read (every type).
    corrupt_bytes : int
        Bytes skipped while resynchronising after a corrupt header.
    corrupt_messages : int
        Data messages dropped: unknown subscription or a size that does not fit its format.
    dropouts : int
        ``O`` messages (the logger lost data: its buffer was full).
    dropout_ms : int
        Their total duration, milliseconds.
    truncated : bool
        The last message is cut by the end of the file.
    """

    messages: int = 0
    corrupt_bytes: int = 0
    corrupt_messages: int = 0
    dropouts: int = 0
    dropout_ms: int = 0
    truncated: bool = False


@dataclass
class ULogChunk:
    """The wanted data of one chunk of the data section.

    ``data[(topic, multi_id)]`` is a structured array (K,) with the fields asked for, in
    file order; ``parameters`` the ``P`` changes met in the chunk, (name, value) in order.
    """

    data: dict[tuple[str, int], np.ndarray] = field(default_factory=dict)
    parameters: list[tuple[str, Any]] = field(default_factory=list)


def _string(raw: bytes) -> str:
    return raw.decode("utf-8", errors="replace")


def parse_format(text: str) -> tuple[str, list[FormatField]]:
    """``"name:type field;type[3] field2;"`` -> (name, fields)."""
    name, _, body = text.partition(":")
    fields = []
    for item in body.split(";"):
        item = item.strip()
        if not item:
            continue
        type_text, _, field_name = item.partition(" ")
        count = 0
        if type_text.endswith("]") and "[" in type_text:
            type_text, _, size = type_text[:-1].partition("[")
            count = int(size)
        fields.append(FormatField(type_text, count, field_name.strip()))
    return name.strip(), fields


def _value(type_text: str, raw: bytes) -> Any:
    """The value of an ``I``/``P`` message: a number, a string (``char[n]``) or bytes."""
    if type_text.startswith("char["):
        return _string(raw)
    code = PRIMITIVES.get(type_text)
    if code is not None and code != "S1" and np.dtype(code).itemsize == len(raw):
        return np.frombuffer(raw, dtype=code)[0].item()
    return bytes(raw)


class ULogFile:
    """A ULog file: header and definitions parsed on opening, data streamed by :meth:`read`.

    Parameters
    ----------
    path : str or PathLike
        The ``.ulg`` file (read twice by ingest: once to scan, once to convert).

    Attributes
    ----------
    version : int
        File format version (the header's byte 7).
    start_us : int
        Logger start, µs since boot.
    formats : dict
        Message name -> list of :class:`FormatField`.
    info : dict
        ``I`` info values (``sys_name``, ``ver_hw``, ``ver_sw``, ...).
    parameters : dict
        Initial parameter values (``P`` messages of the definitions section).
    appended_offsets : list of int
        File offsets of appended data (``B`` flag bits), empty for most logs.
    has_sync : bool
        The data section holds sync messages (learnt while reading).

    Raises
    ------
    FlightLogError
        Not a ULog, cut inside the header or the definitions, or unreadable.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = os.fspath(path)
        self.formats: dict[str, list[FormatField]] = {}
        self.info: dict[str, Any] = {}
        self.parameters: dict[str, Any] = {}
        self.appended_offsets: list[int] = []
        self.has_sync = False
        try:
            with open(self.path, "rb") as handle:
                self._read_definitions(handle)
        except OSError as err:
            raise FlightLogError(f"cannot read {self.path}: {err.strerror or err}") from err

    # --- definitions ----------------------------------------------------------------

    def _read_definitions(self, handle: BinaryIO) -> None:
        header = handle.read(HEADER_SIZE)
        if len(header) < HEADER_SIZE or header[:7] != MAGIC:
            raise FlightLogError(
                f"{self.path}: not a PX4 ULog (no 'ULog' magic in the first 16 bytes)"
            )
        self.version = header[7]
        self.start_us = int.from_bytes(header[8:16], "little")
        position = HEADER_SIZE
        first = True
        while True:
            head = handle.read(3)
            if len(head) < 3:
                raise FlightLogError(f"{self.path}: the log ends inside its definitions")
            size, kind = head[0] | head[1] << 8, head[2]
            if kind in (ord("A"), ord("D")):
                break  # the data section starts here
            payload = handle.read(size)
            if len(payload) < size:
                raise FlightLogError(f"{self.path}: the log ends inside its definitions")
            if kind == ord("B") and first:
                if size >= 40:
                    offsets = struct.unpack_from("<3Q", payload, 16)
                    if payload[8] & 1:
                        self.appended_offsets = [o for o in offsets if o]
            elif kind == ord("F"):
                name, fields = parse_format(_string(payload))
                self.formats[name] = fields
            elif kind in (ord("I"), ord("P"), ord("M")):
                key, value = self._key_value(payload[1:] if kind == ord("M") else payload)
                if key and kind == ord("I"):
                    self.info[key] = value
                elif key and kind == ord("P"):
                    self.parameters[key] = value
            elif kind == ord("Q"):
                pass  # parameter defaults: not needed
            elif size == 0 or kind not in _DATA_TYPES | {ord("B"), ord("F")}:
                raise FlightLogError(
                    f"{self.path}: corrupt ULog definitions at byte {position}"
                    f" (message type {kind}, size {size})"
                )
            position += 3 + size
            first = False
        self.data_start = position

    @staticmethod
    def _key_value(payload: bytes) -> tuple[str, Any]:
        if not payload:
            return "", None
        length = payload[0]
        type_key = _string(payload[1 : 1 + length])
        type_text, _, key = type_key.partition(" ")
        return key, _value(type_text, payload[1 + length :])

    # --- layouts --------------------------------------------------------------------

    def type_size(self, type_text: str) -> int:
        """Bytes of a primitive or nested (format) type."""
        code = PRIMITIVES.get(type_text)
        if code is not None:
            return np.dtype(code).itemsize
        fields = self.formats.get(type_text)
        if fields is None:
            raise FlightLogError(f"{self.path}: format of type {type_text!r} is not defined")
        return sum(self.type_size(f.type) * max(f.count, 1) for f in fields)

    def field_layout(self, topic: str) -> dict[str, tuple[str, int, int]]:
        """Top-level field name -> (type, array length, byte offset) of a topic's format."""
        fields = self.formats.get(topic)
        if fields is None:
            raise FlightLogError(f"{self.path}: no format for topic {topic!r}")
        layout = {}
        offset = 0
        for item in fields:
            layout[item.name] = (item.type, item.count, offset)
            offset += self.type_size(item.type) * max(item.count, 1)
        return layout

    def dtype(self, topic: str, names: Sequence[str]) -> tuple[np.dtype, int]:
        """A structured dtype with the fields ``names`` (those present) at their offsets,
        and the smallest payload size that holds them."""
        layout = self.field_layout(topic)
        names_out: list[str] = []
        formats: list[Any] = []
        offsets: list[int] = []
        end = 0
        for name in names:
            if name not in layout:
                continue
            type_text, count, offset = layout[name]
            code = PRIMITIVES.get(type_text)
            if code is None:
                continue  # nested types are not read as fields
            names_out.append(name)
            formats.append((code, (count,)) if count else code)
            offsets.append(offset)
            end = max(end, offset + np.dtype(code).itemsize * max(count, 1))
        dtype = np.dtype(
            {"names": names_out, "formats": formats, "offsets": offsets, "itemsize": max(end, 1)}
        )
        return dtype, end

    # --- data -----------------------------------------------------------------------

    def read(
        self,
        wanted: Mapping[str, Sequence[str]],
        *,
        chunk_size: int = 4 << 20,
        counts: ULogCounts | None = None,
        progress: Any = None,
    ) -> Iterator[ULogChunk]:
        """Stream the data section: the fields ``wanted[topic]`` of every instance of the
        topics wanted, chunk by chunk (``counts``: filled in while reading)."""
        counts = counts if counts is not None else ULogCounts()
        subscriptions: dict[int, Subscription] = {}
        decoders: dict[int, tuple[np.dtype, int, int]] = {}  # msg_id -> dtype, min, max size
        size_total = os.path.getsize(self.path)
        stops = [*self.appended_offsets, None]
        with open(self.path, "rb") as handle:
            handle.seek(self.data_start)
            position = self.data_start
            carry = b""
            for stop in stops:
                # one stretch: up to the next appended offset (or the end of the file)
                while True:
                    want = chunk_size if stop is None else min(chunk_size, stop - position)
                    block = handle.read(max(want, 0)) if want > 0 else b""
                    position += len(block)
                    final = not block
                    buffer = carry + block
                    chunk, used = self._walk(buffer, final, wanted, subscriptions, decoders, counts)
                    carry = buffer[used:]
                    if progress is not None:
                        progress(float(position), float(size_total))
                    if chunk.data or chunk.parameters:
                        yield chunk
                    if final:
                        break
                if stop is not None:
                    handle.seek(stop)
                    position = stop
                    carry = b""

    def _walk(
        self,
        buffer: bytes,
        final: bool,
        wanted: Mapping[str, Sequence[str]],
        subscriptions: dict[int, Subscription],
        decoders: dict[int, tuple[np.dtype, int, int]],
        counts: ULogCounts,
    ) -> tuple[ULogChunk, int]:
        """The messages of ``buffer`` that are complete: wanted data and parameter changes,
        and the number of bytes used (the rest is carried to the next chunk)."""
        chunk = ULogChunk()
        data_at: list[int] = []  # offsets of D messages
        n = len(buffer)
        position = 0
        while position + 3 <= n:
            size = buffer[position] | buffer[position + 1] << 8
            kind = buffer[position + 2]
            end = position + 3 + size
            if size == 0 or size > _MAX_MESSAGE or kind not in _DATA_TYPES:
                position = self._resync(buffer, position, counts)
                continue
            if end > n:
                break
            counts.messages += 1
            if kind == 68:  # D
                data_at.append(position)
            elif kind == 65:  # A
                if size >= 4:
                    msg_id = buffer[position + 4] | buffer[position + 5] << 8
                    name = _string(buffer[position + 6 : end])
                    subscriptions[msg_id] = Subscription(msg_id, name, buffer[position + 3])
                    if name in wanted:
                        dtype, need = self.dtype(name, wanted[name])
                        full = self.type_size(name)
                        decoders[msg_id] = (dtype, need, full)
            elif kind == 82:  # R
                if size >= 2:
                    gone = buffer[position + 3] | buffer[position + 4] << 8
                    subscriptions.pop(gone, None)
                    decoders.pop(gone, None)
            elif kind == 79:  # O
                counts.dropouts += 1
                if size >= 2:
                    counts.dropout_ms += buffer[position + 3] | buffer[position + 4] << 8
            elif kind == 83:  # S
                self.has_sync = True
            elif kind == 80:  # P (a parameter changed in flight)
                key, value = self._key_value(buffer[position + 3 : end])
                if key:
                    chunk.parameters.append((key, value))
            position = end
        if final and position < n:
            counts.truncated = True
            position = n
        if data_at:
            self._decode(
                buffer, np.asarray(data_at, np.int64), subscriptions, decoders, counts, chunk
            )
        return chunk, position

    def _resync(self, buffer: bytes, position: int, counts: ULogCounts) -> int:
        """After a corrupt header at ``position``: the next sync message (when the log has
        them), else one byte on. The bytes skipped are counted."""
        target = position + 1
        if self.has_sync:
            found = buffer.find(SYNC, position + 1)
            # the sync magic is the payload of an S message: resume after it
            target = found + len(SYNC) if found >= 0 else max(len(buffer) - len(SYNC), target)
        counts.corrupt_bytes += target - position
        return target

    def _decode(
        self,
        buffer: bytes,
        data_at: np.ndarray,
        subscriptions: Mapping[int, Subscription],
        decoders: Mapping[int, tuple[np.dtype, int, int]],
        counts: ULogCounts,
        chunk: ULogChunk,
    ) -> None:
        raw = np.frombuffer(buffer, dtype=np.uint8)
        sizes = raw[data_at].astype(np.int64) | raw[data_at + 1].astype(np.int64) << 8
        ids = raw[data_at + 3].astype(np.int64) | raw[data_at + 4].astype(np.int64) << 8
        known = np.isin(ids, np.fromiter(subscriptions, np.int64, len(subscriptions)))
        counts.corrupt_messages += int((~known).sum())
        for msg_id, (dtype, need, full) in decoders.items():
            rows = np.flatnonzero(ids == msg_id)
            if rows.size == 0:
                continue
            payload = sizes[rows] - 2
            fits = (payload >= need) & (payload <= full)
            counts.corrupt_messages += int((~fits).sum())
            rows = rows[fits]
            if rows.size == 0:
                continue
            # the payload starts after the 3-byte header and the 2-byte msg_id
            window = sliding_window_view(raw, dtype.itemsize)
            starts = data_at[rows] + 5
            inside = starts + dtype.itemsize <= raw.shape[0]
            values = np.ascontiguousarray(window[starts[inside]]).view(dtype)[:, 0]
            sub = subscriptions[msg_id]
            key = (sub.name, sub.multi_id)
            previous = chunk.data.get(key)
            chunk.data[key] = values if previous is None else np.concatenate([previous, values])
