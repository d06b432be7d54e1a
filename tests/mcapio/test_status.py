"""Detector status channels and JSON topics."""

from __future__ import annotations

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from numpy.testing import assert_array_equal
from rosbags.highlevel import AnyReader

from imufdi_cli.detectors.base import DetectionBlock
from imufdi_cli.mcapio import (
    McapWriter,
    encode_status,
    read_json_topic,
    read_status,
    register_status_channel,
)


def _detections(n: int, n_sensors: int, seed: int = 0) -> DetectionBlock:
    rng = np.random.default_rng(seed)
    return DetectionBlock(
        statistic=rng.normal(size=n),
        threshold=np.full(n, 6.63),
        alarm=rng.random(n) > 0.5,
        isolated=rng.integers(-2, n_sensors, n).astype(np.int32),
        amplitude=np.where(rng.random(n) > 0.5, np.nan, rng.normal(size=n)),
        scores=rng.normal(size=(n, n_sensors)),
    )


def test_status_round_trip_and_mcap_ros2(tmp_path) -> None:
    path = tmp_path / "s.mcap"
    t_ns = 10**18 + np.arange(200, dtype=np.int64) * 10_000_000
    gyro = _detections(200, 5)
    accel = _detections(200, 0, seed=1)  # no scores: empty sequence
    with McapWriter(path) as writer:
        ids = [f"imu{k}.gyro.x" for k in range(5)]
        cg = register_status_channel(writer, "glt", "gyro", ids)
        ca = register_status_channel(writer, "glt", "accel", [])
        cb = register_status_channel(writer, "bank", "gyro", ids)
        writer.add_batch(encode_status(cg, t_ns, gyro))
        writer.add_batch(encode_status(ca, t_ns, accel))
        writer.add_batch(encode_status(cb, t_ns, gyro))
        events = writer.register_json_channel("/imufdi/events", "imufdi.Event")
        writer.add_json(events, 5, {"alarm": "start"})
    status = read_status(path)
    assert sorted(status) == [("bank", "gyro"), ("glt", "accel"), ("glt", "gyro")]
    got = status[("bank", "gyro")]
    assert got.sensor_ids == ids
    assert_array_equal(got.t_ns, t_ns)
    for name in ("statistic", "threshold", "alarm", "isolated", "amplitude", "scores"):
        assert_array_equal(getattr(got, name), getattr(gyro, name))
    assert status[("glt", "accel")].scores.shape == (200, 0)
    assert list(read_status(path, detector="glt")) == [("glt", "gyro"), ("glt", "accel")]
    assert read_json_topic(path, "/imufdi/events") == [(5, {"alarm": "start"})]
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        decoded = [d for _, c, _, d in reader.iter_decoded_messages(topics=["/imufdi/bank/gyro"])]
    assert [d.isolated for d in decoded] == gyro.isolated.tolist()
    assert_array_equal(np.array([d.scores for d in decoded]), gyro.scores)
    assert [d.alarm for d in decoded] == gyro.alarm.tolist()


def test_header_and_decision_time_round_trip(tmp_path) -> None:
    from imufdi_cli.mcapio import STATUS_FRAME_ID

    path = tmp_path / "d.mcap"
    t_ns = 1_700_000_000 * 10**9 + np.arange(50, dtype=np.int64) * 10_000_000
    decided = t_ns + np.arange(50, dtype=np.int64) * 7_000_001  # crosses second boundaries
    det = _detections(50, 3, seed=2)
    with McapWriter(path) as writer:
        cid = register_status_channel(writer, "woa", "gyro", ["a", "b", "c"])
        writer.add_batch(encode_status(cid, t_ns, det, decided))
    got = read_status(path)[("woa", "gyro")]
    assert got.has_decided
    assert_array_equal(got.t_ns, t_ns)
    assert_array_equal(got.decided_ns, decided)
    assert_array_equal(got.scores, det.scores)
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        decoded = [d for _, _, _, d in reader.iter_decoded_messages()]
    assert {d.header.frame_id for d in decoded} == {STATUS_FRAME_ID}
    stamps = [d.header.stamp.sec * 10**9 + d.header.stamp.nanosec for d in decoded]
    assert stamps == t_ns.tolist()
    assert [d.decided.sec * 10**9 + d.decided.nanosec for d in decoded] == decided.tolist()
    assert [d.isolated for d in decoded] == det.isolated.tolist()


