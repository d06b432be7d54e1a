"""``sensor_msgs/msg/Imu`` and ``MagneticField`` in MCAP: which channels hold them, and
bulk decoding and in-place patching of their CDR (or JSON) messages (docs/formats.md)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from imufdi_cli.errors import McapInputError, UsageError
from imufdi_cli.jsonin import loads
from imufdi_cli.mcapio.cdr import CdrCodec, codec_for
from imufdi_cli.mcapio.records import (
    ChannelInfo,
    MessageBatch,
    gather_bytes,
)
from imufdi_cli.mcapio.scan import PayloadFields, fill_float_columns

ARRAY_METADATA = "imufdi.array"
IMU_TYPE_NAMES = ("sensor_msgs/msg/Imu", "sensor_msgs/Imu")
MAG_TYPE_NAMES = ("sensor_msgs/msg/MagneticField", "sensor_msgs/MagneticField")
NS_PER_S = 1_000_000_000


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
    contiguous: bool = True,
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
    joint = _read_vector_span(codec, batch, little, positions, vector_paths, contiguous)
    for kind, path in vector_paths.items():
        if joint is not None:
            setattr(out, kind, joint[kind])
        else:
            value = codec.read(batch, little, positions[path], "f8", 3)
            setattr(out, kind, value.astype(np.float64, copy=False))
    return out


def _read_vector_span(
    codec: CdrCodec,
    batch: MessageBatch,
    little: np.ndarray,
    positions: dict[str, np.ndarray],
    vector_paths: dict[str, str],
    contiguous: bool,
) -> dict[str, np.ndarray] | None:
    """Several float64 x/y/z vectors at a constant distance from each other in every
    message (``angular_velocity`` and ``linear_acceleration`` of an Imu: 96 bytes apart),
    read with one gather of the span holding them; each (N, 3) float64, views of that span
    unless ``contiguous``. None when they are not at constant distances, not all
    little-endian, or there is only one."""
    if len(vector_paths) < 2 or not bool(little.all()):
        return None
    leaves = codec.layout.leaves
    first_path = min(vector_paths.values(), key=lambda p: leaves[p].offset)
    first = leaves[first_path]
    deltas = {}
    for kind, path in vector_paths.items():
        leaf = leaves[path]
        if leaf.segment != first.segment or (leaf.offset - first.offset) % 8:
            return None
        deltas[kind] = (leaf.offset - first.offset) // 8
    width = max(deltas.values()) + 3
    if width > 64:  # far apart: separate gathers copy less
        return None
    span = gather_bytes(batch.data, positions[first_path], 8 * width).view("<f8")
    span = span.reshape(len(batch), width)
    out = {kind: span[:, d : d + 3] for kind, d in deltas.items()}
    if contiguous:
        out = {kind: np.ascontiguousarray(value) for kind, value in out.items()}
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
            obj = loads(batch.payload(i), f"{channel.topic}: JSON message", McapInputError)
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
        except (
            KeyError,
            TypeError,
            ValueError,
            AttributeError,
            OverflowError,
            McapInputError,
        ) as err:
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
    contiguous: bool = True,
) -> ImuFields:
    """Decode one channel's messages (``field``: path of an embedded Imu, "" for the message
    itself). Malformed messages raise McapInputError, unless ``valid`` (N,) bool is given:
    then they are left out and their entries set False. With ``contiguous`` False the
    vectors may be strided views (the reader copies them once more anyway)."""
    if channel.message_encoding == "cdr":
        return _decode_cdr(batch, channel, kinds, field, valid, contiguous)
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


# --- fixed-layout fast path ---------------------------------------------------------------


class _Fields:
    """Reads one primitive at a constant offset from each of N payloads of ``data``: a
    typed strided view when the payloads are evenly spaced (one 1-D copy per field, no
    gather), else a typed view sliding by one byte indexed at the payload starts."""

    def __init__(self, data: np.ndarray, offsets: np.ndarray) -> None:
        self.data = data
        self.offsets = offsets
        n = offsets.shape[0]
        self.first = int(offsets[0])
        self.step = int(offsets[1] - offsets[0]) if n > 1 else 1
        self.regular = self.step > 0 and (
            n <= 2
            or (
                int(offsets[-1]) == self.first + (n - 1) * self.step
                and np.count_nonzero(np.diff(offsets) != self.step) == 0
            )
        )

    def view(self, rel: int, dtype: str) -> np.ndarray:
        """(N,) values of ``dtype`` at ``rel`` bytes into every payload (a view when the
        payloads are evenly spaced, else a copy)."""
        if self.regular:
            return np.ndarray(
                (self.offsets.shape[0],), dtype, self.data, self.first + rel, (self.step,)
            )
        size = np.dtype(dtype).itemsize
        windows = np.ndarray((self.data.shape[0] - size + 1,), dtype, self.data, 0, (1,))
        return windows[self.offsets + rel]


class FixedLayoutDecoder:
    """Stamps and vectors of a channel group's CDR messages read at constant offsets.

    An Imu message's field positions depend only on its encapsulation header and the
    lengths of the strings before the fields (``header.frame_id``); a logger writes the
    same ones in every message of a topic. The first message of each channel is located
    by the general decoder (:meth:`CdrCodec.positions`), which also gives those layout
    keys; a batch whose messages all have that payload length and the keys of their
    channel is then read with one strided copy per field and no position arithmetic
    (:meth:`decode`). Anything else (another length, a different ``frame_id`` length,
    big-endian CDR, sequences before the fields, channels laid out differently) returns
    None and is decoded by the general path, with the same results.

    Parameters
    ----------
    channel : ChannelInfo
        A channel of the group (they share schema and Imu field).
    kinds : tuple of str
        ``("gyro", "accel")`` or ``("mag",)``.
    field : str
        Path of the Imu inside the message (``""``: the message is one).
    n_streams : int
        Stream indices of the reader (the table of layout keys has one row per stream).
    """

    def __init__(
        self, channel: ChannelInfo, kinds: Sequence[str], field: str, n_streams: int
    ) -> None:
        self.kinds = tuple(kinds)
        self.usable = True
        self.length = -1
        self.rel: dict[str, int] = {}
        self.keys: list[int] = []
        self.strings: list[str] = []
        self.expected = np.zeros((n_streams, 0), np.uint32)
        self.probed = np.zeros(n_streams, bool)
        self.uniform: list[bool] = []
        try:
            codec = _codec(channel)
            prefix = f"{field}." if field else ""
            self.vector_paths = [_vector_paths(codec, prefix + _VECTORS[k]) for k in kinds]
        except McapInputError:
            self.usable = False
            return
        self.codec = codec
        leaves = codec.layout.leaves
        stamp = [f"{prefix}header.stamp.sec", f"{prefix}header.stamp.nanosec"]
        self.has_stamp = all(path in leaves for path in stamp)
        self.stamp = stamp if self.has_stamp else []
        self.paths = [*self.stamp, *self.vector_paths]
        last_segment = max(leaves[path].segment for path in self.paths)
        for step in codec.layout.steps[:last_segment]:
            if step.kind in ("string", "wstring"):
                self.strings.append(step.path)
            elif step.kind != "align":  # a sequence or an opaque step: the general path
                self.usable = False

    def _probe(self, firsts: MessageBatch, streams: list[int]) -> bool:
        """Locate the fields of the first message of each of ``streams`` (``firsts``, one
        message per stream, in that order) with the general decoder, in one call, and
        remember their layout keys, stream by stream; False at the first stream whose
        layout cannot be shared."""
        valid = np.ones(len(streams), bool)
        try:
            little, positions, _ = self.codec.positions(firsts, self.paths + self.strings, valid)
        except McapInputError:
            return False
        for j, stream in enumerate(streams):
            if not bool(valid[j]) or not bool(little[j]):
                return False
            base = int(firsts.offset[j])
            rel = {path: int(positions[path][j]) - base for path in self.paths}
            keys = [0] + [int(positions[path][j]) - 4 - base for path in self.strings]
            length = int(firsts.length[j])
            if self.length < 0:
                self.rel, self.keys, self.length = rel, keys, length
                self.expected = np.zeros((self.probed.shape[0], len(keys)), np.uint32)
            elif rel != self.rel or keys != self.keys or length != self.length:
                return False
            payload = firsts.data[base : base + length]
            self.expected[stream] = [int(payload[k : k + 4].view("<u4")[0]) for k in keys]
            self.probed[stream] = True
        return True

    def _head(self, fields: _Fields) -> dict[int, np.ndarray]:
        """{offset: (N,) uint32} of the layout keys and stamp fields, from one 16-byte
        copy per payload when they all lie in the first 16 bytes (an Imu's encapsulation,
        stamp and ``frame_id`` length do), else empty."""
        wanted = [*self.keys, *(self.rel[path] for path in self.stamp)]
        if any(rel % 4 or rel + 4 > 16 for rel in wanted) or self.length < 16:
            return {}
        words = fields.view(0, "V16").copy().view("<u4").reshape(-1, 4)
        return {rel: words[:, rel // 4] for rel in wanted}

    def payload_fields(self) -> PayloadFields | None:
        """What the read-ahead thread should read of every payload for :meth:`decode`
        (the 16-byte head and the vector components), once the layout is known and its
        keys and stamps lie in the first 16 bytes; else None."""
        wanted = [*self.keys, *(self.rel[path] for path in self.stamp)]
        if not self.usable or self.length < 16 or any(r % 4 or r + 4 > 16 for r in wanted):
            return None
        offsets = tuple(
            self.rel[path] + 8 * axis for path in self.vector_paths for axis in range(3)
        )
        return PayloadFields(self.length, offsets)

    def decode(
        self, batch: MessageBatch, streams: np.ndarray
    ) -> tuple[np.ndarray | None, np.ndarray] | None:
        """(stamps (N,) int64 ns or None without ``header.stamp``, values (N, 3 per kind)
        float64: gyro then accel, or mag) of the group's messages ``batch`` whose stream
        indices are ``streams``; None when they do not all share the known layout."""
        n = len(batch)
        data = batch.data
        if not self.usable or n == 0 or data.dtype != np.uint8 or not data.flags.c_contiguous:
            return None
        if np.count_nonzero(batch.length != (self.length if self.length >= 0 else batch.length[0])):
            return None
        if not bool(self.probed[streams[0]]) or not bool(self.probed[streams[-1]]):
            present, first = np.unique(streams, return_index=True)
            todo = ~self.probed[present]
            if bool(todo.any()) and not self._probe(
                batch.select(first[todo]), present[todo].tolist()
            ):
                self.usable = False
                return None
        ahead = getattr(batch, "payload_fields", None)
        if ahead is not None and ahead[0] != self.payload_fields():
            ahead = None
        if ahead is None:
            fields = _Fields(batch.data, batch.offset)
            head = self._head(fields)
        else:  # read by the read-ahead thread (PayloadFields.read): the same bytes
            words = ahead[1]
            head = {
                rel: words[:, rel // 4] for rel in [*self.keys, *(self.rel[p] for p in self.stamp)]
            }
        table = self.expected
        for j, rel in enumerate(self.keys):
            got = head[rel] if rel in head else fields.view(rel, "<u4").copy()
            column = table[:, j]
            probed_values = column[self.probed]
            if bool((probed_values == probed_values[0]).all()):
                bad = np.count_nonzero(got != probed_values[0])
            else:
                bad = np.count_nonzero(got != column[streams])
            if bad:
                return None
        t_ns = None
        if self.has_stamp:
            sec, nanosec = (self.rel[path] for path in self.stamp)
            t_ns = (head[sec] if sec in head else fields.view(sec, "<u4")).view("<i4")
            t_ns = t_ns.astype(np.int64)
            t_ns *= NS_PER_S
            t_ns += head[nanosec] if nanosec in head else fields.view(nanosec, "<u4")
        if ahead is not None:
            return t_ns, ahead[2]
        values = np.empty((n, 3 * len(self.vector_paths)))
        offsets = [self.rel[path] + 8 * axis for path in self.vector_paths for axis in range(3)]
        fill_float_columns(values, fields.view, offsets)
        return t_ns, values
