"""FaultEvent / FdiEvent channels: bulk encoding, decoding, and logs of older versions
(JSON event channels) still read and upgraded on pass-through."""

from __future__ import annotations

import json
import math
import struct

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


# --- episode events as report reads them (typed fields, JSON parsed on demand) ----------


def old_fdi_event_schema() -> bytes:
    """The FdiEvent schema text imufdi wrote before ``start_ns``/``end_ns`` were added."""
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA, SEPARATOR

    head, rest = FDI_EVENT_SCHEMA.split(b"int64 start_ns", 1)
    return head + rest[rest.index(b"\n" + SEPARATOR.encode()) :]


def old_fdi_payload(payload: bytes, event: dict) -> bytes:
    """``payload`` (this version's FdiEvent) in the layout before ``start_ns``/``end_ns``:
    the same bytes up to the end of ``detail``."""
    detail = (
        b""
        if event.get("episode") is None
        else json.dumps(event["episode"], allow_nan=False).encode()
    ) + b"\0"
    field = struct.pack("<I", len(detail)) + detail
    end = payload.rindex(field) + len(field)
    episode = event.get("episode") or {}
    tail = struct.pack("<2q", episode.get("start_ns", 0), episode.get("end_ns", 0))
    assert payload[end:] == b"\0" * ((4 - end) % 8) + tail  # padding, start_ns, end_ns
    return payload[:end]


def sample_episodes() -> list[dict]:
    """Explanations as detect writes them (Episode.to_dict), with the corner cases: no
    fit, no sensor, undefined interval, no finite statistic, a non-ASCII detector name."""
    from imufdi_cli.episodes import Episode, FaultFit

    rng = np.random.default_rng(5)
    out = []
    for k in range(40):
        fits = [
            FaultFit(
                str(model),
                float(rng.normal()),
                float(rng.normal()) - 3.0,
                float(rng.normal()) + 3.0 if k % 7 else math.inf,
                int(rng.integers(0, 50)),
                float(rng.normal(0, 100)),
                {"rate_hz": 1.5} if model == "spikes" else {},
            )
            for model in rng.choice(["step", "drift", "noise", "spikes", "stuck"], k % 3)
        ]
        start = 10**12 + int(rng.integers(0, 10**10))
        sensors = [] if k % 11 == 5 else [IDS[k % 3], IDS[(k + 1) % 3]][: 1 + k % 2]
        episode = Episode(
            detector="glt" if k % 5 else "détecteur",
            sensor_type="gyro",
            start_ns=start,
            end_ns=start + int(rng.integers(0, 10**9)),
            decided_start_ns=start + 5,
            decided_end_ns=start + 10**9 + 7,
            alarms=int(rng.integers(1, 100)),
            sensors=sensors,
            peak_ratio=float(rng.exponential(3.0)) if k % 13 else math.nan,
            runner_up=sensors[1] if len(sensors) > 1 else None,
            runner_up_share=0.25 if len(sensors) > 1 else None,
            fits=fits,
            amplitude=0.01 * k if k % 2 else None,
        )
        out.append(episode.to_dict())
    return out


def _fields(event) -> tuple:
    return (event.detector, *event.match_fields())


def _event_channel(schema: bytes):
    from imufdi_cli.mcapio.records import ChannelInfo, SchemaInfo
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA_NAME

    return ChannelInfo(
        1, EVENTS_TOPIC, "cdr", {}, SchemaInfo(1, FDI_EVENT_SCHEMA_NAME, "ros2msg", schema)
    )


def _mixed_batch(episodes: list[dict]):
    """Alarm starts and ends with episode events between them, one batch; and the event
    dicts they encode."""
    from imufdi_cli.mcapio.events import encode_episode_events
    from imufdi_cli.mcapio.records import MessageBatch

    alarms = encode_fdi_events(
        1,
        np.arange(len(episodes)) * 10,
        detector="glt",
        sensor_type="gyro",
        sensor_ids=IDS,
        alarm=np.arange(len(episodes)) % 2 == 0,
        isolated=np.arange(len(episodes)) % 4 - 2,
        amplitude=np.linspace(-1, 1, len(episodes)),
        statistic=np.linspace(0, 9, len(episodes)),
    )
    explained = encode_episode_events(1, episodes)
    payloads, times = [], []
    for i in range(len(episodes)):
        payloads += [alarms.payload(i), explained.payload(i)]
        times += [int(alarms.log_time[i]), int(explained.log_time[i])]
    return MessageBatch.from_payloads(1, np.array(times), payloads)


@pytest.fixture(params=["one by one", "with numpy"])
def walk(request, monkeypatch):
    """Both ways the walk reads the episodes' fields (a few per batch, or many)."""
    from imufdi_cli.mcapio import events

    monkeypatch.setattr(events, "_VECTOR_MIN", 10**9 if request.param == "one by one" else 1)
    return request.param