_OLD_STATUS = """builtin_interfaces/Time stamp
float64 statistic
float64 threshold
bool alarm
int32 isolated
float64 amplitude
float64[] scores
bool[] isolated_set
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""


def test_old_status_channels_without_header_are_still_read(tmp_path) -> None:
    from mcap_ros2.writer import Writer as Ros2Writer

    path = tmp_path / "old.mcap"
    with open(path, "wb") as stream:
        writer = Ros2Writer(stream)
        schema = writer.register_msgdef("imufdi_msgs/msg/FdiStatus", _OLD_STATUS)
        for i in range(5):
            writer.write_message(
                topic="/imufdi/glt/gyro",
                schema=schema,
                message={
                    "stamp": {"sec": 3, "nanosec": i * 10},
                    "statistic": float(i),
                    "threshold": 2.5,
                    "alarm": i > 2,
                    "isolated": i - 1,
                    "amplitude": 0.5,
                    "scores": [1.0, float(i)],
                    "isolated_set": [False, i > 2],
                },
                log_time=3 * 10**9 + i * 10,
                publish_time=3 * 10**9 + i * 10,
            )
        writer.finish()
    got = read_status(path)[("glt", "gyro")]
    assert not got.has_decided
    assert_array_equal(got.t_ns, 3 * 10**9 + np.arange(5) * 10)
    assert_array_equal(got.decided_ns, got.t_ns)  # no decision time: the sample time
    assert_array_equal(got.statistic, np.arange(5.0))
    assert got.alarm.tolist() == [False, False, False, True, True]
    assert_array_equal(got.scores[:, 1], np.arange(5.0))
    # written before per-sensor amplitudes existed: ``amplitude`` on the isolated column
    expected = np.full((5, 2), np.nan)
    expected[1, 0] = expected[2, 1] = 0.5
    assert_array_equal(got.amplitudes, expected)


def test_per_sensor_amplitudes_round_trip_and_independent_readers(tmp_path) -> None:
    """``amplitudes`` (one per sensor, NaN where none) follows the one-byte-per-sensor
    ``isolated_set``, so its length and float64 values need CDR padding: every sensor count
    mod 8 is written and read back by imufdi, mcap-ros2-support and rosbags. Detectors that
    give no per-sensor amplitudes write an empty field, read as ``amplitude`` on the
    isolated sensor's column."""
    path = tmp_path / "a.mcap"
    t_ns = 10**18 + np.arange(40, dtype=np.int64) * 10_000_000
    rng = np.random.default_rng(3)
    blocks = {}
    with McapWriter(path) as writer:
        for n_sensors in range(0, 9):
            det = _detections(40, n_sensors, seed=n_sensors)
            if n_sensors % 2:
                det.amplitudes = np.where(
                    rng.random((40, n_sensors)) > 0.5, rng.normal(size=(40, n_sensors)), np.nan
                )
            ids = [f"imu{k}.gyro.x" for k in range(n_sensors)]
            cid = register_status_channel(writer, f"d{n_sensors}", "gyro", ids)
            writer.add_batch(encode_status(cid, t_ns, det))
            blocks[f"/imufdi/d{n_sensors}/gyro"] = det
    status = read_status(path)
    for topic, det in blocks.items():
        got = status[(topic.split("/")[2], "gyro")]
        assert_array_equal(got.amplitudes, det.amplitude_set())
        assert_array_equal(got.scores, det.scores)
        assert_array_equal(got.isolated_set, det.isolation_set())
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        by_topic: dict[str, list[list[float]]] = {}
        for _, channel, _, msg in reader.iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append(list(msg.amplitudes))
    with AnyReader([path]) as bag:
        rosbags = {topic: [] for topic in blocks}
        for connection, _, raw in bag.messages():
            msg = bag.deserialize(raw, connection.msgtype)
            rosbags[connection.topic].append(np.asarray(msg.amplitudes, dtype=np.float64))
    for topic, det in blocks.items():
        given = det.amplitudes is not None
        expected = det.amplitude_set() if given else np.zeros((40, 0))
        assert_array_equal(np.array(by_topic[topic]).reshape(expected.shape), expected)
        assert_array_equal(np.array(rosbags[topic]).reshape(expected.shape), expected)


