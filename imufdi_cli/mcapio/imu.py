"""IMU arrays in MCAP: ``sensor_msgs/msg/Imu`` / ``MagneticField`` codecs, the array writer,
and the streaming, time-aligning array reader (DESIGN.md §4)."""

from __future__ import annotations

import json
import math
import re
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import ArrayConfigError, McapInputError, UsageError
from imufdi_cli.log import ImuBlock, rechunk
from imufdi_cli.mcapio.cdr import CdrCodec, codec_for
from imufdi_cli.mcapio.records import (
    MESSAGE_FIXED_CONTENT,
    MESSAGE_HEADER_DTYPE,
    MESSAGE_HEADER_SIZE,
    OP_MESSAGE,
    ChannelInfo,
    McapWriter,
    MessageBatch,
)
from imufdi_cli.mcapio.schemas import IMU_SCHEMA, IMU_SCHEMA_NAME, MAG_SCHEMA, MAG_SCHEMA_NAME
from imufdi_cli.mcapio.source import McapSource

ARRAY_METADATA = "imufdi.array"
#: Read-ahead when a reader starts (see ImuArrayReader._prefetch_setup).
_SETUP_MESSAGES = 8
_SETUP_BATCHES = 4096
_SETUP_BYTES = 64 << 20
IMU_TYPE_NAMES = ("sensor_msgs/msg/Imu", "sensor_msgs/Imu")
MAG_TYPE_NAMES = ("sensor_msgs/msg/MagneticField", "sensor_msgs/MagneticField")
NS_PER_S = 1_000_000_000


class NoImuChannelError(McapInputError):
    """The log has no ``sensor_msgs/msg/Imu`` channel (or none of the requested topics)."""


@dataclass
class ImuFields:
    """Decoded values of N Imu (or MagneticField) messages of one channel.

    Attributes
    ----------
    t_ns : ndarray, shape (N,), int64
        ``header.stamp`` in nanoseconds.
    log_time : ndarray, shape (N,), int64
        MCAP log time, nanoseconds.
    gyro : ndarray, shape (N, 3), float64, or None
        ``angular_velocity``, rad/s.
    accel : ndarray, shape (N, 3), float64, or None
        ``linear_acceleration``, m/s^2.
    mag : ndarray, shape (N, 3), float64, or None
        ``magnetic_field``, tesla.
    has_stamp : bool
        False when the messages have no ``header.stamp`` (``t_ns`` is then the log time).
    """

    t_ns: np.ndarray
    log_time: np.ndarray
    gyro: np.ndarray | None = None
    accel: np.ndarray | None = None
    mag: np.ndarray | None = None
    has_stamp: bool = True


