"""Every command's output, read by independent MCAP/ROS 2 readers (docs/testing.md).

The judges: the ``mcap`` package (indexed reader: summary, statistics, chunk, message and
metadata indexes, CRCs validated; and its streaming reader), rosbags ``AnyReader`` (every
message of every topic deserialised), mcap-ros2-support ``read_ros2_messages`` (every
message) and, when node and an installed @mcap/core are found, the TypeScript library
Foxglove uses. Counts and values are checked against what the commands wrote.
"""

from __future__ import annotations

import functools
import json
import math
import os
import shutil
import struct
import subprocess
import zlib
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Footer, Message
from mcap.stream_reader import StreamReader
from mcap_ros2.reader import read_ros2_messages
from rosbags.highlevel import AnyReader

from imufdi_cli.episodes import find_episodes
from imufdi_cli.mcapio import McapSource, decode_imu, read_events, read_status
from tests.cli.conftest import invoke

N_IMUS = 8  # the preset with --imus 8 (of 16): the same records, half the messages to decode
N_SAMPLES = 200  # 2 s at 100 Hz
FAULTS = (
    "step:imu0.gyro.x,at=1.5s,amp=0.9deg/s",
    "drift:imu2.gyro.z,at=0.5s,until=1.2s,rate=2deg/s^2",
)
DETECTORS = ("glt", "pca-parity")
HERE = Path(__file__).parent


def _run(args: list[object], stdin: bytes = b"") -> bytes:
    result = invoke([str(a) for a in args], stdin=stdin)
    assert result.code == 0, result.stderr
    return result.stdout


@pytest.fixture(scope="module")
def outputs(tmp_path_factory) -> dict[str, Path]:
    """Outputs of simulate, ingest, inject and detect, each written to a file and to stdout."""
    d = tmp_path_factory.mktemp("independent")
    files: dict[str, Path] = {}

    def keep(name: str, data: bytes) -> None:
        files[name] = d / f"{name}.mcap"
        files[name].write_bytes(data)

    sim = d / "simulate.mcap"
    capture = d / "capture.bin"
    simulate = ["simulate", "--preset", "paper-table4", "--imus", N_IMUS, "--duration", "2s"]
    _run([*simulate, "--seed", 3, "-o", sim, "--capture", capture, "--corrupt"])
    files["simulate"] = sim
    keep("simulate-stdout", _run([*simulate, "--seed", 3, "-o", "-"]))
    files["ingest"] = d / "ingest.mcap"
    _run(["ingest", capture, "-o", files["ingest"]])
    keep("ingest-stdout", _run(["ingest", "-", "-o", "-"], stdin=capture.read_bytes()))
    faults = [a for f in FAULTS for a in ("--fault", f)]
    files["inject"] = d / "inject.mcap"
    _run(["inject", sim, *faults, "-o", files["inject"]])
    keep("inject-stdout", _run(["inject", "-", *faults, "-o", "-"], stdin=sim.read_bytes()))
    dets = [a for name in DETECTORS for a in ("-d", name)] + ["--calibrate", "0s:1s"]
    dets.append("--named-scores")  # the readers judge the companion topics too
    files["detect"] = d / "detect.mcap"
    _run(["detect", files["inject"], *dets, "-o", files["detect"]])
    keep(
        "detect-stdout",
        _run(["detect", "-", *dets, "-o", "-"], stdin=files["inject-stdout"].read_bytes()),
    )
    # detect on an ingested log (device-time stamps, lost frames)
    files["detect-ingest"] = d / "detect-ingest.mcap"
    _run(
        [
            "detect",
            files["ingest"],
            "-d",
            "glt",
            "--calibrate",
            "0s:1s",
            "--named-scores",
            "-o",
            files["detect-ingest"],
        ]
    )
    # flight-controller logs: a PX4 ULog (3 IMUs, separate accel and gyro topics, GPS
    # time) and an ArduPilot DataFlash log (2 IMUs)
    from tests.capture.fclog_files import (
        ap_imu_messages,
        dataflash_bytes,
        px4_imu_samples,
        ulog_bytes,
    )

    rng = np.random.default_rng(2)
    t_us = 5_000_000 + np.arange(N_SAMPLES, dtype=np.int64) * 5000
    gyro, accel = rng.normal(0, 0.01, (N_SAMPLES, 3, 3)), rng.normal(0, 0.1, (N_SAMPLES, 3, 3))
    gps = [
        (
            "vehicle_gps_position",
            0,
            {"timestamp": 5_000_000, "time_utc_usec": 1_700_000_000_000_000},
        )
    ]
    samples = px4_imu_samples(t_us, gyro, accel, offsets_us=(0, 120, 450)) + gps
    ulog = d / "flight.ulg"
    ulog.write_bytes(
        ulog_bytes(sorted(samples, key=lambda s: s[2].get("timestamp_sample", s[2]["timestamp"])))
    )
    files["ingest-ulog"] = d / "ingest-ulog.mcap"
    _run(["ingest", ulog, "-o", files["ingest-ulog"]])
    dataflash = d / "flight.bin"
    dataflash.write_bytes(dataflash_bytes(ap_imu_messages(t_us, gyro[:, :2], accel[:, :2])))
    keep("ingest-dataflash-stdout", _run(["ingest", "-", "-o", "-"], stdin=dataflash.read_bytes()))
    return files


