"""McapSource robustness: chunk CRCs, malformed records inside chunks, unknown channels,
mutation fuzz. The record stream's tests are in test_recordstream.py, the read-ahead's in
test_readahead.py, a Chunk record's unpacking in test_compression.py."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest

from imufdi_cli.errors import InputDataError, McapInputError
from imufdi_cli.mcapio import ImuArrayReader, McapSource, summarize
from tests.mcapio.mcap_files import (
    Unseekable,
    imu_file,
    read_count,
    read_strict,
    top_records,
    wrap,
)


def test_late_imu_channel_is_reported_not_dropped_silently() -> None:
    data = imu_file(chunked=False, n_imus=2, n_samples=20)
    records = top_records(data)
    data_end = next(i for i, (_, opcode, _) in enumerate(records) if opcode == 0x0F)
    records = records[:data_end]  # the data section

    def raw(opcode: int, channel: int | None = None) -> list[bytes]:
        return [
            data[o : o + 9 + n]
            for o, op, n in records
            if op == opcode and (channel is None or data[o + 9] == channel)
        ]

    # /imu1's channel and messages only after more messages of /imu0 than one read batch
    # holds (past the read-ahead)
    from imufdi_cli.mcapio.scan import _BATCH_MESSAGES

    schema, channels = raw(0x03), raw(0x04)
    first, second = (channel[9] for channel in channels)  # their ids (low bytes)
    repeat = _BATCH_MESSAGES // len(raw(0x05, first)) + 100
    late = wrap(
        b"".join(schema)
        + channels[0]
        + b"".join(raw(0x05, first) * repeat)
        + channels[1]
        + b"".join(raw(0x05, second))
    )
    with ImuArrayReader(Unseekable(late)) as reader:
        assert reader.imu_topics == ["/imu0/data_raw"]
        list(reader.blocks())
    assert any("/imu1/data_raw first appears after" in w for w in reader.warnings)


def _file_with_bad_chunk() -> tuple[bytes, int]:
    data = imu_file(chunked=True, compression="none", n_imus=2, n_samples=60, chunk_size=800)
    chunks = [offset for offset, opcode, _ in top_records(data) if opcode == 0x06]
    bad = bytearray(data)
    bad[chunks[1] + 120] ^= 0x40  # a payload byte of the second chunk's records
    return bytes(bad), chunks[1]


def test_chunk_crc_is_checked_by_default() -> None:
    data, offset = _file_with_bad_chunk()
    count, warnings = read_count(data, seekable=True)
    good, _ = read_count(
        imu_file(chunked=True, compression="none", n_imus=2, n_samples=60, chunk_size=800),
        seekable=False,
    )
    assert 0 < count < good
    assert warnings == [warnings[0]]
    assert f"chunk at byte {offset} skipped: CRC mismatch" in warnings[0]
    with pytest.raises(McapInputError, match=f"chunk at byte {offset} skipped: CRC mismatch"):
        read_strict(data)
    # opting out reads the altered chunk
    with McapSource(io.BytesIO(data), validate_crcs=False) as source:
        assert sum(len(b) for b in source.batches()) == good


def test_array_reader_and_summarize_pass_validate_crcs() -> None:
    data, offset = _file_with_bad_chunk()
    clean = imu_file(chunked=True, compression="none", n_imus=2, n_samples=60, chunk_size=800)
    with ImuArrayReader(io.BytesIO(clean)) as reader:
        n_good = sum(len(b) for b in reader.blocks())
    with ImuArrayReader(io.BytesIO(data)) as reader:
        assert reader.source.validate_crcs
        n_checked = sum(len(b) for b in reader.blocks())
        assert any(f"chunk at byte {offset} skipped: CRC mismatch" in w for w in reader.warnings)
    with ImuArrayReader(io.BytesIO(data), validate_crcs=False) as reader:
        assert not reader.source.validate_crcs
        assert sum(len(b) for b in reader.blocks()) == n_good > n_checked
        assert not any("CRC" in w for w in reader.warnings)
    assert summarize(io.BytesIO(data), validate_crcs=False).n_samples == n_good
    assert summarize(io.BytesIO(data)).n_samples == n_checked


def test_unknown_opcode_inside_a_chunk_keeps_the_messages_before_it() -> None:
    data = imu_file(chunked=True, compression="none", n_imus=1, n_samples=10, chunk_size=10**6)
    (chunk,) = [(o, n) for o, op, n in top_records(data) if op == 0x06]
    offset, _ = chunk
    content_start = offset + 9
    (name_length,) = struct.unpack_from("<I", data, content_start + 28)
    records_start = content_start + 32 + name_length + 8
    # the records are channel/schema records then 10 messages; break the 6th message
    inner = top_records(b"\x00" * 8 + data[records_start:] + b"\x00" * 8)
    sixth = [o for o, op, _ in inner if op == 0x05][5] - 8 + records_start
    bad = bytearray(data)
    bad[sixth] = 0x42
    crc_at = content_start + 24
    records_length = struct.unpack_from("<Q", data, records_start - 8)[0]
    bad[crc_at : crc_at + 4] = struct.pack(
        "<I", zlib.crc32(bytes(bad[records_start : records_start + records_length]))
    )
    count, warnings = read_count(bytes(bad), seekable=False)
    assert count == 5
    assert "malformed record" in warnings[0] and "5 message(s) before it kept" in warnings[0]


def _mutate(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    kind = int(rng.integers(0, 6))
    at = int(rng.integers(8, len(out)))
    if kind == 0:  # flip bits
        for _ in range(int(rng.integers(1, 4))):
            out[int(rng.integers(8, len(out)))] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1:  # random bytes
        n = int(rng.integers(1, 16))
        out[at : at + n] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    elif kind == 2:  # truncate
        del out[at:]
    elif kind == 3:  # a huge or small u64 somewhere (record lengths, sizes)
        values = [0, 1, 2**31, 2**40, 2**63, 2**64 - 1, 77_309_414_278]
        value = values[int(rng.integers(0, len(values)))]
        out[at : at + 8] = struct.pack("<Q", value)
    elif kind == 4:  # delete or duplicate a range
        n = int(rng.integers(1, 200))
        out[at:at] = out[at : at + n] if rng.random() < 0.5 else b""
        if rng.random() < 0.5:
            del out[at : at + n]
    else:  # zero a range
        n = int(rng.integers(1, 64))
        out[at : at + n] = bytes(min(n, len(out) - at))
    return bytes(out)


# Each variant (a reading path) takes 40 mutated files in the default run and 160 more
# under slow (a repeat of the same paths, docs/testing.md); the mutations differ from run
# to run (the seed hashes the variant's name: PYTHONHASHSEED is random).
@pytest.mark.parametrize(
    "mutations",
    [pytest.param(40, id="40"), pytest.param(160, id="160", marks=pytest.mark.slow)],
)
@pytest.mark.parametrize(
    "variant",
    ["zstd", "lz4", "unchunked", "unchunked-stdin", "zstd-stdin"],
)
def test_mutation_fuzz_raises_only_input_errors(variant: str, mutations: int) -> None:
    compression = "lz4" if variant == "lz4" else "zstd"
    base = imu_file(
        chunked=not variant.startswith("unchunked"),
        compression=compression,
        n_imus=3,
        n_samples=25,
        chunk_size=1200,
    )
    rng = np.random.default_rng([abs(hash(variant)) % 2**32, mutations])
    outcomes = {"ok": 0, "error": 0}
    for _ in range(mutations):
        data = _mutate(base, rng)
        for strict in (False, True):
            stream = Unseekable(data) if variant.endswith("stdin") else io.BytesIO(data)
            try:
                summary = summarize(stream, strict=strict)
            except InputDataError as err:
                assert str(err) and "\n" not in str(err)
                outcomes["error"] += 1
                continue
            outcomes["ok"] += 1
            for warning in summary.warnings:
                assert warning.strip() and not warning.endswith(":") and "\n" not in warning
            if strict:
                # reader problems (they name a byte offset, or say what was skipped) are
                # errors with --strict; notes such as "using the log time" may remain
                assert not any("byte" in w or "skipped" in w for w in summary.warnings)
    assert outcomes["ok"] and outcomes["error"]


def test_zstd_frame_checksum_stands_in_for_the_chunk_crc(tmp_path) -> None:
    """Chunks whose zstd frame carries a content checksum (imufdi's writer) are verified
    by it; the CRC-32 is then checked only with ``strict``. A changed record byte is
    caught either way."""
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.mcapio import write_array
    from imufdi_cli.mcapio.compression import frame_checksummed

    from .conftest import make_block

    path = tmp_path / "z.mcap"
    write_array(path, ArrayConfig.co_aligned(2, 100.0), make_block(3000, 2), compression="zstd")
    data = path.read_bytes()
    chunks = [(offset, length) for offset, opcode, length in top_records(data) if opcode == 0x06]
    assert len(chunks) >= 2
    offset, length = chunks[1]
    content = data[offset + 9 : offset + 9 + length]
    (name_length,) = struct.unpack_from("<I", content, 28)
    (size,) = struct.unpack_from("<Q", content, 16)
    frame = content[32 + name_length + 8 :]
    assert frame_checksummed(frame, "zstd", size)
    assert not frame_checksummed(frame, "zstd", size + 1)
    assert not frame_checksummed(frame, "lz4", size)
    good = sum(len(b) for b in McapSource(io.BytesIO(data)).batches())
    wrong_crc = bytearray(data)
    wrong_crc[offset + 9 + 24] ^= 0x01  # the chunk's CRC field; its records are intact
    with McapSource(io.BytesIO(bytes(wrong_crc))) as source:
        assert sum(len(b) for b in source.batches()) == good
        assert source.warnings == []
    with pytest.raises(McapInputError, match=f"chunk at byte {offset} skipped: CRC mismatch"):
        read_strict(bytes(wrong_crc))
    wrong_checksum = bytearray(data)
    wrong_checksum[offset + 9 + length - 1] ^= 0x01  # the frame's checksum: records intact
    with McapSource(io.BytesIO(bytes(wrong_checksum))) as source:
        assert sum(len(b) for b in source.batches()) < good
        assert any(
            f"chunk at byte {offset} skipped: corrupt zstd chunk" in w for w in source.warnings
        )
