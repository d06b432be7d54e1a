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
