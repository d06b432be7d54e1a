"""ros2msg schemas: the text ``ros2 bag record`` writes, parsed into message definitions.

A ``ros2msg`` schema is the main message definition followed by its dependencies, each
after a line of ``=`` and a ``MSG: pkg/Type`` line. :func:`parse_ros2msg` turns that text
into ``{full type name: MsgDef}``; the bulk decoder (:mod:`imufdi_cli.mcapio.cdr`) and the
per-message decoder (:mod:`imufdi_cli.mcapio.cdr_message`) both read these definitions.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from imufdi_cli.errors import McapInputError

#: ROS 2 primitive type -> (numpy dtype code without byte order, size in bytes)
PRIMITIVES: dict[str, tuple[str, int]] = {
    "bool": ("u1", 1),
    "byte": ("u1", 1),
    "char": ("u1", 1),
    "int8": ("i1", 1),
    "uint8": ("u1", 1),
    "int16": ("i2", 2),
    "uint16": ("u2", 2),
    "int32": ("i4", 4),
    "uint32": ("u4", 4),
    "int64": ("i8", 8),
    "uint64": ("u8", 8),
    "float32": ("f4", 4),
    "float64": ("f8", 8),
}
STRING_TYPES = ("string", "wstring")

_BUILTIN_DEFS = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
}


@dataclass(frozen=True)
class FieldDef:
    """One field of a message definition.

    ``type_name`` is a primitive name, ``string``/``wstring``, or a full ``pkg/msg/Type``;
    ``array`` is None (scalar), ``"fixed"`` (``size`` elements) or ``"sequence"``.
    """

    name: str
    type_name: str
    array: str | None = None
    size: int = 0


@dataclass(frozen=True)
class MsgDef:
    name: str
    fields: tuple[FieldDef, ...]


def normalize_type(type_name: str, package: str) -> str:
    """``Header`` -> ``std_msgs/msg/Header``, ``pkg/Type`` -> ``pkg/msg/Type``, bare names
    resolve in ``package``."""
    if type_name in PRIMITIVES or type_name in STRING_TYPES:
        return type_name
    if type_name == "Header":
        return "std_msgs/msg/Header"
    if type_name in ("time", "duration"):
        return f"builtin_interfaces/msg/{type_name.capitalize()}"
    parts = type_name.split("/")
    if len(parts) == 1:
        return f"{package}/msg/{parts[0]}"
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return type_name


_FIELD_RE = re.compile(r"^([A-Za-z0-9_/]+)(<=\d+)?(\[(<=)?(\d*)\])?\s+([A-Za-z_][A-Za-z0-9_]*)")


def _parse_section(name: str, text: str) -> MsgDef:
    package = name.split("/")[0]
    fields = []
    for raw_line in text.splitlines():
        line = raw_line.split("#", 1)[0].strip()
        if not line:
            continue
        match = _FIELD_RE.match(line)
        if match is None:
            raise McapInputError(f"ros2msg schema {name}: cannot parse line {raw_line.strip()!r}")
        base, _bound, array, upper, size, field_name = match.groups()
        rest = line[match.end() :].strip()
        if rest.startswith("="):
            continue  # a constant, not a field
        type_name = normalize_type(base, package)
        if array is None:
            fields.append(FieldDef(field_name, type_name))
        elif size and not upper:
            if len(size) > 18:
                raise McapInputError(
                    f"ros2msg schema {name}: fixed array size of {field_name!r} is too large"
                )
            fields.append(FieldDef(field_name, type_name, "fixed", int(size)))
        else:
            fields.append(FieldDef(field_name, type_name, "sequence"))
    return MsgDef(name, tuple(fields))


def parse_ros2msg(schema_name: str, text: str | bytes) -> dict[str, MsgDef]:
    """Parse a concatenated ros2msg schema into ``{full type name: MsgDef}``.

    The main type is ``schema_name``; dependency sections start with ``MSG: pkg/Type``.
    Missing definitions of ``builtin_interfaces/msg/Time``/``Duration`` and
    ``std_msgs/msg/Header`` are supplied.
    """
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    main = normalize_type(schema_name, schema_name.split("/")[0])
    sections = re.split(r"^=+\s*$", text, flags=re.MULTILINE)
    defs: dict[str, MsgDef] = {}
    defs[main] = _parse_section(main, sections[0])
    for section in sections[1:]:
        lines = section.strip("\n").splitlines()
        header = next((ln for ln in lines if ln.strip()), "")
        if not header.startswith("MSG:"):
            raise McapInputError(f"ros2msg schema {schema_name}: section without 'MSG:' line")
        dep = header[4:].strip()
        dep_name = normalize_type(dep, dep.split("/")[0])
        body = "\n".join(lines[lines.index(header) + 1 :])
        defs[dep_name] = _parse_section(dep_name, body)
    for name, body in _BUILTIN_DEFS.items():
        if name not in defs:
            defs[name] = _parse_section(name, body)
    return defs
