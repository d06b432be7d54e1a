"""Small PX4 ULog and ArduPilot DataFlash logs written from the format specifications, for
the flight-log tests (checked against pyulog and pymavlink in test_fclog.py).

``ulog_bytes`` writes a ULog file: header, flag bits, formats, info, parameters, one
subscription per topic instance and the data messages in time order (optionally with
sync messages, a dropout, corrupt bytes). ``dataflash_bytes`` writes a DataFlash log: the
FMT of FMT, one FMT per message type, then the messages in time order.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

ULOG_MAGIC = b"ULog\x01\x12\x35"
SYNC = b"\x2f\x73\x13\x20\x25\x0c\xbb\x12"

#: topic -> ULog format body (fields in order); trailing padding as PX4 writes it
PX4_FORMATS: dict[str, str] = {
    "sensor_accel": "uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float x;"
    "float y;float z;float temperature;uint32_t error_count;uint8_t[3] clip_counter;"
    "uint8_t samples;uint8_t[4] _padding0;",
    "sensor_gyro": "uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float x;"
    "float y;float z;float temperature;uint32_t error_count;uint8_t[3] clip_counter;"
    "uint8_t samples;uint8_t[4] _padding0;",
    "vehicle_imu": "uint64_t timestamp;uint64_t timestamp_sample;uint32_t accel_device_id;"
    "uint32_t gyro_device_id;float[3] delta_angle;float[3] delta_velocity;"
    "uint16_t delta_angle_dt;uint16_t delta_velocity_dt;uint8_t delta_angle_clipping;"
    "uint8_t delta_velocity_clipping;uint8_t accel_calibration_count;"
    "uint8_t gyro_calibration_count;",
    "vehicle_gps_position": "uint64_t timestamp;uint64_t time_utc_usec;int32_t lat;int32_t lon;",
}

_CODES = {
    "int8_t": "b",
    "uint8_t": "B",
    "int16_t": "h",
    "uint16_t": "H",
    "int32_t": "i",
    "uint32_t": "I",
    "int64_t": "q",
    "uint64_t": "Q",
    "float": "f",
    "double": "d",
    "bool": "?",
    "char": "c",
}


def _fields(body: str) -> list[tuple[str, int, str]]:
    out = []
    for item in body.split(";"):
        if not item:
            continue
        type_text, name = item.split(" ")
        count = 0
        if "[" in type_text:
            type_text, size = type_text[:-1].split("[")
            count = int(size)
        out.append((type_text, count, name))
    return out


def _message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _pack(body: str, values: Mapping[str, Any]) -> bytes:
    """One message of a format, padding fields at the end left out (as PX4 does)."""
    fields = _fields(body)
    while fields and fields[-1][2].startswith("_padding"):
        fields.pop()
    out = b""
    for type_text, count, name in fields:
        code = _CODES[type_text]
        value = values.get(name, [0] * count if count else 0)
        if count:
            out += struct.pack(f"<{count}{code}", *value)
        else:
            out += struct.pack(f"<{code}", value)
    return out


def _info(kind: str, type_key: str, value: bytes) -> bytes:
    key = type_key.encode()
    return _message(kind, bytes([len(key)]) + key + value)


def ulog_bytes(
    samples: Sequence[tuple[str, int, Mapping[str, Any]]],
    *,
    info: Mapping[str, str] | None = None,
    parameters: Mapping[str, int | float] | None = None,
    formats: Mapping[str, str] | None = None,
    start_us: int = 1_000_000,
    sync_every: int = 0,
    dropout_after: int | None = None,
    garbage_after: int | None = None,
    truncate: int = 0,
) -> bytes:
    """A ULog of ``samples``: (topic, multi_id, field values) in the order to write.

    ``sync_every``: an S message every that many data messages; ``dropout_after``: an O
    message of 10 ms after that many; ``garbage_after``: 7 corrupt bytes (a header of
    type 0) after that many; ``truncate``: bytes cut from the end.
    """
    formats = {**PX4_FORMATS, **(formats or {})}
    out = bytearray(ULOG_MAGIC + b"\x01" + struct.pack("<Q", start_us))
    out += _message("B", bytes(8) + bytes(8) + bytes(24))
    used = sorted({topic for topic, _, _ in samples})
    for topic in used:
        out += _message("F", f"{topic}:{formats[topic]}".encode())
    for key, value in (info or {"sys_name": "PX4", "ver_hw": "TEST_BOARD"}).items():
        out += _info("I", f"char[{len(value)}] {key}", value.encode())
    for key, number in (parameters or {}).items():
        if isinstance(number, int):
            out += _info("P", f"int32_t {key}", struct.pack("<i", number))
        else:
            out += _info("P", f"float {key}", struct.pack("<f", number))
    ids: dict[tuple[str, int], int] = {}
    for topic, multi, _ in samples:
        if (topic, multi) not in ids:
            ids[(topic, multi)] = len(ids)
            out += _message(
                "A", bytes([multi]) + struct.pack("<H", ids[(topic, multi)]) + topic.encode()
            )
    for n, (topic, multi, values) in enumerate(samples):
        payload = struct.pack("<H", ids[(topic, multi)]) + _pack(formats[topic], values)
        out += _message("D", payload)
        if sync_every and (n + 1) % sync_every == 0:
            out += _message("S", SYNC)
        if dropout_after is not None and n + 1 == dropout_after:
            out += _message("O", struct.pack("<H", 10))
        if garbage_after is not None and n + 1 == garbage_after:
            out += b"\x05\x00\x00GARBA"
    return bytes(out[: len(out) - truncate] if truncate else out)


def px4_imu_samples(
    t_us: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    *,
    offsets_us: Sequence[int] = (),
    vehicle_imu: bool = False,
    integ_dt_us: int = 5000,
) -> list[tuple[str, int, dict[str, Any]]]:
    """The sensor_gyro/sensor_accel (or vehicle_imu) messages of m IMUs, time-ordered.

    ``t_us`` (N,), gyro/accel (N, m, 3); IMU k is sampled at ``t_us + offsets_us[k]``
    (device id 1000 + k). With ``vehicle_imu`` each sample is a delta angle and delta
    velocity over ``integ_dt_us``, i.e. the value times the interval.
    """
    m = gyro.shape[1]
    offsets = list(offsets_us) or [0] * m
    rows: list[tuple[int, str, int, dict[str, Any]]] = []
    for k in range(m):
        for i, t in enumerate(t_us.tolist()):
            stamp = int(t) + offsets[k]
            if vehicle_imu:
                dt = integ_dt_us * 1e-6
                rows.append(
                    (
                        stamp,
                        "vehicle_imu",
                        k,
                        {
                            "timestamp": stamp + 50,
                            "timestamp_sample": stamp,
                            "accel_device_id": 1000 + k,
                            "gyro_device_id": 1000 + k,
                            "delta_angle": (gyro[i, k] * dt).tolist(),
                            "delta_velocity": (accel[i, k] * dt).tolist(),
                            "delta_angle_dt": integ_dt_us,
                            "delta_velocity_dt": integ_dt_us,
                        },
                    )
                )
                continue
            for topic, values in (("sensor_gyro", gyro), ("sensor_accel", accel)):
                x, y, z = values[i, k].tolist()
                rows.append(
                    (
                        stamp,
                        topic,
                        k,
                        {
                            "timestamp": stamp + 100,
                            "timestamp_sample": stamp,
                            "device_id": 1000 + k,
                            "x": x,
                            "y": y,
                            "z": z,
                        },
                    )
                )
    rows.sort(key=lambda r: (r[0], r[1], r[2]))
    return [(topic, multi, values) for _, topic, multi, values in rows]


# --- DataFlash ---------------------------------------------------------------------------

_DF_CODES = {
    "b": "b",
    "B": "B",
    "h": "h",
    "H": "H",
    "i": "i",
    "I": "I",
    "q": "q",
    "Q": "Q",
    "f": "f",
    "d": "d",
    "n": "4s",
    "N": "16s",
    "Z": "64s",
    "c": "h",
    "C": "H",
    "e": "i",
    "E": "I",
    "L": "i",
    "M": "B",
    "a": "32h",
}

#: name -> (format characters, columns) of the messages the tests write (as ArduPilot 4.x)
AP_FORMATS: dict[str, tuple[str, str]] = {
    "IMU": ("QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
    "ACC": ("QBQfff", "TimeUS,I,SampleUS,AccX,AccY,AccZ"),
    "GYR": ("QBQfff", "TimeUS,I,SampleUS,GyrX,GyrY,GyrZ"),
    "GPS": ("QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    "PARM": ("QNff", "TimeUS,Name,Value,Default"),
    "MSG": ("QZ", "TimeUS,Message"),
    "ISBH": ("QHBBHHQf", "TimeUS,N,type,instance,mul,smp_cnt,SampleUS,smp_rate"),
    "ISBD": ("QHHaaa", "TimeUS,N,seqno,x,y,z"),
    # before ArduPilot 4.0: one message type per instance, no I column
    "IMU2": ("QffffffIIfBBHH", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
}


def _df_size(fmt: str) -> int:
    return struct.calcsize("<" + "".join(_DF_CODES[c] for c in fmt))


def dataflash_bytes(
    messages: Sequence[tuple[str, Mapping[str, Any]]],
    *,
    formats: Mapping[str, tuple[str, str]] | None = None,
    garbage_after: int | None = None,
    truncate: int = 0,
) -> bytes:
    """A DataFlash log of ``messages``: (name, column values) in the order to write."""
    formats = {**AP_FORMATS, **(formats or {})}
    types = {name: 129 + k for k, name in enumerate(sorted({n for n, _ in messages}))}

    def fmt_message(kind: int, length: int, name: str, fmt: str, columns: str) -> bytes:
        return b"\xa3\x95\x80" + struct.pack(
            "<BB4s16s64s", kind, length, name.encode(), fmt.encode(), columns.encode()
        )

    out = bytearray(fmt_message(128, 89, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    for name, kind in types.items():
        fmt, columns = formats[name]
        out += fmt_message(kind, _df_size(fmt) + 3, name, fmt, columns)
    for n, (name, values) in enumerate(messages):
        fmt, columns = formats[name]
        packed = b""
        for char, column in zip(fmt, columns.split(",")):
            value = values.get(column, [0] * 32 if char == "a" else b"" if char in "nNZ" else 0)
            if char == "a":
                packed += struct.pack("<32h", *value)
            elif char in "nNZ":
                packed += struct.pack(
                    "<" + _DF_CODES[char], value.encode() if isinstance(value, str) else value
                )
            else:
                packed += struct.pack("<" + _DF_CODES[char], value)
        out += b"\xa3\x95" + bytes([types[name]]) + packed
        if garbage_after is not None and n + 1 == garbage_after:
            out += b"\x01\x02\x03\xa3\x95\xff\x07"
    return bytes(out[: len(out) - truncate] if truncate else out)


def ap_imu_messages(
    t_us: np.ndarray, gyro: np.ndarray, accel: np.ndarray, *, old_style: bool = False
) -> list[tuple[str, dict[str, Any]]]:
    """IMU messages of m IMUs, all instances with one TimeUS (as Write_IMU does).

    ``old_style``: IMU/IMU2 message types without an I column (ArduPilot before 4.0).
    """
    out = []
    for i, t in enumerate(t_us.tolist()):
        for k in range(gyro.shape[1]):
            values = {
                "TimeUS": int(t),
                "I": k,
                **{f"Gyr{a}": float(gyro[i, k, j]) for j, a in enumerate("XYZ")},
                **{f"Acc{a}": float(accel[i, k, j]) for j, a in enumerate("XYZ")},
            }
            name = "IMU" if not old_style or k == 0 else f"IMU{k + 1}"
            out.append((name, values))
    return out
