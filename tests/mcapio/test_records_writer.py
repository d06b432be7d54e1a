"""McapWriter failure paths: flush/close errors, out-of-range log times, checksummed frames."""

from __future__ import annotations

import errno
import io
import os

import numpy as np
import pytest
import zstandard
from mcap.reader import make_reader

from imufdi_cli.errors import McapInputError, OutputError, UsageError
from imufdi_cli.mcapio import McapWriter, MessageBatch
from imufdi_cli.mcapio.compression import compress, decompress


class _Full:
    """A binary stream that fails like a full disk after ``room`` bytes (on write or on
    the final flush, as a buffered file does)."""

    def __init__(self, real, room: int, err: int, *, on_close: bool) -> None:
        self.real = real
        self.room = room
        self.err = err
        self.on_close = on_close

    def write(self, data) -> int:
        if not self.on_close and self.room < len(data):
            raise OSError(self.err, os.strerror(self.err))
        self.room -= len(data)
        return self.real.write(data)

    def flush(self) -> None:
        self.real.flush()

    def close(self) -> None:
        self.real.close()
        if self.on_close:
            raise OSError(self.err, os.strerror(self.err))


@pytest.mark.parametrize("on_close", [False, True])
@pytest.mark.parametrize("err", [errno.ENOSPC, errno.EFBIG])
def test_disk_full_on_write_or_close_leaves_no_temp_and_keeps_the_target(tmp_path, on_close, err):
    path = tmp_path / "out.mcap"
    path.write_bytes(b"previous")
    with pytest.raises(OutputError) as info, McapWriter(path, chunk_size=4096) as writer:
        schema = writer.register_schema("raw/Blob", "", b"")
        channel = writer.register_channel("/a", "application/octet-stream", schema)
        writer._stream = _Full(writer._stream, 5_000, err, on_close=on_close)
        rng = np.random.default_rng(0)
        writer.add_batch(
            MessageBatch.from_payloads(
                channel,
                np.arange(2000, dtype=np.int64) * 1000,
                [rng.bytes(40) for _ in range(2000)],
            )
        )
    assert str(info.value).startswith(f"cannot write {path}: {os.strerror(err)}")
    assert isinstance(info.value.__cause__, OSError) and info.value.__cause__.errno == err
    assert path.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]


def test_a_log_time_beyond_int64_is_bad_data_naming_topic_and_value(tmp_path):
    path = tmp_path / "out.mcap"
    huge = (1 << 63) + 5
    with pytest.raises(McapInputError) as info, McapWriter(path) as writer:
        schema = writer.register_schema("raw/Blob", "", b"")
        channel = writer.register_channel("/imu3/data_raw", "cdr", schema)
        times = np.array([0, 10, huge], dtype=np.uint64).view(np.int64)  # as read from u64
        writer.add_batch(MessageBatch.from_payloads(channel, times, [b"a", b"b", b"c"]))
    message = str(info.value)
    assert "/imu3/data_raw" in message and str(huge) in message and "\n" not in message
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(McapInputError, match="/r: message log_time"), McapWriter(path) as writer:
        channel = writer.register_channel("/r", "cdr", writer.register_schema("s", "", b""))
        records = np.zeros((2, 31), np.uint8)
        writer.add_records(records, np.array([channel, channel]), np.array([5, -1]))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("ids", [[7], [0, 1, 2], [1, 65535, 2]])
