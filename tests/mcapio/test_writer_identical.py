"""McapWriter writes the bytes recorded before ``mcapio/writer.py`` became a package.

``imufdi_cli/mcapio/writer.py`` was split into the package ``imufdi_cli/mcapio/writer/``
by concern with behaviour unchanged. ``data/writer_identical.json`` was recorded
with the single-module writer (main 34d2aba): one file per compression exercising every
way in: Schema, Channel (with metadata) and Metadata records, a JSON channel, batches of
variable-size messages (:meth:`~McapWriter.add_batch`), ready fixed-size records
(:meth:`~McapWriter.add_records`), templated record sources on worker threads (two
:class:`~imufdi_cli.mcapio.ImuArrayWriter` arrays of different record sizes), an input
chunk copied verbatim (:meth:`~McapWriter.add_raw_chunk`), metadata written while chunks
are still being compressed, chunks small enough to cut records at many phases, and the
summary section and footer.

``none`` has no compressor in the way: its SHA-256 must match everywhere. zstd and lz4
frames depend on the compression library's version too, so those hashes are compared only
when ``zstandard`` and ``lz4`` are the recorded versions (the decompressed chunks are then
still covered by ``none``).

Re-record (only for a deliberate change of the bytes, saying why in the commit):
``PYTHONPATH=. python tests/mcapio/test_writer_identical.py``.
"""

from __future__ import annotations

import hashlib
import io
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from imufdi_cli.array import ArrayConfig
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio import ImuArrayWriter, McapSource, McapWriter, MessageBatch
from imufdi_cli.mcapio.records import build_message_records

RECORD = Path(__file__).parent / "data" / "writer_identical.json"
COMPRESSIONS = ("none", "zstd", "lz4")
T0_NS = 1_700_000_000_000_000_000


def _versions() -> dict[str, str]:
    import lz4
    import zstandard

    return {"zstandard": zstandard.__version__, "lz4": lz4.__version__}


def _block(n: int, n_imus: int, seed: int) -> ImuBlock:
    rng = np.random.default_rng(seed)
    return ImuBlock(
        t_ns=T0_NS + np.arange(n, dtype=np.int64) * 10_000_000,
        gyro=rng.normal(0.0, 0.3, (n, n_imus, 3)),
        accel=rng.normal(0.0, 3.0, (n, n_imus, 3)),
    )


def _blobs(channel: int, n: int, t0: int, seed: int) -> MessageBatch:
    """``n`` messages of 0..40 random bytes on one channel, 1 ms apart from ``t0``."""
    rng = np.random.default_rng(seed)
    payloads = [
        rng.integers(0, 256, int(k), dtype=np.uint8).tobytes() for k in rng.integers(0, 41, n)
    ]
    log_time = t0 + np.arange(n, dtype=np.int64) * 1_000_000
    return MessageBatch.from_payloads(
        channel, log_time, payloads, publish_time=log_time + 7, sequence=np.arange(n)
    )


def _raw_input(compression: str) -> bytes:
    """A log of one chunk (over 4 kB, so read as clean), which the writer under test
    copies verbatim."""
    out = io.BytesIO()
    with McapWriter(out, compression=compression, chunk_size=1 << 20) as writer:
        schema = writer.register_schema("raw/Blob", "", b"")
        writer.register_channel("/copied", "raw", schema)
        writer.add_batch(_blobs(0, 300, T0_NS + 9_000_000_000, seed=5))
    return out.getvalue()


