"""ImuArrayWriter's record sources (records built on the writer's worker threads) give the
same bytes as the per-message encoder, whatever the chunk boundaries; MessageIndex records
match a plain reference."""

from __future__ import annotations

import io
import itertools
import struct
from dataclasses import replace

import numpy as np
import pytest

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import UsageError
from imufdi_cli.mcapio import ImuArrayWriter, McapWriter, read_array
from imufdi_cli.mcapio.records import OP_MESSAGE_INDEX
from imufdi_cli.mcapio.writer import message_index_records

from .conftest import make_block


def _write(blocks, n_imus: int, chunk_size: int, compression: str, *, generic: bool) -> bytes:
    out = io.BytesIO()
    with McapWriter(out, compression=compression, chunk_size=chunk_size) as writer:
        imu_writer = ImuArrayWriter(writer, ArrayConfig.co_aligned(n_imus, 100.0))
        if generic:  # the per-message encoder (encode_messages, add_batch)
            imu_writer._imu_records.uniform = False
        for block in blocks:
            imu_writer.write_block(block)
    return out.getvalue()


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
@pytest.mark.parametrize("chunk_size", [1, 1000, 5 * 355 + 7, 1 << 20])
def test_record_sources_write_the_bytes_of_the_message_encoder(compression, chunk_size) -> None:
    # uneven blocks; chunk sizes that cut samples (and single records) at every phase
    # (a chunk per record at chunk_size 1: 13 samples, 65 chunks)
    n = 13 if chunk_size == 1 else 41 if chunk_size < 2000 else 301
    whole = make_block(n, 5, seed=3)
    cuts = [0, 1, 2, n // 3, n // 2, n]
    blocks = [whole.slice(a, b) for a, b in itertools.pairwise(cuts)]
    fast = _write(blocks, 5, chunk_size, compression, generic=False)
    generic = _write(blocks, 5, chunk_size, compression, generic=True)
    assert fast == generic


@pytest.mark.parametrize("chunk_size", [900, 5 * 355 + 7, 40_000])
def test_two_arrays_in_one_writer_give_the_bytes_of_the_message_encoder(chunk_size) -> None:
    # Two record templates (frame ids of other lengths: other record sizes) alternate in
    # one writer: chunks of one template reuse or re-prime a worker thread's primed
    # buffer, chunks mixing both are built from scratch; the bytes are the same.
    def write(generic: bool) -> bytes:
        out = io.BytesIO()
        with McapWriter(out, compression="none", chunk_size=chunk_size) as writer:
            arrays = [
                ImuArrayWriter(
                    writer,
                    ArrayConfig.co_aligned(m, 100.0),
                    topics=[f"/{name}{k}/data_raw" for k in range(m)],
                    frame_ids=[f"{name}{k}" for k in range(m)],
                )
                for name, m in (("a", 3), ("board_b", 5))
            ]
            if generic:
                for array in arrays:
                    array._imu_records.uniform = False
            for step in range(6):
                for array, seed in zip(arrays, (10, 20)):
                    whole = make_block(60, array.array.n_imus, seed=seed)
                    array.write_block(whole.slice(10 * step, 10 * step + 10 + step % 2))
        return out.getvalue()

    assert write(generic=False) == write(generic=True)


def test_missing_vectors_are_nan_in_both_paths() -> None:
    block = replace(make_block(40, 3, seed=1), accel=None)
    assert _write([block], 3, 700, "zstd", generic=False) == _write(
        [block], 3, 700, "zstd", generic=True
    )


@pytest.mark.parametrize("chunk_size", [700, 1 << 20])
def test_owned_blocks_write_the_same_bytes_without_copies(chunk_size) -> None:
    # write_block(owned=True) keeps the caller's triads (ingest hands its parser's new
    # arrays over) instead of copying them: the same file either way
    # 41 samples in 700-byte chunks (two records a chunk) as in the test above
    n = 41 if chunk_size < 2000 else 301
    whole = make_block(n, 5, seed=4)
    blocks = [whole.slice(a, b) for a, b in itertools.pairwise([0, 7, n // 2, n])]

    def write(owned: bool) -> bytes:
        out = io.BytesIO()
        with McapWriter(out, compression="zstd", chunk_size=chunk_size) as writer:
            imu_writer = ImuArrayWriter(writer, ArrayConfig.co_aligned(5, 100.0))
            for block in blocks:
                imu_writer.write_block(block, owned=owned)
        return out.getvalue()

    assert write(owned=True) == write(owned=False)
    kept = ImuArrayWriter(McapWriter(io.BytesIO()), ArrayConfig.co_aligned(5, 100.0))
    kept.write_block(blocks[1], owned=True)
    source = kept.writer._pending[-1].source
    assert np.shares_memory(source.gyro, blocks[1].gyro)  # not copied
    kept.writer.abort()


def test_the_block_may_change_once_written(tmp_path) -> None:
    # 300 samples, about 100 chunks: the write_block below with owned=True (no copy)
    # fails this test at 100, 300 and 2000 samples alike
    block = make_block(300, 4, seed=2)
    expected = (block.gyro.copy(), block.accel.copy())  # type: ignore[union-attr]
    path = tmp_path / "a.mcap"
    with McapWriter(path, chunk_size=4096) as writer:
        imu_writer = ImuArrayWriter(writer, ArrayConfig.co_aligned(4, 100.0))
        imu_writer.write_block(block)
        # records are built later on worker threads: they must not see this
        block.gyro[...] = 0.0  # type: ignore[index]
        block.accel[...] = 0.0  # type: ignore[index]
        block.t_ns[...] = 0
    _, read = read_array(path)
    assert read.gyro is not None and read.accel is not None
    assert read.gyro.tobytes() == expected[0].tobytes()
    assert read.accel.tobytes() == expected[1].tobytes()


def test_a_stamp_beyond_int32_seconds_is_refused_by_write_block() -> None:
    block = make_block(10, 2)
    block = replace(block, t_ns=block.t_ns + (2**31) * 10**9)
    with McapWriter(io.BytesIO()) as writer:
        imu_writer = ImuArrayWriter(writer, ArrayConfig.co_aligned(2, 100.0))
        with pytest.raises(UsageError, match="int32 seconds"):
            imu_writer.write_block(block)


def _reference_index(channels, times, offsets) -> tuple[bytes, dict[int, int]]:
    """One record per channel (increasing ids), entries sorted by (time, chunk order)."""
    out = b""
    where = {}
    for channel in sorted(set(channels.tolist())):
        rows = [i for i in range(len(channels)) if channels[i] == channel]
        rows.sort(key=lambda i: (int(times[i]), i))
        body = b"".join(struct.pack("<QQ", int(times[i]), int(offsets[i])) for i in rows)
        where[channel] = len(out)
        out += struct.pack("<BQHI", OP_MESSAGE_INDEX, 6 + len(body), channel, len(body)) + body
    return out, where


@pytest.mark.parametrize("ordered", [True, False])
def test_message_index_records_match_a_plain_reference(ordered) -> None:
    rng = np.random.default_rng(7)
    n = 500
    channels = rng.choice(np.array([0, 3, 4, 9, 300], np.uint16), n)
    times = rng.integers(0, 60, n).astype(np.int64)  # ties on purpose
    if ordered:
        times = np.sort(times)
    offsets = np.cumsum(rng.integers(40, 400, n)).astype(np.int64)
    records, where, counts = message_index_records(channels, times, offsets)
    expected, expected_where = _reference_index(channels, times, offsets)
    assert records == expected
    assert where == expected_where
    assert counts == {int(c): int((channels == c).sum()) for c in np.unique(channels)}


def test_message_index_records_of_a_repeated_channel_sequence_match_the_reference() -> None:
    """The second chunk with the same channel ids uses the layout kept from the first
    (sort, heads, offsets): its records are still those of its own times and offsets, in
    time order or not."""
    rng = np.random.default_rng(11)
    channels = np.tile(np.array([4, 1, 7], np.uint16), 40)[5:]  # cycles, cut at a phase
    n = channels.shape[0]
    for ordered in (True, True, False, True):
        times = np.sort(rng.integers(0, 30, n)) if ordered else rng.integers(0, 30, n)
        offsets = np.cumsum(rng.integers(40, 400, n)).astype(np.int64)
        records, where, counts = message_index_records(channels, times.astype(np.int64), offsets)
        expected, expected_where = _reference_index(channels, times, offsets)
        assert records == expected
        assert where == expected_where
        assert counts == {1: 38, 4: 38, 7: 39}
