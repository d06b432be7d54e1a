"""The fixed-layout fast path of Imu decoding (``CdrCodec.uniform_positions``) against the
general per-message walk (``CdrCodec.positions``): identical arrays, or no fast path."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio import ImuArrayReader, MessageBatch, encode_messages
from imufdi_cli.mcapio.cdr import CdrCodec
from imufdi_cli.mcapio.imu_codec import _decode_cdr
from imufdi_cli.mcapio.records import ChannelInfo, SchemaInfo
from imufdi_cli.mcapio.schemas import IMU_SCHEMA, IMU_SCHEMA_NAME
from tests.mcapio.mcap_files import imu_file

T0_NS = 1_700_000_000_000_000_000
CHANNEL = ChannelInfo(
    1, "/imu/data_raw", "cdr", schema=SchemaInfo(1, IMU_SCHEMA_NAME, "ros2msg", IMU_SCHEMA)
)


def _batch(frame_ids: list[str], n: int, seed: int, gap: int = 17) -> MessageBatch:
    """n messages per frame id, interleaved (message i of every frame id, then i + 1),
    in one buffer with ``gap`` bytes of other data before each payload."""
    rng = np.random.default_rng(seed)
    t_ns = T0_NS + np.arange(n, dtype=np.int64) * 10_000_000
    payloads = []
    for k, frame_id in enumerate(frame_ids):
        batch = encode_messages(
            "imu",
            frame_id,
            k,
            t_ns + k,
            {"gyro": rng.normal(0, 0.1, (n, 3)), "accel": rng.normal(0, 1, (n, 3))},
        )
        payloads.append([batch.payload(i) for i in range(n)])
    buf = bytearray()
    offsets, lengths = [], []
    for i in range(n):
        for k in range(len(frame_ids)):
            buf += rng.integers(0, 256, gap, dtype=np.uint8).tobytes()
            offsets.append(len(buf))
            lengths.append(len(payloads[k][i]))
            buf += payloads[k][i]
    m = len(offsets)
    return MessageBatch(
        channel_id=np.ones(m, np.uint16),
        sequence=np.arange(m, dtype=np.uint32),
        log_time=T0_NS + np.arange(m, dtype=np.int64),
        publish_time=T0_NS + np.arange(m, dtype=np.int64),
        data=np.frombuffer(bytes(buf), np.uint8),
        offset=np.array(offsets, np.int64),
        length=np.array(lengths, np.int64),
    )


def _general_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(CdrCodec, "uniform_positions", lambda self, batch, paths: None)


def _decode_both(batch: MessageBatch, monkeypatch: pytest.MonkeyPatch, with_valid: bool):
    valid = np.ones(len(batch), bool) if with_valid else None
    fast = _decode_cdr(batch, CHANNEL, ("gyro", "accel"), valid=valid)
    with monkeypatch.context() as m:
        _general_only(m)
        valid2 = np.ones(len(batch), bool) if with_valid else None
        general = _decode_cdr(batch, CHANNEL, ("gyro", "accel"), valid=valid2)
    if with_valid:
        assert_array_equal(valid, valid2)
    return fast, general


def _uses_fast_path(batch: MessageBatch) -> bool:
    codec = CdrCodec(IMU_SCHEMA_NAME, IMU_SCHEMA)
    paths = ["header.stamp.sec", "header.stamp.nanosec", "angular_velocity.x"]
    return codec.uniform_positions(batch, paths) is not None


@pytest.mark.parametrize(
    ("frame_ids", "fast"),
    [
        (["imu0"], True),  # one layout
        ([f"imu{k}" for k in range(12)], True),  # 5- and 6-byte strings, same padded size
        # four string lengths (5 to 12 bytes with the NUL), one payload length
        (["abcd", "abcde", "abcdefg", "abcdefghijk"], True),
        (["", "ab"], True),  # empty string
        (["", "abcd"], False),  # payload lengths differ (padding to 8): general path
        (["a", "abcdefghi"], False),  # payload lengths differ: general path
        ([f"f{'x' * k}" for k in range(9)], False),
    ],
)
@pytest.mark.parametrize("with_valid", [False, True])
def test_fast_path_equals_general_path(frame_ids, fast, with_valid, monkeypatch) -> None:
    batch = _batch(frame_ids, 40, seed=len(frame_ids))
    assert _uses_fast_path(batch) == fast
    a, b = _decode_both(batch, monkeypatch, with_valid)
    assert_array_equal(a.t_ns, b.t_ns)
    assert_array_equal(a.log_time, b.log_time)
    assert_array_equal(a.gyro, b.gyro)
    assert_array_equal(a.accel, b.accel)
    assert a.has_stamp == b.has_stamp


def test_fast_path_declines_irregular_batches(monkeypatch) -> None:
    batch = _batch(["imu0", "imu1"], 30, seed=3)
    assert _uses_fast_path(batch)
    # a big-endian message (encapsulation kind 0) among little-endian ones
    data = batch.data.copy()
    data[int(batch.offset[5]) + 1] = 0
    odd = MessageBatch(**{**batch.__dict__, "data": data})
    assert not _uses_fast_path(odd)
    # a string length past the payload: the general path raises, the fast path declines
    data = batch.data.copy()
    data[int(batch.offset[0]) + 12 : int(batch.offset[0]) + 16] = 255
    bad = MessageBatch(**{**batch.__dict__, "data": data})
    assert not _uses_fast_path(bad)
    valid = np.ones(len(bad), bool)
    fast = _decode_cdr(bad, CHANNEL, ("gyro", "accel"), valid=valid)
    assert not valid[0] and bool(valid[1:].all())
    with monkeypatch.context() as m:
        _general_only(m)
        valid2 = np.ones(len(bad), bool)
        general = _decode_cdr(bad, CHANNEL, ("gyro", "accel"), valid=valid2)
    assert_array_equal(valid, valid2)
    assert_array_equal(fast.gyro, general.gyro)
    assert_array_equal(fast.t_ns, general.t_ns)


def _read(path, monkeypatch: pytest.MonkeyPatch, general: bool) -> tuple[ImuBlock, list[str]]:
    with monkeypatch.context() as m:
        if general:
            _general_only(m)
        with ImuArrayReader(path) as reader:
            block = ImuBlock.concatenate(list(reader.blocks()))
            return block, list(reader.warnings)


@pytest.mark.parametrize("cut", [None, 0.55, 0.8])
def test_reader_fast_and_general_paths_agree(tmp_path, monkeypatch, cut) -> None:
    """Mixed channels (12 topics, frame ids of 4 and 5 characters) in zstd chunks, whole
    or cut inside a chunk."""
    raw = imu_file(n_imus=12, n_samples=300, chunk_size=8192, seed=4)
    path = tmp_path / "a.mcap"
    path.write_bytes(raw if cut is None else raw[: int(len(raw) * cut)])
    fast, fast_warnings = _read(path, monkeypatch, general=False)
    general, general_warnings = _read(path, monkeypatch, general=True)
    assert len(fast) > 0
    assert fast_warnings == general_warnings
    assert_array_equal(fast.t_ns, general.t_ns)
    assert_array_equal(fast.gyro, general.gyro)
    assert_array_equal(fast.accel, general.accel)
