"""Layouts by name or description: the built-in ``mpu6500-array`` and ``csv`` layouts, and
the TOML/dict form compiled to a :class:`~imufdi_cli.capture.layout.Layout` (the data model
and the value checks are in :mod:`~imufdi_cli.capture.layout`; the TOML keys are documented
in ``docs/capture.md``)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

import numpy as np

from imufdi_cli.capture.checksum import (
    CHECKSUM_KINDS,
    CrcModel,
    ambiguous,
    catalogue_names,
    find_crc,
)
from imufdi_cli.capture.csvcap import default_csv_layout, parse_csv_mapping
from imufdi_cli.capture.layout import (
    _DIMENSION_OF,
    BUILTIN_LAYOUTS,
    FIELD_TYPES,
    HEADER_ROLES,
    MAX_FRAME_BYTES,
    MAX_LAYOUT_IMUS,
    MPU6500_TEMP_OFFSET_C,
    MPU6500_TEMP_SENSITIVITY,
    RECORD_NAMES,
    SENSOR_FIELDS,
    ChecksumSpec,
    HeaderField,
    Layout,
    RecordField,
    _check_keys,
    _choices,
    _endian,
    _int,
    _quantity,
    accel_scale,
    gyro_scale,
    parse_sync,
)
from imufdi_cli.errors import LayoutError
from imufdi_cli.tomlfile import parse_toml

# --- the built-in layout -----------------------------------------------------------------


def mpu6500_array(
    *,
    gyro_fs: str = "500dps",
    accel_fs: str = "4g",
    version: int | None = 1,
    max_imus: int = 64,
    rate_hz: float | None = None,
) -> Layout:
    """The built-in ``mpu6500-array`` layout (byte map in docs/capture.md).

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
_CRC_KEYS: Final[tuple[str, ...]] = ("width", "poly", "init", "refin", "refout", "xorout")
_CHECKSUM_KEYS: Final[set[str]] = {"kind", "start", "end", "at", "endian", *_CRC_KEYS}


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


def _crc_integer(value: Any, key: str, width: int) -> int:
    """A CRC parameter: an integer (TOML ``0x1021``) or a string of one (``"0x1021"``)."""
    where = f"checksum.{key}"
    if isinstance(value, str):
        try:
            value = int(value, 0)
        except ValueError:
            raise LayoutError(f"{where}: {value!r} is not an integer (e.g. 0x1021)") from None
    number = _int(value, where, minimum=0)
    if number >= 1 << width:
        raise LayoutError(f"{where}: 0x{number:X} does not fit in width = {width} bits")
    return number


def _crc_flag(value: Any, key: str) -> bool:
    if not isinstance(value, bool):
        raise LayoutError(f"checksum.{key}: expected true or false, got {value!r}")
    return value


def _crc_model(raw: Mapping[str, Any]) -> CrcModel:
    """A CRC given by its parameters (``kind = "crc"``)."""
    missing = [k for k in ("width", "poly") if k not in raw]
    if missing:
        raise LayoutError(
            f"checksum: kind = 'crc' needs {' and '.join(missing)} (and optionally init,"
            " refin, refout, xorout)"
        )
    width = _int(raw["width"], "checksum.width", minimum=1, maximum=64)
    poly = _crc_integer(raw["poly"], "poly", width)
    if poly == 0:
        raise LayoutError("checksum.poly: must not be 0")
    refin = _crc_flag(raw.get("refin", False), "refin")
    return CrcModel(
        name="crc",
        width=width,
        poly=poly,
        init=_crc_integer(raw.get("init", 0), "init", width),
        refin=refin,
        refout=_crc_flag(raw.get("refout", refin), "refout"),
        xorout=_crc_integer(raw.get("xorout", 0), "xorout", width),
    )


def _checksum_kind(raw: Mapping[str, Any]) -> tuple[str, CrcModel | None]:
    """(kind, CRC model) of a ``[checksum]`` table: a kind of :data:`CHECKSUM_KINDS`, a
    catalogue CRC by name or alias (case and punctuation ignored), or ``crc`` with its
    parameters."""
    text = str(raw.get("kind", "none"))
    kind = text.lower()
    given = [k for k in _CRC_KEYS if k in raw]
    if kind == "crc":
        return "crc", _crc_model(raw)
    if given:
        raise LayoutError(
            f"checksum.{given[0]}: CRC parameters go with kind = 'crc' (kind {text!r} has its own)"
        )
    if kind in CHECKSUM_KINDS:
        return kind, None
    meanings = ambiguous(text)
    if meanings:
        raise LayoutError(
            f"checksum.kind: {text!r} names several CRCs ({', '.join(meanings)}): give the"
            " catalogue name, or kind = 'crc' with width, poly, init, refin, refout, xorout"
        )
    model = find_crc(text)
    if model is None:
        raise LayoutError(
            f"checksum.kind: {text!r} unknown; valid: {_choices(CHECKSUM_KINDS)} (with width,"
            f" poly, init, refin, refout, xorout) or a catalogue CRC: {_choices(catalogue_names())}"
        )
    return model.name, model