ALL = [
    "simulate",
    "simulate-stdout",
    "ingest",
    "ingest-stdout",
    "inject",
    "inject-stdout",
    "detect",
    "detect-stdout",
    "detect-ingest",
    "ingest-ulog",
    "ingest-dataflash-stdout",
]


@functools.cache
def _ours(path: Path) -> tuple[Counter[str], dict[str, dict[str, str]], dict[str, list[bytes]]]:
    """Per-topic message counts, metadata and payloads as imufdi's own reader sees them
    (read once per output file; the tests only compare them)."""
    counts: Counter[str] = Counter()
    payloads: dict[str, list[bytes]] = {}
    with McapSource(path, strict=True) as src:
        for batch in src.batches():
            data = batch.data.tobytes()  # payloads sliced in Python, not one array each
            for cid, index in batch.channel_indices():
                topic = src.channels[cid].topic
                counts[topic] += len(index)
                payloads.setdefault(topic, []).extend(
                    data[start : start + length]
                    for start, length in zip(
                        batch.offset[index].tolist(), batch.length[index].tolist()
                    )
                )
        return counts, dict(src.metadata), payloads


def _episode_count(alarm: np.ndarray, isolated: np.ndarray) -> int:
    """Episodes as docs/episodes.md defines them, from a status's rows at 100 Hz: alarm
    runs merged across gaps of up to 0.1 s (10 rows); a run is joined to the previous
    episode of the sensor it isolated most often (lowest index on a tie) when at most
    1 s (100 quiet rows) separates them; a run that isolated no sensor stands alone."""
    count = 0
    last_alarm: dict[int, int] = {}  # sensor -> last alarmed row of its latest episode
    for start, stop in find_episodes(alarm, merge_gap=10):
        rows = isolated[start:stop][alarm[start:stop]]
        rows = rows[rows >= 0]
        if rows.size == 0:
            count += 1
            continue
        sensor = int(np.argmax(np.bincount(rows)))
        if sensor not in last_alarm or start - last_alarm[sensor] - 1 > 100:
            count += 1  # a new episode (else a fragment of the sensor's last one)
        last_alarm[sensor] = stop - 1
    return count


def _expected_counts(name: str, path: Path) -> Counter[str]:
    """What the command was asked to write, from its inputs (not from the file's index)."""
    imu = {f"/imu{k}/data_raw": N_SAMPLES for k in range(N_IMUS)}
    if name.startswith(("ingest-ulog", "ingest-dataflash")):
        with McapSource(path) as src:
            record = json.loads(src.metadata["imufdi.ingest"]["json"])
        n = record["alignment"]["samples"]
        assert n == N_SAMPLES  # every sample of every IMU became an array sample
        return Counter({f"/imu{k}/data_raw": n for k in range(record["n_imus"])})
    if name.startswith(("ingest", "detect-ingest")):
        with McapSource(path) as src:
            frames = json.loads(src.metadata["imufdi.ingest"]["json"])["stats"]["frames_ok"]
        imu = {t: frames for t in imu}
    counts = Counter(imu)
    if name.startswith(("inject", "detect")) and name != "detect-ingest":
        counts["/imufdi/truth"] = 3  # step: start; drift: start and end
    if name.startswith("detect"):
        n = imu["/imu0/data_raw"]
        status = read_status(path)
        transitions = 0
        for (detector, sensor_type), arrays in status.items():
            counts[f"/imufdi/{detector}/{sensor_type}"] = n
            counts[f"/imufdi/{detector}/{sensor_type}/scores"] = n  # the named scores
            alarm = arrays.alarm.astype(np.int8)
            transitions += int(np.count_nonzero(np.diff(np.concatenate([[0], alarm]))))
            # plus one explained "episode" event per alarm episode
            transitions += _episode_count(arrays.alarm, arrays.isolated)
        if transitions:
            counts["/imufdi/events"] = transitions
    return counts


