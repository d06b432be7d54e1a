"""Frame checksums computed for many frames at once.

Every function takes ``data`` of shape (F, L), uint8 (F frames, the L covered bytes of
each) and returns one checksum per frame, shape (F,), as uint64 (uint32 for the kinds
that fit). No Python call per byte or per frame (except zlib's CRC-32, below).

Kinds (:func:`checksum_function`):

- ``none``; ``sum8`` / ``sum16``: byte sum modulo 2^8 / 2^16; ``xor8``: exclusive or of
  the bytes;
- ``fletcher16``: Fletcher's checksum with sums modulo 255 (``sum1`` of the bytes,
  ``sum2`` of the running ``sum1``; value ``sum2 << 8 | sum1``, check value of
  ``b"abcde"``: 0xC8F0); ``ubx``: the u-blox UBX checksum, the same with sums modulo
  256 (RFC 1145's 8-bit Fletcher; value ``CK_B << 8 | CK_A``, so stored little-endian the
  bytes are ``CK_A, CK_B`` as u-blox sends them);
- any CRC of the "catalogue of parametrised CRC algorithms" (R. Williams, 1993; the
  reveng catalogue): width 1..64, polynomial, init, reflect in, reflect out, xor out,
  by catalogue name (:data:`CRC_CATALOGUE`: CRC-8, CRC-16/XMODEM, CRC-16/MODBUS,
  CRC-16/IBM-3740 alias CCITT-FALSE, CRC-16/KERMIT, CRC-32, CRC-32C, ...) or as
  :class:`CrcModel` parameters.

CRCs are table-driven over the columns: each step is a few numpy operations over all F
frames, two bytes per step through a 65536-entry table ``T16`` (the register after two
zero bytes from each 16-bit head). With the two bytes as one word ``w`` (big-endian when
not reflected, little-endian when reflected) a register ``c`` of ``W >= 16`` bits becomes
``(c >> 16) ^ T16[(c ^ w) & 0xFFFF]`` (reflected) or ``((c << 16) & mask) ^
T16[((c >> (W - 16)) ^ w) & 0xFFFF]`` (not reflected), which for ``W = 16`` is
``T16[c ^ w]``; a reflected register of 9 to 15 bits also ``T16[c ^ w]``; an 8-bit one
``T2[(c ^ b0) << 8 | b1]``; the rest (non-reflected 9-15 bits, narrower than 8, an odd
last byte) one byte per step. CRC-32 (ISO-HDLC, zlib's) of frames of 128 bytes or more
runs zlib's C code once per frame. ``benchmarks/bench_checksum.py`` measures these
against CRC libraries called once per frame: the column loop is faster for 8- and 16-bit
CRCs at every frame length measured, and for 32-bit ones up to about 100 bytes.
"""

from __future__ import annotations

import re
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Final

import numpy as np

#: kinds that are not catalogue CRCs (``crc`` = a CRC given by its parameters)
CHECKSUM_KINDS: Final[tuple[str, ...]] = (
    "none",
    "sum8",
    "sum16",
    "xor8",
    "fletcher16",
    "ubx",
    "crc16-ccitt-false",
    "crc32",
    "crc",
)

#: size in bytes of the stored checksum of each kind that is not a CRC
CHECKSUM_SIZES: Final[dict[str, int]] = {
    "none": 0,
    "sum8": 1,
    "sum16": 2,
    "xor8": 1,
    "fletcher16": 2,
    "ubx": 2,
    "crc16-ccitt-false": 2,
    "crc32": 4,
}


