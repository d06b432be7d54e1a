"""FaultEvent / FdiEvent channels: bulk encoding, decoding, and logs of older versions
(JSON event channels) still read and upgraded on pass-through."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio import (
    ImuArrayWriter,
    McapSource,
    McapWriter,
    read_events,
    read_json_topic,
    register_events_channel,
)
from imufdi_cli.mcapio.events import (
    EVENTS_TOPIC,
    TRUTH_TOPIC,
    decode_events,
    encode_fdi_event_dicts,
    encode_fdi_events,
)
from tests.cli.conftest import invoke
from tests.mcapio.conftest import make_block

IDS = ["imu0.gyro.x", "imu0.gyro.y", "imu10.gyro.z"]


def test_bulk_fdi_events_match_one_by_one_encoding() -> None:
    t_ns = np.array([-1_500_000_000, 5, 2_000_000_007, 3_000_000_000, 4_000_000_000])
    alarm = np.array([True, False, True, True, False])
    isolated = np.array([2, -1, -2, 0, 2])
    amplitude = np.array([0.5, np.nan, np.nan, -1e-3, 7.0])
    statistic = np.array([10.0, 1.0, 20.0, 30.0, 0.5])
    bulk = encode_fdi_events(
        3,
        t_ns,
        detector="glt",
        sensor_type="gyro",
        sensor_ids=IDS,
        alarm=alarm,
        isolated=isolated,
        amplitude=amplitude,
        statistic=statistic,
    )
    dicts = [
        {
            "detector": "glt",
            "sensor_type": "gyro",
            "event": "alarm_start" if a else "alarm_end",
            "t_ns": int(t),
            "isolated": IDS[i] if i >= 0 else None,
            "isolable": i != -2,
            "amplitude": None if math.isnan(amp) else float(amp),
            "statistic": float(s),
        }
        for t, a, i, amp, s in zip(t_ns, alarm, isolated, amplitude, statistic)
    ]
    single = encode_fdi_event_dicts(3, t_ns, dicts)
    assert [bulk.payload(i) for i in range(5)] == [single.payload(i) for i in range(5)]
    assert bulk.log_time.tolist() == t_ns.tolist()
    assert bulk.channel_id.tolist() == [3] * 5


def _legacy_log(path, tmp_path) -> None:
    """A log as imufdi wrote it before FaultEvent/FdiEvent: JSON truth and event channels."""
    block = make_block(300, 4)
    array = ArrayConfig.co_aligned(4, 100.0)
    t0 = int(block.t_ns[0])
    fault = {
        "id": "f0",
        "model": "step",
        "sensors": ["imu0.gyro.x"],
        "at_s": 1.0,
        "until_s": None,
        "params": {"amp": 0.2},
        "spec": "step:imu0.gyro.x,at=1s,amp=0.2rad/s",
    }
    with McapWriter(path) as writer:
        ImuArrayWriter(writer, array).write_block(block)
        writer.add_metadata(
            "imufdi.faults",
            {
                "json": json.dumps(
                    {"format": "imufdi.faults/1", "seed": 0, "t0_ns": t0, "faults": [fault]}
                )
            },
        )
        truth = writer.register_json_channel(TRUTH_TOPIC, "imufdi/FaultEvent")
        event = {"event": "start", "t_ns": t0 + 10**9, "t_s": 1.0, "fault_id": "f0"}
        writer.add_json(truth, t0 + 10**9, {**event, "fault": fault})
        events = writer.register_json_channel(EVENTS_TOPIC, "imufdi_msgs/FdiEvent")
        writer.add_json(
            events,
            t0 + 10**9,
            {
                "detector": "old-detector",
                "sensor_type": "gyro",
                "event": "alarm_start",
                "t_ns": t0 + 10**9,
                "isolated": "imu0.gyro.x",
                "isolable": True,
                "amplitude": 0.2,
                "statistic": 99.0,
            },
        )


def test_legacy_json_events_read_and_upgraded(tmp_path) -> None:
    old = tmp_path / "old.mcap"
    _legacy_log(old, tmp_path)
    ((_, truth),) = read_events(old, TRUTH_TOPIC)
    assert truth["fault"]["model"] == "step" and truth["event"] == "start"
    assert read_json_topic(old, TRUTH_TOPIC)[0][1] == truth
    with pytest.raises(KeyError):
        with AnyReader([old]) as reader:  # why the format changed: rosbags refuses JSON
            list(reader.messages())

    injected = tmp_path / "inj.mcap"
    fault = "drift:imu1.gyro.y,at=0.5s,until=2s,rate=1rad/s^2"
    result = invoke(["inject", old, "--fault", fault, "-o", injected])
    assert result.code == 0, result.stderr
    detected = tmp_path / "det.mcap"
    result = invoke(["detect", injected, "-d", "glt", "-o", detected])
    assert result.code == 0, result.stderr
    for path in (injected, detected):
        truth_events = [e for _, e in read_events(path, TRUTH_TOPIC)]
        assert sorted((e["fault_id"], e["event"]) for e in truth_events) == [
            ("f0", "start"),
            ("f1", "end"),
            ("f1", "start"),
        ]
        with McapSource(path) as src:
            for _ in src.batches():
                pass
            encodings = {c.topic: c.message_encoding for c in src.channels.values()}
        assert "json" not in encodings.values(), encodings
        with AnyReader([path]) as reader:  # now every message deserialises
            n = sum(1 for c, _, raw in reader.messages() if reader.deserialize(raw, c.msgtype))
            assert n == reader.message_count
    kept = [e for _, e in read_events(detected, EVENTS_TOPIC) if e["detector"] == "old-detector"]
    assert kept == [
        {
            "detector": "old-detector",
            "sensor_type": "gyro",
            "event": "alarm_start",
            "t_ns": kept[0]["t_ns"],
            "isolated": "imu0.gyro.x",
            "isolable": True,
            "amplitude": 0.2,
            "statistic": 99.0,
        }
    ]


def test_rerun_keeps_other_detectors_cdr_events(tmp_path) -> None:
    path = tmp_path / "a.mcap"
    block = make_block(50, 4)
    with McapWriter(path) as writer:
        ImuArrayWriter(writer, ArrayConfig.co_aligned(4, 100.0)).write_block(block)
        channel = register_events_channel(writer)
        for detector in ("glt", "bank"):
            writer.add_batch(
                encode_fdi_events(
                    channel,
                    block.t_ns[[3, 7]],
                    detector=detector,
                    sensor_type="gyro",
                    sensor_ids=IDS,
                    alarm=np.array([True, False]),
                    isolated=np.array([1, -1]),
                    amplitude=np.array([0.1, np.nan]),
                    statistic=np.array([5.0, 1.0]),
                )
            )
    out = tmp_path / "b.mcap"
    result = invoke(["detect", path, "-d", "glt", "-o", out, "--calibrate", "0s:0.2s"])
    assert result.code == 0, result.stderr
    events = [e for _, e in read_events(out, EVENTS_TOPIC)]
    bank = [e for e in events if e["detector"] == "bank"]
    assert [(e["event"], e["isolated"]) for e in bank] == [
        ("alarm_start", "imu0.gyro.y"),
        ("alarm_end", None),
    ]
    # the input's glt events are replaced by this run's
    assert not any(e["detector"] == "glt" and e["statistic"] == 5.0 for e in events)


def test_decode_events_refuses_other_channels(tmp_path) -> None:
    path = tmp_path / "a.mcap"
    with McapWriter(path) as writer:
        ImuArrayWriter(writer, ArrayConfig.co_aligned(2, 100.0)).write_block(make_block(5, 2))
    with McapSource(path) as src:
        batch = next(iter(src.batches()))
        channel = src.channels[int(batch.channel_id[0])]
        with pytest.raises(McapInputError, match="not an imufdi event channel"):
            decode_events(batch.select(batch.channel_id == channel.id), channel)


def test_episode_events_round_trip_with_undefined_numbers() -> None:
    """An episode whose alarms had no finite statistic (peak_ratio None) and no fit still
    encodes (the fuzz once found exit 4 here) and decodes to the same explanation."""
    from imufdi_cli.mcapio.events import encode_episode_events
    from imufdi_cli.mcapio.records import ChannelInfo, SchemaInfo
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA, FDI_EVENT_SCHEMA_NAME

    episode = {
        "detector": "glt",
        "sensor_type": "gyro",
        "start_ns": 10,
        "end_ns": 20,
        "decided_start_ns": 10,
        "decided_end_ns": 25,
        "alarms": 2,
        "sensors": [],
        "peak_ratio": None,
        "fits": [],
        "fault_class": None,
    }
    batch = encode_episode_events(1, [episode])
    schema = SchemaInfo(1, FDI_EVENT_SCHEMA_NAME, "ros2msg", FDI_EVENT_SCHEMA)
    channel = ChannelInfo(1, "/imufdi/events", "cdr", {}, schema)
    (event,) = decode_events(batch, channel)
    assert event["event"] == "episode" and event["t_ns"] == 25
    assert event["episode"] == episode
