"""Frame layouts of raw serial captures: the built-in ``mpu6500-array`` and TOML layouts.

Every layout compiles to one :class:`Layout`. A binary frame is::

    sync | header fields | m x IMU record | trailer pad | checksum (if stored at the end)

Offsets are resolved at load time; the IMU count m is fixed (``n_imus``) or read from a
header field with role ``imu_count``. Axis remapping and rotations are not part of a
layout: they belong to the ArrayConfig. The reference for the TOML keys is
``docs/capture.md``; ``docs/layouts/*.toml`` holds examples.

This module is the data model and the value checks; the built-in layouts and the TOML/dict
compiler are in :mod:`~imufdi_cli.capture.layouts` (``load_layout``, ``layout_from_dict``,
``mpu6500_array``, also exported by :mod:`imufdi_cli.capture`).
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from imufdi_cli.capture.checksum import CrcModel, checksum_size
from imufdi_cli.errors import LayoutError, UnitError
from imufdi_cli.units import STANDARD_GRAVITY, parse_quantity

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover
    pass

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
    last bytes of the frame. ``model``: the CRC, for a catalogue CRC (``kind`` its
    catalogue name) or one given by its parameters (``kind`` ``crc``).
    """

    kind: str = "none"
    start: int = 0
    end: int | None = None
    at: int | None = None
    endian: str = "little"
    model: CrcModel | None = None

    @property
    def size(self) -> int:
        return checksum_size(self.kind, self.model)

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
