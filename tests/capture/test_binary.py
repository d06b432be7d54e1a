import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.capture import (
    Corruption,
    encode_capture,
    find_sync,
    layout_from_dict,
    load_layout,
    parse_capture,
)
from imufdi_cli.errors import CaptureError, ImufdiError
from imufdi_cli.log import ImuBlock

from .conftest import LAYOUTS, random_block

BUILTIN = load_layout("mpu6500-array", gyro_fs="500dps", accel_fs="4g")


def parse_all(data, layout, **kwargs):
    blocks, stats = parse_capture(data, layout, **kwargs)
    block = ImuBlock.concatenate(list(blocks))
    assert stats.complete
    return block, stats


def half_lsb(layout, name):
    return 0.5 * next(f.scale for f in layout.record if f.name == name) * (1 + 1e-9)


def test_find_sync_multi_byte():
    data = np.frombuffer(b"\xaa\xaa\x55\x00\xaa\x55\xaa", dtype=np.uint8)
    assert_array_equal(find_sync(data, b"\xaa\x55"), [1, 4])


@pytest.mark.parametrize("chunk_size", [64, 1000, 1 << 20])
def test_round_trip_within_half_an_lsb(chunk_size):
    block = random_block(300, 16, seed=1)
    encoded = encode_capture(block, BUILTIN)
    parsed, stats = parse_all(encoded.data, BUILTIN, chunk_size=chunk_size)
    assert_array_equal(parsed.t_ns, block.t_ns)
    assert np.max(np.abs(parsed.gyro - block.gyro)) <= half_lsb(BUILTIN, "gyro_x")
    assert np.max(np.abs(parsed.accel - block.accel)) <= half_lsb(BUILTIN, "accel_x")
    assert parsed.mag is None
    assert stats.frames_ok == 300 and stats.bytes_dropped == 0 and stats.n_imus == 16
    assert stats.bytes_total == len(encoded.data) == 300 * BUILTIN.frame_size(16)


def test_values_beyond_full_scale_saturate():
    block = random_block(3, 1)
    block.gyro[:] = 100.0  # rad/s, far past 500 dps
    parsed, _ = parse_all(encode_capture(block, BUILTIN).data, BUILTIN)
    assert_allclose(parsed.gyro, 32767 * BUILTIN.record[4].scale)


@pytest.mark.parametrize("chunk_size", [97, 4096, 1 << 20])
def test_corruption_is_counted_exactly(chunk_size):
    block = random_block(1000, 4, seed=2)
    corruption = Corruption(garbage=12, flipped=9, cut=7, dropped=8, duplicated=5)
    encoded = encode_capture(block, BUILTIN, corrupt=corruption, rng=np.random.default_rng(3))
    parsed, stats = parse_all(encoded.data, BUILTIN, chunk_size=chunk_size)
    expected = encoded.expected_stats()
    assert {k: getattr(stats, k) for k in expected} == expected
    assert stats.frames_ok == 1000 - 9 - 7 - 8
    assert stats.frames_lost == 9 + 7 + 8
    assert_array_equal(parsed.t_ns, block.t_ns[encoded.intact])
    assert np.max(np.abs(parsed.gyro - block.gyro[encoded.intact])) <= half_lsb(BUILTIN, "gyro_x")
    assert stats.bytes_total - stats.bytes_dropped == stats.frames_ok * encoded.frame_size


def test_garbage_before_first_and_cut_final_frame():
    block = random_block(20, 2)
    data = encode_capture(block, BUILTIN).data
    size = BUILTIN.frame_size(2)
    capture = b"\x00\x13\xaa" + data + data[:17]  # partial frame at the end
    parsed, stats = parse_all(capture, BUILTIN)
    assert stats.frames_ok == 20
    assert stats.frames_truncated == 1
    assert stats.bytes_dropped == 3 + 17
    assert stats.duplicates == 0
    assert len(parsed) == 20 and size == 10 + 28 + 2


def test_u16_counter_wraps_without_lost_frames():
    n = 65536 + 1000  # counter 65000 .. 131535: wraps at 65536 and 131072
    block = random_block(n, 1, rate_hz=1000.0)
    encoded = encode_capture(block, BUILTIN, start_counter=65000)
    parsed, stats = parse_all(encoded.data, BUILTIN, chunk_size=1 << 18)
    assert stats.counter_wraps == 2
    assert stats.frames_lost == 0 and stats.frames_ok == n
    assert np.all(np.diff(parsed.t_ns) > 0)


def test_u32_microsecond_timestamp_wrap_is_unwrapped():
    t0 = (2**32 - 1_000_000) * 1000  # 1 s before the u32 us wrap
    block = random_block(400, 2, t0_ns=t0)  # 4 s at 100 Hz
    parsed, stats = parse_all(encode_capture(block, BUILTIN).data, BUILTIN, chunk_size=500)
    assert stats.timestamp_wraps == 1
    assert_array_equal(parsed.t_ns, block.t_ns)
    assert np.all(np.diff(parsed.t_ns) > 0)