def test_episode_events_walked_as_decoded_in_full(walk) -> None:
    """The typed fields the report matches on, walked without decoding the alarms or the
    JSON, equal those of the full decode; the explanation parses back to the dict."""
    from imufdi_cli.mcapio.events import EpisodeEvent, decode_episode_events
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA

    episodes = sample_episodes()
    batch = _mixed_batch(episodes)
    channel = _event_channel(FDI_EVENT_SCHEMA)
    walked = decode_episode_events(batch, channel)
    full = [
        EpisodeEvent.from_explanation(e["episode"])
        for e in decode_events(batch, channel)
        if "episode" in e
    ]
    assert [_fields(e) for e in walked] == [_fields(e) for e in full]
    assert [e.explanation() for e in walked] == episodes
    assert any(e.low is None for e in walked) and any(e.fault_class is None for e in walked)
    assert any(e.isolated is None for e in walked) and walked[0].detector == "détecteur"
    # the typed fields are those of the explanation (what matching reads)
    firsts = [(e.get("sensors") or [None])[0] for e in episodes]
    assert [e.isolated for e in walked] == firsts
    assert [e.start_ns for e in walked] == [e["start_ns"] for e in episodes]
    assert [e.end_ns for e in walked] == [e["end_ns"] for e in episodes]


def test_episode_events_of_the_older_schema_give_the_same_fields(walk) -> None:
    """Files written before start_ns/end_ns (their own schema text in the file) decode in
    full and give the same fields and explanations."""
    from imufdi_cli.mcapio.events import decode_episode_events, is_current_fdi_channel
    from imufdi_cli.mcapio.records import MessageBatch
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA

    episodes = sample_episodes()
    batch = _mixed_batch(episodes)
    new = _event_channel(FDI_EVENT_SCHEMA)
    events = decode_events(batch, new)
    old_batch = MessageBatch.from_payloads(
        1, batch.log_time, [old_fdi_payload(batch.payload(i), e) for i, e in enumerate(events)]
    )
    old = _event_channel(old_fdi_event_schema())
    assert is_current_fdi_channel(new) and not is_current_fdi_channel(old)
    assert json.dumps(decode_events(old_batch, old)) == json.dumps(events)  # NaN-safe
    walked, decoded = decode_episode_events(batch, new), decode_episode_events(old_batch, old)
    assert [_fields(e) for e in decoded] == [_fields(e) for e in walked]
    assert [e.explanation() for e in decoded] == episodes


def _big_endian_fdi_event(episode: dict) -> bytes:
    """An ``episode`` FdiEvent in big-endian CDR (as another writer may produce it)."""
    body = bytearray()

    def prim(fmt: str, value) -> None:
        size = struct.calcsize(fmt)
        body.extend(b"\0" * ((-len(body)) % size))
        body.extend(struct.pack(">" + fmt, value))

    def string(text: str) -> None:
        raw = text.encode() + b"\0"
        prim("I", len(raw))
        body.extend(raw)

    fit = (episode.get("fits") or [{}])[0]
    prim("i", 1)
    prim("I", 2)
    for text in ("", episode["detector"], episode["sensor_type"], "episode"):
        string(text)
    string((episode.get("sensors") or [""])[0])
    prim("B", 1)
    prim("d", math.nan)
    prim("d", 1.0)
    string(fit.get("model", ""))
    string(fit.get("size_name", ""))
    for key in ("size", "low", "high"):
        prim("d", math.nan if fit.get(key) is None else fit[key])
    string(json.dumps(episode))
    prim("q", episode["start_ns"])
    prim("q", episode["end_ns"])
    return b"\x00\x00\x00\x00" + bytes(body)


def test_big_endian_episode_events_are_decoded_in_full(walk) -> None:
    from imufdi_cli.mcapio.events import decode_episode_events
    from imufdi_cli.mcapio.records import MessageBatch
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA

    episodes = sample_episodes()[:6]
    batch = MessageBatch.from_payloads(
        1, np.arange(6), [_big_endian_fdi_event(e) for e in episodes]
    )
    decoded = decode_episode_events(batch, _event_channel(FDI_EVENT_SCHEMA))
    assert [e.explanation() for e in decoded] == episodes
    assert [e.start_ns for e in decoded] == [e["start_ns"] for e in episodes]