EXPECTED_METADATA = {
    "simulate": {"imufdi.array", "imufdi.simulate"},
    "ingest": {"imufdi.array", "imufdi.ingest"},
    "inject": {"imufdi.array", "imufdi.simulate", "imufdi.faults"},
    "detect": {
        "imufdi.array",
        "imufdi.simulate",
        "imufdi.faults",
        "imufdi.detect.glt",
        "imufdi.detect.pca-parity",
    },
    "detect-ingest": {"imufdi.array", "imufdi.ingest", "imufdi.detect.glt"},
    "ingest-ulog": {"imufdi.array", "imufdi.ingest"},
    "ingest-dataflash": {"imufdi.array", "imufdi.ingest"},
}


def _base(name: str) -> str:
    return name.removesuffix("-stdout")


# The deserialising readers (rosbags, mcap-ros2-support) decode every message in Python, about
# 0.3 s per file: the default run gives them one file per writer path (file and stdout, each
# command's topics: the same four as the TypeScript reader), the slow run every output.
REPRESENTATIVE = ["simulate", "ingest-stdout", "inject", "detect-stdout"]
SOME = [n if n in REPRESENTATIVE else pytest.param(n, marks=pytest.mark.slow) for n in ALL]


@pytest.mark.parametrize("name", ALL)
def test_mcap_package_indexed_reader(outputs, name) -> None:
    path = outputs[name]
    raw = path.read_bytes()
    counts, metadata, payloads = _ours(path)
    assert counts == _expected_counts(name, path)
    assert set(metadata) == EXPECTED_METADATA[_base(name)]
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        stats = summary.statistics
        topic_of = {cid: ch.topic for cid, ch in summary.channels.items()}
        assert stats.message_count == sum(counts.values())
        assert {topic_of[c]: n for c, n in stats.channel_message_counts.items()} == counts
        assert stats.metadata_count == len(metadata)
        assert stats.chunk_count == len(summary.chunk_indexes) > 0
        # every index entry points at the record it names
        for index in summary.chunk_indexes:
            assert raw[index.chunk_start_offset] == 0x06
            for offset in index.message_index_offsets.values():
                assert raw[offset] == 0x07
        assert [raw[m.offset] for m in summary.metadata_indexes] == [0x0C] * len(metadata)
        found = {m.name: m.metadata for m in reader.iter_metadata()}
        assert found == metadata
        by_topic: dict[str, list[bytes]] = {}
        for _, channel, message in reader.iter_messages(log_time_order=False):
            by_topic.setdefault(channel.topic, []).append(message.data)
        assert by_topic == payloads


@pytest.mark.parametrize("name", ALL)
def test_mcap_package_stream_reader_crcs(outputs, name) -> None:
    path = outputs[name]
    counts, _, _ = _ours(path)
    with open(path, "rb") as stream:
        records = list(StreamReader(stream, validate_crcs=True).records)
    n_messages = sum(isinstance(r, Message) for r in records)
    assert n_messages == sum(counts.values())
    assert isinstance(records[-1], Footer)
    # the summary CRC in the footer covers the summary section and the footer's head
    raw = path.read_bytes()
    footer_start = len(raw) - 8 - 29
    summary_start, _, crc = struct.unpack("<QQI", raw[footer_start + 9 : footer_start + 29])
    assert crc == zlib.crc32(raw[summary_start : footer_start + 25])


