"""Chunk compression and bounded decompression (zstd, lz4, none) for MCAP chunks, and the
unpacking of a Chunk record read from a file (its fields, limit and CRC checked)."""

from __future__ import annotations

import struct
import threading
import zlib
from collections.abc import Callable

from imufdi_cli.errors import McapInputError

#: The CRC-32 function, loaded on first use (see _load_crc32): a reader that never checks a
#: CRC (zstd frames with content checksums, lenient reading) does not import zlib-ng
#: (start-up time, docs/performance.md).
_CRC32: Callable[..., int] | None = None
_CRC32_NAME = ""
#: Bytes checked by zlib's CRC-32 before zlib-ng is loaded (see crc32): loading zlib-ng
#: (and the gzip module it imports) costs as much CPU as zlib's CRC-32 of 4.6-7.1 MiB
#: (measured, docs/performance.md "Start-up"), so up to that much zlib is the cheaper one.
_ZLIB_FIRST = 4 << 20
_ZLIB_LEFT = _ZLIB_FIRST


def _load_crc32() -> Callable[..., int]:
    """zlib-ng's CRC-32 (folding with PCLMULQDQ/VPCLMULQDQ: same value, ~6x zlib's
    speed), or zlib's when zlib-ng is not installed."""
    global _CRC32, _CRC32_NAME
    try:
        from zlib_ng import zlib_ng

        _CRC32, _CRC32_NAME = zlib_ng.crc32, "zlib-ng"
    except ImportError:  # pragma: no cover - zlib-ng is a dependency; zlib: same values
        _CRC32, _CRC32_NAME = zlib.crc32, "zlib"
    return _CRC32


def __getattr__(name: str) -> str:
    if name == "CRC32_IMPLEMENTATION":  # "zlib-ng" or "zlib": which computes crc32
        _load_crc32()
        return _CRC32_NAME
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def crc32(data: bytes | bytearray | memoryview, value: int = 0) -> int:
    """CRC-32 (ISO-HDLC, the MCAP checksum: ``zlib.crc32``'s value) of ``data``, continuing
    from ``value``. Computed by zlib-ng when installed (about 15 GB/s on the build machine
    against zlib's 2.5), else by zlib. The first ``_ZLIB_FIRST`` bytes of a process are
    checked by zlib: loading zlib-ng costs about as much CPU as zlib's CRC of 5 MiB, so a
    command reading a small log (``imufdi info``) does not load it."""
    global _ZLIB_LEFT
    if _CRC32 is None:
        if len(data) <= _ZLIB_LEFT:
            _ZLIB_LEFT -= len(data)
            return zlib.crc32(data, value)
        _load_crc32()
    return int(_CRC32(data, value))  # type: ignore[misc]


#: Per-thread zstd compressors and decompressors (neither may be shared between threads).
_ZSTD_LOCAL = threading.local()
#: zstd compression level of chunks. Fast level -3 compresses these CDR records about 1.8x
#: faster than level 1 for ~1% larger chunks (standard zstd frames; every decoder reads them).
ZSTD_LEVEL = -3


def compress(raw: bytes | memoryview, compression: str) -> bytes:
    """Compress a chunk's records (``compression`` "zstd", "lz4" or "" / "none"); thread-safe."""
    if compression == "zstd":
        compressor = getattr(_ZSTD_LOCAL, "compressor", None)
        if compressor is None:
            import zstandard

            # with the frame's content checksum: every zstd decoder verifies it
            compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True)
            _ZSTD_LOCAL.compressor = compressor
        return bytes(compressor.compress(raw))
    if compression == "lz4":
        import lz4.frame

        return bytes(lz4.frame.compress(raw, content_checksum=True))
    return bytes(raw)


def _error_text(err: BaseException) -> str:
    """``str(err)``, or the exception's type when it has no message (never empty)."""
    text = " ".join(str(err).split())
    return text or type(err).__name__


