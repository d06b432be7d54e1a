"""Bulk CDR decoding with numpy.

:func:`~imufdi_cli.mcapio.msgdef.parse_ros2msg` turns a ros2msg schema into message
definitions; :class:`CdrLayout` flattens a type into a small program: runs of fixed-size fields become constant offsets
from a per-message position, and only strings, sequences and the re-alignment after them
cost vectorised work. :meth:`CdrLayout.locate` runs the program over N messages at once
(one position per message), giving the byte position of every requested field.

CDR (OMG CDR as used by ROS 2 / Fast-CDR): a 4-byte encapsulation header (``00 01``
little-endian, ``00 00`` big-endian), then fields aligned to their own size (at most 8)
counted from the end of that header; strings are ``u32 length`` (including the NUL) and
bytes; sequences are ``u32 count`` and elements (aligned only when count > 0).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.cdr_message import MessageDecoder
from imufdi_cli.mcapio.limits import ReaderLimits
from imufdi_cli.mcapio.msgdef import (
    PRIMITIVES,
    STRING_TYPES,
    FieldDef,
    MsgDef,
    normalize_type,
    parse_ros2msg,
)
from imufdi_cli.mcapio.records import MessageBatch, byte_rows, gather_bytes

# --- layout program ---------------------------------------------------------------------


@dataclass
class _Leaf:
    path: str
    dtype: str  # numpy code without byte order ("f8"), or "string"
    count: int  # elements (fixed arrays), 1 for scalars
    segment: int
    offset: int  # constant offset from the segment's base position


@dataclass
class _Step:
    """Runtime work between segments: advance by a constant, then align, or read a
    string/sequence length and skip it."""

    kind: str  # "align", "string", "sequence"
    advance: int  # constant bytes added to the position first
    align: int = 1  # alignment after advancing ("align") / element alignment ("sequence")
    element_size: int = 0  # sequence element size
    path: str = ""


@dataclass
class CdrLayout:
    """Compiled CDR layout of a message type (see module docstring)."""

    root: str
    steps: list[_Step] = field(default_factory=list)
    leaves: dict[str, _Leaf] = field(default_factory=dict)

    @classmethod
    def compile(
        cls, defs: dict[str, MsgDef], root: str, limits: ReaderLimits | None = None
    ) -> CdrLayout:
        """Layout of ``root``; at most ``limits.max_schema_fields`` leaves are made.

        Fixed arrays of primitives are one leaf whatever their size. Fixed arrays of strings
        or messages are expanded element by element, but only within the field budget: the
        first field that would exceed it ends the layout (an ``opaque`` step, like a
        sequence of messages), so fields before it stay readable in bulk and fields after it
        are refused when asked for. Types nested deeper than ``limits.max_schema_depth``
        (or recursive) raise McapInputError.
        """
        limits = limits if limits is not None else ReaderLimits.from_env()
        builder = _LayoutBuilder(cls(root), defs, limits)
        builder.walk(root, "", 0)
        return builder.layout

    def locate(
        self,
        data: np.ndarray,
        offsets: np.ndarray,
        lengths: np.ndarray,
        paths: Sequence[str],
        valid: np.ndarray | None = None,
        counts_at: dict[str, np.ndarray] | None = None,
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Byte positions of fields in N messages of the same endianness.

        Parameters
        ----------
        data : ndarray, uint8
        offsets, lengths : ndarray, shape (N,)
            Payloads (with their 4-byte encapsulation header).
        paths : sequence of str
            Leaf paths (``angular_velocity.x``, ``header.stamp.sec``, ...).

        Returns
        -------
        positions : dict path -> (N,) int64
            Absolute positions in ``data`` of each requested leaf.
        sizes : dict path -> (N,) int64
            For sequences and strings: element count / byte length (else absent).

        A message whose length fields point past its end makes this raise McapInputError,
        unless ``valid`` (N,) bool is given: then that message's entry is set False (its
        positions are meaningless but every read made here stays inside its payload).
        ``counts_at``, when given, receives the position of the u32 length of every string
        and sequence walked (path -> (N,) int64): the bytes the later positions depend on.
        """
        wanted = {}
        for path in paths:
            leaf = self.leaves.get(path)
            if leaf is None:
                raise McapInputError(f"{self.root} has no field {path!r}")
            wanted[path] = leaf
        last_segment = max((leaf.segment for leaf in wanted.values()), default=0)
        origin = offsets.astype(np.int64) + 4
        payload_end = offsets.astype(np.int64) + lengths.astype(np.int64)
        position = origin.copy()
        positions: dict[str, np.ndarray] = {}
        sizes: dict[str, np.ndarray] = {}
        segment = 0
        for step in self.steps:
            if segment > last_segment:
                break
            for path, leaf in wanted.items():
                if leaf.segment == segment and path not in positions:
                    positions[path] = position + leaf.offset
            if step.kind == "opaque":
                raise McapInputError(
                    f"{self.root}: fields after {step.path!r} need the general decoder"
                )
            position = position + step.advance
            if step.kind == "align":
                rel = position - origin
                position = origin + (-(-rel // step.align)) * step.align
            else:
                rel = position - origin
                position = origin + (-(-rel // 4)) * 4
                count = self._u32(data, position, payload_end, valid, origin)
                if counts_at is not None:
                    counts_at[step.path] = position
                if step.kind in ("string", "wstring"):
                    width = 4 if step.kind == "wstring" else 1
                    sizes[step.path] = count
                    positions[step.path] = position + 4
                    position = position + 4 + count * width
                else:
                    sizes[step.path] = count
                    position = position + 4
                    rel = position - origin
                    aligned = origin + (-(-rel // step.align)) * step.align
                    position = np.where(count > 0, aligned, position)
                    positions[step.path] = position
                    position = position + count * step.element_size
            segment += 1
        for path, leaf in wanted.items():
            if leaf.segment == segment and path not in positions:
                positions[path] = position + leaf.offset
        ends = {p: positions[p] + self.leaf_size(p, sizes) for p in wanted}
        for path, end in ends.items():
            past = end > payload_end
            if end.size and bool(np.any(past)):
                if valid is None:
                    raise McapInputError(f"{self.root}: field {path!r} lies past the message end")
                valid &= ~past
        return positions, sizes

    _endian = "<"

    def leaf_size(self, path: str, sizes: dict[str, np.ndarray]) -> np.ndarray | int:
        leaf = self.leaves[path]
        if leaf.dtype in ("string", "wstring"):
            return sizes[path] * (4 if leaf.dtype == "wstring" else 1)
        if path in sizes:
            return sizes[path] * int(PRIMITIVES_BY_CODE[leaf.dtype])
        return leaf.count * int(PRIMITIVES_BY_CODE[leaf.dtype])

    def _u32(
        self,
        data: np.ndarray,
        position: np.ndarray,
        payload_end: np.ndarray,
        valid: np.ndarray | None,
        origin: np.ndarray,
    ) -> np.ndarray:
        """u32 length fields at ``position``; one past its message's end is an error, or
        (with ``valid``) marks that message invalid and reads as 0."""
        inside = position + 4 <= payload_end
        if not bool(inside.all()):
            if valid is None:
                raise McapInputError(f"{self.root}: a CDR length field lies past the message end")
            valid &= inside
            position = np.where(inside, position, origin - 4)  # the encapsulation header
            out = gather_bytes(data, position, 4).view(self._endian + "u4").reshape(-1)
            return np.where(inside, out.astype(np.int64), 0)
        raw = gather_bytes(data, position, 4)
        return raw.view(self._endian + "u4").reshape(-1).astype(np.int64)


class _LayoutBuilder:
    """Compiles a :class:`CdrLayout` (:meth:`CdrLayout.compile`): walks the type tree,
    keeping the constant offset within the current segment, the alignment known at the
    segment's base, and the field budget."""

    def __init__(self, layout: CdrLayout, defs: dict[str, MsgDef], limits: ReaderLimits):
        self.layout = layout
        self.defs = defs
        self.limits = limits
        self.root = layout.root
        self.segment = 0
        self.const = 0  # bytes from the current segment's base
        self.base_align = 8  # alignment guaranteed at the segment's base
        self.fields = 0  # leaves made so far (the field budget)
        self.stopped = False
        self._shapes: dict[str, tuple[int, int]] = {}

    def shape(self, type_name: str, chain: tuple[str, ...] = ()) -> tuple[int, int]:
        """(leaves of one element once expanded, nesting height) of a type, memoised;
        nothing is expanded."""
        if type_name in PRIMITIVES or type_name in STRING_TYPES:
            return 1, 0
        known = self._shapes.get(type_name)
        if known is not None:
            return known
        depth_limit = self.limits.max_schema_depth
        if type_name in chain or len(chain) > depth_limit:
            raise McapInputError(
                f"ros2msg schema {self.root}: types nested deeper than"
                f" {depth_limit} (IMUFDI_MAX_SCHEMA_DEPTH) or recursive"
            )
        msg = self.defs.get(type_name)
        if msg is None:
            raise McapInputError(
                f"ros2msg schema {self.root}: no definition of {type_name} in the schema text"
            )
        total, height = 0, 0
        for fdef in msg.fields:
            if fdef.array == "sequence" or fdef.type_name in PRIMITIVES:
                total += 1
                continue
            leaves, sub_height = self.shape(fdef.type_name, (*chain, type_name))
            total += leaves * (fdef.size if fdef.array == "fixed" else 1)
            height = max(height, sub_height + 1)
        self._shapes[type_name] = (total, height)
        return total, height

    def expanded(self, type_name: str, depth: int) -> int:
        """Leaves of ``type_name`` met at ``depth``; too deep raises McapInputError."""
        leaves, height = self.shape(type_name)
        if depth + height > self.limits.max_schema_depth:
            raise McapInputError(
                f"ros2msg schema {self.root}: types nested deeper than"
                f" {self.limits.max_schema_depth} (IMUFDI_MAX_SCHEMA_DEPTH)"
            )
        return leaves

    def stop(self, path: str) -> None:
        """End the layout at ``path`` (an opaque step: later fields are unreachable)."""
        self.layout.steps.append(_Step("opaque", self.const, path=path))
        self.segment += 1
        self.const = 0
        self.stopped = True

    def need_runtime_align(self, alignment: int) -> None:
        if alignment <= self.base_align:
            self.const = -(-self.const // alignment) * alignment
            return
        self.layout.steps.append(_Step("align", self.const, alignment))
        self.segment += 1
        self.const = 0
        self.base_align = alignment

    def primitive(self, path: str, type_name: str, count: int) -> None:
        code, size = PRIMITIVES[type_name]
        if self.const + size * count > self.limits.max_record_bytes:
            self.stop(path)  # no message within the record limit holds this field
            return
        self.need_runtime_align(size)
        self.layout.leaves[path] = _Leaf(path, code, count, self.segment, self.const)
        self.const += size * count

    def variable(self, path: str, kind: str, element_size: int) -> None:
        self.need_runtime_align(4)
        self.layout.leaves[path] = _Leaf(path, kind, 1, self.segment, self.const)
        self.layout.steps.append(_Step(kind, self.const, max(element_size, 1), element_size, path))
        self.segment += 1
        self.const = 0
        self.base_align = 1

    def walk(self, type_name: str, prefix: str, depth: int) -> None:
        """Lay out the fields of ``type_name`` (at ``depth``) under ``prefix``."""
        self.expanded(type_name, depth)  # checks depth, recursion and definitions
        for fdef in self.defs[type_name].fields:
            if self.stopped:
                return
            self._field(fdef, f"{prefix}{fdef.name}", depth)

    def _field(self, fdef: FieldDef, path: str, depth: int) -> None:
        elem = fdef.type_name
        cost = 1
        if fdef.array != "sequence" and elem not in PRIMITIVES:
            cost = self.expanded(elem, depth + 1) * (fdef.size if fdef.array == "fixed" else 1)
        if self.fields + cost > self.limits.max_schema_fields:
            self.stop(path)  # the rest of the type is out of the field budget
            return
        self.fields += 1 if elem in PRIMITIVES or fdef.array == "sequence" else 0
        if fdef.array == "sequence":
            if elem in PRIMITIVES:
                self.variable(path, "sequence", PRIMITIVES[elem][1])
                self.layout.leaves[path].dtype = PRIMITIVES[elem][0]
            else:
                # Sequences of strings or messages: skipping them needs a per-message walk;
                # the layout marks the rest as unreachable.
                self.stop(path)
        elif elem in PRIMITIVES:
            self.primitive(path, elem, fdef.size if fdef.array == "fixed" else 1)
        elif elem in STRING_TYPES:
            count = fdef.size if fdef.array == "fixed" else 1
            self.fields += count
            for i in range(count):
                sub = f"{path}[{i}]" if fdef.array == "fixed" else path
                self.variable(sub, "string" if elem == "string" else "wstring", 1)
        elif fdef.array == "fixed":
            if cost == 0:
                return  # elements without fields: nothing to lay out
            for i in range(fdef.size):
                self.walk(elem, f"{path}[{i}].", depth + 1)
        else:
            self.walk(elem, f"{path}.", depth + 1)


PRIMITIVES_BY_CODE = {code: size for code, size in PRIMITIVES.values()}


def encapsulation_endian(batch: MessageBatch) -> np.ndarray:
    """Per message: True for little-endian CDR, False for big-endian.

    Raises McapInputError for payloads shorter than 4 bytes or other encapsulations
    (parameter lists, XCDR2).
    """
    if len(batch) == 0:
        return np.zeros(0, bool)
    if bool(np.any(batch.length < 4)):
        raise McapInputError("CDR message shorter than its 4-byte encapsulation header")
    head = gather_bytes(batch.data, batch.offset, 2)
    kind = head[:, 1]
    if bool(np.any(head[:, 0] != 0)) or bool(np.any(kind > 1)):
        bad = int(kind[(kind > 1) | (head[:, 0] != 0)][0]) if bool(np.any(kind > 1)) else -1
        raise McapInputError(
            f"unsupported CDR encapsulation (kind {bad}); supported: CDR_LE, CDR_BE"
        )
    return kind == 1


def _encapsulation_flags(batch: MessageBatch) -> tuple[np.ndarray, np.ndarray]:
    """Per message: little-endian flag, and whether the encapsulation is CDR_LE/CDR_BE."""
    ok = batch.length >= 4
    if bool(ok.all()):
        head = gather_bytes(batch.data, batch.offset, 2)
    else:
        head = np.zeros((len(batch), 2), np.uint8)
        if bool(ok.any()):
            head[ok] = gather_bytes(batch.data, batch.offset[ok], 2)
    ok &= (head[:, 0] == 0) & (head[:, 1] <= 1)
    return (head[:, 1] == 1) | ~ok, ok


class CdrCodec:
    """Bulk field access for one ros2msg schema (cached per schema)."""

    def __init__(
        self, schema_name: str, schema_text: bytes | str, limits: ReaderLimits | None = None
    ) -> None:
        self.defs = parse_ros2msg(schema_name, schema_text)
        self.root = normalize_type(schema_name, schema_name.split("/")[0])
        self.layout = CdrLayout.compile(self.defs, self.root, limits)
        self._decoders: dict[ReaderLimits, MessageDecoder] = {}
        #: the last uniform layout met per (payload length, paths): the (offset, value)
        #: of the counts its walk read, the field offsets and sizes (:meth:`uniform_rows`)
        self._uniform: dict[
            tuple[int, tuple[str, ...]],
            tuple[list[tuple[int, int]], dict[str, int], dict[str, int]],
        ] = {}

    def decoder(self, limits: ReaderLimits | None = None) -> MessageDecoder:
        """The per-message decoder of this schema (compiled once per ``limits``)."""
        limits = limits if limits is not None else ReaderLimits.from_env()
        decoder = self._decoders.get(limits)
        if decoder is None:
            decoder = self._decoders[limits] = MessageDecoder(self.defs, self.root, limits)
        return decoder

    def positions(
        self, batch: MessageBatch, paths: Sequence[str], valid: np.ndarray | None = None
    ) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Little-endian flags (N,) and positions/sizes of ``paths`` for every message.

        Malformed messages (bad encapsulation, fields past the end) raise McapInputError,
        unless ``valid`` (N,) bool is given: then their entries are set False instead.
        """
        n = len(batch)
        ok = None
        if valid is None:
            little = encapsulation_endian(batch)
        else:
            little, ok = _encapsulation_flags(batch)
            valid &= ok
        positions = {p: np.zeros(n, np.int64) for p in paths}
        sizes: dict[str, np.ndarray] = {}
        for flag in (True, False):
            mask = little == flag
            if ok is not None:
                mask &= ok  # messages without a CDR header are not walked
            if not bool(mask.any()):
                continue
            full = bool(mask.all())
            offs = batch.offset if full else batch.offset[mask]
            lens = batch.length if full else batch.length[mask]
            self.layout._endian = "<" if flag else ">"
            sub_valid = None if valid is None else (valid if full else valid[mask])
            try:
                pos, size = self.layout.locate(batch.data, offs, lens, paths, sub_valid)
            finally:
                self.layout._endian = "<"
            if valid is not None and not full:
                assert sub_valid is not None
                valid[mask] = sub_valid
            for path, value in pos.items():
                if path not in positions:
                    positions[path] = np.zeros(n, np.int64)
                if full:
                    positions[path] = value
                else:
                    positions[path][mask] = value
            for path, value in size.items():
                sizes.setdefault(path, np.zeros(n, np.int64))
                if full:
                    sizes[path] = value
                else:
                    sizes[path][mask] = value
        return little, positions, sizes

    def uniform_rows(
        self, batch: MessageBatch, paths: Sequence[str]
    ) -> tuple[np.ndarray, dict[str, int], dict[str, int]] | None:
        """The payloads of ``batch`` as one (N, L) uint8 array, the offsets of ``paths`` in
        each row and the sizes of the strings and sequences before them, when every
        message has its fields at the same place: all L bytes long, little-endian CDR and
        with the same string lengths and sequence counts (each checked on every message),
        so that one walk of the first message places the fields of all. None when they do
        not (:meth:`positions` then places each message's fields; a malformed first
        message raises the McapInputError :meth:`positions` would).

        The array is a read-only view of ``batch.data`` when the messages are evenly
        spaced in it (:func:`~imufdi_cli.mcapio.records.byte_rows`), else a copy: copy the
        fields read before the buffer changes.
        """
        n = len(batch)
        if n == 0:
            return None
        size = int(batch.length[0])
        if size < 4 or not bool(np.all(batch.length == size)):
            return None
        rows = byte_rows(batch.data, batch.offset, size)
        # (2- and 4-byte fields compared as one integer each, not byte by byte)
        if not bool(np.all(rows[:, 0:2].view("<u2") == 0x0100)):
            return None  # big-endian or malformed encapsulations: the general walk
        key = (size, tuple(paths))
        known = self._uniform.get(key)
        if known is not None and all(
            bool(np.all(rows[:, rel : rel + 4].view("<u4") == value)) for rel, value in known[0]
        ):
            # the counts the last walk read, where it read them: the same walk
            return rows, known[1], known[2]
        counts_at: dict[str, np.ndarray] = {}
        first = batch.select(slice(0, 1))
        positions, sizes = self.layout.locate(
            first.data, first.offset, first.length, paths, counts_at=counts_at
        )
        start = int(first.offset[0])
        checks = []
        for at in counts_at.values():
            rel = int(at[0]) - start
            counts = rows[:, rel : rel + 4].view("<u4")
            if not bool(np.all(counts == counts[0, 0])):
                return None
            checks.append((rel, int(counts[0, 0])))
        offsets = {path: int(value[0]) - start for path, value in positions.items()}
        lengths = {path: int(value[0]) for path, value in sizes.items()}
        # (the walk reads the first count at a fixed place, and each later one where
        # the counts before it put it: messages of this length with these counts at
        # these places have every field where this walk found it)
        if len(self._uniform) >= 64:  # (bounded whatever lengths a file holds)
            self._uniform.clear()
        self._uniform[key] = (checks, offsets, lengths)
        return rows, offsets, lengths

    def read(
        self, batch: MessageBatch, little: np.ndarray, position: np.ndarray, code: str, count: int
    ) -> np.ndarray:
        """Values (N, count) of dtype ``code`` at per-message ``position``."""
        size = PRIMITIVES_BY_CODE[code]
        raw = gather_bytes(batch.data, position, size * count)
        n = len(batch)
        if bool(little.all()) or size == 1:
            return raw.view("<" + code).reshape(n, count)
        out = raw.view(">" + code).reshape(n, count).astype("<" + code)
        if bool(little.any()):
            out[little] = raw[little].view("<" + code).reshape(-1, count)
        return out

    def write(
        self,
        batch: MessageBatch,
        little: np.ndarray,
        position: np.ndarray,
        code: str,
        values: np.ndarray,
    ) -> None:
        """Overwrite values (N, count) at per-message ``position`` in ``batch.data``."""
        n = len(batch)
        values = np.asarray(values).reshape(n, -1)
        count = values.shape[1]
        size = PRIMITIVES_BY_CODE[code]
        as_little = np.ascontiguousarray(values, dtype="<" + code).view(np.uint8)
        raw = as_little.reshape(n, size * count)
        if not bool(little.all()):
            as_big = np.ascontiguousarray(values, dtype=">" + code).view(np.uint8)
            raw = np.where(little[:, None], raw, as_big.reshape(n, size * count))
        index = position[:, None] + np.arange(size * count, dtype=np.int64)[None, :]
        batch.data[index] = raw


_CODECS: dict[tuple[str, bytes], CdrCodec] = {}


def codec_for(schema_name: str, schema_data: bytes) -> CdrCodec:
    """Cached codec of a ros2msg schema."""
    key = (schema_name, bytes(schema_data))
    codec = _CODECS.get(key)
    if codec is None:
        codec = CdrCodec(schema_name, schema_data)
        if len(_CODECS) > 64:
            _CODECS.clear()
        _CODECS[key] = codec
    return codec