def test_messages_of_an_unregistered_channel_are_refused_naming_it(ids):
    first_unknown = min(set(ids) - {0, 1})
    with McapWriter(io.BytesIO()) as writer:
        schema = writer.register_schema("s", "", b"")
        for topic in ("/a", "/b"):
            writer.register_channel(topic, "cdr", schema)
        times = np.arange(len(ids), dtype=np.int64)
        batch = MessageBatch.from_payloads(0, times, [b"x"] * len(ids))
        batch.channel_id[:] = ids
        with pytest.raises(UsageError, match=f"unregistered channel id {first_unknown}$"):
            writer.add_batch(batch)
        records = np.zeros((len(ids), 31), np.uint8)
        with pytest.raises(UsageError, match=f"unregistered channel id {first_unknown}$"):
            writer.add_records(records, np.array(ids), times)
        # registered channels pass
        writer.add_records(np.zeros((2, 31), np.uint8), np.array([1, 0]), np.array([0, 1]))


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_chunks_carry_content_checksums(compression):
    raw = np.random.default_rng(1).integers(0, 4, 50_000, dtype=np.uint8).tobytes()
    frame = compress(raw, compression)
    if compression == "zstd":
        assert zstandard.get_frame_parameters(frame).has_checksum
    else:
        assert frame[4] & 0x04  # FLG content-checksum bit of the lz4 frame descriptor
    assert decompress(frame, compression, len(raw)) == raw
    # a flipped bit in the stored checksum itself: only the checksum can catch it
    corrupt = bytearray(frame)
    corrupt[-1] ^= 0x01
    with pytest.raises(McapInputError, match=f"corrupt {compression} chunk"):
        decompress(bytes(corrupt), compression, len(raw))


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_the_mcap_package_reads_checksummed_chunks(tmp_path, compression):
    path = tmp_path / "x.mcap"
    with McapWriter(path, compression=compression, chunk_size=1000) as writer:
        channel = writer.register_channel("/a", "bin", writer.register_schema("s", "", b""))
        payloads = [bytes([i % 256]) * 30 for i in range(300)]
        writer.add_batch(
            MessageBatch.from_payloads(channel, np.arange(300, dtype=np.int64), payloads)
        )
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        assert [m.data for _, _, m in reader.iter_messages()] == payloads


def _blob_log(path, channels: int = 2, per_channel: int = 200) -> None:
    """A zstd log of one chunk (large enough to be copied verbatim): ``channels`` blob
    channels of 64-byte messages, interleaved."""
    with McapWriter(path) as writer:
        schema = writer.register_schema("raw/Blob", "", b"")
        ids = [writer.register_channel(f"/b{c}", "raw", schema) for c in range(channels)]
        n = channels * per_channel
        payload = (np.arange(n * 64) % 251).astype(np.uint8).tobytes()
        writer.add_batch(
            MessageBatch(
                channel_id=np.tile(np.array(ids, np.uint16), per_channel),
                sequence=np.zeros(n, np.uint32),
                log_time=np.repeat(np.arange(per_channel, dtype=np.int64) * 10 + 100, channels),
                publish_time=np.zeros(n, np.int64),
                data=np.frombuffer(payload, np.uint8),
                offset=np.arange(n, dtype=np.int64) * 64,
                length=np.full(n, 64, np.uint32),
            )
        )


def _raw_runs(path):
    from imufdi_cli.mcapio.source import McapSource

    source = McapSource(str(path), keep_raw_chunks=True)
    out = []
    for batch in source.batches():
        out.append((batch, source.raw_chunks(batch)))
    return source, out


def test_add_raw_chunk_copies_the_chunk_and_writes_queued_messages_of_its_channels_first(
    tmp_path,
):
    src = tmp_path / "in.mcap"
    _blob_log(src)
    source, runs = _raw_runs(src)
    ((batch, chunk_runs),) = runs
    ((raw, count, records_at),) = chunk_runs
    assert raw is not None and count == len(batch)
    out = tmp_path / "out.mcap"
    with McapWriter(out) as writer:
        for cid, info in sorted(source.channels.items()):
            schema = writer.register_schema("raw/Blob", "", b"")
            assert writer.register_channel(info.topic, "raw", schema) == cid
        first = int(batch.channel_id[0])
        # an earlier message of one of the chunk's channels, still queued: written first
        writer.add_batch(
            MessageBatch(
                channel_id=np.array([first], np.uint16),
                sequence=np.zeros(1, np.uint32),
                log_time=np.array([50], np.int64),
                publish_time=np.zeros(1, np.int64),
                data=np.zeros(4, np.uint8),
                offset=np.zeros(1, np.int64),
                length=np.full(1, 4, np.uint32),
            )
        )
        writer.add_raw_chunk(raw, batch, records_at)
    assert raw.content in out.read_bytes()  # the input's chunk, byte for byte
    with open(out, "rb") as f:
        times = [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert times == [50, *batch.log_time.tolist()]


def test_add_raw_chunk_does_not_wait_for_the_chunks_being_built(tmp_path, monkeypatch):
    """An input chunk queued behind a chunk still being built on a worker thread is
    written after it, in call order, without the caller waiting for it."""
    import threading

    from imufdi_cli.mcapio.writer import messages

    src = tmp_path / "in.mcap"
    _blob_log(src)
    source, runs = _raw_runs(src)
    ((batch, chunk_runs),) = runs
    ((raw, _, records_at),) = chunk_runs
    release = threading.Event()
    build = messages._build_chunk

    def held(parts, compression):
        assert release.wait(10)
        return build(parts, compression)

    outputs = []
    for hold in (False, True):
        if hold:
            monkeypatch.setattr(messages, "_build_chunk", held)
        out = tmp_path / f"{hold}.mcap"
        with McapWriter(out) as writer:
            for _cid, info in sorted(source.channels.items()):
                schema = writer.register_schema("raw/Blob", "", b"")
                writer.register_channel(info.topic, "raw", schema)
            other = writer.register_channel("/other", "raw", 0)
            writer.add_batch(
                MessageBatch.from_payloads(other, np.arange(10, dtype=np.int64), [bytes(8)] * 10)
            )
            writer._flush_chunk()  # a chunk on a worker thread (held until released)
            writer.add_raw_chunk(raw, batch, records_at)
            if hold:
                assert [job.raw is not None for job in writer._in_flight] == [False, True]
                assert not writer._in_flight[0].future.done()
                release.set()
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1]
    assert outputs[1].index(raw.content) > 0