@dataclass(frozen=True)
class CrcModel:
    """A parametrised CRC (Williams' model).

    Attributes
    ----------
    name : str
        Catalogue name (``CRC-16/XMODEM``) or ``crc`` for one given by parameters.
    width : int
        Register width in bits, 1..64.
    poly : int
        Generator polynomial without its top bit, not reflected (0x1021 for CCITT).
    init : int
        Register value before the first byte (not reflected).
    refin, refout : bool
        Bytes taken least significant bit first; the register reflected before the xor.
    xorout : int
        Xored into the final value.
    check : int or None
        The CRC of ``b"123456789"`` (the catalogue's check value).
    """

    name: str
    width: int
    poly: int
    init: int
    refin: bool
    refout: bool
    xorout: int
    check: int | None = None

    @property
    def size(self) -> int:
        """Bytes of the stored value."""
        return (self.width + 7) // 8

    @property
    def mask(self) -> int:
        return (1 << self.width) - 1

    def describe(self) -> dict[str, object]:
        """The parameters as a JSON-ready dict (hex strings for the integers)."""
        digits = (self.width + 3) // 4
        return {
            "name": self.name,
            "width": self.width,
            "poly": f"0x{self.poly:0{digits}X}",
            "init": f"0x{self.init:0{digits}X}",
            "refin": self.refin,
            "refout": self.refout,
            "xorout": f"0x{self.xorout:0{digits}X}",
        }


def _m(name: str, width: int, poly: int, init: int, ref: bool, xorout: int, check: int) -> CrcModel:
    return CrcModel(name, width, poly, init, ref, ref, xorout, check)


#: catalogue CRCs (reveng "Catalogue of parametrised CRC algorithms"), check values of
#: ``b"123456789"``; each is checked against its check value in tests/capture/test_checksum.py
CRC_CATALOGUE: Final[tuple[CrcModel, ...]] = (
    _m("CRC-8/SMBUS", 8, 0x07, 0x00, False, 0x00, 0xF4),
    _m("CRC-8/MAXIM-DOW", 8, 0x31, 0x00, True, 0x00, 0xA1),
    _m("CRC-8/AUTOSAR", 8, 0x2F, 0xFF, False, 0xFF, 0xDF),
    _m("CRC-8/CDMA2000", 8, 0x9B, 0xFF, False, 0x00, 0xDA),
    _m("CRC-8/NRSC-5", 8, 0x31, 0xFF, False, 0x00, 0xF7),
    _m("CRC-8/SAE-J1850", 8, 0x1D, 0xFF, False, 0xFF, 0x4B),
    _m("CRC-16/XMODEM", 16, 0x1021, 0x0000, False, 0x0000, 0x31C3),
    _m("CRC-16/IBM-3740", 16, 0x1021, 0xFFFF, False, 0x0000, 0x29B1),
    _m("CRC-16/KERMIT", 16, 0x1021, 0x0000, True, 0x0000, 0x2189),
    _m("CRC-16/MCRF4XX", 16, 0x1021, 0xFFFF, True, 0x0000, 0x6F91),
    _m("CRC-16/IBM-SDLC", 16, 0x1021, 0xFFFF, True, 0xFFFF, 0x906E),
    _m("CRC-16/SPI-FUJITSU", 16, 0x1021, 0x1D0F, False, 0x0000, 0xE5CC),
    _m("CRC-16/GSM", 16, 0x1021, 0x0000, False, 0xFFFF, 0xCE3C),
    _m("CRC-16/MODBUS", 16, 0x8005, 0xFFFF, True, 0x0000, 0x4B37),
    _m("CRC-16/ARC", 16, 0x8005, 0x0000, True, 0x0000, 0xBB3D),
    _m("CRC-16/USB", 16, 0x8005, 0xFFFF, True, 0xFFFF, 0xB4C8),
    _m("CRC-16/MAXIM-DOW", 16, 0x8005, 0x0000, True, 0xFFFF, 0x44C2),
    _m("CRC-16/UMTS", 16, 0x8005, 0x0000, False, 0x0000, 0xFEE8),
    _m("CRC-16/DNP", 16, 0x3D65, 0x0000, True, 0xFFFF, 0xEA82),
    _m("CRC-24/OPENPGP", 24, 0x864CFB, 0xB704CE, False, 0x000000, 0x21CF02),
    _m("CRC-32/ISO-HDLC", 32, 0x04C11DB7, 0xFFFFFFFF, True, 0xFFFFFFFF, 0xCBF43926),
    _m("CRC-32/ISCSI", 32, 0x1EDC6F41, 0xFFFFFFFF, True, 0xFFFFFFFF, 0xE3069283),
    _m("CRC-32/BZIP2", 32, 0x04C11DB7, 0xFFFFFFFF, False, 0xFFFFFFFF, 0xFC891918),
    _m("CRC-32/MPEG-2", 32, 0x04C11DB7, 0xFFFFFFFF, False, 0x00000000, 0x0376E6E7),
    _m("CRC-32/CKSUM", 32, 0x04C11DB7, 0x00000000, False, 0xFFFFFFFF, 0x765E7680),
    _m("CRC-32/JAMCRC", 32, 0x04C11DB7, 0xFFFFFFFF, True, 0x00000000, 0x340BC6D9),
    _m("CRC-64/XZ", 64, 0x42F0E1EBA9EA3693, 2**64 - 1, True, 2**64 - 1, 0x995DC9BBDF1939FA),
    _m("CRC-64/ECMA-182", 64, 0x42F0E1EBA9EA3693, 0, False, 0, 0x6C40DF5F0B497347),
    CrcModel("CRC-7/MMC", 7, 0x09, 0x00, False, False, 0x00, 0x75),
    CrcModel("CRC-5/USB", 5, 0x05, 0x1F, True, True, 0x1F, 0x19),
)

