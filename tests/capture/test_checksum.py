import zlib

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_array_equal

from imufdi_cli.capture.checksum import compute_checksums, crc16_ccitt_false, crc32

CHECK = np.frombuffer(b"123456789", dtype=np.uint8)[None, :]


def test_crc_check_values_of_the_catalogue():
    # reveng catalogue check values for "123456789"
    assert int(crc16_ccitt_false(CHECK)[0]) == 0x29B1
    assert int(crc32(CHECK)[0]) == 0xCBF43926


def test_sums_and_xor_on_a_known_row():
    row = np.array([[0xFF, 0x01, 0x80, 0x7F]], dtype=np.uint8)
    assert int(compute_checksums("sum8", row)[0]) == (0xFF + 0x01 + 0x80 + 0x7F) & 0xFF
    assert int(compute_checksums("sum16", row)[0]) == 0xFF + 0x01 + 0x80 + 0x7F
    assert int(compute_checksums("xor8", row)[0]) == 0xFF ^ 0x01 ^ 0x80 ^ 0x7F


def _crc16_bitwise(data: bytes) -> int:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


@settings(max_examples=50, deadline=None)
@given(st.lists(st.binary(min_size=7, max_size=7), min_size=1, max_size=20))
def test_vectorised_crcs_match_per_frame_references(rows):
    data = np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(len(rows), 7)
    assert_array_equal(crc32(data), [zlib.crc32(r) for r in rows])
    assert_array_equal(crc16_ccitt_false(data), [_crc16_bitwise(r) for r in rows])


@settings(max_examples=40, deadline=None)
@given(
    st.integers(min_value=1, max_value=60),
    st.integers(min_value=0, max_value=40),
    st.integers(min_value=0, max_value=2**32 - 1),
)
def test_crc16_of_strided_frames_of_any_length_matches_binascii(length, n_frames, seed):
    # binascii.crc_hqx with initial value 0xFFFF is CRC-16/CCITT-FALSE (poly 0x1021, not
    # reflected, no final xor): an independent C implementation. Frames are overlapping
    # windows of one buffer (row stride 3, not their length), as the parser passes them.
    import binascii

    from numpy.lib.stride_tricks import sliding_window_view

    buffer = np.random.default_rng(seed).integers(0, 256, 3 * n_frames + length, np.uint8)
    frames = sliding_window_view(buffer, length)[::3][:n_frames]
    expected = [binascii.crc_hqx(bytes(row), 0xFFFF) for row in frames]
    assert_array_equal(crc16_ccitt_false(frames), np.array(expected, np.uint32))