def write_everything(compression: str, tmp: Path) -> bytes:
    """The file (bytes) the writer makes of every way in, with ``compression``."""
    source_path = tmp / f"raw-{compression}.mcap"
    source_path.write_bytes(_raw_input(compression))
    source = McapSource(source_path, keep_raw_chunks=True)
    ((batch, runs),) = [(b, source.raw_chunks(b)) for b in source.batches()]
    ((raw, _, records_at),) = runs
    out = io.BytesIO()
    with McapWriter(out, compression=compression, chunk_size=2000) as writer:
        blob = writer.register_schema("raw/Blob", "", b"")
        copied = writer.register_channel("/copied", "raw", blob)
        blobs = writer.register_channel("/blobs", "raw", blob, {"origin": "test", "k": "v"})
        fixed = writer.register_channel("/fixed", "raw", blob)
        events = writer.register_json_channel("/events", "imufdi.Event")
        writer.add_metadata("imufdi.test", {"a": "1", "b": "two"})
        first = ImuArrayWriter(writer, ArrayConfig.co_aligned(3, 100.0))
        second = ImuArrayWriter(
            writer,
            ArrayConfig.co_aligned(2, 100.0),
            topics=["/second_array_imu0/data_raw", "/second_array_imu1/data_raw"],
        )
        whole = _block(157, 3, seed=1)
        other = _block(157, 2, seed=2)
        for a, b in ((0, 1), (1, 40), (40, 41), (41, 157)):
            first.write_block(whole.slice(a, b))
            second.write_block(other.slice(a, b))
            writer.add_batch(_blobs(blobs, 23, T0_NS + a * 10_000_000, seed=a))
        fixed_batch = _blobs(fixed, 60, T0_NS + 2_000_000_000, seed=9)
        fixed_batch = MessageBatch.from_payloads(
            fixed,
            fixed_batch.log_time,
            [bytes([k]) * 12 for k in range(60)],
            publish_time=fixed_batch.log_time,
            sequence=np.arange(60),
        )
        records, _ = build_message_records(fixed_batch)
        writer.add_records(records.reshape(60, -1), fixed_batch.channel_id, fixed_batch.log_time)
        writer.add_metadata("imufdi.after", {"while": "compressing"})
        writer.add_json(events, T0_NS + 3_000_000_000, {"kind": "alarm", "x": [1, 2.5]})
        writer.add_message(blobs, T0_NS + 4_000_000_000, b"last", sequence=3)
        assert copied == int(batch.channel_id[0])
        writer.add_raw_chunk(raw, batch, records_at)
    data = out.getvalue()
    assert raw.content in data  # the input chunk was copied, not rewritten
    return data


def _digest(compression: str, tmp: Path) -> str:
    return hashlib.sha256(write_everything(compression, tmp)).hexdigest()


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_the_writer_writes_the_recorded_bytes(compression, tmp_path) -> None:
    record = json.loads(RECORD.read_text())
    if compression != "none" and record["versions"] != _versions():
        pytest.skip(f"{compression} frames recorded with {record['versions']}")
    assert _digest(compression, tmp_path) == record["sha256"][compression]


def test_the_recorded_file_takes_every_way_in(tmp_path) -> None:
    """The recorded file is a valid MCAP of many chunks holding every channel's messages."""
    from mcap.reader import make_reader

    data = write_everything("zstd", tmp_path)
    reader = make_reader(io.BytesIO(data), validate_crcs=True)
    summary = reader.get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 20
    counts = {
        summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()
    }
    assert counts == {
        "/copied": 300,
        "/blobs": 4 * 23 + 1,
        "/fixed": 60,
        "/events": 1,
        **{f"/imu{k}/data_raw": 157 for k in range(3)},
        **{f"/second_array_imu{k}/data_raw": 157 for k in range(2)},
    }
    names = [m.name for m in reader.iter_metadata()]
    assert names[0] == "imufdi.test" and names[-1] == "imufdi.after"
    assert sum(1 for _ in reader.iter_messages()) == sum(counts.values())


def _record() -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        digests = {c: _digest(c, Path(tmp)) for c in COMPRESSIONS}
    RECORD.write_text(json.dumps({"versions": _versions(), "sha256": digests}, indent=1) + "\n")
    print(f"recorded {RECORD}", file=sys.stderr)


if __name__ == "__main__":
    _record()