def natural_key(text: str) -> list[Any]:
    """Sort key ordering ``/imu2`` before ``/imu10``."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def schema_name(channel: ChannelInfo) -> str:
    return channel.schema.name if channel.schema is not None else ""


def imu_fields_of(channel: ChannelInfo) -> list[str]:
    """Where a channel's messages hold a ``sensor_msgs/msg/Imu``: ``[""]`` for Imu messages,
    else the field paths of Imu fields inside a CDR message (e.g. ``["imu"]`` for a
    ``custom_interfaces/msg/Vectornav`` with an Imu field ``imu``); empty when none."""
    if schema_name(channel) in IMU_TYPE_NAMES and channel.message_encoding in ("cdr", "json"):
        return [""]
    schema = channel.schema
    if channel.message_encoding != "cdr" or schema is None or schema.encoding != "ros2msg":
        return []
    try:
        codec = codec_for(schema.name, schema.data)
    except Exception:  # a schema we cannot parse holds no Imu we could read
        return []
    found: list[str] = []

    def walk(type_name: str, prefix: str, depth: int) -> None:
        definition = codec.defs.get(type_name)
        if definition is None or depth > 8:
            return
        for fdef in definition.fields:
            if fdef.array is not None or "/" not in fdef.type_name:
                continue
            if fdef.type_name == IMU_TYPE_NAMES[0]:
                found.append(prefix + fdef.name)
            else:
                walk(fdef.type_name, f"{prefix}{fdef.name}.", depth + 1)

    walk(codec.root, "", 0)
    return found


def is_imu_channel(channel: ChannelInfo) -> bool:
    """An Imu channel, or a CDR channel whose type holds exactly one Imu field."""
    return len(imu_fields_of(channel)) == 1


def is_mag_channel(channel: ChannelInfo) -> bool:
    return schema_name(channel) in MAG_TYPE_NAMES and channel.message_encoding in ("cdr", "json")


# --- decoding ---------------------------------------------------------------------------

_VECTORS = {"gyro": "angular_velocity", "accel": "linear_acceleration", "mag": "magnetic_field"}


def _codec(channel: ChannelInfo) -> CdrCodec:
    if channel.schema is None or channel.schema.encoding != "ros2msg":
        enc = channel.schema.encoding if channel.schema else "none"
        raise McapInputError(
            f"channel {channel.topic}: CDR messages need a ros2msg schema, got {enc!r}"
        )
    return codec_for(channel.schema.name, channel.schema.data)


def _vector_paths(codec: CdrCodec, field_name: str) -> str:  # field_name may be nested
    """Path of ``<field>.x``, checking that y and z follow it as contiguous float64."""
    leaves = codec.layout.leaves
    first = leaves.get(f"{field_name}.x")
    ok = first is not None and first.dtype == "f8"
    for i, axis in enumerate("yz", start=1):
        leaf = leaves.get(f"{field_name}.{axis}")
        ok = ok and leaf is not None and first is not None
        ok = ok and leaf.segment == first.segment and leaf.offset == first.offset + 8 * i  # type: ignore[union-attr]
        ok = ok and leaf.dtype == "f8"  # type: ignore[union-attr]
    if not ok:
        raise McapInputError(f"{codec.root}: {field_name} is not a float64 x, y, z vector")
    return f"{field_name}.x"


def _decode_cdr(
    batch: MessageBatch,
    channel: ChannelInfo,
    kinds: Sequence[str],
    field: str = "",
    valid: np.ndarray | None = None,
) -> ImuFields:
    codec = _codec(channel)
    prefix = f"{field}." if field else ""
    vector_paths = {kind: _vector_paths(codec, prefix + _VECTORS[kind]) for kind in kinds}
    stamp = [f"{prefix}header.stamp.sec", f"{prefix}header.stamp.nanosec"]
    has_stamp = all(path in codec.layout.leaves for path in stamp)
    paths = [*(stamp if has_stamp else []), *vector_paths.values()]
    little, positions, _ = codec.positions(batch, paths, valid)
    if valid is not None and not bool(valid.all()):
        batch = batch.select(valid)
        little = little[valid]
        positions = {path: value[valid] for path, value in positions.items()}
    log_time = batch.log_time.astype(np.int64)
    if has_stamp:
        sec = codec.read(batch, little, positions[stamp[0]], "i4", 1)[:, 0]
        nanosec = codec.read(batch, little, positions[stamp[1]], "u4", 1)[:, 0]
        t_ns = sec.astype(np.int64) * NS_PER_S + nanosec.astype(np.int64)
    else:
        t_ns = log_time.copy()
    out = ImuFields(t_ns=t_ns, log_time=log_time, has_stamp=has_stamp)
    for kind, path in vector_paths.items():
        setattr(out, kind, codec.read(batch, little, positions[path], "f8", 3).astype(np.float64))
    return out


def _decode_json(
    batch: MessageBatch,
    channel: ChannelInfo,
    kinds: Sequence[str],
    field: str = "",
    valid: np.ndarray | None = None,
) -> ImuFields:
    n = len(batch)
    t_ns = batch.log_time.astype(np.int64).copy()
    has_stamp = True
    vectors = {kind: np.zeros((n, 3)) for kind in kinds}
    for i in range(n):
        try:
            obj = json.loads(batch.payload(i))
            for part in field.split(".") if field else []:
                obj = obj[part]
            if i == 0:
                has_stamp = isinstance(obj, dict) and "header" in obj
            if has_stamp:
                stamp = obj["header"]["stamp"]
                nanosec = int(stamp.get("nanosec", stamp.get("nsec", 0)))
                t_ns[i] = int(stamp["sec"]) * NS_PER_S + nanosec
            for kind in kinds:
                vec = obj[_VECTORS[kind]]
                vectors[kind][i] = (float(vec["x"]), float(vec["y"]), float(vec["z"]))
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as err:
            if valid is not None:
                valid[i] = False
                continue
            raise McapInputError(
                f"channel {channel.topic}: JSON message {i} is not a {schema_name(channel)}"
                f" ({type(err).__name__}: {err})"
            ) from err
    log_time = batch.log_time.astype(np.int64)
    if valid is not None and not bool(valid.all()):
        t_ns, log_time = t_ns[valid], log_time[valid]
        vectors = {kind: value[valid] for kind, value in vectors.items()}
    return ImuFields(t_ns=t_ns, log_time=log_time, has_stamp=has_stamp, **vectors)


def _decode(
    batch: MessageBatch,
    channel: ChannelInfo,
    kinds: Sequence[str],
    field: str = "",
    valid: np.ndarray | None = None,
) -> ImuFields:
    """Decode one channel's messages (``field``: path of an embedded Imu, "" for the message
    itself). Malformed messages raise McapInputError, unless ``valid`` (N,) bool is given:
    then they are left out and their entries set False."""
    if channel.message_encoding == "cdr":
        return _decode_cdr(batch, channel, kinds, field, valid)
    if channel.message_encoding == "json":
        return _decode_json(batch, channel, kinds, field, valid)
    raise McapInputError(
        f"channel {channel.topic}: message encoding {channel.message_encoding!r} is not"
        " supported; supported: cdr, json"
    )


def decode_imu(batch: MessageBatch, channel: ChannelInfo, field: str = "") -> ImuFields:
    """Stamps, angular velocity and linear acceleration of Imu messages (one channel).

    ``field`` is the path of the Imu inside a larger message (``""``: the message is an
    Imu). Without a ``header.stamp`` the stamps are the log times (``has_stamp`` False).
    CDR payloads are decoded in bulk (one position per message, gathers of 24 bytes);
    JSON payloads one by one.
    """
    return _decode(batch, channel, ("gyro", "accel"), field)


def decode_mag(batch: MessageBatch, channel: ChannelInfo) -> ImuFields:
    """Stamps and magnetic field (tesla) of MagneticField messages (one channel)."""
    return _decode(batch, channel, ("mag",))


def _patch(
    batch: MessageBatch,
    channel: ChannelInfo,
    values: dict[str, np.ndarray | None],
    field: str = "",
) -> MessageBatch:
    if channel.message_encoding != "cdr":
        raise McapInputError(
            f"channel {channel.topic}: only CDR messages can be patched in place, got"
            f" {channel.message_encoding!r}"
        )
    n = len(batch)
    # Copy the payloads into a fresh buffer so the input batch is left untouched.
    data = batch.data.copy()
    out = MessageBatch(
        channel_id=batch.channel_id.copy(),
        sequence=batch.sequence.copy(),
        log_time=batch.log_time.copy(),
        publish_time=batch.publish_time.copy(),
        data=data,
        offset=batch.offset.copy(),
        length=batch.length.copy(),
    )
    codec = _codec(channel)
    requested = {k: v for k, v in values.items() if v is not None}
    if not requested or n == 0:
        return out
    prefix = f"{field}." if field else ""
    paths = {kind: _vector_paths(codec, prefix + _VECTORS[kind]) for kind in requested}
    little, positions, _ = codec.positions(out, list(paths.values()))
    for kind, array in requested.items():
        array = np.asarray(array, dtype=np.float64)
        if array.shape != (n, 3):
            raise UsageError(f"{kind} values must have shape ({n}, 3), got {array.shape}")
        codec.write(out, little, positions[paths[kind]], "f8", array)
    return out


def patch_imu(
    batch: MessageBatch,
    channel: ChannelInfo,
    *,
    gyro: np.ndarray | None = None,
    accel: np.ndarray | None = None,
    field: str = "",
) -> MessageBatch:
    """The same Imu messages with angular velocity and/or linear acceleration (N, 3)
    replaced; every other byte is identical. The input batch is not modified. ``field``:
    path of the Imu inside a larger message, as in :func:`decode_imu`."""
    return _patch(batch, channel, {"gyro": gyro, "accel": accel}, field)


def patch_mag(batch: MessageBatch, channel: ChannelInfo, *, mag: np.ndarray) -> MessageBatch:
    """The same MagneticField messages with ``magnetic_field`` (N, 3) replaced."""
    return _patch(batch, channel, {"mag": mag})


# --- encoding ---------------------------------------------------------------------------


def _cdr_string(text: str, position: int) -> tuple[bytes, int]:
    raw = text.encode("utf-8") + b"\0"
    pad = (-position) % 4
    return b"\0" * pad + len(raw).to_bytes(4, "little") + raw, position + pad + 4 + len(raw)


def _template(kind: str, frame_id: str) -> tuple[np.ndarray, dict[str, int]]:
    """One CDR_LE message with zero values and the byte offsets of the stamp and vectors."""
    body = bytearray(b"\0" * 8)  # stamp sec, nanosec (CDR positions 0..7)
    string, position = _cdr_string(frame_id, 8)
    body += string
    pad = (-position) % 8
    body += b"\0" * pad
    position += pad
    offsets = {"sec": 4, "nanosec": 8}

    def f8(values: Sequence[float]) -> bytes:
        return np.asarray(values, dtype="<f8").tobytes()

    if kind == "imu":
        body += f8([0.0, 0.0, 0.0, 1.0])  # orientation (unknown)
        body += f8([-1.0] + [0.0] * 8)  # orientation_covariance[0] = -1: no orientation
        offsets["gyro"] = 4 + position + 13 * 8
        body += f8([0.0] * 12)
        offsets["accel"] = 4 + position + 25 * 8
        body += f8([0.0] * 12)
    else:
        offsets["mag"] = 4 + position
        body += f8([0.0] * 12)
    payload = b"\x00\x01\x00\x00" + bytes(body)
    return np.frombuffer(payload, dtype=np.uint8).copy(), offsets


def _encode_into(
    out: np.ndarray,
    kind: str,
    frame_id: str,
    t_ns: np.ndarray,
    vectors: dict[str, np.ndarray | None],
) -> None:
    """Fill ``out`` (N, L) uint8 (may be a strided view) with N encoded messages."""
    n = t_ns.shape[0]
    template, offsets = _template(kind, frame_id)
    out[:] = template
    sec = np.floor_divide(t_ns, NS_PER_S)
    if n and (int(sec.min()) < -(2**31) or int(sec.max()) >= 2**31):
        raise UsageError("timestamps do not fit a ROS 2 builtin_interfaces/Time (int32 seconds)")
    out[:, offsets["sec"] : offsets["sec"] + 4] = sec.astype("<i4").view(np.uint8).reshape(n, 4)
    nanosec = (t_ns - sec * NS_PER_S).astype("<u4")
    out[:, offsets["nanosec"] : offsets["nanosec"] + 4] = nanosec.view(np.uint8).reshape(n, 4)
    for name in ("gyro", "accel") if kind == "imu" else ("mag",):
        value = vectors.get(name)
        array = np.full((n, 3), np.nan) if value is None else np.asarray(value, dtype="<f8")
        if array.shape != (n, 3):
            raise UsageError(f"{name} must have shape ({n}, 3), got {array.shape}")
        start = offsets[name]
        out[:, start : start + 24] = (
            np.ascontiguousarray(array, dtype="<f8").view(np.uint8).reshape(n, 24)
        )


def encode_messages(
    kind: str,
    frame_id: str,
    channel_id: int,
    t_ns: np.ndarray,
    vectors: dict[str, np.ndarray | None],
    *,
    first_sequence: int = 0,
) -> MessageBatch:
    """Bulk CDR encoding of N Imu (``kind="imu"``) or MagneticField (``"mag"``) messages.

    ``vectors`` maps ``gyro``/``accel`` (or ``mag``) to (N, 3) arrays in SI units; a missing
    vector is written as NaN. Log and publish times are the stamps.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = t_ns.shape[0]
    length = _template(kind, frame_id)[0].shape[0]
    out = np.empty((n, length), dtype=np.uint8)
    _encode_into(out, kind, frame_id, t_ns, vectors)
    return MessageBatch(
        channel_id=np.full(n, channel_id, np.uint16),
        sequence=(first_sequence + np.arange(n, dtype=np.int64)).astype(np.uint32),
        log_time=t_ns.copy(),
        publish_time=t_ns.copy(),
        data=out.reshape(-1),
        offset=np.arange(n, dtype=np.int64) * length,
        length=np.full(n, length, np.int64),
    )