def test_status_records_write_the_bytes_of_encode_status(tmp_path) -> None:
    """``status_records`` + ``add_records`` (detect's path) and ``encode_status`` +
    ``add_batch`` give the same file: records of 0 and 5 sensors, with and without
    per-sensor amplitudes, another frame id, chunks cutting the blocks."""
    import dataclasses

    from imufdi_cli.mcapio.status import status_records

    t_ns = 1_700_000_000 * 10**9 + np.arange(300, dtype=np.int64) * 10_000_000
    decided = t_ns + 25_000_000
    with_amplitudes = dataclasses.replace(
        _detections(300, 5, seed=4), amplitudes=np.random.default_rng(5).normal(size=(300, 5))
    )
    blocks = [
        (_detections(300, 5, seed=3), None, "imu_array"),
        (_detections(300, 0, seed=6), decided, "imu_array"),
        (with_amplitudes, decided, "body"),
    ]

    def rows(det: DetectionBlock, keep: slice) -> DetectionBlock:
        return DetectionBlock(
            **{
                f.name: None if getattr(det, f.name) is None else getattr(det, f.name)[keep]
                for f in dataclasses.fields(det)
            }
        )

    outputs = []
    for use_records in (False, True):
        path = tmp_path / f"{use_records}.mcap"
        with McapWriter(path, chunk_size=20_000) as writer:
            for k, (det, dec, frame) in enumerate(blocks):
                cid = register_status_channel(writer, f"d{k}", "gyro", [])
                for half in (slice(0, 170), slice(170, 300)):
                    if use_records:
                        records = status_records(
                            cid,
                            t_ns[half],
                            rows(det, half),
                            None if dec is None else dec[half],
                            frame_id=frame,
                        )
                        writer.add_records(records, np.full(records.shape[0], cid), t_ns[half])
                    else:
                        writer.add_batch(
                            encode_status(
                                cid,
                                t_ns[half],
                                rows(det, half),
                                None if dec is None else dec[half],
                                frame_id=frame,
                            )
                        )
        outputs.append(path.read_bytes())
    assert outputs[0] == outputs[1]
    got = read_status(tmp_path / "True.mcap")[("d2", "gyro")]
    assert_array_equal(got.amplitudes, with_amplitudes.amplitudes)
    assert_array_equal(got.decided_ns, decided)


def _annotated(path, imu_chunks: bool = True) -> tuple[np.ndarray, DetectionBlock]:
    """A 16-IMU log of 3000 samples with a glt gyro status channel, each in its own
    chunks (as detect writes them), and a JSON event channel."""
    from imufdi_cli.array import ArrayConfig
    from imufdi_cli.log import ImuBlock
    from imufdi_cli.mcapio import ImuArrayWriter

    rng = np.random.default_rng(3)
    n = 3000
    t_ns = 10**18 + np.arange(n, dtype=np.int64) * 10_000_000
    array = ArrayConfig.co_aligned(16, 100.0)
    det = _detections(n, 48, seed=4)
    with McapWriter(path, chunk_size=1 << 16) as writer:
        imus = ImuArrayWriter(writer, array)
        cid = register_status_channel(writer, "glt", "gyro", array.sensor_ids("gyro"))
        events = writer.register_json_channel("/imufdi/events", "imufdi.Event")
        for start in range(0, n, 1000):
            part = slice(start, start + 1000)
            block = ImuBlock(
                t_ns=t_ns[part],
                gyro=rng.normal(0, 0.003, (1000, 16, 3)),
                accel=rng.normal(0, 0.02, (1000, 16, 3)),
            )
            imus.write_block(block)
            fields = ("statistic", "threshold", "alarm", "isolated", "amplitude", "scores")
            rows = DetectionBlock(**{k: getattr(det, k)[part] for k in fields})
            writer.add_batch(encode_status(cid, t_ns[part], rows))
            writer.add_json(events, int(t_ns[start]), {"alarm": "start"})
    return t_ns, det