def test_counter_only_layout_with_u8_wrap_and_rate_from_layout():
    layout = load_layout(LAYOUTS / "sync1-be-sum16.toml")
    block = random_block(1000, 4, rate_hz=200.0, mag=True, seed=4)
    encoded = encode_capture(
        block, layout, corrupt=Corruption(dropped=3, flipped=2), rng=np.random.default_rng(0)
    )
    parsed, stats = parse_all(encoded.data, layout, chunk_size=333)
    assert stats.counter_wraps == 3
    assert stats.frames_lost == 5 and stats.frames_bad_checksum == 2
    assert_array_equal(parsed.t_ns, block.t_ns[encoded.intact])
    assert np.max(np.abs(parsed.mag - block.mag[encoded.intact])) <= half_lsb(layout, "mag_x")


def test_layout_without_timestamp_needs_a_rate():
    layout = layout_from_dict(
        {
            "sync": "7E",
            "n_imus": 1,
            "record": [{"name": f"gyro_{a}", "type": "f32"} for a in "xyz"],
            "checksum": {"kind": "xor8"},
        }
    )
    block = random_block(10, 1)
    with pytest.raises(CaptureError, match="rate"):
        parse_capture(encode_capture(block, layout).data, layout)
    parsed, _ = parse_all(encode_capture(block, layout).data, layout, rate_hz=100.0)
    assert_allclose(parsed.gyro, block.gyro.astype(np.float32))
    assert_array_equal(parsed.t_ns, block.t_ns)


def test_strict_raises_on_the_first_dropped_byte():
    data = encode_capture(random_block(10, 1), BUILTIN).data
    parse_all(data, BUILTIN, strict=True)
    blocks, _ = parse_capture(data[:30] + b"\x01" + data[30:], BUILTIN, strict=True)
    with pytest.raises(CaptureError, match="strict: "):
        list(blocks)


def test_missing_file_is_a_capture_error(tmp_path):
    with pytest.raises(CaptureError, match="does not exist"):
        parse_capture(tmp_path / "nope.cap", BUILTIN)


def test_file_and_stream_sources(tmp_path):
    block = random_block(50, 3)
    path = tmp_path / "x.cap"
    path.write_bytes(encode_capture(block, BUILTIN).data)
    from_path, _ = parse_all(path, BUILTIN, chunk_size=200)
    with path.open("rb") as handle:
        from_stream, _ = parse_all(handle, BUILTIN, chunk_size=200)
    assert_array_equal(from_path.t_ns, block.t_ns)
    assert_array_equal(from_stream.gyro, from_path.gyro)


VALID = encode_capture(random_block(40, 2, seed=9), BUILTIN).data


@settings(max_examples=200, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=600), chunk=st.integers(1, 300))
def test_arbitrary_bytes_never_raise_foreign_errors(data, chunk):
    try:
        blocks, stats = parse_capture(data, BUILTIN, chunk_size=chunk)
        for block in blocks:
            assert np.all(np.diff(block.t_ns) >= 0) or stats.timestamp_jumps
        assert stats.bytes_total == len(data)
    except ImufdiError:
        pass


@settings(max_examples=200, deadline=2000, suppress_health_check=[HealthCheck.too_slow])
@given(
    edits=st.lists(
        st.tuples(st.integers(0, len(VALID) - 1), st.integers(0, 3), st.binary(max_size=20)),
        max_size=6,
    ),
    chunk=st.integers(1, 500),
)
def test_mutated_captures_parse_and_account_for_every_byte(edits, chunk):
    data = bytearray(VALID)
    for position, action, payload in edits:
        position = min(position, len(data))
        if action == 0:
            data[position:position] = payload  # insert
        elif action == 1:
            del data[position : position + len(payload) + 1]  # delete
        elif action == 2 and position < len(data):
            data[position] ^= 1 << (len(payload) % 8)  # flip a bit
        else:
            data[position : position + len(payload)] = payload  # overwrite
    try:
        blocks, stats = parse_capture(bytes(data), BUILTIN, chunk_size=chunk)
        kept = sum(len(b) for b in blocks)
    except ImufdiError:
        return
    assert kept == stats.frames_ok <= 40 + len(edits)
    size = BUILTIN.frame_size(stats.n_imus) if stats.n_imus else 0
    assert stats.bytes_total - stats.bytes_dropped == stats.frames_ok * size


def _record_layout(record: list[dict], **extra) -> object:
    return layout_from_dict(
        {
            "name": "decode-test",
            "sync": "AA 55",
            "endian": "little",
            "n_imus": 3,
            "rate": "100Hz",
            "gyro_fs": "500dps",
            "accel_fs": "4g",
            "header": [{"name": "counter", "type": "u16", "role": "counter"}],
            "record": record,
            **extra,
        }
    )