def _stamp_fields(t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ROS 2 ``builtin_interfaces/Time`` (sec int32, nanosec uint32) of stamps in ns."""
    sec = np.floor_divide(t_ns, NS_PER_S)
    if t_ns.shape[0] and (int(sec.min()) < -(2**31) or int(sec.max()) >= 2**31):
        raise UsageError("timestamps do not fit a ROS 2 builtin_interfaces/Time (int32 seconds)")
    return sec.astype("<i4"), (t_ns - sec * NS_PER_S).astype("<u4")


def _field_view(records: np.ndarray, start: int, dtype: str, count: int = 1) -> np.ndarray:
    """Writable view of ``count`` ``dtype`` values at byte ``start`` of every record.

    ``records`` is (..., R) uint8 with a contiguous last axis; the result is (..., count).
    """
    width = np.dtype(dtype).itemsize * count
    return records[..., start : start + width].view(dtype)


class _RecordTemplate:
    """Whole Message records (header + CDR Imu payload) of the array's Imu channels, with
    every constant byte filled in, and the byte offsets of the fields that change."""

    def __init__(self, frame_ids: Sequence[str], channel_ids: Sequence[int]) -> None:
        payloads = [_template("imu", frame) for frame in frame_ids]
        lengths = {payload.shape[0] for payload, _ in payloads}
        offsets = {tuple(sorted(o.items())) for _, o in payloads}
        self.uniform = len(lengths) == 1 and len(offsets) == 1
        if not self.uniform:
            return
        length = next(iter(lengths))
        self.record_size = MESSAGE_HEADER_SIZE + length
        self.records = np.empty((len(frame_ids), self.record_size), np.uint8)
        header = np.zeros(len(frame_ids), MESSAGE_HEADER_DTYPE)
        header["opcode"] = OP_MESSAGE
        header["record_length"] = MESSAGE_FIXED_CONTENT + length
        header["channel_id"] = np.asarray(channel_ids, np.uint16)
        self.records[:, :MESSAGE_HEADER_SIZE] = header.view(np.uint8).reshape(len(frame_ids), -1)
        for k, (payload, _) in enumerate(payloads):
            self.records[k, MESSAGE_HEADER_SIZE:] = payload
        fields = MESSAGE_HEADER_DTYPE.fields
        assert fields is not None
        self.at = {name: int(fields[name][1]) for name in ("sequence", "log_time", "publish_time")}
        for name, offset in payloads[0][1].items():
            self.at[name] = MESSAGE_HEADER_SIZE + offset

    def fill(
        self,
        t_ns: np.ndarray,
        sequence: np.ndarray,
        gyro: np.ndarray | None,
        accel: np.ndarray | None,
    ) -> np.ndarray:
        """(N, m, R) records for N samples of the m IMUs (gyro/accel (N, m, 3), SI; None = NaN)."""
        n = t_ns.shape[0]
        sec, nanosec = _stamp_fields(t_ns)
        out = np.empty((n, *self.records.shape), np.uint8)
        out[...] = self.records
        at = self.at
        _field_view(out, at["sequence"], "<u4")[..., 0] = sequence[:, None]
        _field_view(out, at["log_time"], "<u8")[..., 0] = t_ns[:, None]
        _field_view(out, at["publish_time"], "<u8")[..., 0] = t_ns[:, None]
        _field_view(out, at["sec"], "<i4")[..., 0] = sec[:, None]
        _field_view(out, at["nanosec"], "<u4")[..., 0] = nanosec[:, None]
        for name, values in (("gyro", gyro), ("accel", accel)):
            target = _field_view(out, at[name], "<f8", 3)
            if values is None:
                target[...] = np.nan
            else:
                target[...] = values
        return out


class ImuArrayWriter:
    """Writes an IMU array's samples as one Imu channel per IMU (and MagneticField channels
    when the array has magnetometers), DESIGN.md §4.

    Parameters
    ----------
    writer : McapWriter
    array : ArrayConfig
        Written as the ``imufdi.array`` metadata record.
    topics : sequence of str, optional
        Imu topic per IMU (default ``/imu<k>/data_raw``); magnetometer topics are the
        same namespace + ``/mag``.
    frame_ids : sequence of str, optional
        ``header.frame_id`` per IMU (default ``imu<k>``).
    """

    def __init__(
        self,
        writer: McapWriter,
        array: ArrayConfig,
        *,
        topics: Sequence[str] | None = None,
        frame_ids: Sequence[str] | None = None,
    ) -> None:
        m = array.n_imus
        self.writer = writer
        self.array = array
        self.topics = (
            list(topics) if topics is not None else [f"/imu{k}/data_raw" for k in range(m)]
        )
        self.frame_ids = list(frame_ids) if frame_ids is not None else [f"imu{k}" for k in range(m)]
        if len(self.topics) != m or len(self.frame_ids) != m:
            raise UsageError(f"need {m} topics and frame ids (one per IMU)")
        imu_schema = writer.register_schema(IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
        self.imu_channels = [writer.register_channel(t, "cdr", imu_schema) for t in self.topics]
        self.mag_channels: list[int] = []
        if array.has("mag"):
            mag_schema = writer.register_schema(MAG_SCHEMA_NAME, "ros2msg", MAG_SCHEMA)
            self.mag_channels = [
                writer.register_channel(t.rsplit("/", 1)[0] + "/mag", "cdr", mag_schema)
                for t in self.topics
            ]
        writer.add_metadata(ARRAY_METADATA, {"json": array.to_json()})
        self._written = 0
        self._imu_records = _RecordTemplate(self.frame_ids, self.imu_channels)

    def write_block(self, block: ImuBlock) -> None:
        """Bulk-encode a block (all IMUs) and queue it, messages in time order."""
        n = len(block)
        if n == 0:
            return
        if block.n_imus != self.array.n_imus:
            raise UsageError(f"block has {block.n_imus} IMUs but the array has {self.array.n_imus}")
        if self._imu_records.uniform and not (self.mag_channels and block.mag is not None):
            self._write_imu_records(block)
            return
        # (kind, frame id, channel id, vectors) of every channel, in message order per sample
        channels: list[tuple[str, str, int, dict[str, np.ndarray | None]]] = []
        for k, channel_id in enumerate(self.imu_channels):
            vectors = {
                "gyro": None if block.gyro is None else block.gyro[:, k],
                "accel": None if block.accel is None else block.accel[:, k],
            }
            channels.append(("imu", self.frame_ids[k], channel_id, vectors))
        if self.mag_channels and block.mag is not None:
            for k, channel_id in enumerate(self.mag_channels):
                channels.append(("mag", self.frame_ids[k], channel_id, {"mag": block.mag[:, k]}))
        lengths = {_template(kind, frame)[0].shape[0] for kind, frame, _, _ in channels}
        c = len(channels)
        ids = np.array([cid for _, _, cid, _ in channels], np.uint16)
        # Bounded memory and cache-friendly: encode in slices of samples.
        step = max(1, (4 << 20) // (c * max(lengths)))
        for start in range(0, n, step):
            stop = min(n, start + step)
            ns = stop - start
            t_ns = block.t_ns[start:stop]
            sequence = np.repeat(
                np.arange(self._written + start, self._written + stop, dtype=np.int64), c
            ).astype(np.uint32)
            if len(lengths) == 1:
                # Sample-major order: for each stamp imu0..imu(m-1) (then magnetometers).
                length = next(iter(lengths))
                out = np.empty((ns, c, length), np.uint8)
                for j, (kind, frame, _, vectors) in enumerate(channels):
                    sliced = {
                        key: None if v is None else v[start:stop] for key, v in vectors.items()
                    }
                    _encode_into(out[:, j, :], kind, frame, t_ns, sliced)
                batch = MessageBatch(
                    channel_id=np.tile(ids, ns),
                    sequence=sequence,
                    log_time=np.repeat(t_ns, c),
                    publish_time=np.repeat(t_ns, c),
                    data=out.reshape(-1),
                    offset=np.arange(ns * c, dtype=np.int64) * length,
                    length=np.full(ns * c, length, np.int64),
                )
            else:
                parts = [
                    encode_messages(
                        kind,
                        frame,
                        cid,
                        t_ns,
                        {key: None if v is None else v[start:stop] for key, v in vectors.items()},
                        first_sequence=self._written + start,
                    )
                    for kind, frame, cid, vectors in channels
                ]
                joined = MessageBatch.concatenate(parts)
                index = np.arange(len(joined))
                batch = joined.select(np.argsort((index % ns) * c + index // ns, kind="stable"))
            self.writer.add_batch(batch)
        self._written += n

    def _write_imu_records(self, block: ImuBlock) -> None:
        """Imu messages only: build whole Message records straight from the block's arrays
        (constant bytes from a template, fields through strided views) in slices of about
        4 MB, handed to the writer without further copies."""
        template = self._imu_records
        m = self.array.n_imus
        n = len(block)
        step = max(1, (4 << 20) // (m * template.record_size))
        ids = np.asarray(self.imu_channels, np.uint16)
        for start in range(0, n, step):
            stop = min(n, start + step)
            t_ns = np.asarray(block.t_ns[start:stop], np.int64)
            sequence = np.arange(self._written + start, self._written + stop).astype(np.uint32)
            records = template.fill(
                t_ns,
                sequence,
                None if block.gyro is None else block.gyro[start:stop],
                None if block.accel is None else block.accel[start:stop],
            )
            self.writer.add_records(
                records.reshape(-1, template.record_size),
                np.tile(ids, stop - start),
                np.repeat(t_ns, m),
            )
        self._written += n


def write_array(
    output: str | Path | IO[bytes],
    array: ArrayConfig,
    block: ImuBlock,
    *,
    metadata: dict[str, dict[str, str]] | None = None,
    compression: str = "zstd",
) -> None:
    """Write a whole in-memory array log (``imufdi.array`` metadata plus ``metadata``)."""
    with McapWriter(output, compression=compression) as writer:
        array_writer = ImuArrayWriter(writer, array)
        for name, values in (metadata or {}).items():
            writer.add_metadata(name, values)
        array_writer.write_block(block)


# --- alignment --------------------------------------------------------------------------


@dataclass
class AlignmentStats:
    """What time alignment of the IMU topics found (nothing is filled in).

    Attributes
    ----------
    n_aligned : int
        Array samples produced (every topic had a sample at that time).
    gaps : dict
        Per topic: samples missing where other topics have one.
    duplicates : dict
        Per topic: extra samples in the same time slot (the first is kept).
    misaligned : int
        Aligned samples whose stamps matched only within the tolerance (not exactly).
    dropped : int
        Time slots not produced because at least one topic had no sample.
    late : dict
        Per topic: samples that arrived after their time slot was already produced
        (out of order by more than the other topics' lead); dropped.
    messages : dict
        Per topic: messages read.
    max_skew_ns : int
        Largest stamp spread within an aligned sample.
    tolerance_ns : int
        Stamps closer than this are the same time slot.
    """

    n_aligned: int = 0
    gaps: dict[str, int] = field(default_factory=dict)
    duplicates: dict[str, int] = field(default_factory=dict)
    misaligned: int = 0
    dropped: int = 0
    late: dict[str, int] = field(default_factory=dict)
    messages: dict[str, int] = field(default_factory=dict)
    max_skew_ns: int = 0
    tolerance_ns: int = 0


class _Aligner:
    """Groups samples of S streams into time slots (stamps within ``tolerance``).

    Pending samples of all streams are kept together (stamps, stream index, values padded
    to a common width), so adding a chunk and resolving a block are a few numpy calls.
    """

    def __init__(
        self, names: list[str], widths: list[int], tolerance: int, max_pending: int
    ) -> None:
        self.names = names
        self.widths = widths
        self.width = max(widths)
        self.tolerance = int(tolerance)
        self.max_pending = max_pending
        self.pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.counts = np.zeros(len(names), np.int64)
        self.boundary: int | None = None  # stamps <= boundary are resolved
        self.stats = AlignmentStats(
            gaps=dict.fromkeys(names, 0),
            duplicates=dict.fromkeys(names, 0),
            late=dict.fromkeys(names, 0),
            messages=dict.fromkeys(names, 0),
            tolerance_ns=self.tolerance,
        )

    def empty(self) -> tuple[np.ndarray, list[np.ndarray]]:
        return np.zeros(0, np.int64), [np.zeros((0, w)) for w in self.widths]

    def min_pending(self) -> int:
        """Fewest samples waiting in any stream (or the most, if a stream is silent long)."""
        most = int(self.counts.max())
        return most if most > self.max_pending else int(self.counts.min())

    def _tally(self, target: dict[str, int], streams: np.ndarray) -> np.ndarray:
        counts = np.bincount(streams, minlength=len(self.names))
        for s in np.flatnonzero(counts).tolist():
            target[self.names[s]] += int(counts[s])
        return counts

    def add(self, streams: np.ndarray, t_ns: np.ndarray, values: np.ndarray) -> None:
        """Queue samples: stream index (n,), stamps (n,), values (n, <= width)."""
        streams = np.asarray(streams, np.int64)
        self._tally(self.stats.messages, streams)
        if self.boundary is not None:
            late = t_ns <= self.boundary
            if bool(late.any()):
                self._tally(self.stats.late, streams[late])
                keep = ~late
                streams, t_ns, values = streams[keep], t_ns[keep], values[keep]
        if t_ns.shape[0] == 0:
            return
        if values.shape[1] < self.width:
            values = np.pad(values, ((0, 0), (0, self.width - values.shape[1])))
        self.pending.append((t_ns, streams, values))
        self.counts += np.bincount(streams, minlength=len(self.names))

    def resolve(self, final: bool) -> tuple[np.ndarray, list[np.ndarray]]:
        """Stamps (K,) and per-stream values (K, width) of the time slots now complete."""
        if not self.pending:
            return self.empty()
        n_streams = len(self.names)
        all_t = np.concatenate([p[0] for p in self.pending])
        all_s = np.concatenate([p[1] for p in self.pending])
        all_v = np.concatenate([p[2] for p in self.pending])
        present = self.counts > 0
        horizon: int | None = None
        if not final:
            if not bool(present.all()) and int(self.counts.max()) <= self.max_pending:
                return self.empty()
            # Newest stamp of each stream; a stream silent for long does not hold the rest.
            newest = np.full(n_streams, np.iinfo(np.int64).max)
            order_s = np.lexsort((all_t, all_s))
            last_of = np.flatnonzero(np.r_[all_s[order_s][1:] != all_s[order_s][:-1], True])
            newest[all_s[order_s][last_of]] = all_t[order_s][last_of]
            horizon = int(newest.min())
        order = np.argsort(all_t, kind="stable")
        t_sorted, s_sorted = all_t[order], all_s[order]
        new_slot = np.empty(t_sorted.shape[0], bool)
        new_slot[0] = True
        np.greater(np.diff(t_sorted), self.tolerance, out=new_slot[1:])
        slot = np.cumsum(new_slot) - 1
        slot_start = np.flatnonzero(new_slot)
        slot_end = t_sorted[np.r_[slot_start[1:] - 1, t_sorted.shape[0] - 1]]
        n_slots = slot_start.shape[0]
        if horizon is None:
            n_done = n_slots
        else:
            # A future sample (stamp >= horizon) cannot join a slot ending before this.
            n_done = int(np.searchsorted(slot_end + self.tolerance, horizon, side="left"))
        if n_done == 0:
            return self.empty()
        n_items = int(slot_start[n_done]) if n_done < n_slots else t_sorted.shape[0]
        slot, s_done, rows = slot[:n_items], s_sorted[:n_items], order[:n_items]
        boundary = int(slot_end[n_done - 1])
        self.boundary = boundary if self.boundary is None else max(self.boundary, boundary)
        key = slot * n_streams + s_done
        counts = np.bincount(key, minlength=n_done * n_streams).reshape(n_done, n_streams)
        complete = np.all(counts >= 1, axis=1)
        missing = counts == 0
        for s, name in enumerate(self.names):
            self.stats.gaps[name] += int(missing[:, s].sum())
            self.stats.duplicates[name] += int(np.maximum(counts[:, s] - 1, 0).sum())
        self.stats.dropped += int((~complete).sum())
        unique_keys, first = np.unique(key, return_index=True)
        first_slot = unique_keys // n_streams
        first_stream = unique_keys % n_streams
        keep = complete[first_slot]
        first, first_slot, first_stream = first[keep], first_slot[keep], first_stream[keep]
        rank = np.cumsum(complete) - 1
        k = int(complete.sum())
        row = np.zeros((k, n_streams), np.int64)
        row[rank[first_slot], first_stream] = rows[first]
        stamps = all_t[row]
        values = [all_v[row[:, s], : self.widths[s]] for s in range(n_streams)]
        if k:
            skew = stamps.max(axis=1) - stamps.min(axis=1)
            self.stats.misaligned += int(np.count_nonzero(skew))
            self.stats.max_skew_ns = max(self.stats.max_skew_ns, int(skew.max()))
        self.stats.n_aligned += k
        rest = order[n_items:]
        if rest.shape[0]:
            rest = np.sort(rest)  # keep arrival order
            self.pending = [(all_t[rest], all_s[rest], all_v[rest])]
            self.counts = np.bincount(all_s[rest], minlength=n_streams)
        else:
            self.pending = []
            self.counts = np.zeros(n_streams, np.int64)
        return stamps[:, 0].copy(), values


# --- reader -----------------------------------------------------------------------------


class ImuArrayReader:
    """Streaming reader of an IMU array from any MCAP with ``sensor_msgs/msg/Imu`` channels.

    Parameters
    ----------
    source : path, ``"-"``, binary stream or McapSource
    topics : sequence of str, optional
        Imu topics to read, in array order (default: every Imu channel, sorted naturally).
        A channel whose type holds exactly one ``sensor_msgs/msg/Imu`` field (e.g. a
        driver's message with an ``imu`` field) counts as an Imu channel; ``"/topic:path"``
        picks the Imu field at ``path`` explicitly. Magnetometers are read from
        ``<namespace>/mag`` MagneticField topics when every selected IMU has one.
    strict : bool
        Raise McapInputError on a truncated or corrupt file instead of adding a warning.
    time_source : {"auto", "header", "log_time"}
        Stamp used for alignment and output: ``header.stamp``, the MCAP log time, or
        (``auto``) the header stamp unless the Imu has no header or its stamps are all
        zero, in which case the log time is used with a warning.
    block_size : int
        Samples per block yielded by :meth:`blocks`.
    tolerance_ns : int, optional
        Stamps of different topics closer than this are the same sample (default: 30 % of
        the sample period).

    Attributes
    ----------
    array : ArrayConfig
        From the ``imufdi.array`` metadata when it matches the topics, else inferred
        (co-aligned, one IMU per topic, measured rate).
    imu_fields : dict
        Topic -> path of the Imu inside its messages (``""``: the messages are Imu).
    imu_types : dict
        Topic -> message type name.
    time_source : str
        ``"header"`` or ``"log_time"``, as resolved.
    """

    def __init__(
        self,
        source: str | Path | IO[bytes] | McapSource,
        *,
        topics: Sequence[str] | None = None,
        strict: bool = False,
        time_source: str = "auto",
        block_size: int = 4096,
        tolerance_ns: int | None = None,
    ) -> None:
        if time_source not in ("auto", "header", "log_time"):
            raise UsageError(f"unknown time source {time_source!r}; valid: auto, header, log_time")
        if block_size < 1:
            raise UsageError(f"block_size must be >= 1, got {block_size}")
        self.source = (
            source if isinstance(source, McapSource) else McapSource(source, strict=strict)
        )
        self.time_source = time_source
        self.block_size = block_size
        self.warnings = self.source.warnings
        self._batches = self.source.batches()
        self._prefetched: deque[MessageBatch] = deque()
        self._exhausted = False
        self._imu_like: dict[int, tuple[ChannelInfo, bool]] = {}
        self._topics_given = topics is not None
        self._prefetch_setup(topics)
        try:
            self._select_topics(topics)
        except Exception:
            self.source.push_back(list(self._prefetched))
            if not isinstance(source, McapSource):
                self.close()
            raise
        imu_channels = {t: self.source.channels[cid] for t, cid in self._topic_channel.items()}
        mag_channels = {c.topic: c for c in self.source.channels.values() if is_mag_channel(c)}
        mag_topics = [t.rsplit("/", 1)[0] + "/mag" for t in self.imu_topics]
        self.mag_topics = (
            mag_topics
            if all(t in mag_channels for t in mag_topics) and not any(self.imu_fields.values())
            else []
        )
        self._imu_channel = {imu_channels[t].id: k for k, t in enumerate(self.imu_topics)}
        self._mag_channel = (
            {mag_channels[t].id: k for k, t in enumerate(self.mag_topics)}
            if self.mag_topics
            else {}
        )
        self._known_channels = -1  # check for late Imu channels on the first batch
        self._late_topics: set[str] = set()
        self._resolve_time_source()
        self.array = self._array_config()
        if self.array.has("mag") and not self.mag_topics:
            self.warnings.append(
                "array config has magnetometers but not every IMU topic has a <ns>/mag topic;"
                " magnetometers are not read"
            )
        period_ns = NS_PER_S / self.array.rate_hz
        tolerance = int(0.3 * period_ns) if tolerance_ns is None else int(tolerance_ns)
        names = list(self.imu_topics) + list(self.mag_topics)
        widths = [6] * len(self.imu_topics) + [3] * len(self.mag_topics)
        self._aligner = _Aligner(names, widths, tolerance, max_pending=max(8 * block_size, 65536))
        self.stats = self._aligner.stats
        self._groups: list[tuple[np.ndarray, ChannelInfo, tuple[str, ...], str]] | None = None
        self._stream_of = np.zeros(0, np.int64)

    # --- setup helpers --------------------------------------------------------------------

    def _select_topics(self, topics: Sequence[str] | None) -> None:
        """Fill ``imu_topics``, ``imu_fields``, ``imu_types`` and the topic -> channel id map."""
        channels = list(self.source.channels.values())
        by_topic = {c.topic: c for c in channels}
        found = {c.topic: imu_fields_of(c) for c in channels}
        self.imu_fields: dict[str, str] = {}
        self._topic_channel: dict[str, int] = {}
        if topics is None:
            usable = sorted((t for t, f in found.items() if len(f) == 1), key=natural_key)
            if not usable:
                listed = sorted(
                    (f"{c.topic} ({schema_name(c) or 'no schema'})" for c in channels),
                    key=natural_key,
                )
                raise NoImuChannelError(
                    f"{self.source.name}: no sensor_msgs/msg/Imu channel (CDR or JSON), and no"
                    " message type holding exactly one Imu field; topics: "
                    + (", ".join(listed) or "none")
                    + (f"; {self.warnings[0]}" if self.warnings else "")
                )
            self.imu_topics = usable
            for topic in usable:
                self.imu_fields[topic] = found[topic][0]
                self._topic_channel[topic] = by_topic[topic].id
        else:
            self.imu_topics = []
            for spec in topics:
                topic, _, path = spec.partition(":")
                channel = by_topic.get(topic)
                if channel is None:
                    usable = [t for t, f in found.items() if f]
                    raise NoImuChannelError(
                        f"{self.source.name}: no Imu channel on topic {topic or '(none)'};"
                        " Imu topics: " + (", ".join(sorted(usable, key=natural_key)) or "none")
                    )
                fields = found[topic]
                kind = schema_name(channel) or "no schema"
                if path and path not in fields:
                    raise McapInputError(
                        f"topic {topic} ({kind}, {channel.message_encoding}) has no"
                        f" sensor_msgs/msg/Imu field {path!r}; Imu fields: "
                        + (", ".join(f or "(the message)" for f in fields) or "none")
                    )
                if not path and len(fields) != 1:
                    if fields:
                        raise McapInputError(
                            f"topic {topic} ({kind}) holds {len(fields)} sensor_msgs/msg/Imu"
                            f" fields ({', '.join(fields)}); choose one with --topic"
                            f" {topic}:{fields[0]}"
                        )
                    raise McapInputError(
                        f"topic {topic} has type {kind} ({channel.message_encoding}), which is"
                        " not sensor_msgs/msg/Imu and holds no Imu field (CDR)"
                    )
                if topic in self.imu_fields:
                    raise UsageError(f"topic {topic} is selected twice")
                self.imu_topics.append(topic)
                self.imu_fields[topic] = path or fields[0]
                self._topic_channel[topic] = channel.id
            if not self.imu_topics:
                raise UsageError("no topic selected")
        self.imu_types = {t: schema_name(by_topic[t]) for t in self.imu_topics}

    def _resolve_time_source(self) -> None:
        """``auto``: header stamps, unless the first Imu topic has none or they are all 0."""
        requested = self.time_source
        if requested == "log_time":
            return
        topic = self.imu_topics[0]
        cid = self._topic_channel[topic]
        channel = self.source.channels[cid]
        # malformed messages are left out here and reported when the data are read
        fields = [
            _decode(
                sub, channel, ("gyro", "accel"), self.imu_fields[topic], np.ones(len(sub), bool)
            )
            for sub in (b.select(b.channel_id == cid) for b in self._prefetched)
            if len(sub)
        ]
        if not fields:
            self.time_source = "header"
            return
        has_stamp = all(f.has_stamp for f in fields)
        zero = has_stamp and all(not bool(np.any(f.t_ns)) for f in fields)
        if has_stamp and not zero:
            self.time_source = "header"
            return
        why = "has no header.stamp" if not has_stamp else "has header stamps that are all zero"
        if requested == "header":
            raise McapInputError(
                f"{topic} ({self.imu_types[topic]}) {why}; use --stamps log (MCAP log time)"
            )
        self.time_source = "log_time"
        self.warnings.append(f"{topic} ({self.imu_types[topic]}) {why}: using the log time")

    def _prefetch_setup(self, topics: Sequence[str] | None) -> None:
        """Read ahead until the IMU set and the rate are known.

        Without a summary (stdin, a truncated file) channels are only known as their records
        are met, so batches are read until every Imu channel met so far (or every requested
        topic) has at least ``_SETUP_MESSAGES`` messages, within ``_SETUP_BATCHES`` batches
        and ``_SETUP_BYTES`` of buffered data. An Imu channel first met later is reported
        (:meth:`_check_new_channels`), never silently dropped.
        """
        counts: dict[int, int] = {}
        buffered = 0
        wanted = {spec.partition(":")[0] for spec in topics} if topics is not None else None
        while not self._exhausted:
            if len(self._prefetched) >= _SETUP_BATCHES or buffered >= _SETUP_BYTES:
                break
            imu_ids = [
                c.id
                for c in list(self.source.channels.values())
                if (c.topic in wanted if wanted is not None else self._holds_one_imu(c))
            ]
            seen_topics = {self.source.channels[i].topic for i in imu_ids}
            ready = bool(imu_ids) and (wanted is None or wanted <= seen_topics)
            if ready and all(counts.get(i, 0) >= _SETUP_MESSAGES for i in imu_ids):
                break
            try:
                batch = next(self._batches)
            except StopIteration:
                self._exhausted = True
                break
            self._prefetched.append(batch)
            buffered += int(batch.data.nbytes)
            ids, n = np.unique(batch.channel_id, return_counts=True)
            for i, c in zip(ids.tolist(), n.tolist()):
                counts[i] = counts.get(i, 0) + c

    def _holds_one_imu(self, channel: ChannelInfo) -> bool:
        """The channel is read as an IMU by default (an Imu, or one Imu field); cached."""
        known = self._imu_like.get(channel.id)
        if known is None or known[0] is not channel:
            known = (channel, len(imu_fields_of(channel)) == 1)
            self._imu_like[channel.id] = known
        return known[1]

    def _check_new_channels(self) -> None:
        """Warn about Imu channels first met after the IMU set was fixed (not read)."""
        channels = self.source.channels
        if len(channels) == self._known_channels or self._topics_given:
            return
        self._known_channels = len(channels)
        selected = {self.source.channels[cid].topic for cid in self._imu_channel}
        for channel in list(channels.values()):
            if (
                self._holds_one_imu(channel)
                and channel.topic not in selected
                and channel.topic not in self._late_topics
            ):
                self._late_topics.add(channel.topic)
                self.warnings.append(
                    f"Imu topic {channel.topic} first appears after the IMU set was fixed from"
                    f" the first {_SETUP_MESSAGES} messages of each topic; it is not read"
                    " (select topics with --topic)"
                )

    def _array_config(self) -> ArrayConfig:
        m = len(self.imu_topics)
        meta = self.source.metadata.get(ARRAY_METADATA)
        if meta is not None and "json" in meta:
            try:
                array = ArrayConfig.from_json(meta["json"])
            except ArrayConfigError as err:
                self.warnings.append(f"ignoring the imufdi.array metadata: {err}")
            else:
                if array.n_imus == m:
                    return array
                self.warnings.append(
                    f"imufdi.array metadata describes {array.n_imus} IMUs but {m} topics are"
                    " read; using an inferred co-aligned array"
                )
        rate = self._measured_rate()
        sensors = ["gyro", "accel"] + (["mag"] if self.mag_topics else [])
        return ArrayConfig.co_aligned(m, rate, sensors=sensors)

    def _measured_rate(self) -> float:
        channels = {c.id: c for c in self.source.channels.values()}
        first = self.imu_topics[0]
        cid = next(i for i, k in self._imu_channel.items() if k == 0)
        stamps = []
        for batch in self._prefetched:
            sub = batch.select(batch.channel_id == cid)
            if len(sub):
                # malformed messages are left out here and reported when the data are read
                fields = _decode(
                    sub,
                    channels[cid],
                    ("gyro", "accel"),
                    self.imu_fields[first],
                    np.ones(len(sub), bool),
                )
                stamps.append(fields.t_ns if self.time_source == "header" else fields.log_time)
        t = np.sort(np.concatenate(stamps)) if stamps else np.zeros(0, np.int64)
        steps = np.diff(t)
        steps = steps[steps > 0]
        if steps.size == 0:
            self.warnings.append(f"cannot measure the sample rate of {first}; assuming 100 Hz")
            return 100.0
        rate = NS_PER_S / float(np.median(steps))
        return float(f"{rate:.6g}") if math.isfinite(rate) and rate > 0 else 100.0

    # --- reading ------------------------------------------------------------------------

    def _raw_batches(self) -> Iterator[MessageBatch]:
        while self._prefetched:
            yield self._prefetched.popleft()
        if not self._exhausted:
            yield from self._batches
            self._exhausted = True

    def _decode_groups(self) -> list[tuple[np.ndarray, ChannelInfo, tuple[str, ...], str]]:
        """Channels read together: CDR channels sharing a schema (and Imu field) are decoded
        in one pass (their layout is the same); JSON channels one by one."""
        groups: dict[Any, list[int]] = {}
        field_of = {self._topic_channel[t]: f for t, f in self.imu_fields.items()}
        for cid in list(self._imu_channel) + list(self._mag_channel):
            channel = self.source.channels[cid]
            kind = "imu" if cid in self._imu_channel else "mag"
            path = field_of.get(cid, "") if kind == "imu" else ""
            if channel.message_encoding == "cdr" and channel.schema is not None:
                key: Any = (kind, channel.schema.name, channel.schema.data, path)
            else:
                key = (kind, cid, path)
            groups.setdefault(key, []).append(cid)
        out: list[tuple[np.ndarray, ChannelInfo, tuple[str, ...], str]] = []
        for key, ids in groups.items():
            kinds: tuple[str, ...] = ("gyro", "accel") if key[0] == "imu" else ("mag",)
            out.append((np.array(ids, np.int64), self.source.channels[ids[0]], kinds, key[-1]))
        return out

    def _feed(self, batch: MessageBatch) -> None:
        self._check_new_channels()
        if len(batch) == 0:
            return
        if self._groups is None:
            self._groups = self._decode_groups()
            m = len(self.imu_topics)
            self._stream_of = np.full(65536, -1, np.int64)
            for cid, k in self._imu_channel.items():
                self._stream_of[cid] = k
            for cid, k in self._mag_channel.items():
                self._stream_of[cid] = m + k
        stream_of_message = self._stream_of[batch.channel_id]
        for ids, channel, kinds, path in self._groups:
            if ids.shape[0] == 1:
                mask = batch.channel_id == ids[0]
            else:
                mask = np.isin(batch.channel_id, ids)
            if not bool(mask.any()):
                continue
            selected = batch if bool(mask.all()) else batch.select(mask)
            valid = np.ones(len(selected), bool)
            fields = _decode(selected, channel, kinds, path, valid)
            streams = stream_of_message[mask]
            if not bool(valid.all()):
                streams = streams[valid]
                self.source._problem(
                    f"{int((~valid).sum())} malformed {schema_name(channel)} message(s) on"
                    f" {channel.topic} skipped (fields past the message end or not decodable)"
                )
            t = fields.t_ns if self.time_source == "header" else fields.log_time
            if kinds == ("mag",):
                values = fields.mag
            else:
                values = np.concatenate([fields.gyro, fields.accel], axis=1)  # type: ignore[list-item]
            self._aligner.add(streams, t, values)  # type: ignore[arg-type]

    def _block(self, t_ns: np.ndarray, values: list[np.ndarray]) -> ImuBlock:
        m = len(self.imu_topics)
        n = t_ns.shape[0]
        imu = np.stack(values[:m], axis=1) if m else np.zeros((n, 0, 6))
        gyro = imu[:, :, 0:3] if self.array.has("gyro") else None
        accel = imu[:, :, 3:6] if self.array.has("accel") else None
        mag = None
        if self.mag_topics and self.array.has("mag"):
            mag = np.stack(values[m:], axis=1)
        return ImuBlock(
            t_ns=t_ns,
            gyro=None if gyro is None else np.ascontiguousarray(gyro),
            accel=None if accel is None else np.ascontiguousarray(accel),
            mag=mag,
        )

    def stream(self) -> Iterator[tuple[MessageBatch, ImuBlock]]:
        """Each raw batch (all channels, for pass-through copying) with the aligned samples
        completed by it (possibly none); a final (empty batch, rest) pair at the end."""
        for batch in self._raw_batches():
            self._feed(batch)
            # Resolve in large groups: per-call numpy overhead is paid per block, not per chunk.
            if self._aligner.min_pending() >= self.block_size:
                t_ns, values = self._aligner.resolve(final=False)
                yield batch, self._block(t_ns, values)
            else:
                yield batch, self._block(*self._aligner.empty())
        t_ns, values = self._aligner.resolve(final=True)
        if t_ns.shape[0]:
            yield MessageBatch.empty(), self._block(t_ns, values)

    def blocks(self) -> Iterator[ImuBlock]:
        """Aligned array samples in blocks of ``block_size`` (the last may be shorter)."""
        yield from rechunk((block for _, block in self.stream()), self.block_size)

    def close(self) -> None:
        self.source.close()

    def __enter__(self) -> ImuArrayReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def read_array(source: str | Path | IO[bytes], **kw: Any) -> tuple[ArrayConfig, ImuBlock]:
    """Read a whole log into memory: (array config, all aligned samples)."""
    with ImuArrayReader(source, **kw) as reader:
        blocks = [b for _, b in reader.stream() if len(b)]
        if not blocks:
            return reader.array, reader._block(
                np.zeros(0, np.int64), [np.zeros((0, w)) for w in reader._aligner.widths]
            )
        return reader.array, ImuBlock.concatenate(blocks)
