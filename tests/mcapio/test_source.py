"""McapSource robustness: truncation at every point, corrupt records, mutation fuzz, and
the IMU set of files read without their summary (stdin, truncated)."""

from __future__ import annotations

import io
import os
import signal
import struct
import zlib

import numpy as np
import pytest
from mcap.stream_reader import StreamReader

from imufdi_cli.errors import InputDataError, McapInputError
from imufdi_cli.mcapio import ImuArrayReader, McapSource, summarize
from imufdi_cli.mcapio.limits import ReaderLimits
from tests.mcapio.mcap_files import chunk_record, imu_file, wrap


class Unseekable(io.BytesIO):
    """A stream like stdin in a pipe: no seeking, so no summary."""

    def seekable(self) -> bool:
        return False


def _mcap_package_count(data: bytes) -> int:
    """Messages the mcap package's non-indexed reader yields before it stops."""
    count = 0
    try:
        for record in StreamReader(io.BytesIO(data), skip_magic=False).records:
            count += type(record).__name__ == "Message"
    except Exception:
        pass
    return count


def _our_count(data: bytes, *, seekable: bool) -> tuple[int, list[str]]:
    stream = io.BytesIO(data) if seekable else Unseekable(data)
    with McapSource(stream) as source:
        return sum(len(batch) for batch in source.batches()), source.warnings


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, content length) of the top-level records of a whole file."""
    out = []
    position = 8
    while position + 9 <= len(data) - 8:
        opcode = data[position]
        (length,) = struct.unpack_from("<Q", data, position + 1)
        out.append((position, opcode, length))
        position += 9 + length
    return out


@pytest.mark.parametrize("chunked", [True, False], ids=["chunked", "unchunked"])
def test_truncation_reads_what_the_mcap_package_reads(chunked: bool) -> None:
    data = imu_file(chunked=chunked, n_imus=3, n_samples=30, chunk_size=1500)
    boundaries = [offset for offset, _, _ in _records(data)]
    rng = np.random.default_rng(5)
    cuts = sorted(
        {*boundaries, *(b + 1 for b in boundaries), *rng.integers(8, len(data), 60).tolist()}
    )
    for cut in cuts:
        expected = _mcap_package_count(data[:cut])
        for seekable in (True, False):
            count, warnings = _our_count(data[:cut], seekable=seekable)
            assert count == expected, (cut, seekable)
            # a cut before the end of the data section is reported, with its byte offset
            if expected < 90:
                assert warnings and "byte" in warnings[0], (cut, warnings)


@pytest.mark.parametrize("seekable", [True, False], ids=["file", "stdin"])
def test_unchunked_without_summary_reads_every_imu(seekable: bool) -> None:
    data = imu_file(chunked=False, n_imus=4, n_samples=40)
    records = _records(data)
    data_end = next(offset for offset, opcode, _ in records if opcode == 0x0F)
    # Whole file through stdin, and truncated files (no summary) at many points.
    messages = [offset for offset, opcode, _ in records if opcode == 0x05]
    for cut in [len(data), data_end, *messages[8::13]]:
        stream = io.BytesIO(data[:cut]) if seekable else Unseekable(data[:cut])
        with ImuArrayReader(stream) as reader:
            assert reader.imu_topics == [f"/imu{k}/data_raw" for k in range(4)]
            n = sum(len(block) for block in reader.blocks())
        complete = sum(1 for m in messages if m < cut) // 4
        assert n == (40 if cut >= data_end else complete)


def test_late_imu_channel_is_reported_not_dropped_silently() -> None:
    data = imu_file(chunked=False, n_imus=2, n_samples=20)
    records = _records(data)
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
    chunks = [offset for offset, opcode, _ in _records(data) if opcode == 0x06]
    bad = bytearray(data)
    bad[chunks[1] + 120] ^= 0x40  # a payload byte of the second chunk's records
    return bytes(bad), chunks[1]


def test_chunk_crc_is_checked_by_default() -> None:
    data, offset = _file_with_bad_chunk()
    count, warnings = _our_count(data, seekable=True)
    good, _ = _our_count(
        imu_file(chunked=True, compression="none", n_imus=2, n_samples=60, chunk_size=800),
        seekable=False,
    )
    assert 0 < count < good
    assert warnings == [warnings[0]]
    assert f"chunk at byte {offset} skipped: CRC mismatch" in warnings[0]
    with pytest.raises(McapInputError, match=f"chunk at byte {offset} skipped: CRC mismatch"):
        _read_strict(data)
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


def _read_strict(data: bytes) -> None:
    with McapSource(Unseekable(data), strict=True) as source:
        for _ in source.batches():
            pass


def test_corrupt_record_length_reads_up_to_it_and_resumes_from_the_chunk_index() -> None:
    data = imu_file(chunked=True, n_imus=2, n_samples=60, chunk_size=800)
    chunks = [offset for offset, opcode, _ in _records(data) if opcode == 0x06]
    bad = bytearray(data)
    bad[chunks[2] + 1 : chunks[2] + 9] = struct.pack("<Q", 77_309_414_278)
    full, _ = _our_count(data, seekable=True)
    before = _mcap_package_count(data[: chunks[2]])
    in_chunk = _mcap_package_count(data[: chunks[3]]) - before
    # through a pipe: up to the damaged record; from a file: the summary's chunk index
    # gives where the next chunk starts, so only the damaged chunk is lost
    for seekable, expected in ((False, before), (True, full - in_chunk)):
        count, warnings = _our_count(bytes(bad), seekable=seekable)
        assert count == expected and 0 < before
        assert f"at byte {chunks[2]} claims 77309414278 bytes" in warnings[0]
    assert (
        warnings[1]
        == f"resumed reading at the chunk at byte {chunks[3]} (from the summary's chunk index)"
    )
    with pytest.raises(McapInputError, match="claims 77309414278 bytes"):
        _read_strict(bytes(bad))


def test_record_over_the_limit_is_refused_before_reading() -> None:
    data = imu_file(chunked=True, n_imus=2, n_samples=60, chunk_size=800)
    limits = ReaderLimits(max_record_bytes=100, max_chunk_bytes=100)
    with McapSource(Unseekable(data), limits=limits) as source:
        assert sum(len(b) for b in source.batches()) == 0
    assert "over the limit of 100 (IMUFDI_MAX_RECORD_BYTES)" in source.warnings[0]


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
@pytest.mark.parametrize("lie", ["small", "large"])
def test_chunk_size_other_than_declared_is_a_named_problem(compression: str, lie: str) -> None:
    records = bytes(range(200)) * 20
    declared = 1000 if lie == "small" else len(records) + 1000
    data = wrap(chunk_record(records, compression, declared=declared))
    with McapSource(io.BytesIO(data)) as source:
        assert list(source.batches()) == []
    (warning,) = source.warnings
    assert warning.startswith("chunk at byte 33 skipped: ")
    assert "declared" in warning and not warning.endswith(":")


def test_corrupt_compressed_data_has_a_reason() -> None:
    records = bytes(range(200)) * 20
    for compression in ("zstd", "lz4"):
        chunk = bytearray(chunk_record(records, compression))
        chunk[60:70] = b"\xff" * 10
        with McapSource(io.BytesIO(wrap(bytes(chunk)))) as source:
            list(source.batches())
        (warning,) = source.warnings
        reason = warning.split(":", 1)[1].strip()
        assert reason and not warning.endswith(":"), warning


def test_unknown_opcode_inside_a_chunk_keeps_the_messages_before_it() -> None:
    data = imu_file(chunked=True, compression="none", n_imus=1, n_samples=10, chunk_size=10**6)
    (chunk,) = [(o, n) for o, op, n in _records(data) if op == 0x06]
    offset, _ = chunk
    content_start = offset + 9
    (name_length,) = struct.unpack_from("<I", data, content_start + 28)
    records_start = content_start + 32 + name_length + 8
    # the records are channel/schema records then 10 messages; break the 6th message
    inner = _records(b"\x00" * 8 + data[records_start:] + b"\x00" * 8)
    sixth = [o for o, op, _ in inner if op == 0x05][5] - 8 + records_start
    bad = bytearray(data)
    bad[sixth] = 0x42
    crc_at = content_start + 24
    records_length = struct.unpack_from("<Q", data, records_start - 8)[0]
    bad[crc_at : crc_at + 4] = struct.pack(
        "<I", zlib.crc32(bytes(bad[records_start : records_start + records_length]))
    )
    count, warnings = _our_count(bytes(bad), seekable=False)
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


@pytest.mark.parametrize(
    "variant",
    ["zstd", "lz4", "unchunked", "unchunked-stdin", "zstd-stdin"],
)
def test_mutation_fuzz_raises_only_input_errors(variant: str) -> None:
    compression = "lz4" if variant == "lz4" else "zstd"
    base = imu_file(
        chunked=not variant.startswith("unchunked"),
        compression=compression,
        n_imus=3,
        n_samples=25,
        chunk_size=1200,
    )
    rng = np.random.default_rng(abs(hash(variant)) % 2**32)
    outcomes = {"ok": 0, "error": 0}
    for _ in range(80):
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


def _read_all(
    data: bytes, strict: bool, read_ahead: bool
) -> tuple[list[tuple[int, int]], list[str], str]:
    """(length and first log time of each batch, warnings, error text or "")."""
    seen: list[tuple[int, int]] = []
    with McapSource(Unseekable(data), strict=strict, read_ahead=read_ahead) as source:
        try:
            for batch in source.batches():
                seen.append((len(batch), int(batch.log_time[0])))
        except McapInputError as err:
            return seen, list(source.warnings), str(err)
        return seen, list(source.warnings), ""


@pytest.mark.parametrize("strict", [False, True], ids=["lenient", "strict"])
def test_read_ahead_on_the_worker_thread_keeps_the_order(strict: bool) -> None:
    """Large chunks are decompressed ahead on a worker thread: batches, warnings and the
    strict error are the same, in the same order, as when every chunk is read in line."""
    data = imu_file(chunked=True, compression="zstd", n_imus=4, n_samples=1500, chunk_size=150_000)
    chunks = [(offset, length) for offset, opcode, length in _records(data) if opcode == 0x06]
    assert len(chunks) >= 6
    bad = bytearray(data)
    bad[chunks[2][0] + 9 + 24] ^= 0x01  # the CRC field of the third chunk
    cut = bytes(bad[: chunks[5][0] + 9 + chunks[5][1] // 2])  # the sixth chunk cut short
    with McapSource(io.BytesIO(data), read_ahead=True) as source:
        n_threaded = sum(len(b) for b in source.batches())
        assert source._pool is not None  # the large chunks did go through the worker
    threaded = _read_all(cut, strict, read_ahead=True)
    inline = _read_all(cut, strict, read_ahead=False)
    assert threaded == inline
    assert inline[1] or inline[2]
    assert ("CRC mismatch" in inline[2]) if strict else any("CRC" in w for w in inline[1])
    with McapSource(io.BytesIO(data), read_ahead=False) as source:
        assert sum(len(b) for b in source.batches()) == n_threaded == 4 * 1500
        assert source._pool is None


@pytest.mark.slow  # multi-process, 4 s (docs/testing.md); the read-ahead path has default tests
@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_read_ahead_survives_a_fork(monkeypatch) -> None:
    """A child forked while chunks are in flight on the parent's worker thread (which the
    child does not have) reads the rest of the file itself instead of waiting forever."""
    import time

    import imufdi_cli.mcapio.source as source_module

    unpack = source_module._unpack_chunk

    def slow_unpack(*args):  # type: ignore[no-untyped-def]
        time.sleep(0.1)  # chunks are still in flight when the fork happens
        return unpack(*args)

    monkeypatch.setattr(source_module, "_unpack_chunk", slow_unpack)
    n = 4 * 4000  # 5.7 MB of records: the first 4 MiB batch leaves chunks in flight
    data = imu_file(chunked=True, compression="zstd", n_imus=4, n_samples=4000, chunk_size=150_000)
    with McapSource(io.BytesIO(data), read_ahead=True) as source:
        batches = source.batches()
        first = len(next(batches))
        assert source._pool is not None and first < n
        pid = os.fork()
        if pid == 0:  # the child: exit code 0 if it reads every remaining message
            signal.alarm(30)  # a hang kills the child; the parent then sees a failure
            rest = sum(len(b) for b in batches)
            os._exit(0 if first + rest == n else 1)
        _, status = os.waitpid(pid, 0)
        assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
        assert first + sum(len(b) for b in batches) == n


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
    chunks = [(offset, length) for offset, opcode, length in _records(data) if opcode == 0x06]
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
        _read_strict(bytes(wrong_crc))
    wrong_checksum = bytearray(data)
    wrong_checksum[offset + 9 + length - 1] ^= 0x01  # the frame's checksum: records intact
    with McapSource(io.BytesIO(bytes(wrong_checksum))) as source:
        assert sum(len(b) for b in source.batches()) < good
        assert any(
            f"chunk at byte {offset} skipped: corrupt zstd chunk" in w for w in source.warnings
        )
