"""Per-message CDR decoding into nested dicts (the general, slow path), and JSON payloads.

The bulk decoder (:class:`imufdi_cli.mcapio.cdr.CdrCodec`) locates fields of N messages at
once; messages whose fields it does not locate (the event channels, any schema on ``imufdi
info --strict``) are decoded one at a time here, with the same definitions
(:mod:`imufdi_cli.mcapio.msgdef`) and the same reader limits.
"""

from __future__ import annotations

import struct
from typing import Any

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio.limits import ReaderLimits
from imufdi_cli.mcapio.msgdef import PRIMITIVES, STRING_TYPES, FieldDef, MsgDef
from imufdi_cli.mcapio.records import MessageBatch

#: numpy dtype code -> struct format character.
_STRUCT_CODES = {
    "u1": "B",
    "i1": "b",
    "i2": "h",
    "u2": "H",
    "i4": "i",
    "u4": "I",
    "i8": "q",
    "u8": "Q",
    "f4": "f",
    "f8": "d",
}


def decode_cdr_message(
    defs: dict[str, MsgDef], root: str, payload: bytes, limits: ReaderLimits | None = None
) -> dict[str, Any]:
    """Decode one CDR message into nested dicts (general, slow path).

    At most ``limits.max_schema_fields`` values are decoded (fixed arrays and sequences of
    field-less types would otherwise loop without consuming bytes); more raises
    McapInputError. To decode many messages of one schema, build a
    :class:`MessageDecoder` once (:meth:`CdrCodec.decoder`) and call it per message.
    """
    return MessageDecoder(defs, root, limits)(payload)


_U32 = {"<": struct.Struct("<I"), ">": struct.Struct(">I")}

#: a compiled field: (payload, position, value counter) -> (value, next position)
_FieldOp = Any