def test_status_reading_steps_over_the_imu_chunks_and_reads_the_same(tmp_path) -> None:
    # iter_status / read_status read only the chunks holding a status channel (and, with
    # others_wanted, the channels asked for): the summary's chunk index says which; the
    # rows are those of a read of every chunk
    from imufdi_cli.mcapio import McapSource, iter_status

    path = tmp_path / "a.mcap"
    t_ns, det = _annotated(path)
    got = read_status(path)[("glt", "gyro")]
    assert_array_equal(got.t_ns, t_ns)
    for name in ("statistic", "threshold", "alarm", "isolated", "amplitude", "scores"):
        assert_array_equal(getattr(got, name), getattr(det, name))
    seen: dict[str, int] = {}

    def others(batch, channel) -> None:
        seen[channel.topic] = seen.get(channel.topic, 0) + len(batch)

    with McapSource(path) as source:
        rows = list(
            iter_status(
                source,
                others=others,
                others_wanted=lambda channel: channel.topic == "/imufdi/events",
            )
        )
        skipped = len(source._skipped_chunks)
    assert sum(r[3]["t_ns"].size for r in rows) == t_ns.size
    assert seen["/imufdi/events"] == 3
    # only the Imu messages of the few chunks they share with status rows were read
    assert sum(v for k, v in seen.items() if k.startswith("/imu")) < 0.1 * 16 * t_ns.size
    assert skipped >= 100
    # others without others_wanted: every chunk, as before
    everything: list[str] = []
    with McapSource(path) as source:
        list(iter_status(source, others=lambda batch, channel: everything.append(channel.topic)))
        assert not source._skipped_chunks
    assert any(topic.startswith("/imu") for topic in everything)


def test_chunks_the_index_does_not_describe_are_read(tmp_path) -> None:
    # a writer that wrote no message indexes leaves the chunk index's channel map empty:
    # those chunks are read (nothing says what they hold); so are the chunks of a file
    # read without its summary (a stream)
    import io as _io

    from mcap.writer import IndexType, Writer

    from imufdi_cli.mcapio import McapSource

    path = tmp_path / "a.mcap"
    _annotated(path)
    copy = tmp_path / "b.mcap"
    with McapSource(path) as source, open(copy, "wb") as out:
        writer = Writer(out, index_types=IndexType.NONE, chunk_size=1 << 16)
        writer.start()
        schemas = {
            cid: writer.register_schema(c.schema.name, c.schema.encoding, c.schema.data)
            for cid, c in source.channels.items()
            if c.schema is not None
        }
        ids = {
            cid: writer.register_channel(
                c.topic, c.message_encoding, schemas.get(cid, 0), c.metadata
            )
            for cid, c in source.channels.items()
        }
        for batch in source.batches():
            for i in range(len(batch)):
                writer.add_message(
                    ids[int(batch.channel_id[i])],
                    int(batch.log_time[i]),
                    batch.payload(i),
                    int(batch.log_time[i]),
                )
        writer.finish()
    assert_array_equal(
        read_status(copy)[("glt", "gyro")].t_ns, read_status(path)[("glt", "gyro")].t_ns
    )
    with McapSource(copy) as source:
        assert source.skip_chunks_without(lambda channel: False) == 0
    with McapSource(_io.BytesIO(path.read_bytes())) as source:
        assert source.skip_chunks_without(lambda channel: False) > 0  # seekable: indexed


def _general_walk_only(monkeypatch) -> None:
    """Read every status batch through the per-message walk (no fixed-offset read)."""
    from imufdi_cli.mcapio.cdr import CdrCodec

    monkeypatch.setattr(CdrCodec, "uniform_rows", lambda self, batch, paths: None)


def _rows_of(path, **options) -> list[tuple[str, str, list[str], dict[str, np.ndarray]]]:
    from imufdi_cli.mcapio import McapSource, iter_status

    with McapSource(path) as source:
        return list(iter_status(source, **options))


def _assert_same_rows(got, expected) -> None:
    assert [r[:3] for r in got] == [r[:3] for r in expected]
    for (_, _, _, a), (_, _, _, b) in zip(got, expected):
        assert a.keys() == b.keys()
        for key in a:
            assert a[key].dtype == b[key].dtype and a[key].shape == b[key].shape, key
            assert a[key].tobytes() == b[key].tobytes(), key  # NaN payloads too