def _parse_checksum(raw: Any, default_endian: str, sync_len: int) -> ChecksumSpec:
    if raw is None:
        return ChecksumSpec()
    if not isinstance(raw, Mapping):
        raise LayoutError("checksum: expected a table with kind, start, end, at")
    _check_keys(raw, _CHECKSUM_KEYS, "checksum")
    kind, model = _checksum_kind(raw)
    end = raw.get("end")
    at = raw.get("at")
    return ChecksumSpec(
        kind=kind,
        start=_int(raw.get("start", sync_len), "checksum.start"),
        end=None if end is None else _int(end, "checksum.end"),
        at=None if at is None else _int(at, "checksum.at"),
        endian=_endian(raw.get("endian", default_endian), "checksum.endian"),
        model=model,
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
    rate_hz = _rate(data)
    fmt = str(data.get("format", "csv" if "csv" in data else "binary"))
    if fmt not in ("binary", "csv"):
        raise LayoutError(f"format: {fmt!r} unknown; valid: binary, csv")
    if fmt == "csv":
        if "csv" not in data:
            raise LayoutError("format = 'csv' needs a [csv] table")
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
    header = _header_fields(data, len(sync), default_endian)
    record, record_size = _record_fields(data, default_endian)
    n_imus, max_imus = _imu_count(data, header)
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
        record_size=record_size,
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
            f" ({len(header)} header fields, {record_size}-byte records, trailer_pad"
            f" {trailer}); the limit is {MAX_FRAME_BYTES} bytes per frame"
        )
    _check_frame(layout)
    return layout


def _rate(data: Mapping[str, Any]) -> float | None:
    """The nominal rate (``rate`` or ``rate_hz``), Hz, or None."""
    rate_hz: float | None = None
    if "rate" in data:
        rate_hz = _quantity(data["rate"], "frequency", "rate")
    elif "rate_hz" in data:
        rate_hz = _quantity(data["rate_hz"], "frequency", "rate_hz")
    if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
        raise LayoutError(f"rate: must be a positive frequency, got {rate_hz}")
    return rate_hz


def _header_fields(
    data: Mapping[str, Any], sync_size: int, default_endian: str
) -> list[HeaderField]:
    """The ``[[header]]`` fields, at their offsets after the sync bytes."""
    header: list[HeaderField] = []
    offset = sync_size
    raw_header = data.get("header", [])
    if not isinstance(raw_header, list):
        raise LayoutError("header: expected an array of tables [[header]]")
    for i, item in enumerate(raw_header):
        field = _header_field(item, i, offset, header, default_endian)
        header.append(field)
        offset += field.size
    return header


def _header_field(
    item: Any, i: int, offset: int, before: list[HeaderField], default_endian: str
) -> HeaderField:
    """Header field ``i`` (``before``: the fields already read, for unique roles)."""
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
    if role != "other" and any(h.role == role for h in before):
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
    return HeaderField(
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


def _record_fields(data: Mapping[str, Any], default_endian: str) -> tuple[list[RecordField], int]:
    """The ``[[record]]`` fields of one IMU and the record size in bytes."""
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
    return record, record_offset


def _imu_count(data: Mapping[str, Any], header: list[HeaderField]) -> tuple[int | None, int]:
    """(fixed ``n_imus`` or None when a header field gives it, ``max_imus``)."""
    count_field = next((h for h in header if h.role == "imu_count"), None)
    n_imus: int | None = None
    if "n_imus" in data:
        n_imus = _int(data["n_imus"], "n_imus", minimum=1, maximum=MAX_LAYOUT_IMUS)
    elif count_field is None:
        raise LayoutError("n_imus: give a fixed IMU count or a header field with role 'imu_count'")
    max_imus = _int(data.get("max_imus", 64), "max_imus", minimum=1, maximum=MAX_LAYOUT_IMUS)
    if count_field is not None and n_imus is not None:
        raise LayoutError("n_imus: give a fixed n_imus or an 'imu_count' field, not both")
    return n_imus, max_imus


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
    data = parse_toml(raw, path, LayoutError)
    if builtin_options:
        data.update(builtin_options)
    return layout_from_dict(data, source=str(path))