#: other names of catalogue CRCs (the catalogue's aliases and common usage)
CRC_ALIASES: Final[dict[str, str]] = {
    "CRC-8": "CRC-8/SMBUS",
    "CRC-8/MAXIM": "CRC-8/MAXIM-DOW",
    "CRC-16/CCITT-FALSE": "CRC-16/IBM-3740",
    "CRC-16/AUTOSAR": "CRC-16/IBM-3740",
    "CRC-16/CCITT-TRUE": "CRC-16/KERMIT",
    "CRC-16/X-25": "CRC-16/IBM-SDLC",
    "CRC-16/MAVLINK": "CRC-16/MCRF4XX",
    "CRC-16": "CRC-16/ARC",
    "CRC-16/AUG-CCITT": "CRC-16/SPI-FUJITSU",
    "CRC-16/BUYPASS": "CRC-16/UMTS",
    "CRC-16/MAXIM": "CRC-16/MAXIM-DOW",
    "CRC-32": "CRC-32/ISO-HDLC",
    "CRC-32C": "CRC-32/ISCSI",
    "CRC-32/CASTAGNOLI": "CRC-32/ISCSI",
    "CRC-32/POSIX": "CRC-32/CKSUM",
    "CRC-24": "CRC-24/OPENPGP",
    "CRC-64": "CRC-64/ECMA-182",
}
#: names used for several CRCs (datasheets disagree): refused, with what they can mean
AMBIGUOUS: Final[dict[str, tuple[str, ...]]] = {
    "crc16ccitt": ("CRC-16/IBM-3740 (CCITT-FALSE)", "CRC-16/KERMIT", "CRC-16/XMODEM"),
    "crcccitt": ("CRC-16/IBM-3740 (CCITT-FALSE)", "CRC-16/KERMIT", "CRC-16/XMODEM"),
}


def _key(name: str) -> str:
    """``"CRC-16/XMODEM"``, ``"crc16-xmodem"``, ``"crc_16_xmodem"`` -> ``crc16xmodem``."""
    return re.sub(r"[^0-9a-z]", "", name.lower())


@cache
def _by_key() -> dict[str, CrcModel]:
    table = {_key(m.name): m for m in CRC_CATALOGUE}
    for alias, name in CRC_ALIASES.items():
        table[_key(alias)] = next(m for m in CRC_CATALOGUE if m.name == name)
    return table


def find_crc(name: str) -> CrcModel | None:
    """The catalogue CRC of a name or alias, punctuation and case ignored
    (``"crc16-modbus"``, ``"CRC-16/MODBUS"``); None when it names none."""
    return _by_key().get(_key(name))


def catalogue_names() -> list[str]:
    return [m.name for m in CRC_CATALOGUE]


def ambiguous(name: str) -> tuple[str, ...] | None:
    """The CRCs a name used for several means (``crc16-ccitt``), else None."""
    return AMBIGUOUS.get(_key(name))


def _reflect(value: int, width: int) -> int:
    out = 0
    for _ in range(width):
        out = (out << 1) | (value & 1)
        value >>= 1
    return out


