"""Frame checksums computed for many frames at once.

Every function takes ``data`` of shape (F, L), uint8 (F frames, the L covered bytes of
each) and returns one checksum per frame, shape (F,), as uint32. Table-driven CRCs loop
over the L byte columns only; each step is one numpy operation over all F frames, so the
cost per byte is a few vector operations, never a Python call.

Definitions (the "catalogue of parametrised CRC algorithms", R. Williams 1993, and the
reveng catalogue):

- ``sum8``  : sum of the bytes modulo 2^8.
- ``sum16`` : sum of the bytes modulo 2^16.
- ``xor8``  : exclusive or of the bytes.
- ``crc16-ccitt-false`` : CRC-16, poly 0x1021, init 0xFFFF, not reflected, xorout 0
  (check value of ``b"123456789"``: 0x29B1).
- ``crc32`` : CRC-32 (ISO-HDLC, zlib), poly 0x04C11DB7 reflected (0xEDB88320), init and
  xorout 0xFFFFFFFF (check value 0xCBF43926).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Final

import numpy as np

CHECKSUM_KINDS: Final[tuple[str, ...]] = (
    "none",
    "sum8",
    "sum16",
    "xor8",
    "crc16-ccitt-false",
    "crc32",
)

#: size in bytes of the stored checksum of each kind
CHECKSUM_SIZES: Final[dict[str, int]] = {
    "none": 0,
    "sum8": 1,
    "sum16": 2,
    "xor8": 1,
    "crc16-ccitt-false": 2,
    "crc32": 4,
}


def _crc16_ccitt_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint32)
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
        table[byte] = crc
    return table


def _crc32_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint32)
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xEDB88320 if crc & 1 else crc >> 1
        table[byte] = crc
    return table


_CRC16_TABLE: Final[np.ndarray] = _crc16_ccitt_table()
_CRC32_TABLE: Final[np.ndarray] = _crc32_table()


def _columns(data: np.ndarray) -> np.ndarray:
    """(L, F) contiguous copy, so each byte column is one contiguous vector."""
    return np.ascontiguousarray(np.asarray(data, dtype=np.uint8).T)


def sum8(data: np.ndarray) -> np.ndarray:
    """Byte sum modulo 256 of each row of ``data`` (F, L) -> (F,) uint32."""
    return np.asarray(data, np.uint8).sum(axis=1, dtype=np.uint64).astype(np.uint32) & 0xFF


def sum16(data: np.ndarray) -> np.ndarray:
    """Byte sum modulo 65536 of each row of ``data`` (F, L) -> (F,) uint32."""
    return np.asarray(data, np.uint8).sum(axis=1, dtype=np.uint64).astype(np.uint32) & 0xFFFF


def xor8(data: np.ndarray) -> np.ndarray:
    """Exclusive or of the bytes of each row of ``data`` (F, L) -> (F,) uint32."""
    data = np.asarray(data, np.uint8)
    if data.shape[1] == 0:
        return np.zeros(data.shape[0], np.uint32)
    return np.bitwise_xor.reduce(data, axis=1).astype(np.uint32)


def crc16_ccitt_false(data: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of each row of ``data`` (F, L) -> (F,) uint32 (16-bit values).

    Table-driven, most significant bit first:
    ``crc = (crc << 8) ^ T[(crc >> 8) ^ byte]``, init 0xFFFF.
    """
    columns = _columns(data)
    crc = np.full(columns.shape[1], 0xFFFF, dtype=np.uint32)
    index = np.empty_like(crc)
    for column in columns:
        np.right_shift(crc, 8, out=index)
        np.bitwise_xor(index, column, out=index)
        np.left_shift(crc, 8, out=crc)
        np.bitwise_and(crc, 0xFF00, out=crc)
        np.bitwise_xor(crc, _CRC16_TABLE[index], out=crc)
    return crc


def crc32(data: np.ndarray) -> np.ndarray:
    """CRC-32 (zlib) of each row of ``data`` (F, L) -> (F,) uint32.

    Table-driven, reflected: ``crc = T[(crc ^ byte) & 0xFF] ^ (crc >> 8)``, init and
    final xor 0xFFFFFFFF.
    """
    columns = _columns(data)
    crc = np.full(columns.shape[1], 0xFFFFFFFF, dtype=np.uint32)
    index = np.empty_like(crc)
    for column in columns:
        np.bitwise_xor(crc, column, out=index)
        np.bitwise_and(index, 0xFF, out=index)
        np.right_shift(crc, 8, out=crc)
        np.bitwise_xor(crc, _CRC32_TABLE[index], out=crc)
    return crc ^ np.uint32(0xFFFFFFFF)


def _none(data: np.ndarray) -> np.ndarray:
    return np.zeros(np.asarray(data).shape[0], np.uint32)


CHECKSUM_FUNCTIONS: Final[dict[str, Callable[[np.ndarray], np.ndarray]]] = {
    "none": _none,
    "sum8": sum8,
    "sum16": sum16,
    "xor8": xor8,
    "crc16-ccitt-false": crc16_ccitt_false,
    "crc32": crc32,
}


def compute_checksums(kind: str, data: np.ndarray) -> np.ndarray:
    """Checksum ``kind`` (one of :data:`CHECKSUM_KINDS`) of each row of ``data`` (F, L)."""
    return CHECKSUM_FUNCTIONS[kind](data)