def test_add_raw_chunk_refuses_unregistered_channels(tmp_path):
    src = tmp_path / "in.mcap"
    _blob_log(src)
    _, runs = _raw_runs(src)
    ((batch, chunk_runs),) = runs
    ((raw, _, records_at),) = chunk_runs
    with McapWriter(tmp_path / "out.mcap") as writer:
        schema = writer.register_schema("raw/Blob", "", b"")
        writer.register_channel("/b0", "raw", schema)  # the second channel is not registered
        with pytest.raises(UsageError, match="unregistered channel id 1"):
            writer.add_raw_chunk(raw, batch, records_at)


def _blob_batch(n: int) -> MessageBatch:
    log_time = np.arange(n, dtype=np.int64) * 1_000
    return MessageBatch.from_payloads(0, log_time, [bytes(8)] * n)


def test_the_switch_interval_is_short_while_workers_run_and_restored_on_every_path(tmp_path):
    """The writer shortens the interpreter's switch interval while its worker threads
    exist (``chunks.fast_switching_on``) and gives the old value back on close, on abort,
    and only when the last of two overlapping writers is done."""
    import sys

    from imufdi_cli.mcapio.writer import chunks

    before = sys.getswitchinterval()
    assert before > chunks.SWITCH_INTERVAL  # the interpreter's default, 5 ms

    def open_writer(name: str) -> McapWriter:
        writer = McapWriter(tmp_path / name, chunk_size=64)
        writer.register_channel("/a", "raw", 0)
        writer.add_batch(_blob_batch(50))  # several chunks: the worker threads start
        return writer

    first = open_writer("a.mcap")
    assert sys.getswitchinterval() == pytest.approx(chunks.SWITCH_INTERVAL)
    second = open_writer("b.mcap")
    first.close()
    assert sys.getswitchinterval() == pytest.approx(chunks.SWITCH_INTERVAL)  # b still runs
    second.close()
    assert sys.getswitchinterval() == before
    with pytest.raises(RuntimeError), open_writer("c.mcap"):
        assert sys.getswitchinterval() == pytest.approx(chunks.SWITCH_INTERVAL)
        raise RuntimeError("stop")
    assert sys.getswitchinterval() == before
    assert not (tmp_path / "c.mcap").exists()


def test_a_switch_interval_set_meanwhile_by_someone_else_is_kept(tmp_path):
    import sys

    before = sys.getswitchinterval()
    try:
        with McapWriter(tmp_path / "a.mcap", chunk_size=64) as writer:
            writer.register_channel("/a", "raw", 0)
            writer.add_batch(_blob_batch(50))
            sys.setswitchinterval(0.001)  # the program's own choice: not undone
        assert sys.getswitchinterval() == pytest.approx(0.001)
    finally:
        sys.setswitchinterval(before)


