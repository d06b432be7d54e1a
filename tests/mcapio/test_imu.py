"""IMU arrays: round trips, independent readers and writers, JSON, big-endian CDR,
alignment statistics, bad input."""

from __future__ import annotations

import itertools
import json
import struct
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from numpy.testing import assert_array_equal

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import McapInputError
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio import (
    ImuArrayReader,
    McapSource,
    McapWriter,
    MessageBatch,
    decode_imu,
    patch_imu,
    read_array,
    summarize,
    write_array,
)
from imufdi_cli.mcapio.schemas import IMU_SCHEMA, IMU_SCHEMA_NAME

from .conftest import T0_NS, make_block


def test_round_trip_bit_exact(tmp_path, block4, array4) -> None:
    path = tmp_path / "a.mcap"
    write_array(path, array4, block4, metadata={"imufdi.ingest": {"json": "{}"}})
    array, block = read_array(path)
    assert array == array4
    assert_array_equal(block.t_ns, block4.t_ns)
    assert block.gyro is not None and block.accel is not None
    assert block.gyro.tobytes() == block4.gyro.tobytes()  # type: ignore[union-attr]
    assert block.accel.tobytes() == block4.accel.tobytes()  # type: ignore[union-attr]
    assert block.mag is None


def test_round_trip_with_magnetometer_and_blocks(tmp_path) -> None:
    array = ArrayConfig.co_aligned(3, 100.0, sensors=("gyro", "accel", "mag"))
    data = make_block(1000, 3, mag=True)
    path = tmp_path / "m.mcap"
    write_array(path, array, data, compression="lz4")
    with ImuArrayReader(path, block_size=128) as reader:
        blocks = list(reader.blocks())
        assert reader.mag_topics == ["/imu0/mag", "/imu1/mag", "/imu2/mag"]
        assert reader.stats.n_aligned == 1000 and reader.stats.misaligned == 0
    assert [len(b) for b in blocks] == [128] * 7 + [104]
    joined = ImuBlock.concatenate(blocks)
    assert_array_equal(joined.mag, data.mag)  # type: ignore[arg-type]
    assert_array_equal(joined.gyro, data.gyro)  # type: ignore[arg-type]


def test_the_default_block_holds_about_the_same_values_whatever_the_imu_count(tmp_path) -> None:
    # 4096 samples up to 16 IMUs, then fewer (a run's memory scales with samples x IMUs)
    from imufdi_cli.mcapio.imu import block_samples

    assert [block_samples(n) for n in (1, 8, 16, 17, 32, 64, 256, 1000)] == [
        4096, 4096, 4096, 3855, 2048, 1024, 256, 256,
    ]  # fmt: skip
    array = ArrayConfig.co_aligned(32, 100.0)
    data = make_block(2500, 32)
    path = tmp_path / "wide.mcap"
    write_array(path, array, data)
    with ImuArrayReader(path) as reader:
        assert reader.block_size == 2048
        blocks = list(reader.blocks())
    assert [len(b) for b in blocks] == [2048, 452]
    assert_array_equal(ImuBlock.concatenate(blocks).gyro, data.gyro)  # type: ignore[arg-type]
    with ImuArrayReader(path, block_size=4096) as reader:  # an explicit size is kept
        assert reader.block_size == 4096


def test_independent_readers_agree(tmp_path, array4) -> None:
    # 100 samples (not the 500 of block4): mcap-ros2-support decodes each in Python
    block = make_block(100, 4)
    path = tmp_path / "a.mcap"
    write_array(path, array4, block)
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        seen = 0
        for _, channel, message, decoded in reader.iter_decoded_messages():
            k = int(channel.topic.split("/")[1][3:])
            i = (message.log_time - T0_NS) // 10_000_000
            assert decoded.header.frame_id == f"imu{k}"
            assert decoded.orientation_covariance[0] == -1.0
            stamp = decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec
            assert stamp == block.t_ns[i]
            v = decoded.angular_velocity
            assert (v.x, v.y, v.z) == tuple(block.gyro[i, k])  # type: ignore[index]
            a = decoded.linear_acceleration
            assert (a.x, a.y, a.z) == tuple(block.accel[i, k])  # type: ignore[index]
            seen += 1
    assert seen == 4 * 100
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as bag:
        connections = [c for c in bag.connections if c.topic == "/imu2/data_raw"]
        values = [
            bag.deserialize(raw, c.msgtype).angular_velocity.z
            for c, _, raw in bag.messages(connections=connections)
        ]
    assert_array_equal(values, block.gyro[:, 2, 2])  # type: ignore[index]


