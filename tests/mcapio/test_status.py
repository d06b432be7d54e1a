"""Detector status channels and JSON topics."""

from __future__ import annotations

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from numpy.testing import assert_array_equal

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
