import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_array_equal

from imufdi_cli.capture.checksum import (
    CRC_ALIASES,
    CRC_CATALOGUE,
    CrcModel,
    compute_checksums,
    crc,
    crc16_ccitt_false,
    crc32,
    find_crc,
    fletcher16,
    ubx,
)

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


# --- parametrised CRCs, the catalogue, Fletcher --------------------------------------------


def _reflect_bits(value: int, width: int) -> int:
    return int(f"{value:0{width}b}"[::-1], 2)


def _crc_bitwise(model: CrcModel, data: bytes) -> int:
    """Williams' model, one bit at a time (the definition, no table)."""
    top, mask = 1 << (model.width - 1), (1 << model.width) - 1
    register = model.init
    for byte in data:
        if model.refin:
            byte = _reflect_bits(byte, 8)
        for bit in range(7, -1, -1):
            feed = ((byte >> bit) & 1) ^ (1 if register & top else 0)
            register = ((register << 1) & mask) ^ (model.poly if feed else 0)
    if model.refout:
        register = _reflect_bits(register, model.width)
    return register ^ model.xorout


@pytest.mark.parametrize("model", CRC_CATALOGUE, ids=lambda m: m.name)
def test_every_catalogue_crc_gives_its_check_value(model):
    assert int(crc(model, CHECK)[0]) == model.check
    assert int(compute_checksums(model.name, CHECK)[0]) == model.check
    assert _crc_bitwise(model, b"123456789") == model.check


def test_catalogue_names_and_aliases_are_found_whatever_the_spelling():
    assert find_crc("crc16-xmodem").name == "CRC-16/XMODEM"
    assert find_crc("CRC_16_MODBUS").name == "CRC-16/MODBUS"
    assert find_crc("crc16-ccitt-false").name == "CRC-16/IBM-3740"
    assert find_crc("CRC-32C").name == "CRC-32/ISCSI"
    assert find_crc("crc8").name == "CRC-8/SMBUS"
    assert find_crc("crc-16/mavlink").name == "CRC-16/MCRF4XX"
    assert find_crc("crc16-ccitt") is None  # ambiguous: refused by the layout
    assert all(find_crc(alias).name == name for alias, name in CRC_ALIASES.items())


@settings(max_examples=150, deadline=None)
@given(
    st.integers(min_value=1, max_value=64).flatmap(
        lambda w: st.tuples(
            st.just(w),
            st.integers(min_value=1, max_value=(1 << w) - 1),
            st.integers(min_value=0, max_value=(1 << w) - 1),
            st.booleans(),
            st.booleans(),
            st.integers(min_value=0, max_value=(1 << w) - 1),
        )
    ),
    st.integers(min_value=0, max_value=23),
    st.integers(min_value=0, max_value=9),
    st.integers(min_value=0, max_value=2**32 - 1),
)
def test_any_parametrised_crc_of_strided_frames_matches_the_bitwise_definition(
    params, length, n_frames, seed
):
    """Any width (1..64), polynomial, init, reflections and xorout; frames of any length as
    overlapping windows of one buffer (row stride 3), as the parser passes them: the table
    and two-bytes-per-step paths give the bit-by-bit definition's value."""
    from numpy.lib.stride_tricks import sliding_window_view

    model = CrcModel("crc", *params)
    buffer = np.random.default_rng(seed).integers(0, 256, 3 * n_frames + length, np.uint8)
    frames = sliding_window_view(buffer, length)[::3][:n_frames]
    expected = [_crc_bitwise(model, bytes(row)) for row in frames]
    assert [int(v) for v in crc(model, frames)] == expected


def test_crcs_match_independent_c_implementations():
    import binascii

    xmodem, iso_hdlc = find_crc("CRC-16/XMODEM"), find_crc("CRC-32")
    for length in (37, 127, 128, 300):  # CRC-32: the column loop, then zlib per frame
        rows = np.random.default_rng(length).integers(0, 256, (50, length), np.uint8)
        assert_array_equal(crc(xmodem, rows), [binascii.crc_hqx(bytes(r), 0) for r in rows])
        assert_array_equal(crc(iso_hdlc, rows), [zlib.crc32(bytes(r)) for r in rows])
        assert_array_equal(compute_checksums("CRC-32", rows), [zlib.crc32(bytes(r)) for r in rows])
        assert_array_equal(compute_checksums("crc32", rows), [zlib.crc32(bytes(r)) for r in rows])


def test_fletcher16_and_ubx_on_published_vectors():
    def row(text: bytes) -> np.ndarray:
        return np.frombuffer(text, np.uint8)[None, :]

    # Fletcher-16 test vectors (sums modulo 255)
    assert int(fletcher16(row(b"abcde"))[0]) == 0xC8F0
    assert int(fletcher16(row(b"abcdef"))[0]) == 0x2057
    assert int(fletcher16(row(b"abcdefgh"))[0]) == 0x0627
    # u-blox UBX-ACK-ACK of CFG-MSG: B5 62 | 05 01 02 00 06 01 | CK_A 0x0F CK_B 0x38
    assert int(ubx(row(bytes([0x05, 0x01, 0x02, 0x00, 0x06, 0x01])))[0]) == 0x380F
    long = np.full((2, 5000), 255, np.uint8)  # sums far past one byte: no overflow
    total = sum(255 * (5000 - i) for i in range(5000))
    assert int(ubx(long)[0]) == ((total % 256) << 8) | (255 * 5000 % 256)
