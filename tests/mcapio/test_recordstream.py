"""The file's records (RecordStream, through McapSource): truncation at every point, a
corrupt record length resumed from the summary's chunk index, the record limit, and the
IMU set of files read without their summary (stdin, truncated)."""

from __future__ import annotations

import io
import struct

import numpy as np
import pytest

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio import ImuArrayReader, McapSource
from imufdi_cli.mcapio.limits import ReaderLimits
from tests.mcapio.mcap_files import (
    Unseekable,
    imu_file,
    mcap_package_count,
    read_count,
    read_strict,
    top_records,
)


@pytest.mark.parametrize("chunked", [True, False], ids=["chunked", "unchunked"])
def test_truncation_reads_what_the_mcap_package_reads(chunked: bool) -> None:
    # 45 messages: about 60 records (10 chunks or 45 messages, indexes, summary), each
    # cut at and one byte past its start, plus 60 cuts anywhere
    data = imu_file(chunked=chunked, n_imus=3, n_samples=15, chunk_size=1500)
    boundaries = [offset for offset, _, _ in top_records(data)]
    rng = np.random.default_rng(5)
    cuts = sorted(
        {*boundaries, *(b + 1 for b in boundaries), *rng.integers(8, len(data), 60).tolist()}
    )
    for cut in cuts:
        expected = mcap_package_count(data[:cut])
        for seekable in (True, False):
            count, warnings = read_count(data[:cut], seekable=seekable)
            assert count == expected, (cut, seekable)
            # a cut before the end of the data section is reported, with its byte offset
            if expected < 3 * 15:
                assert warnings and "byte" in warnings[0], (cut, warnings)


@pytest.mark.parametrize("seekable", [True, False], ids=["file", "stdin"])
def test_unchunked_without_summary_reads_every_imu(seekable: bool) -> None:
    data = imu_file(chunked=False, n_imus=4, n_samples=40)
    records = top_records(data)
    data_end = next(offset for offset, opcode, _ in records if opcode == 0x0F)
    # Whole file through stdin, and truncated files (no summary) at many points.
    messages = [offset for offset, opcode, _ in records if opcode == 0x05]
    for cut in [len(data), data_end, *messages[8::13]]:
        stream = io.BytesIO(data[:cut]) if seekable else Unseekable(data[:cut])
        with ImuArrayReader(stream) as reader:
            assert reader.imu_topics == [f"/imu{k}/data_raw" for k in range(4)]
            n = sum(len(block) for block in reader.blocks())
        read = sum(1 for m in messages if m < cut)
        # a sample cut short is kept when at least half the IMUs (2 of 4) have it
        complete = read // 4 + (read % 4 >= 2)
        assert n == (40 if cut >= data_end else complete)


def test_corrupt_record_length_reads_up_to_it_and_resumes_from_the_chunk_index() -> None:
    data = imu_file(chunked=True, n_imus=2, n_samples=60, chunk_size=800)
    chunks = [offset for offset, opcode, _ in top_records(data) if opcode == 0x06]
    bad = bytearray(data)
    bad[chunks[2] + 1 : chunks[2] + 9] = struct.pack("<Q", 77_309_414_278)
    full, _ = read_count(data, seekable=True)
    before = mcap_package_count(data[: chunks[2]])
    in_chunk = mcap_package_count(data[: chunks[3]]) - before
    # through a pipe: up to the damaged record; from a file: the summary's chunk index
    # gives where the next chunk starts, so only the damaged chunk is lost
    for seekable, expected in ((False, before), (True, full - in_chunk)):
        count, warnings = read_count(bytes(bad), seekable=seekable)
        assert count == expected and 0 < before
        assert f"at byte {chunks[2]} claims 77309414278 bytes" in warnings[0]
    assert (
        warnings[1]
        == f"resumed reading at the chunk at byte {chunks[3]} (from the summary's chunk index)"
    )
    with pytest.raises(McapInputError, match="claims 77309414278 bytes"):
        read_strict(bytes(bad))


def test_record_over_the_limit_is_refused_before_reading() -> None:
    data = imu_file(chunked=True, n_imus=2, n_samples=60, chunk_size=800)
    limits = ReaderLimits(max_record_bytes=100, max_chunk_bytes=100)
    with McapSource(Unseekable(data), limits=limits) as source:
        assert sum(len(b) for b in source.batches()) == 0
    assert "over the limit of 100 (IMUFDI_MAX_RECORD_BYTES)" in source.warnings[0]