@pytest.mark.parametrize("name", SOME)
def test_rosbags_any_reader(outputs, name) -> None:
    path = outputs[name]
    counts, _, _ = _ours(path)
    gyro: dict[str, list[tuple[float, float, float]]] = {}
    seen: Counter[str] = Counter()
    truth = []
    named: dict[str, list] = {}
    with AnyReader([path]) as reader:
        assert reader.message_count == sum(counts.values())
        for connection, _, rawdata in reader.messages():
            msg = reader.deserialize(rawdata, connection.msgtype)
            seen[connection.topic] += 1
            if connection.msgtype == "sensor_msgs/msg/Imu":
                v = msg.angular_velocity
                gyro.setdefault(connection.topic, []).append((v.x, v.y, v.z))
            elif connection.topic == "/imufdi/truth":
                truth.append(msg)
            elif connection.topic.endswith("/scores"):
                named.setdefault(connection.topic, []).append(msg)
    assert seen == counts
    # the named scores: one field per sensor, the status channel's scores in id order
    status = read_status(path) if named else {}
    for topic, messages in named.items():
        detector, sensor_type = topic.split("/")[2:4]
        arrays = status[(detector, sensor_type)]
        fields = [sid.replace(".", "_") for sid in arrays.sensor_ids]
        values = np.array([[getattr(m, f) for f in fields] for m in messages])
        np.testing.assert_array_equal(values, arrays.scores)
        stamps = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in messages]
        np.testing.assert_array_equal(stamps, arrays.t_ns)
    with McapSource(path) as src:
        channels = {c.topic: c for c in src.channels.values()}
        for batch in src.batches():
            for topic, values in gyro.items():
                sub = batch.select(batch.channel_id == channels[topic].id)
                if len(sub):
                    ours = decode_imu(sub, channels[topic]).gyro
                    np.testing.assert_array_equal(np.array(values[: len(sub)]), ours)
                    gyro[topic] = values[len(sub) :]
    assert all(not rest for rest in gyro.values())
    if "/imufdi/truth" in counts:
        marks = [(m.fault_id, m.event, m.model, list(m.sensors)) for m in truth]
        assert sorted(marks) == [
            ("f0", "start", "step", ["imu0.gyro.x"]),
            ("f1", "end", "drift", ["imu2.gyro.z"]),
            ("f1", "start", "drift", ["imu2.gyro.z"]),
        ]
        step = next(m for m in truth if m.model == "step")
        assert step.param_names == ["amp"]
        assert step.param_values[0] == pytest.approx(math.radians(0.9))
        assert math.isnan(step.until_s) and step.at_s == 1.5


@pytest.mark.parametrize("name", SOME)
def test_mcap_ros2_support(outputs, name) -> None:
    path = outputs[name]
    counts, _, _ = _ours(path)
    seen: Counter[str] = Counter()
    events = []
    for message in read_ros2_messages(str(path)):
        seen[message.channel.topic] += 1
        if message.channel.topic == "/imufdi/events":
            events.append(message)
    assert seen == counts
    if events:
        ours = read_events(path, "/imufdi/events")
        assert len(ours) == len(events)
        by_time = sorted(
            (
                m.log_time_ns,
                m.ros_msg.detector,
                m.ros_msg.event,
                m.ros_msg.header.stamp.sec * 1_000_000_000 + m.ros_msg.header.stamp.nanosec,
            )
            for m in events
        )
        assert by_time == sorted((t, e["detector"], e["event"], e["t_ns"]) for t, e in ours)
        # the typed episode fields (start_ns, end_ns) read as the explanation has them
        episodes = [m.ros_msg for m in events if m.ros_msg.event == "episode"]
        for msg in episodes:
            detail = json.loads(msg.detail)
            assert (msg.start_ns, msg.end_ns) == (detail["start_ns"], detail["end_ns"])
        assert episodes or not name.startswith("detect")  # detect explains its alarms


@pytest.fixture(scope="module")
def mcap_core_results(outputs) -> dict[str, dict] | str:
    """What @mcap/core reads in each representative output (``mcap_core_check.js``, one
    node process for all of them), or why it cannot run (no ``node``, or @mcap/core or
    fzstd not on NODE_PATH)."""
    node = shutil.which("node")
    if node is None:
        return "no `node` on PATH"
    paths = [str(outputs[name]) for name in REPRESENTATIVE]
    done = subprocess.run(
        [node, str(HERE / "mcap_core_check.js"), *paths],
        env=dict(os.environ),
        capture_output=True,
        check=False,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr.decode()
    found = json.loads(done.stdout)
    if "missing" in found:
        return str(found["missing"])
    return {name: found["results"][path] for name, path in zip(REPRESENTATIVE, paths)}


@pytest.mark.parametrize("name", REPRESENTATIVE)
def test_mcap_core_typescript(outputs, mcap_core_results, name) -> None:
    if isinstance(mcap_core_results, str):
        pytest.skip(
            f"@mcap/core check skipped ({mcap_core_results}): needs `node` and the npm packages"
            " @mcap/core and fzstd on NODE_PATH (e.g. npm install @mcap/core fzstd;"
            " NODE_PATH=.../node_modules)"
        )
    counts, metadata, _ = _ours(outputs[name])
    result = mcap_core_results[name]
    assert result["indexed"] == dict(counts)
    assert result["stream"] == dict(counts)
    assert result["statistics"] == sum(counts.values())
    assert sorted(result["metadata"]) == sorted(metadata)