def _blob_batches(channel: int, seed: int = 0) -> list[MessageBatch]:
    """Three batches of 600 messages of 40 random bytes: about 127 kB of records, some
    thirty 4 KiB chunks (the write-behind thread starts at 1 KiB in these tests)."""
    rng = np.random.default_rng(seed)
    return [
        MessageBatch.from_payloads(
            channel,
            (np.arange(600, dtype=np.int64) + 600 * k) * 1000,
            [rng.bytes(40) for _ in range(600)],
        )
        for k in range(3)
    ]


def _write_blobs(output, chunk_size: int = 4096) -> McapWriter:
    writer = McapWriter(output, chunk_size=chunk_size)
    schema = writer.register_schema("raw/Blob", "", b"")
    channel = writer.register_channel("/a", "application/octet-stream", schema)
    for batch in _blob_batches(channel):
        writer.add_batch(batch)
    return writer


def test_a_file_written_behind_is_the_bytes_of_a_stream(tmp_path, monkeypatch):
    """From the first chunk on, a file's bytes are written on a thread of their own
    (``output._WriteBehind``): the same bytes as a stream written in place."""
    import threading

    from imufdi_cli.mcapio.writer import output

    monkeypatch.setattr(output, "WRITE_BEHIND_FROM", 1024)
    stream = io.BytesIO()
    with _write_blobs(stream):
        pass
    writer = _write_blobs(tmp_path / "a.mcap")
    assert writer._behind is not None
    assert "mcap-write" in [t.name for t in threading.enumerate()]
    writer.close()
    assert writer._behind is None and "mcap-write" not in [t.name for t in threading.enumerate()]
    assert (tmp_path / "a.mcap").read_bytes() == stream.getvalue()


def test_short_writev_writes_go_on_where_they_stopped(tmp_path, monkeypatch):
    """The write-behind thread writes its pieces with ``os.writev``, which may write less
    than asked: the rest follows, byte for byte."""
    from imufdi_cli.mcapio.writer import output

    monkeypatch.setattr(output, "WRITE_BEHIND_FROM", 1024)
    calls = []
    writev = os.writev

    def short(fd, buffers):  # at most 1000 bytes a call, cut inside a piece
        calls.append(len(buffers))
        head, left = [], 1000
        for buffer in buffers:
            view = memoryview(buffer)[:left]
            head.append(view)
            left -= len(view)
            if not left:
                break
        return writev(fd, head)

    monkeypatch.setattr(os, "writev", short)
    stream = io.BytesIO()
    with _write_blobs(stream):
        pass
    with _write_blobs(tmp_path / "a.mcap") as writer:
        assert writer._behind is not None
    assert calls and max(calls) > 1  # several pieces per call
    assert (tmp_path / "a.mcap").read_bytes() == stream.getvalue()


@pytest.mark.parametrize("on_close", [False, True])
def test_disk_full_behind_the_caller_leaves_no_temp_and_keeps_the_target(
    tmp_path, monkeypatch, on_close
):
    from imufdi_cli.mcapio.writer import output

    monkeypatch.setattr(output, "WRITE_BEHIND_FROM", 1024)
    path = tmp_path / "out.mcap"
    path.write_bytes(b"previous")
    with pytest.raises(OutputError) as info, McapWriter(path, chunk_size=4096) as writer:
        schema = writer.register_schema("raw/Blob", "", b"")
        channel = writer.register_channel("/a", "application/octet-stream", schema)
        writer._stream = _Full(writer._stream, 30_000, errno.ENOSPC, on_close=on_close)
        for batch in _blob_batches(channel):
            writer.add_batch(batch)
        assert writer._behind is not None
    assert str(info.value).startswith(f"cannot write {path}: {os.strerror(errno.ENOSPC)}")
    assert path.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]


def test_an_interrupt_stops_the_write_behind_thread_and_removes_the_temp(tmp_path, monkeypatch):
    import threading

    from imufdi_cli.mcapio.writer import output

    monkeypatch.setattr(output, "WRITE_BEHIND_FROM", 1024)
    with pytest.raises(KeyboardInterrupt), _write_blobs(tmp_path / "a.mcap") as writer:
        assert writer._behind is not None
        raise KeyboardInterrupt
    assert "mcap-write" not in [t.name for t in threading.enumerate()]
    assert list(tmp_path.iterdir()) == []
