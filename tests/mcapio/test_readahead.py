"""Read-ahead of large chunks on a worker thread: the same batches, warnings and errors
in the same order as in line, and a forked child that reads on by itself."""

from __future__ import annotations

import io
import os
import signal

import pytest

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio import McapSource
from tests.mcapio.mcap_files import (
    Unseekable,
    imu_file,
    top_records,
)


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
    chunks = [(offset, length) for offset, opcode, length in top_records(data) if opcode == 0x06]
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

    import imufdi_cli.mcapio.readahead as readahead_module

    unpack = readahead_module._unpack_chunk

    def slow_unpack(*args):  # type: ignore[no-untyped-def]
        time.sleep(0.1)  # chunks are still in flight when the fork happens
        return unpack(*args)

    monkeypatch.setattr(readahead_module, "_unpack_chunk", slow_unpack)  # the worker's
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


def _whole_read(data: bytes, read_ahead: bool, strict: bool = False) -> tuple[list, list, str]:
    """Every raw batch's arrays and every aligned block of an ImuArrayReader, the
    warnings and the error text ("" if none)."""
    import numpy as np

    from imufdi_cli.mcapio import ImuArrayReader

    out: list = []
    source = McapSource(io.BytesIO(data), read_ahead=read_ahead, strict=strict)
    try:
        with ImuArrayReader(source) as reader:
            for batch, block in reader.stream():
                out.append(
                    [
                        np.array(getattr(batch, name))
                        for name in ("channel_id", "sequence", "log_time", "publish_time")
                    ]
                    + [batch.offset, batch.length, np.array(batch.data)]
                    + [block.t_ns, block.gyro, block.accel]
                )
            out.append(repr(reader.stats))
    except McapInputError as err:
        return out, list(source.warnings), str(err)
    return out, list(source.warnings), ""


def _same(a: tuple[list, list, str], b: tuple[list, list, str]) -> None:
    import numpy as np

    assert len(a[0]) == len(b[0])
    for left, right in zip(a[0], b[0]):
        if isinstance(left, str):
            assert left == right
            continue
        for x, y in zip(left, right):
            assert x.dtype == y.dtype and x.shape == y.shape
            if x.tobytes() != y.tobytes():  # equal bytes are equal arrays (the usual case)
                np.testing.assert_array_equal(x, y)
    assert a[1:] == b[1:]


@pytest.mark.parametrize("damage", ["none", "crc", "cut"])
def test_read_ahead_reads_heads_and_fields_on_the_worker(damage: str, monkeypatch) -> None:
    """With read-ahead, chunks of uniform Imu records are decompressed into the batch
    buffers (no copy) and the worker checks their record heads and reads the message
    heads and the Imu fields the reader asked for (in line, the same is read right after
    each chunk's decompression): the batches, blocks, statistics and warnings are those
    of reading in line and of reading every field per batch, also with a bad chunk (the
    chunks after it are copied, not used in place) and a cut one."""
    import imufdi_cli.mcapio.readahead as readahead_module
    import imufdi_cli.mcapio.scan as scan_module

    for module in (scan_module, readahead_module):  # 1 MiB batches: 5 of them here
        monkeypatch.setattr(module, "_BATCH_BYTES", 1 << 20)
        monkeypatch.setattr(module, "_BATCH_CAPACITY", 3 << 20)
    data = imu_file(chunked=True, compression="zstd", n_imus=4, n_samples=4000, chunk_size=150_000)
    chunks = [(offset, length) for offset, opcode, length in top_records(data) if opcode == 0x06]
    if damage == "crc":
        bad = bytearray(data)
        bad[chunks[6][0] + 9 + 24] ^= 0x01  # the CRC field of the seventh chunk
        data = bytes(bad)
    elif damage == "cut":
        data = data[: chunks[20][0] + 9 + chunks[20][1] // 2]
    import imufdi_cli.mcapio.source as source_module

    for strict in (False, True):
        inline = _whole_read(data, False, strict)
        _same(_whole_read(data, True, strict), inline)
        with monkeypatch.context() as patch:  # in line, every field read per batch
            patch.setattr(source_module, "chunk_digest", lambda *args: None)
            _same(_whole_read(data, False, strict), inline)
    if damage == "none":
        from imufdi_cli.mcapio import ImuArrayReader

        for ahead in (True, False):
            source = McapSource(io.BytesIO(data), read_ahead=ahead)
            with ImuArrayReader(source) as reader:
                used = [hasattr(batch, "payload_fields") for batch, _ in reader.stream()]
            assert source.payload_fields is not None and any(used)


def test_read_ahead_default(monkeypatch, tmp_path) -> None:
    """Off by default; IMUFDI_READ_AHEAD=1 turns it on for every source (also a stream of
    unknown size), anything else leaves it off; an explicit argument wins."""
    path = tmp_path / "imu.mcap"
    data = imu_file(chunked=True, n_imus=2, n_samples=200, chunk_size=4096)
    path.write_bytes(data)
    monkeypatch.delenv("IMUFDI_READ_AHEAD", raising=False)
    with McapSource(path) as source:
        assert not source.read_ahead
    monkeypatch.setenv("IMUFDI_READ_AHEAD", "1")
    with McapSource(path) as source:
        assert source.read_ahead
    with McapSource(Unseekable(data)) as source:
        assert source.read_ahead
    with McapSource(path, read_ahead=False) as source:
        assert not source.read_ahead
    monkeypatch.setenv("IMUFDI_READ_AHEAD", "0")
    with McapSource(path) as source:
        assert not source.read_ahead
    with McapSource(path, read_ahead=True) as source:
        assert source.read_ahead