def _dtype(width: int) -> type[np.unsignedinteger]:
    return (
        np.uint8
        if width <= 8
        else np.uint16
        if width <= 16
        else np.uint32
        if width <= 32
        else np.uint64
    )


@dataclass(frozen=True)
class _Engine:
    """A CRC model compiled for the column loop: the register holds ``bits`` bits (the
    width, or 8 for widths below 8, left-aligned when not reflected)."""

    model: CrcModel
    bits: int
    table: np.ndarray  # (256,) one byte per step
    pair: np.ndarray | None  # (65536,) two bytes per step (8 and 16 bits)
    start: int  # register before the first byte

    @property
    def dtype(self) -> type[np.unsignedinteger]:
        return _dtype(self.bits)


@cache
def _engine(model: CrcModel) -> _Engine:
    width = model.width
    bits = max(width, 8)
    mask = (1 << bits) - 1
    table = np.arange(256, dtype=np.uint64)
    if model.refin:
        poly = np.uint64(_reflect(model.poly, width))
        for _ in range(8):
            table = np.where(
                table & np.uint64(1), (table >> np.uint64(1)) ^ poly, table >> np.uint64(1)
            )
        start = _reflect(model.init, width)
    else:
        shift = bits - width  # left-align a narrow CRC in an 8-bit register
        poly = np.uint64((model.poly << shift) & mask)
        top = np.uint64(1 << (bits - 1))
        table = table << np.uint64(bits - 8)
        for _ in range(8):
            table = np.where(
                table & top, (table << np.uint64(1)) ^ poly, table << np.uint64(1)
            ) & np.uint64(mask)
        start = (model.init << shift) & mask
    dtype = _dtype(bits)
    table = table.astype(dtype)
    pair = None
    if bits == 8:
        # two bytes: T2[(c ^ b0) << 8 | b1] (the register is one byte)
        x = np.arange(1 << 16, dtype=np.uint32)
        pair = table[table[x >> 8] ^ (x & 0xFF)].astype(np.uint8)
    elif bits >= 16 or model.refin:
        # two zero bytes from every 16-bit register head: T16 (see _crc_columns)
        wide = table.astype(np.uint64)
        x = np.arange(1 << 16, dtype=np.uint64)
        eight = np.uint64(8)
        if model.refin:
            for _ in range(2):
                x = (x >> eight) ^ wide[x & np.uint64(0xFF)]
        else:
            x = x << np.uint64(bits - 16)
            for _ in range(2):
                x = ((x << eight) & np.uint64(mask)) ^ wide[x >> np.uint64(bits - 8)]
        pair = x.astype(dtype)
    return _Engine(model, bits, table, pair, start)


