"""RecordPattern: chunks continuing a known record pattern are located exactly as
scan_records locates them, and anything else is left to scan_records."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from imufdi_cli.mcapio.scan import (
    RecordPattern,
    fill_float_columns,
    message_batch,
    scan_records,
)


def records(lengths: list[int], opcode: int = 0x05) -> bytes:
    return b"".join(
        struct.pack("<BQ", opcode, n) + bytes([i % 251]) * n for i, n in enumerate(lengths)
    )


@pytest.mark.parametrize("period", [[30], [30, 31, 30], [40, 40, 12, 40]])
@pytest.mark.parametrize("phase", [0, 1, 2])
@pytest.mark.parametrize("count", [1, 7, 50, 51])
def test_match_equals_scan_records(period: list[int], phase: int, count: int) -> None:
    phase %= len(period)
    lengths = [period[(phase + i) % len(period)] for i in range(count)]
    buf = np.frombuffer(records(lengths), np.uint8)
    pattern = RecordPattern(period)
    found = pattern.match(buf, phase)
    assert found is not None
    starts, got, after = found
    want = scan_records(buf)
    assert want[3] == buf.shape[0] and bool((want[1] == 0x05).all())
    np.testing.assert_array_equal(starts, want[0] + 9)
    np.testing.assert_array_equal(got, want[2])
    assert after == (phase + count) % len(period)


def test_match_finds_another_phase() -> None:
    period = [30, 50, 70]
    buf = np.frombuffer(records([70, 30, 50, 70, 30]), np.uint8)
    found = RecordPattern(period).match(buf, 0)  # the hint is wrong: phase 2 fits
    assert found is not None
    assert found[2] == (2 + 5) % 3
    np.testing.assert_array_equal(found[0], scan_records(buf)[0] + 9)


def test_match_refuses_what_does_not_follow_the_pattern() -> None:
    pattern = RecordPattern([30, 31])
    good = bytearray(records([30, 31] * 20))
    assert pattern.match(np.frombuffer(bytes(good), np.uint8), 0) is not None
    bad_length = bytearray(good)
    bad_length[(9 + 30 + 9 + 31) * 7 + 1] ^= 0x04  # a record length in the middle
    assert pattern.match(np.frombuffer(bytes(bad_length), np.uint8), 0) is None
    bad_opcode = bytearray(good)
    bad_opcode[(9 + 30 + 9 + 31) * 11] = 0x04  # a Channel record, not a Message
    assert pattern.match(np.frombuffer(bytes(bad_opcode), np.uint8), 0) is None
    cut = np.frombuffer(bytes(good[:-5]), np.uint8)  # the last record is cut
    assert pattern.match(cut, 0) is None
    assert pattern.match(np.frombuffer(bytes(good) + b"\x05", np.uint8), 0) is None
    assert pattern.match(np.zeros(0, np.uint8), 0) is None


@pytest.mark.parametrize("phase", [0, 5, 15])
@pytest.mark.parametrize("count", [1, 16, 37])
def test_uniform_match_equals_scan_records(phase: int, count: int) -> None:
    """A period of 16 records of one length (an IMU array's Imu messages) is checked
    through two strided views; starts, lengths and phase are scan_records' answer."""
    pattern = RecordPattern([40] * 16)
    assert pattern.uniform == 40
    buf = np.frombuffer(records([40] * count), np.uint8)
    found = pattern.match(buf, phase)
    assert found is not None
    want = scan_records(buf)
    np.testing.assert_array_equal(found[0], want[0] + 9)
    np.testing.assert_array_equal(found[1], want[2])
    assert found[0].dtype == np.int64 and found[1].dtype == np.int64
    assert found[2] == (phase + count) % 16


@pytest.mark.parametrize(
    "where",
    [0, 1, 7, 8],  # the opcode, the length's low byte, its 7th and its high byte
)
def test_uniform_match_checks_every_head_byte(where: int) -> None:
    pattern = RecordPattern([40] * 4)
    good = records([40] * 30)
    assert pattern.match(np.frombuffer(good, np.uint8), 0) is not None
    for record in (0, 13, 29):
        bad = bytearray(good)
        bad[49 * record + where] ^= 0x01
        assert pattern.match(np.frombuffer(bytes(bad), np.uint8), 0) is None
    assert pattern.match(np.frombuffer(good[:-1], np.uint8), 0) is None
    assert pattern.match(np.frombuffer(good + b"\x05", np.uint8), 0) is None
    other = np.frombuffer(records([41] * 30), np.uint8)  # another length
    assert pattern.match(other, 0) is None


def test_learn() -> None:
    lengths = np.array([30, 31, 32] * 5 + [30], np.int64)
    size = int(lengths.sum()) + 9 * lengths.shape[0]
    pattern = RecordPattern.learn(np.full(16, 5, np.uint8), lengths, size)
    assert pattern is not None and pattern.lengths == [30, 31, 32]
    assert pattern.phase_after(0, 16) == 1
    assert RecordPattern.learn(np.full(16, 5, np.uint8), lengths, size + 1) is None
    ops = np.full(16, 5, np.uint8)
    ops[3] = 4
    assert RecordPattern.learn(ops, lengths, size) is None
    irregular = np.arange(16, dtype=np.int64) + 30
    size = int(irregular.sum()) + 9 * 16
    assert RecordPattern.learn(np.full(16, 5, np.uint8), irregular, size) is None


@pytest.mark.parametrize(
    "lengths", [[30, 30, 30, 30], [30, 41, 22, 30, 25]], ids=["even", "uneven"]
)
def test_message_batch_reads_every_header(lengths: list[int]) -> None:
    """Header fields of Message records (channel u16, sequence u32, log and publish time
    u64) read at once, evenly spaced (strided view) or not (gather), as struct reads them."""
    heads = [(3 + i, 100 + i, 10**18 + i, 2 * 10**18 - i) for i in range(len(lengths))]
    parts = []
    for (channel, sequence, log_time, publish_time), length in zip(heads, lengths):
        content = struct.pack("<HIQQ", channel, sequence, log_time, publish_time)
        content += bytes(range(length - len(content)))
        parts.append(struct.pack("<BQ", 0x05, len(content)) + content)
    buf = np.frombuffer(b"".join(parts), np.uint8)
    starts, _, content_lengths, _ = scan_records(buf)
    batch = message_batch(buf, starts + 9, content_lengths)
    assert batch.channel_id.dtype == np.uint16 and batch.log_time.dtype == np.int64
    assert (
        list(
            zip(
                batch.channel_id.tolist(),
                batch.sequence.tolist(),
                batch.log_time.tolist(),
                batch.publish_time.tolist(),
            )
        )
        == heads
    )
    assert (batch.length == np.array(lengths) - 22).all()
    for i in range(len(lengths)):
        assert batch.payload(i) == bytes(range(lengths[i] - 22))


def _float_bits() -> np.ndarray:
    """float64 bit patterns a byte copy must keep and a float copy might not: signalling
    and quiet NaNs with payloads, both zeros, infinities, subnormals, extremes."""
    special = np.array(
        [
            0x7FF0000000000001,  # signalling NaN
            0x7FF8000000000ABC,  # quiet NaN, payload
            0xFFF4000000000000,  # negative signalling NaN
            0x8000000000000000,  # -0.0
            0x0000000000000000,
            0x7FF0000000000000,  # +inf
            0xFFF0000000000000,  # -inf
            0x0000000000000001,  # smallest subnormal
            0x800FFFFFFFFFFFFF,  # largest negative subnormal
            0x7FEFFFFFFFFFFFFF,  # largest finite
        ],
        np.uint64,
    )
    rng = np.random.default_rng(2)
    return np.concatenate([special, rng.integers(0, 2**63, 60, dtype=np.uint64)])


@pytest.mark.parametrize(
    "offsets",
    [
        (3, 11, 19, 40, 48, 56),  # gyro and accel: two 24-byte copies (unaligned)
        (8, 16, 24),  # one vector (a magnetometer)
        (3, 11, 20, 40, 48, 56),  # first vector not consecutive: per column, then a triple
        (40, 48, 56, 3, 11, 19),  # vectors in the other order
        (3, 11),  # not a whole vector
    ],
)
@pytest.mark.parametrize("regular", [True, False])
def test_fill_float_columns_copies_the_bytes(offsets: tuple[int, ...], regular: bool) -> None:
    """The vector copies give exactly the bytes of one strided float64 copy per column,
    for strided views and for gathers at uneven payload starts."""
    bits = _float_bits()
    n, size = 10, 72
    step = 75
    starts = np.arange(n) * step + (0 if regular else np.arange(n) % 3)
    buf = np.zeros(int(starts[-1]) + size + 8, np.uint8)
    for i, start in enumerate(starts.tolist()):
        for k, offset in enumerate(offsets):
            at = start + offset
            buf[at : at + 8] = np.frombuffer(
                bits[(i * len(offsets) + k) % bits.shape[0]].tobytes(), np.uint8
            )

    def column(offset: int, dtype: str) -> np.ndarray:
        if regular:  # a strided view
            return np.ndarray((n,), dtype, buf, offset, (step,))
        item = np.dtype(dtype).itemsize  # a gather
        windows = np.ndarray((buf.shape[0] - item + 1,), dtype, buf, 0, (1,))
        return windows[starts + offset]

    got = np.empty((n, len(offsets)))
    fill_float_columns(got, column, offsets)
    expected = np.empty((n, len(offsets)), np.uint64)
    for i, start in enumerate(starts.tolist()):
        for k, offset in enumerate(offsets):
            expected[i, k] = buf[start + offset : start + offset + 8].view("<u8")[0]
    assert got.view(np.uint64).tolist() == expected.tolist()


def _walk(buf: bytes, allowed: frozenset[int]) -> tuple[list[int], list[int], list[int], int]:
    """The records of ``buf`` one by one (the reference of scan_records)."""
    starts, opcodes, lengths = [], [], []
    pos = 0
    while pos + 9 <= len(buf):
        opcode, length = struct.unpack_from("<BQ", buf, pos)
        if pos + 9 + length > len(buf) or opcode not in allowed:
            break
        starts.append(pos)
        opcodes.append(opcode)
        lengths.append(length)
        pos += 9 + length
    return starts, opcodes, lengths, pos


@pytest.mark.parametrize("seed", range(30))
def test_scan_records_finds_the_records_a_walk_finds(seed: int) -> None:
    # runs of repeating patterns (found and checked in bulk) between records of varied
    # lengths (walked), as a chunk of status channels and episode events holds them; a
    # pattern broken by one record, a cut end and a foreign opcode stop where a walk does
    rng = np.random.default_rng(seed)
    parts: list[bytes] = []
    for _ in range(int(rng.integers(1, 8))):
        kind = rng.integers(0, 3)
        if kind == 0:  # a pattern run of 1 to 4 record lengths
            period = rng.integers(9, 60, int(rng.integers(1, 5))).tolist()
            count = int(rng.integers(1, 200))
            lengths = [period[i % len(period)] for i in range(count)]
            if rng.random() < 0.3:
                lengths[int(rng.integers(0, count))] += 1
        else:  # varied lengths
            lengths = rng.integers(0, 80, int(rng.integers(1, 150))).tolist()
        opcode = 0x05 if rng.random() < 0.9 else 0x04
        parts.append(records(lengths, opcode))
    buf = b"".join(parts)
    if rng.random() < 0.3:
        buf = buf[: int(rng.integers(1, len(buf)))]
    if rng.random() < 0.2:
        at = int(rng.integers(0, len(buf)))
        buf = buf[:at] + b"\x70" + buf[at + 1 :]
    allowed = frozenset(range(0x01, 0x10))
    starts, opcodes, lengths, end = scan_records(np.frombuffer(buf, np.uint8), allowed)
    want = _walk(buf, allowed)
    assert starts.tolist() == want[0]
    assert opcodes.tolist() == want[1]
    assert lengths.tolist() == want[2]
    assert end == want[3]
