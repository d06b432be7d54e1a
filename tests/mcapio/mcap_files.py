"""Small IMU-array MCAP files written by the ``mcap`` package (chunked or not), for the
reader's robustness tests, and helpers to read them (through a pipe, with the ``mcap``
package, record by record)."""

from __future__ import annotations

import functools
import io
import struct
import zlib

import lz4.frame
import numpy as np
import zstandard
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from imufdi_cli.mcapio import McapSource, encode_messages
from imufdi_cli.mcapio.schemas import IMU_SCHEMA, IMU_SCHEMA_NAME

T0_NS = 1_700_000_000_000_000_000


@functools.cache  # bytes: the tests that ask for the same file share one copy
def imu_file(
    *,
    n_imus: int = 4,
    n_samples: int = 50,
    chunked: bool = True,
    compression: str = "zstd",
    chunk_size: int = 2048,
    seed: int = 0,
) -> bytes:
    """An MCAP of ``n_imus`` Imu topics at 100 Hz, each channel declared just before its
    first message (as a streaming recorder does), written by the ``mcap`` package (once
    per set of arguments in a process)."""
    rng = np.random.default_rng(seed)
    stream = io.BytesIO()
    kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
    writer = Writer(
        stream, chunk_size=chunk_size, compression=kind[compression], use_chunking=chunked
    )
    writer.start(profile="ros2", library="test")
    schema = writer.register_schema(IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
    t_ns = T0_NS + np.arange(n_samples, dtype=np.int64) * 10_000_000
    payloads = []
    for k in range(n_imus):
        batch = encode_messages(
            "imu",
            f"imu{k}",
            k,
            t_ns,
            {"gyro": rng.normal(0, 0.1, (n_samples, 3)), "accel": rng.normal(0, 1, (n_samples, 3))},
        )
        payloads.append([batch.payload(i) for i in range(n_samples)])
    channels: list[int] = []
    for i in range(n_samples):
        for k in range(n_imus):
            if len(channels) <= k:
                channels.append(writer.register_channel(f"/imu{k}/data_raw", "cdr", schema))
            writer.add_message(channels[k], int(t_ns[i]), payloads[k][i], int(t_ns[i]), i)
    writer.finish()
    return stream.getvalue()


def _record(opcode: int, content: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(content)) + content


def _string(text: str) -> bytes:
    raw = text.encode()
    return struct.pack("<I", len(raw)) + raw


def chunk_record(records: bytes, compression: str, *, declared: int | None = None) -> bytes:
    """A Chunk record of ``records`` compressed with ``compression`` ("zstd", "lz4", "");
    ``declared`` overrides the uncompressed size it claims."""
    if compression == "zstd":
        payload = zstandard.ZstdCompressor().compress(records)
    elif compression == "lz4":
        payload = lz4.frame.compress(records)
    else:
        payload = records
    size = len(records) if declared is None else declared
    content = (
        struct.pack("<QQQI", 0, 0, size, zlib.crc32(records))
        + _string(compression)
        + struct.pack("<Q", len(payload))
        + payload
    )
    return _record(0x06, content)


def zero_chunk(size: int, compression: str, *, declared: int | None = None) -> bytes:
    """A Chunk record of ``size`` zero bytes compressed with "zstd" or "lz4", built in 1 MiB
    pieces (the zeros are never held whole); ``declared`` overrides the size it claims."""
    piece = bytes(1 << 20)
    crc = 0
    parts = []
    if compression == "zstd":
        zstd_writer = zstandard.ZstdCompressor().compressobj(size=size)
        for _ in range(size >> 20):
            parts.append(zstd_writer.compress(piece))
        parts.append(zstd_writer.flush())
    else:
        lz4_writer = lz4.frame.LZ4FrameCompressor()
        parts.append(lz4_writer.begin(source_size=size))
        for _ in range(size >> 20):
            parts.append(lz4_writer.compress(piece))
        parts.append(lz4_writer.flush())
    for _ in range(size >> 20):
        crc = zlib.crc32(piece, crc)
    payload = b"".join(parts)
    content = (
        struct.pack("<QQQI", 0, 0, size if declared is None else declared, crc)
        + _string(compression)
        + struct.pack("<Q", len(payload))
        + payload
    )
    return _record(0x06, content)


def wrap(data_records: bytes) -> bytes:
    """A whole MCAP: magic, Header, the given records, DataEnd, an empty Footer, magic."""
    magic = b"\x89MCAP0\r\n"
    header = _record(0x01, _string("ros2") + _string("test"))
    footer = _record(0x02, struct.pack("<QQI", 0, 0, 0))
    return magic + header + data_records + _record(0x0F, struct.pack("<I", 0)) + footer + magic


def imu_file_with_schema(schema_text: bytes, *, n_samples: int = 20) -> bytes:
    """An un-chunked one-IMU file whose Imu channel carries ``schema_text``."""
    stream = io.BytesIO()
    writer = Writer(stream, use_chunking=False)
    writer.start(profile="ros2", library="test")
    schema = writer.register_schema(IMU_SCHEMA_NAME, "ros2msg", schema_text)
    channel = writer.register_channel("/imu0/data_raw", "cdr", schema)
    t_ns = T0_NS + np.arange(n_samples, dtype=np.int64) * 10_000_000
    batch = encode_messages("imu", "imu0", channel, t_ns, {"gyro": None, "accel": None})
    for i in range(n_samples):
        writer.add_message(channel, int(t_ns[i]), batch.payload(i), int(t_ns[i]), i)
    writer.finish()
    return stream.getvalue()


class Unseekable(io.BytesIO):
    """A stream like stdin in a pipe: no seeking, so no summary."""

    def seekable(self) -> bool:
        return False


def mcap_package_count(data: bytes) -> int:
    """Messages the mcap package's non-indexed reader yields before it stops."""
    count = 0
    try:
        for record in StreamReader(io.BytesIO(data), skip_magic=False).records:
            count += type(record).__name__ == "Message"
    except Exception:
        pass
    return count


def read_count(data: bytes, *, seekable: bool) -> tuple[int, list[str]]:
    """Messages McapSource reads from ``data`` (through a pipe unless ``seekable``), and
    its warnings."""
    stream = io.BytesIO(data) if seekable else Unseekable(data)
    with McapSource(stream) as source:
        return sum(len(batch) for batch in source.batches()), source.warnings


def top_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, content length) of the top-level records of a whole file."""
    out = []
    position = 8
    while position + 9 <= len(data) - 8:
        opcode = data[position]
        (length,) = struct.unpack_from("<Q", data, position + 1)
        out.append((position, opcode, length))
        position += 9 + length
    return out


def read_strict(data: bytes) -> None:
    """Read ``data`` through a pipe with ``strict`` (raises at the first problem)."""
    with McapSource(Unseekable(data), strict=True) as source:
        for _ in source.batches():
            pass


#: The ROS 2 definitions of an Imu and the types it holds, as in the ROS 2 Humble
#: interfaces (rosbags' Humble store generates the same message definitions from them).
ROS2_IMU_MSGS = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\n"
        "float64[9] linear_acceleration_covariance\n"
    ),
}


def ros2_imu_typestore():
    """A new rosbags type store holding ``sensor_msgs/msg/Imu`` and its field types
    (:data:`ROS2_IMU_MSGS`): the types a bag of Imu messages needs, without importing
    rosbags' whole Humble store (hundreds of types, about 0.1 s of CPU per process)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    for name, text in ROS2_IMU_MSGS.items():
        store.register(get_types_from_msg(text, name))
    return store