def _crc_columns(engine: _Engine, data: np.ndarray) -> np.ndarray:
    """The final register (before reflection and xor) of each row, (F,) of the engine's
    dtype."""
    n_frames, length = data.shape
    bits = engine.bits
    dtype = engine.dtype
    crc = np.full(n_frames, engine.start, dtype=dtype)
    if n_frames == 0 or length == 0:
        return crc
    refin = engine.model.refin
    done = 0
    if engine.pair is not None and length >= 2:
        pairs = length // 2
        head = data[:, : 2 * pairs]
        if head.strides[-1] != 1:
            head = np.ascontiguousarray(head)
        # the two bytes of each step as one word (big-endian when not reflected, so the
        # first byte is the high one), one row per word position: one strided copy
        words = np.empty((pairs, n_frames), np.uint16)
        words[...] = head.view("<u2" if refin and bits > 8 else ">u2").T
        index = np.empty(n_frames, np.uint16 if bits <= 16 else dtype)
        table2 = engine.pair
        if bits == 8:
            for column in words:  # T2[(c ^ b0) << 8 | b1]
                np.left_shift(crc, 8, out=index, dtype=np.uint16)
                np.bitwise_xor(index, column, out=index)
                table2.take(index, out=crc, mode="wrap")
        elif bits == 16 or (refin and bits < 16):
            # the 16-bit head of the register and the word: c' = T16[c ^ w]
            spare = np.empty_like(crc)
            for column in words:
                np.bitwise_xor(crc, column, out=crc, casting="unsafe")
                table2.take(crc, out=spare, mode="wrap")
                crc, spare = spare, crc
        else:
            # reflected: c' = (c >> 16) ^ T16[(c ^ w) & 0xFFFF]; not reflected:
            # c' = ((c << 16) & mask) ^ T16[((c >> (bits - 16)) ^ w) & 0xFFFF]
            sixteen = dtype(16)
            top = dtype(bits - 16)
            low16 = dtype(0xFFFF)
            mask = dtype((1 << bits) - 1) if bits < 64 else dtype(2**64 - 1)
            looked = np.empty_like(crc)
            # take's indices as int64 (values < 2^16, the same bits): numpy 2.0 refuses to
            # cast uint64 indices, later releases do it
            take_index = index.view(np.int64) if index.dtype == np.uint64 else index
            for column in words:
                if refin:
                    np.bitwise_xor(crc, column, out=index)
                    np.right_shift(crc, sixteen, out=crc)
                else:
                    np.right_shift(crc, top, out=index)
                    np.bitwise_xor(index, column, out=index)
                    np.left_shift(crc, sixteen, out=crc)
                    if bits < 64:
                        np.bitwise_and(crc, mask, out=crc)
                np.bitwise_and(index, low16, out=index)
                table2.take(take_index, out=looked)
                np.bitwise_xor(crc, looked, out=crc)
        done = 2 * pairs
    if done == length:
        return crc
    table = engine.table
    shift = dtype(bits - 8)
    eight = dtype(8)
    low = dtype(0xFF)
    mask = dtype((1 << bits) - 1) if bits < 64 else dtype(2**64 - 1)
    # the remaining columns as rows of one contiguous copy (a strided column of a large
    # chunk touches a cache line per frame at every step)
    columns = np.ascontiguousarray(data[:, done:].T).astype(dtype)
    index = np.empty_like(crc)
    for column in columns:
        if refin:
            np.bitwise_xor(crc, column, out=index)
        else:
            np.right_shift(crc, shift, out=index)
            np.bitwise_xor(index, column, out=index)
        np.bitwise_and(index, low, out=index)
        if bits == 8:
            table.take(index, out=crc)
        elif refin:
            np.right_shift(crc, eight, out=crc)
            np.bitwise_xor(crc, table[index], out=crc)
        else:
            np.left_shift(crc, eight, out=crc)
            np.bitwise_and(crc, mask, out=crc)
            np.bitwise_xor(crc, table[index], out=crc)
    return crc


def crc(model: CrcModel, data: np.ndarray) -> np.ndarray:
    """The CRC ``model`` of each row of ``data`` (F, L) uint8 -> (F,) uint64."""
    data = np.asarray(data, dtype=np.uint8)
    if data.ndim != 2:
        raise ValueError(f"crc needs (frames, bytes) data, got shape {data.shape}")
    engine = _engine(model)
    register = _crc_columns(engine, data).astype(np.uint64)
    width = model.width
    if not model.refin and engine.bits > width:
        register >>= np.uint64(engine.bits - width)
    if model.refin != model.refout:
        register = _reflect_array(register, width)
    return register ^ np.uint64(model.xorout)


def _reflect_array(values: np.ndarray, width: int) -> np.ndarray:
    out = np.zeros_like(values)
    v = values.copy()
    one = np.uint64(1)
    for _ in range(width):
        out = (out << one) | (v & one)
        v >>= one
    return out


# --- the other kinds ----------------------------------------------------------------------

IBM_3740: Final[CrcModel] = next(m for m in CRC_CATALOGUE if m.name == "CRC-16/IBM-3740")
ISO_HDLC: Final[CrcModel] = next(m for m in CRC_CATALOGUE if m.name == "CRC-32/ISO-HDLC")


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


def _fletcher(data: np.ndarray, modulus: int) -> np.ndarray:
    """``sum2 << 8 | sum1`` with ``sum1 = sum b_i``, ``sum2 = sum (L - i) b_i`` (the sum
    of the running sum1), both modulo ``modulus``."""
    data = np.asarray(data, np.uint8)
    length = data.shape[1]
    weights = np.arange(length, 0, -1, dtype=np.uint64)
    # exact in uint64: at most 255 * L * (L + 1) / 2, far below 2^64 for any frame
    sum1 = data.sum(axis=1, dtype=np.uint64) % np.uint64(modulus)
    sum2 = (
        (data.astype(np.uint64) @ weights) % np.uint64(modulus) if length else sum1 * np.uint64(0)
    )
    return ((sum2 << np.uint64(8)) | sum1).astype(np.uint32)