def _i16(name: str, **extra) -> dict:
    return {"name": name, "type": "i16", **extra}


DECODE_LAYOUTS = {
    "builtin (one cast, adjacent triads)": BUILTIN,
    "one type, axes interleaved": _record_layout(
        [_i16(n) for n in ("gyro_x", "accel_x", "gyro_y", "accel_y", "gyro_z", "accel_z")]
    ),
    "one type, per-axis scales, mag, pad": _record_layout(
        [
            _i16("gyro_z", endian="big"),
            _i16("gyro_x", endian="big"),
            _i16("gyro_y", endian="big"),
            _i16("accel_x", endian="big", scale="0.01m/s^2"),
            _i16("accel_y", endian="big", scale="0.02m/s^2"),
            _i16("accel_z", endian="big"),
            {"name": "pad", "type": "pad", "size": 2},
            _i16("mag_x", scale="0.15uT"),
            _i16("mag_y", scale="0.15uT"),
            _i16("mag_z", scale="0.15uT"),
        ]
    ),
    "mixed types (per-field views)": _record_layout(
        [
            *(_i16(f"gyro_{a}") for a in "xyz"),
            *({"name": f"accel_{a}", "type": "i32", "scale": "1e-6m/s^2"} for a in "xyz"),
        ]
    ),
    "float fields (per-field views)": _record_layout(
        [
            *({"name": f"gyro_{a}", "type": "f32"} for a in "xyz"),
            *({"name": f"accel_{a}", "type": "f64", "endian": "big"} for a in "xyz"),
        ]
    ),
}


@pytest.mark.parametrize("name", list(DECODE_LAYOUTS))
def test_decoded_triads_match_a_per_field_reference(name):
    """Whatever path decodes the records (one cast or per-field views), every value is
    the field's own bytes as its type times its scale, to the bit."""
    from imufdi_cli.capture.binary import _decode_triads

    layout = DECODE_LAYOUTS[name]
    m = 3
    rng = np.random.default_rng(11)
    frames = rng.integers(0, 256, (57, layout.frame_size(m)), dtype=np.uint8)
    with np.errstate(all="raise"):  # random float bits: the decoder must not warn
        triads = _decode_triads(layout, frames, m)
    assert set(triads) == set(layout.sensor_types)
    for sensor, values in triads.items():
        assert values.shape == (57, m, 3) and values.dtype == np.float64
        for axis, a in enumerate("xyz"):
            item = next(f for f in layout.record if f.name == f"{sensor}_{a}")
            for k in range(m):
                at = layout.header_end + k * layout.record_size + item.offset
                raw = np.ascontiguousarray(frames[:, at : at + item.size]).view(item.dtype)[:, 0]
                with np.errstate(all="ignore"):
                    expected = raw * item.scale
                assert values[:, k, axis].tobytes() == expected.astype(np.float64).tobytes()


@pytest.mark.parametrize(
    "checksum",
    [
        {"kind": "CRC-16/XMODEM", "endian": "big"},
        {"kind": "crc16-modbus"},
        {"kind": "CRC-16/KERMIT"},
        {"kind": "crc-8/maxim-dow"},
        {"kind": "CRC-24/OPENPGP", "endian": "big"},
        {"kind": "CRC-32C"},
        {"kind": "crc-64/xz"},
        {"kind": "fletcher16", "endian": "big"},
        {"kind": "ubx"},
        {"kind": "crc", "width": 12, "poly": 0x80F, "init": 0, "refin": False, "xorout": 0},
    ],
    ids=lambda c: c["kind"] + ("" if "width" not in c else str(c["width"])),
)
def test_every_checksum_kind_round_trips_and_finds_flipped_bits(checksum):
    """Frames written with a checksum parse back, and a flipped bit in a record is a bad
    checksum (counted, the frame dropped), for catalogue CRCs of widths 8 to 64, a CRC given
    by its parameters, Fletcher-16 and the u-blox checksum."""
    layout = layout_from_dict(
        {
            "sync": "B5 62",
            "n_imus": 2,
            "gyro_fs": "500dps",
            "accel_fs": "4g",
            "rate": "100Hz",
            "header": [{"name": "counter", "type": "u16", "role": "counter"}],
            "record": [
                {"name": f"{s}_{a}", "type": "i16"} for s in ("gyro", "accel") for a in "xyz"
            ],
            "checksum": checksum,
        }
    )
    block = random_block(400, 2, seed=3)
    encoded = encode_capture(
        block, layout, corrupt=Corruption(flipped=6), rng=np.random.default_rng(5)
    )
    parsed, stats = parse_all(encoded.data, layout, chunk_size=333)
    assert stats.frames_bad_checksum == 6 and stats.frames_ok == 394
    assert_array_equal(parsed.t_ns, block.t_ns[encoded.intact])
