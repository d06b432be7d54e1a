"""MCAP record layer: MessageBatch, McapWriter output read by the mcap package."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from imufdi_cli.errors import UsageError
from imufdi_cli.mcapio import McapSource, McapWriter, MessageBatch
from imufdi_cli.mcapio.source import scan_records


def _batch(n: int, channel: int = 0, seed: int = 0, var: bool = False) -> MessageBatch:
    rng = np.random.default_rng(seed)
    payloads = [
        rng.integers(0, 256, int(rng.integers(0, 40)) if var else 16, dtype=np.uint8).tobytes()
        for _ in range(n)
    ]
    return MessageBatch.from_payloads(
        channel, np.arange(n, dtype=np.int64) * 1000 + 5, payloads, sequence=np.arange(n)
    )


def test_batch_select_concatenate_sort() -> None:
    a = _batch(5, var=True)
    b = _batch(3, seed=1, var=True)
    joined = MessageBatch.concatenate([a, b])
    assert len(joined) == 8
    assert joined.payload(6) == b.payload(1)
    assert joined.payload(2) == a.payload(2)
    picked = joined.select([7, 0])
    assert picked.payload(0) == b.payload(2)
    shuffled = joined.select(np.array([3, 1, 2, 0]))
    shuffled.log_time = np.array([30, 10, 10, 0])
    ordered = shuffled.sorted_by_time()
    assert ordered.log_time.tolist() == [0, 10, 10, 30]
    assert ordered.payload(1) == a.payload(1)  # stable: 1 before 2
    assert ordered.payload(2) == a.payload(2)


def test_by_channel_matches_unique_and_select() -> None:
    rng = np.random.default_rng(3)
    batch = _batch(200, var=True)
    batch.channel_id = rng.choice(np.array([9, 2, 40000, 5], np.uint16), 200)
    groups = batch.by_channel()
    expected = np.unique(batch.channel_id).tolist()
    assert [cid for cid, _ in groups] == expected
    for (cid, part), (cid2, index) in zip(groups, batch.channel_indices()):
        reference = batch.select(batch.channel_id == cid)
        assert cid == cid2 and isinstance(cid, int)
        assert np.array_equal(index, np.flatnonzero(batch.channel_id == cid))
        assert part.sequence.tolist() == reference.sequence.tolist()
        assert [part.payload(i) for i in range(len(part))] == [
            reference.payload(i) for i in range(len(reference))
        ]
    assert sum(len(part) for _, part in groups) == len(batch)
    single = _batch(4, channel=7)
    assert [(cid, part is single) for cid, part in single.by_channel()] == [(7, True)]
    assert MessageBatch.empty().by_channel() == []


def test_gather_bytes_irregular_positions() -> None:
    from imufdi_cli.mcapio.records import gather_bytes

    data = np.random.default_rng(1).integers(0, 256, 1000, dtype=np.uint8)
    positions = np.array([0, 7, 3, 990, 500, 500], np.int64)
    out = gather_bytes(data, positions, 10)
    assert out.shape == (6, 10) and out.dtype == np.uint8
    for row, p in zip(out, positions):
        assert row.tolist() == data[p : p + 10].tolist()
    with pytest.raises(IndexError):
        gather_bytes(data, np.array([0, 5, 991]), 10)  # one byte past the end
    strided = gather_bytes(data[::2], np.array([1, 4, 2]), 3)  # not contiguous
    assert strided.tolist() == [data[::2][p : p + 3].tolist() for p in (1, 4, 2)]


@pytest.mark.parametrize("n_lengths", [1, 3, 60])
def test_message_records_are_the_spec_layout(n_lengths: int) -> None:
    """Every record is opcode 0x05, u64 length, channel u16, sequence u32, log and publish
    time u64, payload (mcap.dev/spec), packed one after another: for one payload length
    (rows), a few (copied per length) and many (joined per message), with payloads read
    out of order from a buffer holding other bytes."""
    import struct

    from imufdi_cli.mcapio.records import build_message_records

    rng = np.random.default_rng(n_lengths)
    n = 120
    lengths = rng.choice(rng.permutation(70)[:n_lengths], n)
    batch = MessageBatch.from_payloads(
        rng.integers(0, 3, n),
        rng.integers(0, 2**62, n),
        [rng.integers(0, 256, int(k), dtype=np.uint8).tobytes() for k in lengths],
        publish_time=rng.integers(0, 2**62, n),
        sequence=rng.integers(0, 2**32, n),
    )
    batch = batch.select(rng.permutation(n))
    batch.data = np.concatenate([np.full(5, 7, np.uint8), batch.data])
    batch.offset = batch.offset + 5
    records, starts = build_message_records(batch)
    expected = [
        struct.pack(
            "<BQHIQQ",
            5,
            22 + int(batch.length[i]),
            int(batch.channel_id[i]),
            int(batch.sequence[i]),
            int(batch.log_time[i]),
            int(batch.publish_time[i]),
        )
        + batch.payload(i)
        for i in range(n)
    ]
    assert records.dtype == np.uint8 and records.tobytes() == b"".join(expected)
    assert starts.tolist() == np.cumsum([0] + [len(r) for r in expected[:-1]]).tolist()


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
@pytest.mark.parametrize("variable", [False, True])
def test_mcap_package_reads_our_file(tmp_path, compression: str, variable: bool) -> None:
    path = tmp_path / "x.mcap"
    with McapWriter(path, compression=compression, chunk_size=500) as writer:
        schema = writer.register_schema("raw/Blob", "", b"")
        ch0 = writer.register_channel("/a", "application/octet-stream", schema, {"k": "v"})
        ch1 = writer.register_channel("/b", "application/octet-stream", schema)
        writer.add_metadata("imufdi.test", {"x": "1"})
        a = _batch(60, ch0, var=variable)
        b = _batch(40, ch1, seed=3, var=variable)
        writer.add_batch(a)
        writer.add_batch(b)
        writer.add_metadata("imufdi.after", {"y": "2"})  # chunks still being compressed
        writer.add_message(ch0, 10**9, b"last")
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics.message_count == 101
        assert summary.statistics.channel_message_counts == {ch0: 61, ch1: 40}
        assert len(summary.chunk_indexes) > 1
        messages = list(reader.iter_messages(log_time_order=False))
        assert [m.data for _, c, m in messages if c.topic == "/a"][:60] == [
            a.payload(i) for i in range(60)
        ]
        assert messages[-1][2].data == b"last"
        assert messages[0][1].metadata == {"k": "v"}
        assert {m.name: m.metadata for m in reader.iter_metadata()} == {
            "imufdi.test": {"x": "1"},
            "imufdi.after": {"y": "2"},
        }
    with McapSource(str(path)) as source:  # our reader takes them from the summary index
        assert source.metadata == {"imufdi.test": {"x": "1"}, "imufdi.after": {"y": "2"}}
    # the non-seeking reader checks every CRC, DataEnd and the footer
    with open(path, "rb") as stream:
        records = list(StreamReader(stream, validate_crcs=True).records)
    assert type(records[-1]).__name__ == "Footer"
    # every chunk carries a real CRC-32 (0 would mean "not computed" and skip the check)
    with open(path, "rb") as stream:
        raw = list(StreamReader(stream, emit_chunks=True, validate_crcs=True).records)
    chunks = [r for r in raw if type(r).__name__ == "Chunk"]
    assert chunks and all(c.uncompressed_crc != 0 for c in chunks)


def test_our_source_reads_batches(tmp_path) -> None:
    path = tmp_path / "x.mcap"
    with McapWriter(path, chunk_size=300) as writer:
        schema = writer.register_schema("raw/Blob", "", b"")
        ch = writer.register_channel("/a", "bin", schema)
        batch = _batch(50, ch, var=True)
        writer.add_batch(batch)
    with McapSource(path) as source:
        got = MessageBatch.concatenate(list(source.batches()))
        assert source.channels[ch].topic == "/a"
    assert [got.payload(i) for i in range(50)] == [batch.payload(i) for i in range(50)]
    np.testing.assert_array_equal(got.log_time, batch.log_time)
    np.testing.assert_array_equal(got.sequence, batch.sequence)


def test_scan_records_mixed_pattern() -> None:
    # 40 records with a period-3 length pattern, then irregular ones
    lengths = [5, 9, 5] * 40 + [1, 2, 3, 70, 0]
    raw = b"".join(bytes([5]) + n.to_bytes(8, "little") + b"\0" * n for n in lengths)
    starts, opcodes, got_lengths, end = scan_records(np.frombuffer(raw, np.uint8))
    assert got_lengths.tolist() == lengths
    assert set(opcodes.tolist()) == {5}
    assert end == len(raw)
    assert starts[1] == 9 + 5
    cut = np.frombuffer(raw[:-3], np.uint8)  # last record cut
    _, _, cut_lengths, cut_end = scan_records(cut)
    assert cut_lengths.tolist() == lengths[:-1]
    assert cut_end == len(raw) - 9


def test_atomic_write_and_abort(tmp_path) -> None:
    path = tmp_path / "out.mcap"
    path.write_bytes(b"previous")
    with pytest.raises(RuntimeError), McapWriter(path) as writer:
        writer.register_schema("a", "", b"")
        raise RuntimeError("boom")
    assert path.read_bytes() == b"previous"  # untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]  # no temp file left
    with McapWriter(path) as writer:
        writer.add_metadata("m", {"a": "b"})
    assert path.read_bytes()[:8] == b"\x89MCAP0\r\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]


def test_stream_output_and_json_channel() -> None:
    buffer = io.BytesIO()
    with McapWriter(buffer, compression="none") as writer:
        ch = writer.register_json_channel("/events", "imufdi.Event")
        writer.add_json(ch, 7, {"kind": "alarm", "x": [1, 2]})
    buffer.seek(0)
    reader = make_reader(buffer)
    ((schema, channel, message),) = list(reader.iter_messages())
    assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
    assert json.loads(message.data) == {"kind": "alarm", "x": [1, 2]}
    assert message.log_time == 7


def test_copy_channels_keeps_ids(tmp_path) -> None:
    src_path = tmp_path / "a.mcap"
    with McapWriter(src_path) as writer:
        schema = writer.register_schema("s", "", b"")
        writer.register_channel("/x", "bin", schema)
        ch = writer.register_channel("/y", "bin", schema)
        writer.add_batch(_batch(10, ch))
    with McapSource(src_path) as source:
        batches = list(source.batches())
        with McapWriter(tmp_path / "b.mcap") as writer:
            writer.copy_channels(source.channels)
            for batch in batches:
                writer.add_batch(batch)
    with McapSource(tmp_path / "b.mcap") as copy:
        got = MessageBatch.concatenate(list(copy.batches()))
        assert {c.id: c.topic for c in copy.channels.values()} == {0: "/x", 1: "/y"}
    assert got.channel_id.tolist() == [1] * 10


def test_bad_options() -> None:
    with pytest.raises(UsageError, match="valid: zstd, lz4, none"):
        McapWriter(io.BytesIO(), compression="gzip")


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_metadata_index_points_at_metadata_records(tmp_path, compression) -> None:
    """Metadata added while chunks are still compressing on worker threads: the
    MetadataIndex must hold the offset the record landed at (read by the mcap package)."""
    path = tmp_path / "m.mcap"
    with McapWriter(path, compression=compression, chunk_size=256) as writer:
        schema = writer.register_schema("s", "", b"")
        ch = writer.register_channel("/x", "bin", schema)
        writer.add_metadata("first", {"a": "1"})
        for k in range(3):
            writer.add_batch(_batch(200, ch))  # several chunks, some still in flight
            writer.add_metadata(f"after{k}", {"k": str(k)})
    raw = path.read_bytes()
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        assert [raw[m.offset] for m in summary.metadata_indexes] == [0x0C] * 4
        assert [(m.name, m.metadata) for m in reader.iter_metadata()] == [
            ("first", {"a": "1"}),
            ("after0", {"k": "0"}),
            ("after1", {"k": "1"}),
            ("after2", {"k": "2"}),
        ]
        assert sum(1 for _ in reader.iter_messages()) == 600