def test_status_laid_out_alike_is_read_at_fixed_offsets_as_the_walk_reads_it(
    tmp_path, monkeypatch
) -> None:
    # what detect writes (one length, one frame id, one sensor count per channel) is read
    # through CdrCodec.uniform_rows: the same arrays, bit for bit, as the per-message walk
    from imufdi_cli.mcapio.cdr import CdrCodec

    path = tmp_path / "a.mcap"
    _annotated(path)
    calls: list[bool] = []
    uniform = CdrCodec.uniform_rows

    def counted(self, batch, paths):
        found = uniform(self, batch, paths)
        calls.append(found is not None)
        return found

    monkeypatch.setattr(CdrCodec, "uniform_rows", counted)
    fast = _rows_of(path)
    assert calls and all(calls)
    _general_walk_only(monkeypatch)
    _assert_same_rows(fast, _rows_of(path))


def _frame_ids_of_one_length(n_a: int, n_b: int) -> tuple[str, str]:
    """Two frame ids whose status messages of n_a and n_b sensors have the same length."""
    from imufdi_cli.mcapio.status import _status_template

    for a in range(1, 40):
        for b in range(1, 40):
            frame_a, frame_b = "f" * a, "g" * b
            if (
                _status_template(1, frame_a.encode() + b"\0", n_a, 0)[1]["length"]
                == _status_template(1, frame_b.encode() + b"\0", n_b, 0)[1]["length"]
            ):
                return frame_a, frame_b
    raise AssertionError("no such frame ids")


def test_status_messages_laid_out_differently_are_walked_one_by_one(tmp_path, monkeypatch) -> None:
    # the same length but another frame id length and sensor count, a big-endian
    # message, or another length: uniform_rows declines, and the walk reads each message
    from imufdi_cli.mcapio import McapSource
    from imufdi_cli.mcapio.cdr import codec_for
    from imufdi_cli.mcapio.records import MessageBatch
    from imufdi_cli.mcapio.status import _decode_status

    t_ns = 10**18 + np.arange(6, dtype=np.int64) * 10_000_000
    frame_a, frame_b = _frame_ids_of_one_length(3, 2)
    path = tmp_path / "m.mcap"
    with McapWriter(path) as writer:
        cid = register_status_channel(writer, "glt", "gyro", ["a", "b", "c"])
        writer.add_batch(encode_status(cid, t_ns[:3], _detections(3, 3), frame_id=frame_a))
        writer.add_batch(encode_status(cid, t_ns[3:], _detections(3, 2, 1), frame_id=frame_b))
    with McapSource(path) as source:
        channel = source.channels[cid]
        batch = MessageBatch.concatenate(list(source.batches()))
    codec = codec_for(channel.schema.name, channel.schema.data)
    paths = ["statistic", "scores", "isolated_set"]
    assert len(set(batch.length.tolist())) == 1
    assert codec.uniform_rows(batch, paths) is None  # the counts differ
    assert codec.uniform_rows(batch.select(slice(0, 3)), paths) is not None
    mixed = _decode_status(batch, channel)
    assert mixed["scores"].shape == (6, 3) and np.isnan(mixed["scores"][3:, 2]).all()
    assert_array_equal(mixed["scores"][3:, :2], _detections(3, 2, 1).scores)
    assert_array_equal(mixed["statistic"][3:], _detections(3, 2, 1).statistic)
    # a big-endian first message (not written by imufdi): declined
    flipped = MessageBatch(**{**batch.__dict__, "data": batch.data.copy()})
    flipped.data[int(flipped.offset[0]) + 1] = 0
    assert codec.uniform_rows(flipped.select(slice(0, 3)), paths) is None
    # other lengths: declined
    longer = tmp_path / "l.mcap"
    with McapWriter(longer) as writer:
        cid = register_status_channel(writer, "glt", "gyro", ["a", "b", "c"])
        writer.add_batch(encode_status(cid, t_ns[:3], _detections(3, 3)))
        writer.add_batch(encode_status(cid, t_ns[3:], _detections(3, 3), frame_id="other"))
    with McapSource(longer) as source:
        both = MessageBatch.concatenate(list(source.batches()))
    assert codec.uniform_rows(both, paths) is None
    fast = _rows_of(longer)
    _general_walk_only(monkeypatch)
    _assert_same_rows(fast, _rows_of(longer))


