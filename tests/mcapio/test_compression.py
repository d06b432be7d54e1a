"""Chunk compression helpers: the CRC-32 every chunk carries."""

from __future__ import annotations

import zlib

import numpy as np

from imufdi_cli.mcapio import compression


def test_crc32_is_zlibs_crc32() -> None:
    """zlib-ng's CRC-32 (when installed) gives zlib's values: MCAP's checksum, ISO-HDLC."""
    rng = np.random.default_rng(0)
    assert compression.crc32(b"123456789") == 0xCBF43926  # the CRC-32 check value
    for size in (0, 1, 15, 64, 4095, 1 << 20):
        data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        assert compression.crc32(data) == zlib.crc32(data)
        assert compression.crc32(memoryview(data)) == zlib.crc32(data)
        head, tail = data[: size // 3], data[size // 3 :]
        assert compression.crc32(tail, compression.crc32(head)) == zlib.crc32(data)
    assert compression.CRC32_IMPLEMENTATION in ("zlib-ng", "zlib")
