"""Chunk compression helpers: the CRC-32 every chunk carries, bounded decompression, and a
Chunk record's unpacking (fields, limit, CRC) with the reader's warnings about it."""

from __future__ import annotations

import io
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio import McapSource, compression
from imufdi_cli.mcapio.compression import decompress_into
from tests.mcapio.mcap_files import chunk_record, wrap


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


def test_crc32_switches_from_zlib_to_zlib_ng_with_the_same_values(monkeypatch) -> None:
    """The first bytes of a process go through zlib (zlib-ng not loaded: start-up time),
    the rest through the loaded implementation; continued CRCs across the switch agree."""
    monkeypatch.setattr(compression, "_CRC32", None)
    monkeypatch.setattr(compression, "_ZLIB_LEFT", 1000)
    rng = np.random.default_rng(1)
    data = rng.integers(0, 256, 5000, dtype=np.uint8).tobytes()
    first = compression.crc32(data[:600])  # by zlib: 400 bytes left
    assert compression._CRC32 is None and compression._ZLIB_LEFT == 400
    assert compression.crc32(data[600:], first) == zlib.crc32(data)  # loads the fast one
    assert compression._CRC32 is not None
    assert compression.crc32(data[:10]) == zlib.crc32(data[:10])


def test_reading_the_small_sample_log_does_not_load_zlib_ng() -> None:
    """``imufdi info`` on the sample log CRC-checks 2.7 MiB (its chunks carry no zstd
    content checksum): less than loading zlib-ng costs in zlib's CRC-32, so zlib does it
    (start-up time; the 2 MiB of the code before loaded zlib-ng here)."""
    root = Path(__file__).resolve().parents[2]
    probe = (
        "import sys\n"
        "from imufdi_cli.info import log_info\n"
        f"log_info({str(root / 'imufdi_cli' / 'sample_logs' / 'paper-table4.mcap')!r})\n"
        "from imufdi_cli.mcapio import compression\n"
        "print(compression._ZLIB_LEFT, 'zlib_ng' in sys.modules)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=root, check=True
    )
    left, loaded = done.stdout.split()
    assert int(left) < compression._ZLIB_FIRST  # it did check CRCs through zlib
    assert loaded == "False"


def _into(raw: bytes, compression: str, size: int) -> bytes:
    out = np.zeros(size, np.uint8)
    decompress_into(raw, compression, memoryview(out))  # type: ignore[arg-type]
    return out.tobytes()


@pytest.mark.parametrize("kind", ["zstd", "lz4", ""])
def test_decompress_into_matches_decompress(kind: str) -> None:
    """The in-place decoder gives the same records, and the same errors, as decompress."""
    import zstandard

    rng = np.random.default_rng(2)
    records = rng.integers(0, 4, 300_000, dtype=np.uint8).tobytes()
    packed = compression.compress(records, kind or "none")
    assert _into(packed, kind, len(records)) == records
    cases = [
        (len(records) - 1, "exceed|hold|past"),  # declared one byte short: a bomb's signature
        (len(records) + 1, "hold|incomplete|not the declared"),  # declared one byte long
    ]
    if kind == "zstd":  # two frames, one without a content size: read across both
        half = len(records) // 2
        stream = zstandard.ZstdCompressor(write_content_size=False).compress(records[:half])
        two = stream + zstandard.ZstdCompressor().compress(records[half:])
        assert _into(two, kind, len(records)) == records
        bad = bytearray(packed)
        bad[-2] ^= 0xFF  # the frame's content checksum
        with pytest.raises(McapInputError, match="corrupt zstd chunk") as in_place:
            _into(bytes(bad), kind, len(records))
        with pytest.raises(McapInputError) as whole:  # read-ahead and small chunks
            compression.decompress(bytes(bad), kind, len(records))
        assert str(whole.value) == str(in_place.value)  # one message, however read
    for size, pattern in cases[:2]:
        with pytest.raises(McapInputError, match=pattern):
            compression.decompress(packed, kind, size)
        with pytest.raises(McapInputError, match=pattern):
            _into(packed, kind, size)


@pytest.mark.parametrize("kind", ["zstd", "lz4", ""])
@pytest.mark.parametrize("lie", ["small", "large"])
def test_chunk_size_other_than_declared_is_a_named_problem(kind: str, lie: str) -> None:
    records = bytes(range(200)) * 20
    declared = 1000 if lie == "small" else len(records) + 1000
    data = wrap(chunk_record(records, kind, declared=declared))
    with McapSource(io.BytesIO(data)) as source:
        assert list(source.batches()) == []
    (warning,) = source.warnings
    assert warning.startswith("chunk at byte 33 skipped: ")
    assert "declared" in warning and not warning.endswith(":")


def test_corrupt_compressed_data_has_a_reason() -> None:
    records = bytes(range(200)) * 20
    for kind in ("zstd", "lz4"):
        chunk = bytearray(chunk_record(records, kind))
        chunk[60:70] = b"\xff" * 10
        with McapSource(io.BytesIO(wrap(bytes(chunk)))) as source:
            list(source.batches())
        (warning,) = source.warnings
        reason = warning.split(":", 1)[1].strip()
        assert reason and not warning.endswith(":"), warning


@pytest.mark.parametrize("kind", ["zstd", "lz4", ""])
def test_unpack_chunk_gives_the_records_or_why_not(kind: str) -> None:
    """A Chunk record's content unpacks to its records, into a caller's buffer too (zstd
    over 4 KiB); a wrong CRC, a size over the limit and a cut record are named reasons."""
    records = bytes(range(256)) * 40  # 10240 bytes
    content = chunk_record(records, kind)[9:]
    assert compression._declared_size(content) == len(records)
    raw, why = compression._unpack_chunk(content, 1 << 20, True)
    assert bytes(raw) == records and why == ""  # type: ignore[arg-type]
    target = bytearray(len(records))
    raw, why = compression._unpack_chunk(content, 1 << 20, True, lambda n: memoryview(target)[:n])
    assert bytes(raw) == records and why == ""  # type: ignore[arg-type]
    assert (bytes(target) == records) == (kind == "zstd")  # only zstd goes into the slot
    bad_crc = bytearray(content)
    bad_crc[24] ^= 0x01
    assert compression._unpack_chunk(bytes(bad_crc), 1 << 20, True)[1].startswith("CRC mismatch")
    assert compression._unpack_chunk(bytes(bad_crc), 1 << 20, False)[0] is not None
    raw, why = compression._unpack_chunk(content, len(records) - 1, True)
    assert raw is None and "IMUFDI_MAX_CHUNK_BYTES" in why
    raw, why = compression._unpack_chunk(content[:-1], 1 << 20, True)
    assert raw is None and "records length" in why
    assert compression._unpack_chunk(content[:30], 1 << 20, True) == (
        None,
        "malformed Chunk record (shorter than its fields)",
    )