def test_rows_for_scoring_leave_out_the_amplitude_and_score_matrices(tmp_path) -> None:
    # iter_status(amplitude_columns=False, score_columns=False), what report reads: no
    # (k, n) NaN amplitudes where the messages carry none per sensor, and each row's
    # best_score (the column of its first largest finite score) instead of the scores
    from imufdi_cli.sweep import best_columns

    path = tmp_path / "a.mcap"
    t_ns = 10**18 + np.arange(40, dtype=np.int64) * 10_000_000
    single = _detections(40, 4, seed=1)
    single.scores[3] = np.nan
    single.scores[5, :2] = np.inf
    per_sensor = _detections(40, 4, seed=2)
    per_sensor.amplitudes = np.random.default_rng(5).normal(size=(40, 4))
    with McapWriter(path) as writer:
        ids = [f"imu{k}.gyro.x" for k in range(4)]
        for name, det in (("one", single), ("all", per_sensor)):
            cid = register_status_channel(writer, name, "gyro", ids)
            writer.add_batch(encode_status(cid, t_ns, det))
    full = {r[0]: r[3] for r in _rows_of(path)}
    lean = {r[0]: r[3] for r in _rows_of(path, amplitude_columns=False, score_columns=False)}
    assert "amplitudes" not in lean["one"] and "scores" not in lean["one"]
    assert_array_equal(lean["all"]["amplitudes"], per_sensor.amplitudes)
    for name in ("one", "all"):
        assert_array_equal(lean[name]["best_score"], best_columns(full[name]["scores"]))
        assert_array_equal(lean[name]["amplitude"], full[name]["amplitude"])
    assert lean["one"]["best_score"][3] == -1 and lean["one"]["best_score"][5] >= 2


class _CountingFile:
    """A binary file that counts the bytes read from it."""

    def __init__(self, path) -> None:
        self._file = open(path, "rb")  # closed by close()
        self.read_bytes = 0

    def read(self, n: int = -1) -> bytes:
        out = self._file.read(n)
        self.read_bytes += len(out)
        return out

    def readinto(self, view) -> int:
        got = self._file.readinto(view)
        self.read_bytes += got or 0
        return got

    def seek(self, *args) -> int:
        return self._file.seek(*args)

    def tell(self) -> int:
        return self._file.tell()

    def seekable(self) -> bool:
        return True

    def close(self) -> None:
        self._file.close()


def test_skipped_chunks_and_their_message_indexes_are_stepped_over_unread(
    tmp_path, monkeypatch
) -> None:
    # a chunk iter_status skips is stepped over with its message indexes in one seek
    # (the summary's chunk index gives both lengths); only its 9-byte head is read (when
    # the read-ahead after the record before does not hold it already). A span that does
    # not match the head is read record by record, with the same rows.
    from imufdi_cli.mcapio import McapSource, iter_status

    path = tmp_path / "a.mcap"
    t_ns, det = _annotated(path)
    stream = _CountingFile(path)
    try:
        with McapSource(stream) as source:
            rows = list(iter_status(source))
            spans = dict(source._chunk_spans)
            skipped = sorted(source._skipped_chunks)
            read = stream.read_bytes
    finally:
        stream.close()
    assert sum(r[3]["t_ns"].size for r in rows) == t_ns.size
    skipped_bytes = sum(spans[c][0] + spans[c][1] for c in skipped)
    assert len(skipped) >= 100 and skipped_bytes > 0.5 * path.stat().st_size
    assert read < path.stat().st_size - 0.5 * skipped_bytes
    # spans the heads contradict (a stale or damaged index): read as any record
    with McapSource(path) as source:
        source._chunk_spans = {c: (n + 1, m) for c, (n, m) in source._chunk_spans.items()}
        wrong = list(iter_status(source))
        assert not source.warnings
    _assert_same_rows(wrong, rows)
    assert_array_equal(read_status(path)[("glt", "gyro")].scores, det.scores)
