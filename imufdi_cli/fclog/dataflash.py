"""A streaming reader of ArduPilot DataFlash logs (``.bin``), vectorised per chunk.

The format (ArduPilot ``libraries/AP_Logger/LogStructure.h``) is self-describing: every
message is ``A3 95 | u8 type | payload``, its length fixed per type by a ``FMT`` message
(type 128, 89 bytes: type, length including the 3 header bytes, a 4-character name, up
to 16 format characters and up to 64 characters of comma-separated column names) written
before the first message of the type.

:class:`DataFlashFile` streams a log in chunks. Per chunk, with numpy: every ``A3 95``
is a candidate message start; the ``FMT`` candidates are decoded and kept when their
format characters add up to their declared length; each candidate's end follows from its
type's length. A walk along "the next message starts where this one ends" (one Python
step per message, no per-byte work) keeps the real messages; a candidate of an unknown
type, or bytes between a message's end and the next ``A3 95``, are corruption: counted
and skipped (the walk resumes at the next candidate). Then, per type wanted, one gather
of the payloads and one view as a numpy structured array. Memory is bounded by the chunk
size.

Format characters (LogStructure.h): ``a`` int16[32], ``b``/``B`` int8/uint8, ``h``/``H``
int16/uint16, ``i``/``I`` int32/uint32, ``q``/``Q`` int64/uint64, ``f`` float, ``d``
double, ``n``/``N``/``Z`` char[4]/[16]/[64], ``c``/``C`` int16/uint16 x 100, ``e``/``E``
int32/uint32 x 100, ``L`` int32 latitude/longitude x 1e7, ``M`` uint8 flight mode.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from imufdi_cli.errors import FlightLogError

HEAD: Final[bytes] = b"\xa3\x95"
FMT_TYPE: Final[int] = 128
FMT_LENGTH: Final[int] = 89

#: format character -> (numpy dtype, scale to the value pymavlink reports)
FORMAT_CHARS: Final[dict[str, tuple[Any, float]]] = {
    "a": (("<i2", (32,)), 1.0),
    "b": ("i1", 1.0),
    "B": ("u1", 1.0),
    "h": ("<i2", 1.0),
    "H": ("<u2", 1.0),
    "i": ("<i4", 1.0),
    "I": ("<u4", 1.0),
    "q": ("<i8", 1.0),
    "Q": ("<u8", 1.0),
    "f": ("<f4", 1.0),
    "d": ("<f8", 1.0),
    "n": ("S4", 1.0),
    "N": ("S16", 1.0),
    "Z": ("S64", 1.0),
    "c": ("<i2", 0.01),
    "C": ("<u2", 0.01),
    "e": ("<i4", 0.01),
    "E": ("<u4", 0.01),
    "L": ("<i4", 1e-7),
    "M": ("u1", 1.0),
}


@dataclass(frozen=True)
class MessageFormat:
    """A ``FMT`` definition: type id, total length (header included), name, format
    characters and column names."""

    type: int
    length: int
    name: str
    format: str
    columns: tuple[str, ...]

    def layout(self) -> dict[str, tuple[Any, float, int]]:
        """Column -> (numpy dtype, scale, payload offset)."""
        out = {}
        offset = 0
        for char, column in zip(self.format, self.columns):
            code, scale = FORMAT_CHARS[char]
            out[column] = (code, scale, offset)
            offset += np.dtype(code).itemsize
        return out

    def dtype(self, columns: Sequence[str]) -> np.dtype:
        """Structured dtype of the payload with ``columns`` (those present) at their offsets."""
        layout = self.layout()
        names = [c for c in columns if c in layout]
        return np.dtype(
            {
                "names": names,
                "formats": [layout[c][0] for c in names],
                "offsets": [layout[c][2] for c in names],
                "itemsize": self.length - 3,
            }
        )

    def scale(self, column: str) -> float:
        return float(FORMAT_CHARS[self.format[self.columns.index(column)]][1])


def payload_size(fmt: str) -> int | None:
    """Bytes of a payload of format characters ``fmt`` (None: an unknown character)."""
    total = 0
    for char in fmt:
        entry = FORMAT_CHARS.get(char)
        if entry is None:
            return None
        total += np.dtype(entry[0]).itemsize
    return total


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("ascii", errors="replace")


def parse_fmt(payload: bytes) -> MessageFormat | None:
    """A FMT payload (86 bytes) as a :class:`MessageFormat`, or None when it is not a
    consistent definition (its format characters do not add up to its length)."""
    if len(payload) < FMT_LENGTH - 3:
        return None
    kind, length = payload[0], payload[1]
    name = _text(payload[2:6])
    fmt = _text(payload[6:22])
    columns = tuple(c for c in _text(payload[22:86]).split(","))
    if not name or not name.isprintable() or length < 3:
        return None
    if kind == FMT_TYPE:
        return MessageFormat(
            kind, FMT_LENGTH, "FMT", "BBnNZ", ("Type", "Length", "Name", "Format", "Columns")
        )
    size = payload_size(fmt)
    if size is None or size + 3 != length or len(columns) != len(fmt):
        return None
    return MessageFormat(kind, length, name, fmt, columns)


@dataclass
class DataFlashCounts:
    """Counts of a DataFlash read.

    Attributes
    ----------
    messages : int
        Messages read (every type).
    corrupt_bytes : int
        Bytes that are not part of a message: garbage, messages of an undefined type,
        resynchronisation.
    truncated : bool
        The last message is cut by the end of the file.
    """

    messages: int = 0
    corrupt_bytes: int = 0
    truncated: bool = False


@dataclass
class DataFlashChunk:
    """The wanted messages of one chunk: ``data[name]`` structured arrays (K,) in file order."""

    data: dict[str, np.ndarray] = field(default_factory=dict)


class DataFlashFile:
    """An ArduPilot DataFlash log, streamed by :meth:`read`.

    Raises
    ------
    FlightLogError
        Not a DataFlash log (it must start with a FMT message, ``A3 95 80``) or unreadable.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = os.fspath(path)
        #: type id -> format, learnt while reading
        self.formats: dict[int, MessageFormat] = {}
        try:
            with open(self.path, "rb") as handle:
                head = handle.read(3)
        except OSError as err:
            raise FlightLogError(f"cannot read {self.path}: {err.strerror or err}") from err
        if head != HEAD + bytes([FMT_TYPE]):
            raise FlightLogError(
                f"{self.path}: not an ArduPilot DataFlash log (it does not start with a FMT"
                " message, bytes A3 95 80)"
            )

    def format_named(self, name: str) -> MessageFormat | None:
        for fmt in self.formats.values():
            if fmt.name == name:
                return fmt
        return None

    def read(
        self,
        wanted: Mapping[str, Sequence[str]],
        *,
        chunk_size: int = 4 << 20,
        counts: DataFlashCounts | None = None,
        progress: Any = None,
    ) -> Iterator[DataFlashChunk]:
        """Stream the log: the columns ``wanted[name]`` of every message type wanted."""
        counts = counts if counts is not None else DataFlashCounts()
        size_total = os.path.getsize(self.path)
        lengths = np.zeros(256, np.int64)
        lengths[FMT_TYPE] = FMT_LENGTH
        for kind, fmt in self.formats.items():
            lengths[kind] = fmt.length
        with open(self.path, "rb") as handle:
            carry = b""
            position = 0
            while True:
                block = handle.read(chunk_size)
                position += len(block)
                final = not block
                buffer = carry + block
                chunk, used = self._walk(buffer, final, wanted, lengths, counts)
                carry = buffer[used:]
                if progress is not None:
                    progress(float(position), float(size_total))
                if chunk.data:
                    yield chunk
                if final:
                    return

    def _learn_formats(self, raw: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> None:
        """Decode the FMT candidates among ``starts`` (complete ones) into ``self.formats``."""
        fmts = starts[(raw[starts + 2] == FMT_TYPE) & (starts + FMT_LENGTH <= raw.shape[0])]
        for start in fmts.tolist():
            fmt = parse_fmt(raw[start + 3 : start + FMT_LENGTH].tobytes())
            if fmt is None or fmt.type == FMT_TYPE:
                continue
            known = self.formats.get(fmt.type)
            if known is None or known != fmt:
                self.formats[fmt.type] = fmt
                lengths[fmt.type] = fmt.length

    def _walk(
        self,
        buffer: bytes,
        final: bool,
        wanted: Mapping[str, Sequence[str]],
        lengths: np.ndarray,
        counts: DataFlashCounts,
    ) -> tuple[DataFlashChunk, int]:
        raw = np.frombuffer(buffer, dtype=np.uint8)
        n = raw.shape[0]
        chunk = DataFlashChunk()
        if n < 3:
            if final:
                counts.truncated = counts.truncated or n > 0
                counts.corrupt_bytes += n
                return chunk, n
            return chunk, 0
        starts = np.flatnonzero((raw[:-2] == 0xA3) & (raw[1:-1] == 0x95))
        self._learn_formats(raw, starts, lengths)
        kinds = raw[starts + 2]
        sizes = lengths[kinds]
        ends = starts + sizes
        following = np.searchsorted(starts, ends, side="left").tolist()
        ends_list = ends.tolist()
        sizes_list = sizes.tolist()
        count = starts.shape[0]
        chosen: list[int] = []
        i = 0
        pending: int | None = None
        while i < count:
            if sizes_list[i] == 0:  # a type without a FMT: not a message we can follow
                i += 1
                continue
            if ends_list[i] > n:
                pending = i
                break
            chosen.append(i)
            i = following[i]
        if pending is not None:
            used = int(starts[pending])
            if final:
                counts.truncated = True
                used = n
        elif chosen and ends_list[chosen[-1]] == n:
            used = n
        else:
            # trailing bytes hold no complete header; keep the last two (A3 95 of the next)
            last_end = ends_list[chosen[-1]] if chosen else 0
            used = n if final else max(last_end, n - 2)
        picked = np.asarray(chosen, np.int64)
        kept_bytes = int(sizes[picked].sum()) if picked.size else 0
        counts.corrupt_bytes += used - kept_bytes
        counts.messages += int(picked.size)
        if picked.size:
            self._decode(raw, starts[picked], kinds[picked], wanted, chunk)
        return chunk, used

    def _decode(
        self,
        raw: np.ndarray,
        starts: np.ndarray,
        kinds: np.ndarray,
        wanted: Mapping[str, Sequence[str]],
        chunk: DataFlashChunk,
    ) -> None:
        for kind in np.unique(kinds).tolist():
            fmt = self.formats.get(int(kind))
            if fmt is None or fmt.name not in wanted:
                continue
            try:
                dtype = fmt.dtype(wanted[fmt.name])
            except KeyError:
                continue
            at = starts[kinds == kind] + 3
            rows = sliding_window_view(raw, dtype.itemsize)[at]
            chunk.data[fmt.name] = np.ascontiguousarray(rows).view(dtype)[:, 0]