def _zstd_decompress(raw: bytes | memoryview, size: int) -> bytes:
    import zstandard

    # per thread: readers decompress on a worker thread too, and a ZstdDecompressor must
    # not be used by two threads at once
    dctx = getattr(_ZSTD_LOCAL, "decompressor", None)
    if dctx is None:
        dctx = zstandard.ZstdDecompressor()
        _ZSTD_LOCAL.decompressor = dctx
    # ``decompress`` allocates what the frame header claims (ignoring max_output_size), so
    # it is used only when that claim is the chunk's declared size; otherwise read at most
    # one byte more than declared through a stream reader (also reads across frames).
    if zstandard.frame_content_size(raw) == size:
        try:
            out = bytes(dctx.decompress(raw))
        except zstandard.ZstdError:
            pass  # read again below: the stream reader's message, as decompress_into gives
        else:
            if len(out) == size:
                return out
    with dctx.stream_reader(raw, read_across_frames=True) as reader:
        out = bytes(reader.read(size + 1))
    return out


def _lz4_decompress(raw: bytes | memoryview, size: int) -> bytes:
    import lz4.frame

    dctx = lz4.frame.LZ4FrameDecompressor()
    out = bytes(dctx.decompress(raw, max_length=size + 1))
    if len(out) <= size and not dctx.eof:
        raise McapInputError(f"lz4 frame incomplete after {len(out)} of {size} declared bytes")
    return out


def frame_checksummed(raw: bytes | memoryview, compression: str, size: int) -> bool:
    """Whether decompressing ``raw`` verifies all ``size`` record bytes by itself: a zstd
    frame that declares exactly ``size`` bytes and carries a content checksum (XXH64 of
    those bytes, which zstd checks when the frame ends; any further frame would give bytes
    past ``size``, an error). Then a chunk CRC-32 over the same bytes adds no check."""
    if compression != "zstd" or len(raw) < 6:
        return False
    import zstandard

    try:
        params = zstandard.get_frame_parameters(raw)
    except zstandard.ZstdError:
        return False
    return bool(params.has_checksum) and params.content_size == size


def decompress_into(raw: bytes | memoryview, compression: str, out: memoryview) -> None:
    """Decompress chunk records into ``out``, which must be exactly the declared size.

    Same checks and messages as :func:`decompress` (a size other than ``len(out)`` is an
    error; nothing past ``len(out)`` is produced but one byte), without allocating the
    records: zstd frames are decoded straight into ``out`` (the reader's batch buffer).

    Raises
    ------
    McapInputError
        As :func:`decompress`; ``out`` then holds partial data.
    """
    size = len(out)
    if compression != "zstd":
        out[:] = decompress(raw, compression, size)
        return
    import zstandard

    dctx = getattr(_ZSTD_LOCAL, "decompressor", None)
    if dctx is None:
        dctx = zstandard.ZstdDecompressor()
        _ZSTD_LOCAL.decompressor = dctx
    filled = 0
    try:
        with dctx.stream_reader(raw, read_across_frames=True) as reader:
            while filled < size:
                n = reader.readinto(out[filled:])
                if not n:
                    break
                filled += n
            # one byte more: past the declared size (a bomb), and the end of the last
            # frame is reached, so its content checksum is verified
            extra = reader.read(1) if filled == size else b""
    except Exception as err:  # zstandard.ZstdError
        raise McapInputError(f"corrupt zstd chunk ({_error_text(err)})") from err
    if extra:
        raise McapInputError(f"zstd records exceed the declared size of {size} bytes")
    if filled < size:
        raise McapInputError(f"zstd records hold {filled} bytes, not the declared {size}")