def _ros2_imu_dict(t_ns: int, frame: str, gyro, accel) -> dict:
    return {
        "header": {"stamp": {"sec": t_ns // 10**9, "nanosec": t_ns % 10**9}, "frame_id": frame},
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        "orientation_covariance": [-1.0] + [0.0] * 8,
        "angular_velocity": dict(zip("xyz", map(float, gyro))),
        "angular_velocity_covariance": [0.0] * 9,
        "linear_acceleration": dict(zip("xyz", map(float, accel))),
        "linear_acceleration_covariance": [0.0] * 9,
    }


def test_reads_mcap_ros2_writer_file_with_gaps(tmp_path) -> None:
    from mcap_ros2.writer import Writer

    data = make_block(200, 3, seed=4)
    topics = ["/left/imu", "/right/imu", "/center/imu"]  # imufdi sorts them naturally
    missing = {1: {10, 11, 150}}  # samples absent on /right/imu
    path = tmp_path / "ros2.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef(IMU_SCHEMA_NAME, IMU_SCHEMA.decode())
        for i in range(200):
            for k, topic in enumerate(topics):
                if i in missing.get(k, ()):
                    continue
                t = int(data.t_ns[i])
                msg = _ros2_imu_dict(t, f"frame_{k}_long", data.gyro[i, k], data.accel[i, k])  # type: ignore[index]
                writer.write_message(topic, schema, msg, log_time=t + 1000, publish_time=t)
        writer.finish()
    order = [0, 1, 2]
    keep = np.array([i not in missing[1] for i in range(200)])
    # only the samples every topic has (partial=False)
    with ImuArrayReader(path, topics=topics, partial=False) as reader:
        block = ImuBlock.concatenate(list(reader.blocks()))
        stats = reader.stats
        assert reader.array.n_imus == 3
        assert reader.array.rate_hz == pytest.approx(100.0)
    assert_array_equal(block.t_ns, data.t_ns[keep])
    assert_array_equal(block.gyro, data.gyro[keep][:, order])  # type: ignore[index]
    assert_array_equal(block.accel, data.accel[keep][:, order])  # type: ignore[index]
    assert block.missing is None
    assert stats.gaps == {"/left/imu": 0, "/right/imu": 3, "/center/imu": 0}
    assert stats.dropped == 3 and stats.n_aligned == 197 and stats.misaligned == 0
    # default: every sample, the missing IMU's values NaN and flagged
    with ImuArrayReader(path, topics=topics) as reader:
        block = ImuBlock.concatenate(list(reader.blocks()))
        stats = reader.stats
    assert_array_equal(block.t_ns, data.t_ns)
    assert block.missing is not None
    assert_array_equal(block.missing[:, 1], ~keep)
    assert not block.missing[:, [0, 2]].any()
    assert np.isnan(block.gyro[~keep, 1]).all() and np.isnan(block.accel[~keep, 1]).all()  # type: ignore[index]
    assert_array_equal(block.gyro[keep], data.gyro[keep][:, order])  # type: ignore[index]
    assert_array_equal(block.gyro[:, [0, 2]], data.gyro[:, [0, 2]])  # type: ignore[index]
    assert stats.gaps == {"/left/imu": 0, "/right/imu": 3, "/center/imu": 0}
    assert stats.dropped == 0 and stats.partial == 3 and stats.n_aligned == 200
    # default order is natural sort of the topics
    with ImuArrayReader(path) as reader:
        assert reader.imu_topics == ["/center/imu", "/left/imu", "/right/imu"]
    # log time instead of header stamps
    with ImuArrayReader(path, topics=topics, time_source="log_time") as reader:
        assert_array_equal(ImuBlock.concatenate(list(reader.blocks())).t_ns, data.t_ns + 1000)


def test_reads_rosbags_writer_file(tmp_path) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer

    from .mcap_files import ros2_imu_typestore

    typestore = ros2_imu_typestore()
    Imu = typestore.types["sensor_msgs/msg/Imu"]
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    Vector3 = typestore.types["geometry_msgs/msg/Vector3"]
    Quaternion = typestore.types["geometry_msgs/msg/Quaternion"]
    data = make_block(120, 2, seed=5)
    bag = tmp_path / "bag"
    skipped = {(0, 30), (0, 31), (1, 99)}
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = [
            writer.add_connection(
                f"/sensors/imu_{name}", "sensor_msgs/msg/Imu", typestore=typestore
            )
            for name in ("a", "b")
        ]
        for i in range(120):
            t = int(data.t_ns[i])
            for k in range(2):
                if (k, i) in skipped:
                    continue
                msg = Imu(
                    header=Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id=f"x{k}"),
                    orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.zeros(9),
                    angular_velocity=Vector3(*data.gyro[i, k]),  # type: ignore[index]
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=Vector3(*data.accel[i, k]),  # type: ignore[index]
                    linear_acceleration_covariance=np.zeros(9),
                )
                writer.write(conns[k], t, typestore.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
    (path,) = list(bag.glob("*.mcap"))
    _, block = read_array(path, partial=False)
    keep = np.array([all((k, i) not in skipped for k in range(2)) for i in range(120)])
    assert_array_equal(block.gyro, data.gyro[keep])  # type: ignore[index]
    assert_array_equal(block.accel, data.accel[keep])  # type: ignore[index]
    with ImuArrayReader(path) as reader:
        list(reader.blocks())
        assert reader.stats.gaps == {"/sensors/imu_a": 2, "/sensors/imu_b": 1}


def _cdr_imu(t_ns: int, frame: str, gyro, accel, big: bool) -> bytes:
    """Hand-built CDR Imu message (either endianness)."""
    e = ">" if big else "<"
    out = bytearray(b"\x00\x00\x00\x00" if big else b"\x00\x01\x00\x00")

    def align(n: int) -> None:
        out.extend(b"\0" * ((-(len(out) - 4)) % n))

    out += struct.pack(e + "iI", t_ns // 10**9, t_ns % 10**9)
    raw = frame.encode() + b"\0"
    out += struct.pack(e + "I", len(raw)) + raw
    align(8)
    out += struct.pack(e + "4d", 0, 0, 0, 1) + struct.pack(e + "9d", -1, *[0] * 8)
    out += struct.pack(e + "3d", *gyro) + struct.pack(e + "9d", *[0] * 9)
    out += struct.pack(e + "3d", *accel) + struct.pack(e + "9d", *[0] * 9)
    return bytes(out)


@pytest.mark.parametrize("encoding", ["cdr-big", "cdr-mixed", "json"])
def test_big_endian_and_json_channels(tmp_path, encoding: str) -> None:
    data = make_block(50, 2, seed=6)
    path = tmp_path / "x.mcap"
    with McapWriter(path) as writer:
        if encoding == "json":
            schema = writer.register_schema(IMU_SCHEMA_NAME, "jsonschema", b"{}")
        else:
            schema = writer.register_schema(IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
        enc = "json" if encoding == "json" else "cdr"
        channels = [writer.register_channel(f"/imu{k}/data_raw", enc, schema) for k in range(2)]
        for i in range(50):
            t = int(data.t_ns[i])
            for k in range(2):
                g, a = data.gyro[i, k], data.accel[i, k]  # type: ignore[index]
                if encoding == "json":
                    payload = json.dumps(_ros2_imu_dict(t, "f", g, a)).encode()
                else:
                    big = encoding == "cdr-big" or (i + k) % 3 == 0
                    payload = _cdr_imu(t, "frame" * (i % 3), g, a, big)
                writer.add_message(channels[k], t, payload)
    _, block = read_array(path)
    assert_array_equal(block.t_ns, data.t_ns)
    assert_array_equal(block.gyro, data.gyro)  # type: ignore[arg-type]
    assert_array_equal(block.accel, data.accel)  # type: ignore[arg-type]


def test_patch_imu_changes_only_the_vectors(tmp_path, block4, array4) -> None:
    path = tmp_path / "a.mcap"
    write_array(path, array4, block4)
    with McapSource(path) as source:
        batch = MessageBatch.concatenate(list(source.batches()))
        channel = next(c for c in source.channels.values() if c.topic == "/imu1/data_raw")
    sub = batch.select(batch.channel_id == channel.id)
    before = [sub.payload(i) for i in range(len(sub))]
    new_gyro = block4.gyro[:, 1] + 0.5  # type: ignore[index]
    patched = patch_imu(sub, channel, gyro=new_gyro)
    assert [sub.payload(i) for i in range(len(sub))] == before  # input untouched
    fields = decode_imu(patched, channel)
    assert_array_equal(fields.gyro, new_gyro)
    assert_array_equal(fields.accel, block4.accel[:, 1])  # type: ignore[index]
    for i in (0, 17):
        old, new = np.frombuffer(before[i], np.uint8), np.frombuffer(patched.payload(i), np.uint8)
        changed = np.flatnonzero(old != new)
        assert changed.size > 0 and changed.min() >= 4 + 24 + 104  # angular_velocity
        assert changed.max() < 4 + 24 + 104 + 24


def test_duplicates_and_jitter_are_counted(tmp_path) -> None:
    data = make_block(100, 2, seed=7)
    path = tmp_path / "j.mcap"
    jitter = np.zeros(100, np.int64)
    jitter[::10] = 1_000_000  # 1 ms late on imu1, within the 3 ms tolerance
    with McapWriter(path) as writer:
        schema = writer.register_schema(IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
        channels = [writer.register_channel(f"/imu{k}/data_raw", "cdr", schema) for k in range(2)]
        for i in range(100):
            for k in range(2):
                t = int(data.t_ns[i] + (jitter[i] if k == 1 else 0))
                payload = _cdr_imu(t, "f", data.gyro[i, k], data.accel[i, k], False)  # type: ignore[index]
                writer.add_message(channels[k], t, payload)
                if k == 0 and i == 42:  # a duplicate on imu0
                    writer.add_message(channels[k], t, payload)
    with ImuArrayReader(path) as reader:
        block = ImuBlock.concatenate(list(reader.blocks()))
        stats = reader.stats
    assert len(block) == 100
    assert_array_equal(block.t_ns, data.t_ns)  # stamps of the first topic
    assert stats.misaligned == 10 and stats.max_skew_ns == 1_000_000
    assert stats.duplicates == {"/imu0/data_raw": 1, "/imu1/data_raw": 0}
    assert stats.gaps == {"/imu0/data_raw": 0, "/imu1/data_raw": 0}


# --- bad input ---------------------------------------------------------------------------


def test_missing_file(tmp_path) -> None:
    with pytest.raises(McapInputError, match="no such file"):
        ImuArrayReader(tmp_path / "nope.mcap")


def test_not_mcap(tmp_path) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(b"hello, this is not an mcap file at all")
    with pytest.raises(McapInputError, match="not an MCAP file"):
        read_array(path)


def test_no_imu_channel(tmp_path) -> None:
    path = tmp_path / "x.mcap"
    with McapWriter(path) as writer:
        ch = writer.register_json_channel("/events", "x")
        writer.add_json(ch, 1, {})
    with pytest.raises(McapInputError, match=r"no sensor_msgs/msg/Imu channel.*topics: /events"):
        read_array(path)
    assert summarize(path).topics[0].message_count == 1


def test_unknown_topic(tmp_path, block4, array4) -> None:
    path = tmp_path / "a.mcap"
    write_array(path, array4, block4)
    with pytest.raises(McapInputError, match=r"/imu9/data_raw.*Imu topics: /imu0/data_raw"):
        ImuArrayReader(path, topics=["/imu9/data_raw"])


def test_truncated_file_warns_or_raises(tmp_path) -> None:
    data = make_block(3000, 4, seed=8)
    path = tmp_path / "a.mcap"
    write_array(path, ArrayConfig.co_aligned(4), data, compression="none")
    raw = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: len(raw) * 2 // 3])
    with ImuArrayReader(cut) as reader:
        block = ImuBlock.concatenate(list(reader.blocks()))
        assert any("truncated" in w for w in reader.warnings)
    assert 0 < len(block) < 3000
    assert_array_equal(block.gyro, data.gyro[: len(block)])  # type: ignore[index]
    with pytest.raises(McapInputError, match="truncated"):
        read_array(cut, strict=True)


def test_summarize(tmp_path, block4, array4) -> None:
    path = tmp_path / "a.mcap"
    write_array(path, array4, block4)
    summary = summarize(path)
    assert summary.n_imus == 4 and summary.n_samples == 500
    assert summary.rate_hz == pytest.approx(100.0)
    assert summary.duration_s == pytest.approx(4.99)
    assert [t.message_count for t in summary.topics] == [500] * 4
    assert summary.metadata_names == ["imufdi.array"]
    assert summary.array_from_metadata
    json.dumps(summary.to_dict())


def test_stdin_like_stream(tmp_path, block4, array4) -> None:
    path = tmp_path / "a.mcap"
    write_array(path, array4, block4)

    class Pipe:
        def __init__(self, raw: bytes) -> None:
            self.raw, self.pos = raw, 0

        def read(self, n: int) -> bytes:
            out = self.raw[self.pos : self.pos + min(n, 1000)]
            self.pos += len(out)
            return out

        def seekable(self) -> bool:
            return False

    _, block = read_array(Pipe(Path(path).read_bytes()))  # type: ignore[arg-type]
    assert_array_equal(block.gyro, block4.gyro)  # type: ignore[arg-type]


def test_summarize_counts_gaps_of_every_topic(tmp_path, array4) -> None:
    """Samples missing from all topics at once (lost frames): counted against the period,
    and the rate is measured with them, not biased by them."""
    block = make_block(1000, 4)
    keep = np.ones(1000, bool)
    keep[[10, 11, 12, 500, 700]] = False  # one hole of 3 samples, two of 1
    path = tmp_path / "a.mcap"
    write_array(path, array4, block.mask(keep))
    summary = summarize(path)
    assert summary.gaps["count"] == 3
    assert summary.gaps["missing_samples"] == 5
    assert summary.gaps["expected_samples"] == 1000
    assert summary.gaps["longest_s"] == pytest.approx(0.04)
    assert summary.rate_hz == pytest.approx(100.0)
    assert summary.stats is not None and sum(summary.stats.gaps.values()) == 0


@pytest.mark.parametrize("sizes", [[5, 5, 5], [1, 9, 3, 30, 2], [12], [0, 4, 0, 4, 4], [3, 3]])
@pytest.mark.parametrize("block_size", [1, 4, 7])
def test_recut_cuts_as_rechunk(sizes, block_size) -> None:
    from imufdi_cli.log import rechunk
    from imufdi_cli.mcapio.imu import recut

    whole = make_block(sum(sizes), 2, mag=True)
    bounds = np.cumsum([0, *sizes])
    parts = [whole.slice(int(a), int(b)) for a, b in itertools.pairwise(bounds.tolist())]
    got = list(recut(iter(parts), block_size))
    want = list(rechunk(iter(parts), block_size))
    assert [len(b) for b in got] == [len(b) for b in want]
    for a, b in zip(got, want):
        for name in ("t_ns", "gyro", "accel", "mag"):
            assert_array_equal(getattr(a, name), getattr(b, name))