def test_malformed_episode_events_are_input_errors(walk) -> None:
    from imufdi_cli.mcapio.events import decode_episode_events, encode_episode_events
    from imufdi_cli.mcapio.records import MessageBatch
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA

    channel = _event_channel(FDI_EVENT_SCHEMA)
    payload = encode_episode_events(1, sample_episodes()[:1]).payload(0)
    for cut in (3, 20, len(payload) // 2, len(payload) - 8):
        batch = MessageBatch.from_payloads(1, np.zeros(1), [payload[:cut]])
        with pytest.raises(McapInputError, match="malformed"):
            decode_episode_events(batch, channel)
    # a detail that is not JSON fails when it is needed (the listed episodes)
    at = payload.index(b'{"detector"')
    broken = payload[:at] + b"#" + payload[at + 1 :]
    (event,) = decode_episode_events(MessageBatch.from_payloads(1, np.zeros(1), [broken]), channel)
    with pytest.raises(McapInputError, match="malformed episode detail"):
        event.explanation()


def test_rerun_reencodes_events_of_the_older_schema(tmp_path) -> None:
    """``detect`` keeps the input's events of detectors it does not run again: those of
    the FdiEvent schema before start_ns/end_ns are re-encoded in this one (not copied as
    raw bytes under a schema they do not follow), and read as before."""
    from imufdi_cli.mcapio.events import decode_episode_events, encode_episode_events
    from imufdi_cli.mcapio.records import MessageBatch
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA, FDI_EVENT_SCHEMA_NAME

    path = tmp_path / "old.mcap"
    block = make_block(50, 4)
    episodes = [{**e, "detector": "bank"} for e in sample_episodes()[:8]]
    batch = _mixed_batch(episodes)
    events = decode_events(batch, _event_channel(FDI_EVENT_SCHEMA))
    with McapWriter(path) as writer:
        ImuArrayWriter(writer, ArrayConfig.co_aligned(4, 100.0)).write_block(block)
        schema = writer.register_schema(FDI_EVENT_SCHEMA_NAME, "ros2msg", old_fdi_event_schema())
        channel = writer.register_channel(EVENTS_TOPIC, "cdr", schema)
        payloads = [old_fdi_payload(batch.payload(i), e) for i, e in enumerate(events)]
        writer.add_batch(MessageBatch.from_payloads(channel, batch.log_time, payloads))
    before = [(t, e) for t, e in read_events(path, EVENTS_TOPIC) if e["detector"] != "glt"]
    assert len(before) == len(episodes)
    out = tmp_path / "new.mcap"
    result = invoke(["detect", path, "-d", "glt", "-o", out, "--calibrate", "0s:0.2s"])
    assert result.code == 0, result.stderr
    after = [(t, e) for t, e in read_events(out, EVENTS_TOPIC) if e["detector"] != "glt"]
    assert json.dumps(after) == json.dumps(before)
    with McapSource(out) as src:
        for _ in src.batches():
            pass
        (channel_info,) = [c for c in src.channels.values() if c.topic == EVENTS_TOPIC]
    assert channel_info.schema is not None and channel_info.schema.data == FDI_EVENT_SCHEMA
    kept = [e for _, e in read_events(out, EVENTS_TOPIC) if e["event"] == "episode"]
    assert [e["episode"] for e in kept if e["detector"] == "bank"] == episodes
    # and the report's walk reads the re-encoded ones
    reencoded = encode_episode_events(1, episodes)
    walked = decode_episode_events(reencoded, _event_channel(FDI_EVENT_SCHEMA))
    assert [e.start_ns for e in walked] == [e["start_ns"] for e in episodes]


def test_only_episode_events_with_an_explanation_are_episodes(walk) -> None:
    """The walk and the full decode agree on what an episode event is: event "episode"
    (trailing NULs stripped, as the decoder does) with a non-empty detail."""
    from imufdi_cli.mcapio.events import decode_episode_events, encode_fdi_event_dicts
    from imufdi_cli.mcapio.records import MessageBatch
    from imufdi_cli.mcapio.schemas import FDI_EVENT_SCHEMA

    episodes = sample_episodes()[:6]
    names = ["episode", "episode\0", "episodeX", "episod", "alarm_start", "episode"]
    events = [
        {
            "detector": e["detector"],
            "sensor_type": e["sensor_type"],
            "event": name,
            "t_ns": k,
            "isolated": (e["sensors"] or [None])[0],
            "episode": e,
        }
        for k, (name, e) in enumerate(zip(names, episodes))
    ]
    events[-1] = {**events[-1], "episode": None}  # no detail
    batch = encode_fdi_event_dicts(1, list(range(6)), events)
    new = decode_episode_events(batch, _event_channel(FDI_EVENT_SCHEMA))
    assert [e.explanation() for e in new] == episodes[:2]
    old_batch = MessageBatch.from_payloads(
        1, batch.log_time, [old_fdi_payload(batch.payload(i), e) for i, e in enumerate(events)]
    )
    old = decode_episode_events(old_batch, _event_channel(old_fdi_event_schema()))
    assert [_fields(e) for e in old] == [_fields(e) for e in new]