class MessageDecoder:
    """Per-message CDR decoding of one ros2msg schema into nested dicts.

    Each message type's fields are turned into small decoding functions once per byte
    order (on first use), so decoding a message walks a list of prepared calls instead of
    interpreting the definitions again: the event channels' messages decode several times
    faster than by re-interpreting the schema per message.

    Parameters
    ----------
    defs : dict of str to MsgDef
        The schema's message definitions (:func:`parse_ros2msg`).
    root : str
        Full name of the message type, e.g. ``imufdi_msgs/msg/FdiEvent``.
    limits : ReaderLimits, optional
        ``max_schema_fields`` bounds the values decoded per message; from the environment
        when omitted (read once, here).
    """

    def __init__(
        self, defs: dict[str, MsgDef], root: str, limits: ReaderLimits | None = None
    ) -> None:
        self.defs = defs
        self.root = root
        self.max_values = (
            limits if limits is not None else ReaderLimits.from_env()
        ).max_schema_fields
        # (endian, type name) -> [(field name, op)]
        self._compiled: dict[tuple[str, str], list[tuple[str, _FieldOp]]] = {}

    def __call__(self, payload: bytes) -> dict[str, Any]:
        """The message as nested dicts; McapInputError when it is malformed."""
        if len(payload) < 4 or payload[0] != 0 or payload[1] > 1:
            raise McapInputError("unsupported or missing CDR encapsulation header")
        endian = "<" if payload[1] == 1 else ">"
        try:
            return self._message(endian, self.root, payload, 4, [0])[0]
        except RecursionError as err:
            raise McapInputError(
                f"CDR message of type {self.root}: types nested too deeply"
            ) from err
        except (struct.error, KeyError) as err:
            raise McapInputError(f"malformed CDR message of type {self.root}: {err}") from err

    def _message(
        self, endian: str, type_name: str, payload: bytes, pos: int, count: list[int]
    ) -> tuple[dict[str, Any], int]:
        ops = self._compiled.get((endian, type_name))
        if ops is None:
            ops = [(f.name, self._field_op(endian, f)) for f in self.defs[type_name].fields]
            self._compiled[(endian, type_name)] = ops
        out: dict[str, Any] = {}
        for name, op in ops:
            out[name], pos = op(payload, pos, count)
        return out, pos

    def _too_many(self) -> McapInputError:
        return McapInputError(
            f"CDR message of type {self.root} has more than {self.max_values} values"
            " (IMUFDI_MAX_SCHEMA_FIELDS)"
        )

    def _prims(self, endian: str, type_name: str) -> _FieldOp:
        """``count`` consecutive primitives in one unpack (aligned once, if any)."""
        code, size = PRIMITIVES[type_name]
        char = _STRUCT_CODES[code]
        single = struct.Struct(endian + char)
        is_bool = type_name == "bool"
        root = self.root

        def prims(payload: bytes, pos: int, n: int) -> tuple[Any, int]:
            if n == 0:
                return [], pos
            pos += (4 - pos) % size  # aligned relative to the end of the 4-byte header
            end = pos + n * size
            if end > len(payload):
                raise McapInputError(
                    f"malformed CDR message of type {root}: {n} x {type_name} past its end"
                )
            if n == 1:
                values: Any = single.unpack_from(payload, pos)
            else:
                values = struct.unpack_from(f"{endian}{n}{char}", payload, pos)
            return ([bool(v) for v in values] if is_bool else list(values)), end

        return prims

    def _value_op(self, endian: str, type_name: str) -> _FieldOp:
        """One value of ``type_name``, counted against ``max_values``."""
        limit, too_many = self.max_values, self._too_many
        if type_name in PRIMITIVES:
            prims = self._prims(endian, type_name)

            def prim(payload: bytes, pos: int, count: list[int]) -> tuple[Any, int]:
                count[0] += 1
                if count[0] > limit:
                    raise too_many()
                values, pos = prims(payload, pos, 1)
                return values[0], pos

            return prim
        if type_name in STRING_TYPES:
            u32 = _U32[endian]

            def string(payload: bytes, pos: int, count: list[int]) -> tuple[str, int]:
                count[0] += 1
                if count[0] > limit:
                    raise too_many()
                pos += (4 - pos) % 4
                (length,) = u32.unpack_from(payload, pos)
                pos += 4
                raw = payload[pos : pos + length]
                return raw.rstrip(b"\0").decode("utf-8", errors="replace"), pos + length

            return string
        message = self._message

        def nested(payload: bytes, pos: int, count: list[int]) -> tuple[dict[str, Any], int]:
            count[0] += 1
            if count[0] > limit:
                raise too_many()
            return message(endian, type_name, payload, pos, count)

        return nested

    def _field_op(self, endian: str, fdef: FieldDef) -> _FieldOp:
        if fdef.array is None:
            return self._value_op(endian, fdef.type_name)
        fixed = fdef.size if fdef.array == "fixed" else None
        u32 = _U32[endian]

        def length(payload: bytes, pos: int) -> tuple[int, int]:
            if fixed is not None:
                return fixed, pos
            pos += (4 - pos) % 4
            return u32.unpack_from(payload, pos)[0], pos + 4

        if fdef.type_name in PRIMITIVES:
            prims = self._prims(endian, fdef.type_name)

            def prim_array(payload: bytes, pos: int, count: list[int]) -> tuple[Any, int]:
                n, pos = length(payload, pos)
                # bounded by the payload: no per-element work, no field budget
                values, pos = prims(payload, pos, n)
                count[0] += 1
                return values, pos

            return prim_array
        element = self._value_op(endian, fdef.type_name)
        limit, root, name = self.max_values, self.root, fdef.name

        def array(payload: bytes, pos: int, count: list[int]) -> tuple[list[Any], int]:
            n, pos = length(payload, pos)
            if n > limit:
                raise McapInputError(
                    f"CDR message of type {root}: {name} has {n} elements, more than"
                    f" {limit} (IMUFDI_MAX_SCHEMA_FIELDS)"
                )
            out = []
            for _ in range(n):
                value, pos = element(payload, pos, count)
                out.append(value)
            return out, pos

        return array


def decode_json_payloads(batch: MessageBatch) -> list[Any]:
    """JSON-decode every payload (general path)."""
    from imufdi_cli.jsonin import loads  # nesting bounded: never a RecursionError

    return [
        loads(batch.payload(i), "malformed JSON message", McapInputError) for i in range(len(batch))
    ]