def decompress(raw: bytes | memoryview, compression: str, uncompressed_size: int) -> bytes:
    """Decompress chunk records, producing at most ``uncompressed_size`` bytes.

    The output is bounded by the declared size for every compression (a decompression bomb
    stops one byte past it); a size other than the declared one is an error.

    Raises
    ------
    McapInputError
        Unknown compression, corrupt data, or a size other than ``uncompressed_size``
        (the message says which, never empty).
    """
    if compression not in ("", "zstd", "lz4"):
        raise McapInputError(
            f"unsupported chunk compression {compression[:40]!r}; supported: zstd, lz4"
        )
    try:
        if compression == "":
            out = bytes(raw)
        elif compression == "zstd":
            out = _zstd_decompress(raw, uncompressed_size)
        else:
            out = _lz4_decompress(raw, uncompressed_size)
    except McapInputError:
        raise
    except Exception as err:  # zstandard.ZstdError, lz4's RuntimeError, ...
        raise McapInputError(f"corrupt {compression} chunk ({_error_text(err)})") from err
    if len(out) > uncompressed_size:
        raise McapInputError(
            f"{compression or 'uncompressed'} records exceed the declared size of"
            f" {uncompressed_size} bytes"
        )
    if len(out) < uncompressed_size:
        raise McapInputError(
            f"{compression or 'uncompressed'} records hold {len(out)} bytes, not the declared"
            f" {uncompressed_size}"
        )
    return out


#: Chunk record fields before the compression name: start/end time, uncompressed size,
#: CRC, and the compression name's length.
_CHUNK_HEAD = struct.Struct("<QQQII")
#: Chunks of at most this many record bytes are walked in Python (numpy costs more there),
#: and decompressed into bytes of their own (larger zstd chunks go into the batch buffer).
_SMALL_CHUNK = 4096

#: (records, "") of a usable chunk, or (None, why it is not)
_Unpacked = tuple[bytes | memoryview | None, str]


def _declared_size(content: bytes) -> int:
    """The uncompressed size a Chunk record's content declares (0 if it is too short)."""
    if len(content) < _CHUNK_HEAD.size:
        return 0
    return int(_CHUNK_HEAD.unpack_from(content)[2])


def _unpack_chunk(
    content: bytes,
    max_chunk_bytes: int,
    validate_crcs: bool,
    slot: Callable[[int], memoryview] | None = None,
    trust_frame_checksum: bool = False,
) -> _Unpacked:
    """A Chunk record's records, decompressed and (with ``validate_crcs``) CRC-checked, or
    why the chunk is unusable. A zstd chunk of more than ``_SMALL_CHUNK`` bytes is
    decompressed into ``slot(size)`` when given (no allocation, no later copy). Touches
    no reader state (runs on the worker thread, without ``slot``). With
    ``trust_frame_checksum`` the CRC-32 is skipped when the zstd frame's content checksum
    already verified every record byte (:func:`~imufdi_cli.mcapio.compression.frame_checksummed`)."""
    try:
        if len(content) < _CHUNK_HEAD.size + 8:
            raise McapInputError("malformed Chunk record (shorter than its fields)")
        _, _, uncompressed_size, crc, name_length = _CHUNK_HEAD.unpack_from(content)
        records_at = _CHUNK_HEAD.size + name_length + 8
        if records_at > len(content):
            raise McapInputError("malformed Chunk record (compression name past its end)")
        compression = content[_CHUNK_HEAD.size : records_at - 8].decode("utf-8", "replace")
        (records_length,) = struct.unpack_from("<Q", content, records_at - 8)
        if records_length != len(content) - records_at:
            raise McapInputError(
                f"records length {records_length} does not match the record"
                f" ({len(content) - records_at} bytes left)"
            )
        if uncompressed_size > max_chunk_bytes:
            raise McapInputError(
                f"declares {uncompressed_size} uncompressed bytes, over the limit of"
                f" {max_chunk_bytes} (IMUFDI_MAX_CHUNK_BYTES)"
            )
        data = memoryview(content)[records_at:]
        framed = (
            validate_crcs
            and trust_frame_checksum
            and frame_checksummed(data, compression, uncompressed_size)
        )
        raw: bytes | memoryview
        if slot is not None and compression == "zstd" and uncompressed_size > _SMALL_CHUNK:
            raw = slot(uncompressed_size)
            decompress_into(data, compression, raw)
        else:
            raw = decompress(data, compression, uncompressed_size)
    except McapInputError as err:
        return None, str(err)
    if validate_crcs and crc != 0 and not framed:
        actual = crc32(raw)
        if actual != crc:
            return None, (f"CRC mismatch (records CRC-32 {actual:#010x}, chunk says {crc:#010x})")
    return raw, ""
