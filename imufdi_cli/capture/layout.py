"""Frame layouts of raw serial captures: the built-in ``mpu6500-array`` and TOML layouts.

Every layout compiles to one :class:`Layout`. A binary frame is::

    sync | header fields | m x IMU record | trailer pad | checksum (if stored at the end)

Offsets are resolved at load time; the IMU count m is fixed (``n_imus``) or read from a
header field with role ``imu_count``. Axis remapping and rotations are not part of a
layout: they belong to the ArrayConfig. The reference for the TOML keys is
``docs/capture.md``; ``docs/layouts/*.toml`` holds examples.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from imufdi_cli.capture.checksum import CHECKSUM_KINDS, CHECKSUM_SIZES
from imufdi_cli.errors import LayoutError, UnitError
from imufdi_cli.units import STANDARD_GRAVITY, parse_quantity

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: field type name -> numpy dtype code (without byte order)
FIELD_TYPES: Final[dict[str, str]] = {
    "u8": "u1",
    "u16": "u2",
    "u32": "u4",
    "i8": "i1",
    "i16": "i2",
    "i32": "i4",
    "f32": "f4",
    "f64": "f8",
}
ENDIANS: Final[tuple[str, ...]] = ("little", "big")
HEADER_ROLES: Final[tuple[str, ...]] = ("counter", "timestamp", "imu_count", "other")
SENSOR_FIELDS: Final[tuple[str, ...]] = tuple(
    f"{s}_{a}" for s in ("accel", "gyro", "mag") for a in "xyz"
)
RECORD_NAMES: Final[tuple[str, ...]] = (*SENSOR_FIELDS, "temperature", "pad")
BUILTIN_LAYOUTS: Final[tuple[str, ...]] = ("mpu6500-array", "csv")

#: MPU-6500 gyro sensitivity, LSB per deg/s, by full scale (datasheet PS-MPU-6500A §3.1)
GYRO_FULL_SCALES: Final[dict[str, float]] = {
    "250dps": 131.0,
    "500dps": 65.5,
    "1000dps": 32.8,
    "2000dps": 16.4,
}
#: MPU-6500 accelerometer sensitivity, LSB per g, by full scale (datasheet §3.2)
ACCEL_FULL_SCALES: Final[dict[str, float]] = {
    "2g": 16384.0,
    "4g": 8192.0,
    "8g": 4096.0,
    "16g": 2048.0,
}
#: MPU-6500 temperature: degC = raw / 333.87 + 21 (datasheet §3.4.2)
MPU6500_TEMP_SENSITIVITY: Final[float] = 333.87
MPU6500_TEMP_OFFSET_C: Final[float] = 21.0

#: Bounds checked when a layout is loaded, before any buffer is sized from it: IMUs per
#: frame (``n_imus``, ``max_imus``) and bytes per frame (any ``pad`` size, ``trailer_pad``
#: and the whole frame with the most IMUs). Documented in docs/capture.md.
MAX_LAYOUT_IMUS: Final[int] = 1024
MAX_FRAME_BYTES: Final[int] = 1 << 20

_DIMENSION_OF: Final[dict[str, str]] = {
    "gyro": "angular_rate",
    "accel": "acceleration",
    "mag": "magnetic_field",
}


def _byte_order(endian: str) -> str:
    return "<" if endian == "little" else ">"


@dataclass(frozen=True)
class HeaderField:
    """A field between the sync bytes and the first IMU record.

    Attributes
    ----------
    name : str
        Field name (``counter``, ``timestamp``, ``version``, ... or ``pad``).
    type : str
        One of :data:`FIELD_TYPES`, or ``pad`` (bytes skipped).
    offset : int
        Byte offset from the start of the frame (the first sync byte).
    size : int
        Size in bytes.
    endian : str
        ``little`` or ``big``.
    role : str
        ``counter``, ``timestamp``, ``imu_count`` or ``other``.
    expect : int or None
        Value the field must have (frames with another value are not frames).
    tick_s : float or None
        Timestamp tick length, seconds (role ``timestamp``).
    wrap_bits : int or None
        The counter/timestamp wraps modulo 2**wrap_bits (default: the type's width).
    """

    name: str
    type: str
    offset: int
    size: int
    endian: str = "little"
    role: str = "other"
    expect: int | None = None
    tick_s: float | None = None
    wrap_bits: int | None = None

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(_byte_order(self.endian) + FIELD_TYPES[self.type])


@dataclass(frozen=True)
class RecordField:
    """A field of the per-IMU record.

    ``value_SI = raw * scale + offset``; ``offset`` is only used for ``temperature``
    (degrees Celsius).
    """

    name: str
    type: str
    offset: int
    size: int
    endian: str = "little"
    scale: float = 1.0
    value_offset: float = 0.0

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(_byte_order(self.endian) + FIELD_TYPES[self.type])

    @property
    def is_integer(self) -> bool:
        return self.type[0] in "ui"


@dataclass(frozen=True)
class ChecksumSpec:
    """Checksum kind, the bytes it covers and where it is stored.

    ``start``/``end`` follow Python slice rules on the frame bytes (negative counts from
    the end of the frame; ``end=None`` is up to the stored checksum). ``at`` is the offset
    where the checksum is stored (negative from the end); ``None`` means appended as the
    last bytes of the frame.
    """

    kind: str = "none"
    start: int = 0
    end: int | None = None
    at: int | None = None
    endian: str = "little"

    @property
    def size(self) -> int:
        return CHECKSUM_SIZES[self.kind]

    def resolve(self, frame_size: int) -> tuple[int, int, int]:
        """(start, end, at) as absolute offsets in a frame of ``frame_size`` bytes."""
        at = frame_size - self.size if self.at is None else self.at
        if at < 0:
            at += frame_size
        start = self.start + frame_size if self.start < 0 else self.start
        if self.end is None:
            end = at if at > start else frame_size
        else:
            end = self.end + frame_size if self.end < 0 else self.end
        return start, end, at


@dataclass(frozen=True)
class CsvSensorColumns:
    """Columns of one sensor triad of one IMU and the factor to SI."""

    columns: tuple[str, str, str]
    scale: float


@dataclass(frozen=True)
class CsvMapping:
    """How CSV/TSV columns map to time and per-IMU triads.

    Attributes
    ----------
    delimiter : str or None
        ``None``: detected from the header row (comma, tab, semicolon or space).
    time_column : str or None
        Column with the sample time; ``None``: row index x nominal period.
    time_scale_ns : float
        Nanoseconds per unit of the time column.
    imus : tuple of dict
        Per IMU, sensor type -> :class:`CsvSensorColumns` (explicit columns).
    templates : dict
        Sensor type -> (column name template with ``{k}`` and ``{axis}``, factor to SI),
        used when ``imus`` is empty.
    n_imus : int or None
        IMU count for templates; None: every k whose columns are all in the header.
    """

    delimiter: str | None = None
    time_column: str | None = None
    time_scale_ns: float = 1e9
    imus: tuple[Mapping[str, CsvSensorColumns], ...] = ()
    templates: Mapping[str, tuple[str, float]] = field(default_factory=dict)
    n_imus: int | None = None


@dataclass(frozen=True)
class Layout:
    """A compiled capture layout (binary frames or CSV).

    Attributes
    ----------
    name : str
    kind : str
        ``binary`` or ``csv``.
    sync : bytes
        Sync bytes at the start of every frame (binary; at least one byte).
    header : tuple of HeaderField
        Fields after the sync bytes, offsets from the frame start.
    record : tuple of RecordField
        Fields of one IMU record, offsets from the record start.
    record_size : int
        Bytes per IMU record.
    trailer_size : int
        Bytes skipped after the last record (before an appended checksum).
    n_imus : int or None
        Fixed IMU count, or None when a header field with role ``imu_count`` gives it.
    max_imus : int
        Largest IMU count accepted from an ``imu_count`` field.
    checksum : ChecksumSpec
    rate_hz : float or None
        Nominal sample rate (timestamps from the counter when there is no timestamp field).
    csv : CsvMapping or None
    description : dict
        The layout as a JSON-ready dict (stored in the ``imufdi.ingest`` metadata).
    """

    name: str
    kind: str = "binary"
    sync: bytes = b""
    header: tuple[HeaderField, ...] = ()
    record: tuple[RecordField, ...] = ()
    record_size: int = 0
    trailer_size: int = 0
    n_imus: int | None = None
    max_imus: int = 64
    checksum: ChecksumSpec = field(default_factory=ChecksumSpec)
    rate_hz: float | None = None
    csv: CsvMapping | None = None
    description: Mapping[str, Any] = field(default_factory=dict)

    @property
    def header_end(self) -> int:
        """Offset of the first IMU record."""
        if not self.header:
            return len(self.sync)
        last = self.header[-1]
        return last.offset + last.size

    def frame_size(self, n_imus: int) -> int:
        """Bytes in a frame of ``n_imus`` records."""
        appended = self.checksum.size if self.checksum.at is None else 0
        return self.header_end + n_imus * self.record_size + self.trailer_size + appended

    def role(self, role: str) -> HeaderField | None:
        """The header field with a role (``counter``, ``timestamp``, ``imu_count``)."""
        for item in self.header:
            if item.role == role:
                return item
        return None

    @property
    def sensor_types(self) -> tuple[str, ...]:
        """Sensor types with a full xyz triad in the record, in gyro, accel, mag order."""
        if self.kind == "csv" and self.csv is not None:
            present = set(self.csv.templates)
            for imu in self.csv.imus:
                present |= set(imu)
            return tuple(s for s in ("gyro", "accel", "mag") if s in present)
        names = {f.name for f in self.record}
        return tuple(s for s in ("gyro", "accel", "mag") if f"{s}_x" in names)

    @property
    def max_frame_size(self) -> int:
        return self.frame_size(self.n_imus if self.n_imus is not None else self.max_imus)


# --- helpers ---------------------------------------------------------------------------


def _choices(values: Any) -> str:
    return ", ".join(str(v) for v in values)


def _check_keys(table: Mapping[str, Any], valid: set[str], where: str) -> None:
    for key in table:
        if key not in valid:
            raise LayoutError(f"{where}: unknown key {key!r}; valid: {_choices(sorted(valid))}")


def _endian(value: Any, where: str) -> str:
    text = str(value).lower()
    aliases = {"le": "little", "be": "big", "<": "little", ">": "big"}
    text = aliases.get(text, text)
    if text not in ENDIANS:
        raise LayoutError(f"{where}: endian {value!r} unknown; valid: little, big")
    return text


def _int(value: Any, where: str, *, minimum: int | None = None, maximum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise LayoutError(f"{where}: expected an integer, got {value!r}")
    if minimum is not None and value < minimum:
        raise LayoutError(f"{where}: must be >= {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise LayoutError(f"{where}: must be <= {maximum}, got {value}")
    return value


def parse_sync(value: Any, where: str = "sync") -> bytes:
    """Sync bytes from ``"AA 55"``, ``"0xAA55"``, ``"AA55"`` or ``[170, 85]``."""
    if isinstance(value, list):
        if not value or not all(isinstance(v, int) and 0 <= v <= 255 for v in value):
            raise LayoutError(f"{where}: a list of sync bytes must hold integers 0..255")
        return bytes(value)
    if not isinstance(value, str):
        raise LayoutError(f"{where}: give the sync bytes as hex, e.g. 'AA 55'")
    text = re.sub(r"0x", "", value.replace(",", " "), flags=re.IGNORECASE).replace(" ", "")
    if not text or len(text) % 2 or not re.fullmatch(r"[0-9a-fA-F]+", text):
        raise LayoutError(f"{where}: {value!r} is not hex bytes (e.g. 'AA 55')")
    return bytes.fromhex(text)


def _full_scale(value: Any, table: Mapping[str, float], unit: str, where: str) -> float:
    text = str(value).strip().lower().replace(" ", "")
    text = text.replace("deg/s", "dps").replace("°/s", "dps").lstrip("+").lstrip("±")
    if text and text.replace(".", "").isdigit():
        text += unit
    if text not in table:
        raise LayoutError(f"{where}: full scale {value!r} unknown; valid: {_choices(table)}")
    return table[text]


def gyro_scale(full_scale: Any) -> float:
    """rad/s per LSB of an MPU-6500 gyro at a full scale (``"500dps"``)."""
    lsb_per_dps = _full_scale(full_scale, GYRO_FULL_SCALES, "dps", "gyro_fs")
    return math.pi / 180.0 / lsb_per_dps


def accel_scale(full_scale: Any) -> float:
    """m/s^2 per LSB of an MPU-6500 accelerometer at a full scale (``"4g"``)."""
    lsb_per_g = _full_scale(full_scale, ACCEL_FULL_SCALES, "g", "accel_fs")
    return STANDARD_GRAVITY / lsb_per_g


def _quantity(value: Any, dimension: str, where: str) -> float:
    try:
        return parse_quantity(value, dimension, name=where)
    except UnitError as err:
        raise LayoutError(str(err)) from err


# --- the built-in layout -----------------------------------------------------------------


def mpu6500_array(
    *,
    gyro_fs: str = "500dps",
    accel_fs: str = "4g",
    version: int | None = 1,
    max_imus: int = 64,
    rate_hz: float | None = None,
) -> Layout:
    """The built-in ``mpu6500-array`` layout (DESIGN.md §5, byte map in docs/capture.md).

    ``AA 55 | u8 version | u8 m | u16 LE counter | u32 LE timestamp (us) |
    m x (accel xyz, temperature, gyro xyz as big-endian int16) | CRC-16/CCITT-FALSE (LE)``
    over every byte after the sync.

    Parameters
    ----------
    gyro_fs, accel_fs : str
        Full scales the board configured (``250dps``..``2000dps``, ``2g``..``16g``).
    version : int or None
        Required value of the version byte (None: any).
    max_imus : int
        Largest IMU count accepted.
    rate_hz : float or None
        Nominal rate (only used when timestamps are missing; they never are here).
    """
    description = {
        "name": "mpu6500-array",
        "sync": "AA 55",
        "endian": "little",
        "max_imus": max_imus,
        "header": [
            {"name": "version", "type": "u8", **({} if version is None else {"expect": version})},
            {"name": "n_imus", "type": "u8", "role": "imu_count"},
            {"name": "counter", "type": "u16", "role": "counter"},
            {"name": "timestamp", "type": "u32", "role": "timestamp", "tick": "1us"},
        ],
        "gyro_fs": str(gyro_fs),
        "accel_fs": str(accel_fs),
        "record": [
            {"name": n, "type": "i16", "endian": "big"}
            for n in (
                "accel_x",
                "accel_y",
                "accel_z",
                "temperature",
                "gyro_x",
                "gyro_y",
                "gyro_z",
            )
        ],
        "checksum": {"kind": "crc16-ccitt-false", "start": 2, "endian": "little"},
    }
    if rate_hz is not None:
        description["rate_hz"] = float(rate_hz)
    return layout_from_dict(description, source="mpu6500-array")


# --- TOML / dict layouts -----------------------------------------------------------------

_TOP_KEYS: Final[set[str]] = {
    "name",
    "format",
    "sync",
    "endian",
    "header",
    "record",
    "trailer_pad",
    "n_imus",
    "max_imus",
    "checksum",
    "gyro_fs",
    "accel_fs",
    "rate",
    "rate_hz",
    "csv",
}
_HEADER_KEYS: Final[set[str]] = {
    "name",
    "type",
    "size",
    "endian",
    "role",
    "expect",
    "tick",
    "wrap_bits",
}
_RECORD_KEYS: Final[set[str]] = {"name", "type", "size", "endian", "scale", "unit", "offset"}
_CHECKSUM_KEYS: Final[set[str]] = {"kind", "start", "end", "at", "endian"}


def _field_type(item: Mapping[str, Any], where: str) -> tuple[str, int]:
    if "type" not in item:
        raise LayoutError(f"{where}: missing key 'type'; valid: {_choices(FIELD_TYPES)}, pad")
    type_name = str(item["type"])
    if type_name == "pad":
        return "pad", _int(item.get("size", 1), f"{where}.size", minimum=1, maximum=MAX_FRAME_BYTES)
    if type_name not in FIELD_TYPES:
        raise LayoutError(
            f"{where}: unknown field type {type_name!r}; valid: {_choices(FIELD_TYPES)}, pad"
        )
    if "size" in item:
        raise LayoutError(f"{where}: 'size' is only for type = 'pad'")
    return type_name, int(FIELD_TYPES[type_name][1])


def _record_scale(
    item: Mapping[str, Any],
    name: str,
    fs: Mapping[str, float | None],
    where: str,
    type_name: str = "i16",
) -> tuple[float, float]:
    """(scale to SI per LSB, offset) of a record field (float fields default to SI)."""
    if name == "pad":
        return 1.0, 0.0
    if name == "temperature":
        scale = item.get("scale", 1.0 / MPU6500_TEMP_SENSITIVITY)
        offset = item.get("offset", MPU6500_TEMP_OFFSET_C)
        if not isinstance(scale, (int, float)) or not isinstance(offset, (int, float)):
            raise LayoutError(f"{where}: temperature scale and offset must be numbers (degC)")
        return float(scale), float(offset)
    if "offset" in item:
        raise LayoutError(f"{where}: 'offset' is only for the temperature field")
    sensor = name.split("_")[0]
    dimension = _DIMENSION_OF[sensor]
    if "scale" in item:
        scale_value = item["scale"]
        if isinstance(scale_value, str):
            if "unit" in item:
                raise LayoutError(f"{where}: give scale as a quantity or scale + unit, not both")
            scale = _quantity(scale_value, dimension, f"{where}.scale")
        elif isinstance(scale_value, (int, float)) and not isinstance(scale_value, bool):
            unit = item.get("unit")
            factor = 1.0 if unit is None else _quantity(f"1{unit}", dimension, f"{where}.unit")
            scale = float(scale_value) * factor
        else:
            raise LayoutError(f"{where}.scale: expected a number or a quantity like '0.15uT'")
        if not (math.isfinite(scale) and scale != 0.0):
            raise LayoutError(f"{where}.scale: must be finite and non-zero")
        return scale, 0.0
    if "unit" in item:
        return _quantity(f"1{item['unit']}", dimension, f"{where}.unit"), 0.0
    known = fs.get(sensor)
    if known is None and type_name in ("f32", "f64"):
        return 1.0, 0.0
    if known is None:
        hint = {"gyro": "gyro_fs", "accel": "accel_fs"}.get(sensor, "scale")
        raise LayoutError(f"{where}: no scale for {name}; give 'scale' or the layout's {hint}")
    return known, 0.0


def _parse_checksum(raw: Any, default_endian: str, sync_len: int) -> ChecksumSpec:
    if raw is None:
        return ChecksumSpec()
    if not isinstance(raw, Mapping):
        raise LayoutError("checksum: expected a table with kind, start, end, at")
    _check_keys(raw, _CHECKSUM_KEYS, "checksum")
    kind = str(raw.get("kind", "none")).lower()
    if kind not in CHECKSUM_KINDS:
        raise LayoutError(f"checksum.kind: {kind!r} unknown; valid: {_choices(CHECKSUM_KINDS)}")
    end = raw.get("end")
    at = raw.get("at")
    return ChecksumSpec(
        kind=kind,
        start=_int(raw.get("start", sync_len), "checksum.start"),
        end=None if end is None else _int(end, "checksum.end"),
        at=None if at is None else _int(at, "checksum.at"),
        endian=_endian(raw.get("endian", default_endian), "checksum.endian"),
    )


def _check_frame(layout: Layout) -> None:
    """Validate offsets against the smallest and largest frames."""
    counts = (layout.n_imus,) if layout.n_imus is not None else (1, layout.max_imus)
    spec = layout.checksum
    for count in counts:
        size = layout.frame_size(count)
        if spec.kind == "none":
            continue
        if spec.at is not None and not (-size <= spec.at <= size - spec.size):
            raise LayoutError(
                f"checksum.at = {spec.at} is past the frame ({size} bytes with {count} IMUs)"
            )
        for key, value in (("start", spec.start), ("end", spec.end)):
            if value is not None and not (-size <= value <= size):
                raise LayoutError(
                    f"checksum.{key} = {value} is past the frame ({size} bytes with {count} IMUs)"
                )
        start, end, at = spec.resolve(size)
        if end <= start:
            raise LayoutError(f"checksum covers no bytes (start {start} >= end {end})")
        if at < end and at + spec.size > start:
            raise LayoutError(
                f"checksum is stored at {at}, inside the bytes it covers ({start}..{end})"
            )
        if spec.at is not None and at < layout.header_end:
            stored = range(at, at + spec.size)
            for item in layout.header:
                if item.type != "pad" and set(stored) & set(
                    range(item.offset, item.offset + item.size)
                ):
                    raise LayoutError(
                        f"checksum.at = {spec.at} overlaps header field {item.name!r}"
                    )


def layout_from_dict(data: Mapping[str, Any], *, source: str = "layout") -> Layout:
    """Compile a layout description (the TOML form, as a dict) to a :class:`Layout`.

    Raises
    ------
    LayoutError
        One line naming the bad key and the valid choices.
    """
    try:
        return _layout_from_dict(data, source)
    except LayoutError as err:
        message = str(err)
        if not message.startswith(source):
            raise LayoutError(f"{source}: {message}") from err
        raise


def _layout_from_dict(data: Mapping[str, Any], source: str) -> Layout:
    if not isinstance(data, Mapping):
        raise LayoutError("expected a table at the top level")
    _check_keys(data, _TOP_KEYS, "layout")
    name = str(data.get("name", source))
    rate_hz: float | None = None
    if "rate" in data:
        rate_hz = _quantity(data["rate"], "frequency", "rate")
    elif "rate_hz" in data:
        rate_hz = _quantity(data["rate_hz"], "frequency", "rate_hz")
    if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
        raise LayoutError(f"rate: must be a positive frequency, got {rate_hz}")
    fmt = str(data.get("format", "csv" if "csv" in data else "binary"))
    if fmt not in ("binary", "csv"):
        raise LayoutError(f"format: {fmt!r} unknown; valid: binary, csv")
    if fmt == "csv":
        if "csv" not in data:
            raise LayoutError("format = 'csv' needs a [csv] table")
        from imufdi_cli.capture.csvcap import parse_csv_mapping

        mapping = parse_csv_mapping(data["csv"])
        return Layout(
            name=name,
            kind="csv",
            rate_hz=rate_hz,
            csv=mapping,
            description=dict(data),
        )
    if "sync" not in data:
        raise LayoutError("missing key 'sync' (the frame's sync bytes, e.g. 'AA 55')")
    sync = parse_sync(data["sync"])
    default_endian = _endian(data.get("endian", "little"), "endian")

    header: list[HeaderField] = []
    offset = len(sync)
    raw_header = data.get("header", [])
    if not isinstance(raw_header, list):
        raise LayoutError("header: expected an array of tables [[header]]")
    for i, item in enumerate(raw_header):
        where = f"header[{i}]"
        if not isinstance(item, Mapping):
            raise LayoutError(f"{where}: expected a table")
        _check_keys(item, _HEADER_KEYS, where)
        type_name, size = _field_type(item, where)
        role = str(item.get("role", "other"))
        if role not in HEADER_ROLES:
            raise LayoutError(f"{where}.role: {role!r} unknown; valid: {_choices(HEADER_ROLES)}")
        if role != "other" and (type_name == "pad" or type_name[0] == "f"):
            raise LayoutError(f"{where}: a {role} field must be an integer type")
        if role != "other" and any(h.role == role for h in header):
            raise LayoutError(f"{where}: a second field with role {role!r}")
        tick_s = None
        if role == "timestamp":
            tick_s = _quantity(item.get("tick", "1us"), "time", f"{where}.tick")
            if not (math.isfinite(tick_s) and tick_s > 0):
                raise LayoutError(f"{where}.tick: must be a positive time")
        elif "tick" in item:
            raise LayoutError(f"{where}: 'tick' is only for role = 'timestamp'")
        wrap_bits = None
        if role in ("counter", "timestamp"):
            wrap_bits = _int(item.get("wrap_bits", 8 * size), f"{where}.wrap_bits", minimum=1)
            if wrap_bits > 8 * size:
                raise LayoutError(f"{where}.wrap_bits: {wrap_bits} > the field's {8 * size} bits")
        elif "wrap_bits" in item:
            raise LayoutError(f"{where}: 'wrap_bits' is only for counter and timestamp fields")
        expect = item.get("expect")
        if expect is not None:
            expect = _int(expect, f"{where}.expect")
            if type_name == "pad" or type_name[0] == "f":
                raise LayoutError(f"{where}: 'expect' needs an integer type")
            info = np.iinfo(np.dtype(FIELD_TYPES[type_name]))
            if not info.min <= expect <= info.max:
                raise LayoutError(f"{where}.expect: {expect} does not fit in {type_name}")
        header.append(
            HeaderField(
                name=str(item.get("name", "pad" if type_name == "pad" else f"field{i}")),
                type=type_name,
                offset=offset,
                size=size,
                endian=_endian(item.get("endian", default_endian), f"{where}.endian"),
                role=role,
                expect=expect,
                tick_s=tick_s,
                wrap_bits=wrap_bits,
            )
        )
        offset += size

    fs: dict[str, float | None] = {"gyro": None, "accel": None, "mag": None}
    if "gyro_fs" in data:
        fs["gyro"] = gyro_scale(data["gyro_fs"])
    if "accel_fs" in data:
        fs["accel"] = accel_scale(data["accel_fs"])
    raw_record = data.get("record")
    if not isinstance(raw_record, list) or not raw_record:
        raise LayoutError("record: needs an array of tables [[record]] (the per-IMU fields)")
    record: list[RecordField] = []
    record_offset = 0
    seen: set[str] = set()
    for i, item in enumerate(raw_record):
        where = f"record[{i}]"
        if not isinstance(item, Mapping):
            raise LayoutError(f"{where}: expected a table")
        _check_keys(item, _RECORD_KEYS, where)
        field_name = str(item.get("name", ""))
        if field_name not in RECORD_NAMES:
            raise LayoutError(
                f"{where}.name: {field_name!r} unknown; valid: {_choices(RECORD_NAMES)}"
            )
        if field_name != "pad" and field_name in seen:
            raise LayoutError(f"{where}: field {field_name!r} appears twice")
        seen.add(field_name)
        type_name, size = _field_type(item, where)
        if field_name != "pad" and type_name == "pad":
            raise LayoutError(f"{where}: only a field named 'pad' can have type 'pad'")
        scale, value_offset = _record_scale(item, field_name, fs, where, type_name)
        record.append(
            RecordField(
                name=field_name,
                type=type_name,
                offset=record_offset,
                size=size,
                endian=_endian(item.get("endian", default_endian), f"{where}.endian"),
                scale=scale,
                value_offset=value_offset,
            )
        )
        record_offset += size
    for sensor in ("gyro", "accel", "mag"):
        present = [a for a in "xyz" if f"{sensor}_{a}" in seen]
        if present and len(present) != 3:
            raise LayoutError(
                f"record: {sensor} needs all of {sensor}_x, {sensor}_y, {sensor}_z "
                f"(axis remapping belongs to the array config)"
            )
    if not any(f"{s}_x" in seen for s in ("gyro", "accel", "mag")):
        raise LayoutError("record: no sensor fields; valid: " + _choices(SENSOR_FIELDS))

    count_field = next((h for h in header if h.role == "imu_count"), None)
    n_imus: int | None = None
    if "n_imus" in data:
        n_imus = _int(data["n_imus"], "n_imus", minimum=1, maximum=MAX_LAYOUT_IMUS)
    elif count_field is None:
        raise LayoutError("n_imus: give a fixed IMU count or a header field with role 'imu_count'")
    max_imus = _int(data.get("max_imus", 64), "max_imus", minimum=1, maximum=MAX_LAYOUT_IMUS)
    if count_field is not None and n_imus is not None:
        raise LayoutError("n_imus: give a fixed n_imus or an 'imu_count' field, not both")
    trailer = _int(data.get("trailer_pad", 0), "trailer_pad", minimum=0, maximum=MAX_FRAME_BYTES)
    checksum = _parse_checksum(data.get("checksum"), default_endian, len(sync))
    if not sync:
        raise LayoutError("sync: at least one sync byte is needed")
    layout = Layout(
        name=name,
        kind="binary",
        sync=sync,
        header=tuple(header),
        record=tuple(record),
        record_size=record_offset,
        trailer_size=trailer,
        n_imus=n_imus,
        max_imus=max_imus if n_imus is None else n_imus,
        checksum=checksum,
        rate_hz=rate_hz,
        description=dict(data),
    )
    largest = layout.max_frame_size
    if largest > MAX_FRAME_BYTES:
        count_key = "n_imus" if n_imus is not None else "max_imus"
        raise LayoutError(
            f"{count_key}: a frame of {layout.max_imus} IMUs is {largest} bytes"
            f" ({len(header)} header fields, {record_offset}-byte records, trailer_pad"
            f" {trailer}); the limit is {MAX_FRAME_BYTES} bytes per frame"
        )
    _check_frame(layout)
    return layout


def load_layout(spec: str | Path, **builtin_options: Any) -> Layout:
    """A layout by name or file.

    Parameters
    ----------
    spec : str or Path
        ``"mpu6500-array"`` (built-in binary), ``"csv"`` (CSV with columns named by sensor
        id, SI units, time column ``t`` in seconds), or a path to a ``.toml`` layout.
    **builtin_options
        Options of the built-in layouts (``gyro_fs="1000dps"``, ``accel_fs="8g"`` ...).

    Raises
    ------
    LayoutError
        Unknown name, unreadable or invalid file.
    """
    text = str(spec)
    if text == "mpu6500-array":
        try:
            return mpu6500_array(**builtin_options)
        except TypeError as err:
            raise LayoutError(
                "mpu6500-array options: valid: gyro_fs, accel_fs, version, max_imus, rate_hz"
            ) from err
    if text == "csv":
        from imufdi_cli.capture.csvcap import default_csv_layout

        try:
            return default_csv_layout(**builtin_options)
        except TypeError as err:
            raise LayoutError("csv options: valid: n_imus, sensors, delimiter, rate_hz") from err
    path = Path(text)
    if path.suffix.lower() != ".toml":
        raise LayoutError(
            f"layout {text!r} unknown; valid: {_choices(BUILTIN_LAYOUTS)} or a .toml file"
        )
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise LayoutError(f"cannot read layout {path}: {err.strerror}") from err
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise LayoutError(f"{path}: not valid TOML ({err})") from err
    except RecursionError as err:  # tomllib parses nested arrays/tables recursively
        raise LayoutError(f"{path}: not valid TOML (arrays or tables nested too deeply)") from err
    if builtin_options:
        data.update(builtin_options)
    return layout_from_dict(data, source=str(path))
