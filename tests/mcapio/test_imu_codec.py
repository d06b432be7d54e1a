"""FixedLayoutDecoder: the fixed-layout fast path gives exactly what the general CDR
decoder gives (blocks, statistics, warnings, raw batches), and falls back to it whenever
the messages of a batch do not all share a layout located before."""

from __future__ import annotations

import dataclasses
import struct

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from imufdi_cli.array import ArrayConfig
from imufdi_cli.mcapio import ImuArrayReader, McapWriter, write_array
from imufdi_cli.mcapio.imu_codec import FixedLayoutDecoder, _decode, _Fields
from imufdi_cli.mcapio.records import MessageBatch
from imufdi_cli.mcapio.schemas import IMU_SCHEMA, IMU_SCHEMA_NAME

from .conftest import make_block

# per endianness: the orientation (0, 0, 0, 1) and its covariance (-1: not given), and a
# zero covariance (the constant parts of every message below, packed once)
_ORIENTATION = {
    e: struct.pack(e + "4d", 0, 0, 0, 1) + struct.pack(e + "9d", -1, *[0] * 8) for e in "<>"
}
_ZERO_COVARIANCE = {e: struct.pack(e + "9d", *[0] * 9) for e in "<>"}


def cdr_imu(t_ns: int, frame: str, gyro, accel, big: bool = False, extra: int = 0) -> bytes:
    """Hand-built CDR Imu message (either endianness; ``extra`` bytes appended)."""
    e = ">" if big else "<"
    out = bytearray(b"\x00\x00\x00\x00" if big else b"\x00\x01\x00\x00")
    out += struct.pack(e + "iI", t_ns // 10**9, t_ns % 10**9)
    raw = frame.encode() + b"\0"
    out += struct.pack(e + "I", len(raw)) + raw
    out.extend(b"\0" * ((-(len(out) - 4)) % 8))
    out += _ORIENTATION[e]
    out += struct.pack(e + "3d", *gyro) + _ZERO_COVARIANCE[e]
    out += struct.pack(e + "3d", *accel) + _ZERO_COVARIANCE[e]
    return bytes(out) + b"\0" * extra


def write_log(path, frames, *, n: int = 400, big=lambda i, k: False, extra=lambda i, k: 0,
              skip=lambda i, k: False, order=lambda i: None) -> None:  # fmt: skip
    """A log of len(frames) Imu topics written one sample of each per time slot;
    ``frames(i, k)`` gives the frame id of sample i of topic k."""
    data = make_block(n, len(frames(0)), seed=3)
    with McapWriter(path) as writer:
        schema = writer.register_schema(IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
        m = len(frames(0))
        channels = [writer.register_channel(f"/imu{k}/data_raw", "cdr", schema) for k in range(m)]
        ids, times, payloads = [], [], []
        for i in range(n):
            t = int(data.t_ns[i])
            for k in order(i) or range(m):
                if skip(i, k):
                    continue
                g, a = data.gyro[i, k], data.accel[i, k]  # type: ignore[index]
                ids.append(channels[k])
                times.append(t)
                payloads.append(cdr_imu(t, frames(i)[k], g, a, big(i, k), extra(i, k)))
        # one batch: the file add_message would write message by message (the writer cuts
        # chunks at the same messages either way), without its per-call overhead
        writer.add_batch(MessageBatch.from_payloads(np.array(ids), np.array(times), payloads))


def read_everything(path, monkeypatch, fast: bool, **kw):
    """Raw batches, blocks, statistics and warnings of a whole read."""
    with monkeypatch.context() as patch:
        calls = {"fast": 0}
        decode = FixedLayoutDecoder.decode

        def counted(self, batch, streams):
            out = decode(self, batch, streams) if fast else None
            calls["fast"] += out is not None
            return out

        patch.setattr(FixedLayoutDecoder, "decode", counted)
        with ImuArrayReader(path, **kw) as reader:
            pairs = list(reader.stream())
            stats = dataclasses.asdict(reader.stats)
            warnings = list(reader.warnings)
    return pairs, stats, warnings, calls["fast"]


def assert_same_read(path, monkeypatch, **kw) -> int:
    """The read with the fast path equals the read with the general decoder only;
    returns how many group batches the fast path decoded."""
    fast = read_everything(path, monkeypatch, True, **kw)
    slow = read_everything(path, monkeypatch, False, **kw)
    assert slow[3] == 0
    assert fast[1:3] == slow[1:3]
    assert len(fast[0]) == len(slow[0])
    for (b1, k1), (b2, k2) in zip(fast[0], slow[0]):
        for name in ("channel_id", "sequence", "log_time", "publish_time", "offset", "length"):
            assert_array_equal(getattr(b1, name), getattr(b2, name))
        for name in ("t_ns", "gyro", "accel", "mag"):
            a, b = getattr(k1, name), getattr(k2, name)
            assert (a is None) == (b is None)
            if a is not None:
                assert a.dtype == b.dtype and a.shape == b.shape
                assert_array_equal(a, b)
    return fast[3]


def frames_of(names):
    return lambda i: names


def test_regular_log_takes_the_fast_path(tmp_path, monkeypatch) -> None:
    path = tmp_path / "a.mcap"
    write_array(path, ArrayConfig.co_aligned(4, 100.0), make_block(3000, 4, seed=1))
    assert assert_same_read(path, monkeypatch, block_size=500) > 0


def test_magnetometers(tmp_path, monkeypatch) -> None:
    path = tmp_path / "m.mcap"
    array = ArrayConfig.co_aligned(3, 100.0, sensors=("gyro", "accel", "mag"))
    write_array(path, array, make_block(2000, 3, mag=True), compression="lz4")
    assert assert_same_read(path, monkeypatch, block_size=128) > 0


@pytest.mark.parametrize("stamps", ["auto", "log_time"])
def test_frame_ids_of_other_lengths_per_topic(tmp_path, monkeypatch, stamps) -> None:
    # frame ids of 4 to 11 characters: the same field offsets after the padding to 8
    path = tmp_path / "f.mcap"
    write_log(path, frames_of(["imu9", "imu10", "imu_123", "imu_1234567"]))
    assert assert_same_read(path, monkeypatch, time_source=stamps) > 0
    # "a" moves the fields by 8 bytes: the general decoder reads that group
    path = tmp_path / "g.mcap"
    write_log(path, frames_of(["imu9", "a"]))
    assert assert_same_read(path, monkeypatch, time_source=stamps) == 0


def test_payloads_not_evenly_spaced(tmp_path, monkeypatch) -> None:
    # other payload lengths per topic: the records are not evenly spaced in the chunk
    path = tmp_path / "u.mcap"
    write_log(path, frames_of(["a", "b", "c"]), extra=lambda i, k: 8 * k)
    assert_same_read(path, monkeypatch)
    path = tmp_path / "v.mcap"
    write_log(path, frames_of(["a", "b", "c"]), skip=lambda i, k: (i * 7 + k) % 11 == 0)
    assert assert_same_read(path, monkeypatch) > 0


def test_layout_changes_fall_back(tmp_path, monkeypatch) -> None:
    # a frame id that changes length mid-log (field offsets move), samples out of order,
    # and big-endian messages: each batch holding one is decoded by the general path
    path = tmp_path / "c.mcap"
    write_log(
        path,
        lambda i: ["imu0", "imu1" if i < 200 else "a_much_longer_frame", "imu2"],
        n=600,
        order=lambda i: [2, 0, 1] if i % 50 == 7 else None,
        big=lambda i, k: i == 450 and k == 0,
    )
    assert_same_read(path, monkeypatch)


def test_malformed_messages_are_left_to_the_general_path(tmp_path, monkeypatch) -> None:
    path = tmp_path / "bad.mcap"
    data = make_block(300, 2, seed=2)
    with McapWriter(path) as writer:
        schema = writer.register_schema(IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
        channels = [writer.register_channel(f"/imu{k}/data_raw", "cdr", schema) for k in range(2)]
        payloads = []
        for i in range(300):
            t = int(data.t_ns[i])
            for k in range(2):
                payload = cdr_imu(t, "f", data.gyro[i, k], data.accel[i, k])  # type: ignore[index]
                if i == 150 and k == 1:
                    payload = payload[:100]  # cut inside angular_velocity
                payloads.append(payload)
        ids = np.tile(np.array(channels), 300)
        writer.add_batch(MessageBatch.from_payloads(ids, np.repeat(data.t_ns, 2), payloads))
    assert_same_read(path, monkeypatch)
    _, _, warnings, _ = read_everything(path, monkeypatch, True)
    # named by its own topic (the decode group's first topic was named before)
    assert any(
        "1 malformed sensor_msgs/msg/Imu message(s) on /imu1/data_raw" in w for w in warnings
    )
    assert not any("/imu0/data_raw" in w for w in warnings)


def _batch(payloads: list[bytes], gap: int = 0) -> MessageBatch:
    batch = MessageBatch.from_payloads(
        np.arange(len(payloads)) % 2, np.zeros(len(payloads)), payloads
    )
    if gap:  # payloads not evenly spaced in the buffer
        spread = b"".join(p + b"\xee" * (gap * (i % 3)) for i, p in enumerate(payloads))
        starts = np.cumsum([0] + [len(p) + gap * (i % 3) for i, p in enumerate(payloads[:-1])])
        batch.data = np.frombuffer(spread, np.uint8)
        batch.offset = np.asarray(starts, np.int64)
    return batch


@pytest.mark.parametrize("gap", [0, 5])
def test_decode_equals_the_general_decoder(gap: int) -> None:
    from imufdi_cli.mcapio.records import ChannelInfo, SchemaInfo

    channel = ChannelInfo(
        1, "/imu0", "cdr", {}, SchemaInfo(1, IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
    )
    rng = np.random.default_rng(0)
    payloads = [
        cdr_imu(
            1_700_000_000_000_000_000 + i * 10**7,
            ["imu9", "imu10"][i % 2],
            rng.normal(size=3),
            rng.normal(size=3),
        )
        for i in range(40)
    ]
    batch = _batch(payloads, gap)
    assert _Fields(batch.data, batch.offset).regular == (gap == 0)
    streams = np.arange(40) % 2
    decoder = FixedLayoutDecoder(channel, ("gyro", "accel"), "", 2)
    got = decoder.decode(batch, streams)
    assert got is not None
    want = _decode(batch, channel, ("gyro", "accel"))
    assert_array_equal(got[0], want.t_ns)
    assert_array_equal(got[1], np.concatenate([want.gyro, want.accel], axis=1))
    # a frame id of another length in one message: not this layout
    moved = list(payloads)
    moved[13] = cdr_imu(0, "imu9_but_longer", [0, 0, 0], [0, 0, 0])[: len(payloads[13])]
    assert decoder.decode(_batch(moved, gap), streams) is None
    # a big-endian channel never takes the fast path
    big = FixedLayoutDecoder(channel, ("gyro", "accel"), "", 2)
    swapped = [cdr_imu(0, "imu9", [1, 2, 3], [4, 5, 6], big=True)] * 4
    assert big.decode(_batch(swapped), np.arange(4) % 2) is None
    assert not big.usable