def fletcher16(data: np.ndarray) -> np.ndarray:
    """Fletcher-16 (sums modulo 255) of each row of ``data`` (F, L) -> (F,) uint32."""
    return _fletcher(data, 255)


def ubx(data: np.ndarray) -> np.ndarray:
    """u-blox UBX checksum ``CK_B << 8 | CK_A`` (8-bit Fletcher, sums modulo 256) of each
    row of ``data`` (F, L) -> (F,) uint32."""
    return _fletcher(data, 256)


def crc16_ccitt_false(data: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE (CRC-16/IBM-3740) of each row of ``data`` (F, L) -> (F,) uint32."""
    return crc(IBM_3740, data).astype(np.uint32)


#: frames at least this long get CRC-32/ISO-HDLC from zlib, one call per frame (faster
#: than the column loop from about 128 bytes: benchmarks/bench_checksum.py)
ZLIB_FROM_BYTES: Final[int] = 128


def crc32(data: np.ndarray) -> np.ndarray:
    """CRC-32 (ISO-HDLC, zlib's) of each row of ``data`` (F, L) -> (F,) uint32.

    Reflected, init and final xor 0xFFFFFFFF: the column loop for short frames,
    :func:`zlib.crc32` of each row from :data:`ZLIB_FROM_BYTES` on.
    """
    data = np.asarray(data, dtype=np.uint8)
    n_frames, length = data.shape
    if n_frames == 0 or length == 0:
        return np.zeros(n_frames, np.uint32)
    if length < ZLIB_FROM_BYTES:
        return crc(ISO_HDLC, data).astype(np.uint32)
    data = np.ascontiguousarray(data)
    flat = data.reshape(-1).data
    return np.fromiter(
        (zlib.crc32(flat[i : i + length]) for i in range(0, n_frames * length, length)),
        dtype=np.uint32,
        count=n_frames,
    )


def _none(data: np.ndarray) -> np.ndarray:
    return np.zeros(np.asarray(data).shape[0], np.uint32)


CHECKSUM_FUNCTIONS: Final[dict[str, Callable[[np.ndarray], np.ndarray]]] = {
    "none": _none,
    "sum8": sum8,
    "sum16": sum16,
    "xor8": xor8,
    "fletcher16": fletcher16,
    "ubx": ubx,
    "crc16-ccitt-false": crc16_ccitt_false,
    "crc32": crc32,
}


def checksum_function(
    kind: str, model: CrcModel | None = None
) -> Callable[[np.ndarray], np.ndarray]:
    """The function computing checksum ``kind`` of rows (F, L) -> (F,): a kind of
    :data:`CHECKSUM_KINDS`, or a CRC ``model`` (kind ``crc`` or a catalogue name)."""
    if model is not None:
        if model.name == "CRC-32/ISO-HDLC":
            return crc32  # zlib's C code for long frames (crc32's docstring)
        return lambda data: crc(model, data)
    function = CHECKSUM_FUNCTIONS.get(kind)
    if function is not None:
        return function
    found = find_crc(kind)
    if found is None:
        raise ValueError(f"unknown checksum kind {kind!r}")
    return checksum_function(kind, found)


def checksum_size(kind: str, model: CrcModel | None = None) -> int:
    """Bytes of the stored checksum."""
    if model is not None:
        return model.size
    if kind in CHECKSUM_SIZES:
        return CHECKSUM_SIZES[kind]
    found = find_crc(kind)
    if found is None:
        raise ValueError(f"unknown checksum kind {kind!r}")
    return found.size


def compute_checksums(kind: str, data: np.ndarray, model: CrcModel | None = None) -> np.ndarray:
    """Checksum ``kind`` (or the CRC ``model``) of each row of ``data`` (F, L)."""
    return checksum_function(kind, model)(data)
