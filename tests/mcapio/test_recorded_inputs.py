"""Logs as users record them, written by rosbags' own rosbag2 writer (an independent
writer): an Imu inside a driver's message, an Imu without a header, all-zero stamps, and a
rosbag2 directory split into several MCAP files."""

from __future__ import annotations

import functools
import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from imufdi_cli.errors import McapInputError
from imufdi_cli.mcapio import ImuArrayReader, McapSource, read_array, summarize
from imufdi_cli.mcapio.bagdir import bag_files
from tests.cli.conftest import assert_one_line_error, invoke
from tests.mcapio.mcap_files import ros2_imu_typestore

T0 = 1_700_000_000_000_000_000
PERIOD = 5_000_000  # 200 Hz
N = 400

VECTORNAV = """std_msgs/Header header
sensor_msgs/Imu imu
float64 temperature
string mode
"""
TWO_IMUS = "sensor_msgs/Imu left\nsensor_msgs/Imu right\n"
HEADERLESS_IMU = """geometry_msgs/Quaternion orientation
float64[9] orientation_covariance
geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance
geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance
"""


def _gyro(i: int, k: int = 0) -> tuple[float, float, float]:
    """Sample i of IMU k: a slow ramp plus a deterministic wiggle that differs per IMU."""
    wiggle = 1e-3 * np.sin(0.7 * i * (k + 1) + k)
    return (0.001 * i + wiggle, -0.5 - wiggle, 0.25 + 1e-4 * i + 2 * wiggle)


@functools.cache
def _typestore(headerless: bool = False):
    """The type store of the bags (made once: rosbags compiles a type's serialiser on its
    first use in a store; the tests only read the store)."""
    if headerless:  # a sensor_msgs/msg/Imu whose definition has no header (seen in real bags)
        store = get_typestore(Stores.EMPTY)
        store.register(
            get_types_from_msg(
                "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n", "geometry_msgs/msg/Quaternion"
            )
        )
        store.register(
            get_types_from_msg("float64 x\nfloat64 y\nfloat64 z\n", "geometry_msgs/msg/Vector3")
        )
        store.register(get_types_from_msg(HEADERLESS_IMU, "sensor_msgs/msg/Imu"))
        return store
    store = ros2_imu_typestore()
    store.register(get_types_from_msg(VECTORNAV, "custom_interfaces/msg/Vectornav"))
    store.register(get_types_from_msg(TWO_IMUS, "custom_interfaces/msg/StereoImu"))
    store.register(get_types_from_msg("string data\n", "custom_interfaces/msg/Text"))
    return store


def _imu(store, i: int, stamp_ns: int | None, k: int = 0):
    T = store.types
    vector = T["geometry_msgs/msg/Vector3"]
    fields = {
        "orientation": T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        "orientation_covariance": np.zeros(9),
        "angular_velocity": vector(*_gyro(i, k)),
        "angular_velocity_covariance": np.zeros(9),
        "linear_acceleration": vector(*(10 * w for w in _gyro(i, k + 5))),
        "linear_acceleration_covariance": np.zeros(9),
    }
    if stamp_ns is not None:
        fields["header"] = _header(store, stamp_ns)
    return T["sensor_msgs/msg/Imu"](**fields)


def _header(store, stamp_ns: int):
    T = store.types
    time = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=time, frame_id="vn100")


def write_bag(
    path: Path, kind: str, *, start: int = 0, stop: int = N, extra: bool = False, imus: int = 1
):
    """A rosbag2 directory (one MCAP file) of samples ``start..stop`` of ``imus`` topics."""
    store = _typestore(headerless=kind == "headerless")
    shutil.rmtree(path, ignore_errors=True)
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        if extra:  # shifts the channel ids of the topics below
            text = writer.add_connection("/status", "custom_interfaces/msg/Text", typestore=store)
            writer.write(
                text,
                T0,
                store.serialize_cdr(
                    store.types["custom_interfaces/msg/Text"](data="ok"),
                    "custom_interfaces/msg/Text",
                ),
            )
        msgtype = {
            "vectornav": "custom_interfaces/msg/Vectornav",
            "stereo": "custom_interfaces/msg/StereoImu",
        }.get(kind, "sensor_msgs/msg/Imu")
        topics = ["/vectornav/imu" if kind == "vectornav" else "/imu"]
        if imus > 1:
            topics = [f"/vn{k}/imu" for k in range(imus)]
        connections = [writer.add_connection(t, msgtype, typestore=store) for t in topics]
        for i in range(start, stop):
            t = T0 + i * PERIOD
            if kind == "vectornav":
                for k, connection in enumerate(connections):
                    msg = store.types[msgtype](
                        header=_header(store, t),
                        imu=_imu(store, i, t, k),
                        temperature=20.0,
                        mode="x" * (i % 3),
                    )
                    writer.write(connection, t, store.serialize_cdr(msg, msgtype))
                continue
            elif kind == "stereo":
                msg = store.types[msgtype](left=_imu(store, i, t), right=_imu(store, i, t))
            elif kind == "headerless":
                msg = _imu(store, i, None)
            else:  # zero stamps
                msg = _imu(store, i, 0)
            writer.write(connections[0], t, store.serialize_cdr(msg, msgtype))
    return path


def split_bag(path: Path, kind: str = "vectornav", imus: int = 1) -> Path:
    """One rosbag2 directory whose metadata.yaml lists two MCAP files (as a bag split by
    size), the second with different channel and schema ids."""
    first = write_bag(path.parent / "part0", kind, stop=N // 2, imus=imus)
    second = write_bag(path.parent / "part1", kind, start=N // 2, extra=True, imus=imus)
    path.mkdir()
    shutil.copy(first / "part0.mcap", path / "rec_0.mcap")
    shutil.copy(second / "part1.mcap", path / "rec_1.mcap")
    meta = (first / "metadata.yaml").read_text()
    meta = meta.replace("  - part0.mcap\n", "  - rec_0.mcap\n  - rec_1.mcap\n")
    (path / "metadata.yaml").write_text(meta)
    return path


def _expected_gyro(start: int = 0, stop: int = N) -> np.ndarray:
    return np.array([_gyro(i) for i in range(start, stop)])


def test_imu_inside_a_driver_message(tmp_path) -> None:
    bag = write_bag(tmp_path / "vn", "vectornav")
    with ImuArrayReader(bag) as reader:
        assert reader.imu_topics == ["/vectornav/imu"]
        assert reader.imu_fields == {"/vectornav/imu": "imu"}
        assert reader.time_source == "header"
        array, block = read_array(bag)
    np.testing.assert_array_equal(block.gyro[:, 0], _expected_gyro())
    assert block.t_ns.tolist() == [T0 + i * PERIOD for i in range(N)]
    assert array.rate_hz == pytest.approx(200.0)
    _, explicit = read_array(bag, topics=["/vectornav/imu:imu"])
    np.testing.assert_array_equal(explicit.gyro, block.gyro)
    with pytest.raises(
        McapInputError,
        match=r"custom_interfaces/msg/Vectornav.*no sensor_msgs/msg/Imu field 'bogus'",
    ):
        ImuArrayReader(bag, topics=["/vectornav/imu:bogus"])


def test_type_with_two_imus_needs_a_field(tmp_path) -> None:
    bag = write_bag(tmp_path / "stereo", "stereo")
    with pytest.raises(McapInputError, match=r"no sensor_msgs/msg/Imu channel.*StereoImu"):
        ImuArrayReader(bag)
    with pytest.raises(
        McapInputError,
        match=r"holds 2 sensor_msgs/msg/Imu fields \(left, right\); choose one with --topic /imu:left",
    ):
        ImuArrayReader(bag, topics=["/imu"])
    _, block = read_array(bag, topics=["/imu:right"])
    np.testing.assert_array_equal(block.gyro[:, 0], _expected_gyro())


def test_unusable_topic_error_names_its_type(tmp_path, cli=invoke) -> None:
    bag = write_bag(tmp_path / "vn", "vectornav", extra=True)
    result = cli(["info", bag, "--topic", "/status"])
    assert_one_line_error(result, 3, "/status has type custom_interfaces/msg/Text")


@pytest.mark.parametrize("kind", ["headerless", "zero"])
def test_no_header_stamps_fall_back_to_log_time(tmp_path, kind) -> None:
    bag = write_bag(tmp_path / kind, kind)
    with ImuArrayReader(bag) as reader:
        assert reader.time_source == "log_time"
        assert any("using the log time" in w for w in reader.warnings)
        block = next(iter(reader.blocks()))
    assert block.t_ns.tolist() == [T0 + i * PERIOD for i in range(N)]
    np.testing.assert_array_equal(block.gyro[:, 0], _expected_gyro())
    with pytest.raises(McapInputError, match="use --stamps log"):
        ImuArrayReader(bag, time_source="header")
    result = invoke(["info", bag, "--stamps", "header"])
    assert_one_line_error(result, 3, "--stamps log")
    result = invoke(["info", bag, "--stamps", "log", "--json"])
    assert result.code == 0, result.stderr
    assert "using the log time" not in result.stderr
    result = invoke(["info", bag])
    assert result.code == 0 and "using the log time" in result.stderr


def test_split_bag_directory_is_one_log(tmp_path) -> None:
    bag = split_bag(tmp_path / "rec")
    assert [f.name for f in bag_files(bag)] == ["rec_0.mcap", "rec_1.mcap"]
    assert [f.name for f in bag_files(bag / "metadata.yaml")] == ["rec_0.mcap", "rec_1.mcap"]
    with McapSource(bag) as src:
        topics = {c.id: c.topic for c in src.channels.values()}
        assert sorted(topics.values()) == ["/status", "/vectornav/imu"]
        assert src.summary_channel_counts is not None
        counts = {topics[c]: n for c, n in src.summary_channel_counts.items()}
        assert counts == {"/vectornav/imu": N, "/status": 1}
    _, block = read_array(bag)
    np.testing.assert_array_equal(block.gyro[:, 0], _expected_gyro())
    with McapSource(bag, read_ahead=True, validate_crcs=False) as src:  # options reach parts
        assert src.read_ahead and not src.validate_crcs
        assert all(p.read_ahead and not p.validate_crcs for p in src._parts)
        assert sum(len(b) for b in src.batches()) == N + 1
        src._problem("a problem after reading")  # reported as in any source
        assert src.warnings[-1] == "a problem after reading"
    summary = summarize(bag)
    assert (
        summary.n_samples == N
        and summary.stats is not None
        and summary.stats.gaps == {"/vectornav/imu": 0}
    )


def test_every_command_reads_a_split_bag(tmp_path) -> None:
    bag = split_bag(tmp_path / "rec", imus=4)
    faulty = tmp_path / "faulty.mcap"
    result = invoke(["inject", bag, "--fault", "step:imu0.gyro.x,at=1s,amp=0.5rad/s", "-o", faulty])
    assert result.code == 0, result.stderr
    detected = tmp_path / "detected.mcap"
    result = invoke(["detect", faulty, "-d", "glt", "-o", detected, "--calibrate", "0s:0.5s"])
    assert result.code == 0, result.stderr
    result = invoke(
        ["detect", bag, "-d", "glt", "-o", tmp_path / "d2.mcap", "--calibrate", "0s:0.5s"]
    )
    assert result.code == 0, result.stderr
    # the fault lands in the embedded Imu, read back by rosbags
    gyro = []
    with AnyReader([faulty]) as reader:
        for connection, _, raw in reader.messages():
            if connection.topic == "/vn0/imu":
                msg = reader.deserialize(raw, connection.msgtype)
                gyro.append(msg.imu.angular_velocity.x)
                assert msg.mode in ("", "x", "xx")  # the rest of the message is intact
    expected = _expected_gyro()[:, 0] + np.where(np.arange(N) * PERIOD >= 10**9, 0.5, 0.0)
    np.testing.assert_allclose(gyro, expected, rtol=0, atol=1e-15)
    assert invoke(["info", bag]).code == 0
    report = invoke(["report", detected, "--json", "-"])
    assert report.code == 0, report.stderr
    assert '"detector": "glt"' in report.out


WBAG = Path(__file__).parent / "data" / "rosbag2_wbag"


def test_real_rosbag2_split_directory() -> None:
    """A bag split into 5 files by rosbag2 itself (tests/mcapio/data/rosbag2_wbag/README.md):
    every message of every file, in order, as rosbags reads the directory."""
    ours: dict[str, list[bytes]] = {}
    with McapSource(WBAG, strict=True) as src:
        assert [f.name for f in src.files] == [f"wbag_{k}.mcap" for k in range(5)]
        for batch in src.batches():
            for i in range(len(batch)):
                ours.setdefault(src.channels[int(batch.channel_id[i])].topic, []).append(
                    batch.payload(i)
                )
        assert src.warnings == []
    theirs: dict[str, list[bytes]] = {}
    with AnyReader([WBAG]) as reader:
        for connection, _, raw in reader.messages():
            theirs.setdefault(connection.topic, []).append(bytes(raw))
    assert {t: len(v) for t, v in ours.items()} == {t: len(v) for t, v in theirs.items()}
    assert sum(len(v) for v in ours.values()) == 6074  # message_count in metadata.yaml
    for topic in theirs:
        assert sorted(ours[topic]) == sorted(theirs[topic])


def test_real_bag_without_imu_is_refused_naming_its_types() -> None:
    result = invoke(["info", WBAG])
    assert_one_line_error(result, 3, "AAA (std_msgs/msg/String)")


def test_metadata_yaml_forms_and_refusals(tmp_path) -> None:
    bag = write_bag(tmp_path / "one", "vectornav")
    meta = bag / "metadata.yaml"
    text = meta.read_text()
    # flow sequence, quoted names
    meta.write_text(
        text.replace(
            "  relative_file_paths:\n  - one.mcap\n", "  relative_file_paths: ['one.mcap']\n"
        )
    )
    assert [f.name for f in bag_files(bag)] == ["one.mcap"]
    meta.write_text(text.replace("storage_identifier: mcap", "storage_identifier: sqlite3"))
    with pytest.raises(McapInputError, match="storage 'sqlite3' is not supported"):
        bag_files(bag)
    meta.write_text(text.replace("compression_mode: ''", "compression_mode: FILE"))
    with pytest.raises(McapInputError, match="whole-file compressed"):
        bag_files(bag)
    meta.write_text(text.replace("  - one.mcap\n", "  - one.mcap\n  - two.mcap\n"))
    result = invoke(["info", bag])
    assert_one_line_error(result, 3, "two.mcap, listed in metadata.yaml, is missing")
    # a listed file that exists but is no file: said so, not "missing"
    two = bag / "two.mcap"
    for make, said in (
        (lambda: two.mkdir(), "is a directory, not an MCAP file"),
        (lambda: two.symlink_to(two), "is a symlink loop"),
        (lambda: two.symlink_to(bag / "gone.mcap"), "is a symlink to"),
    ):
        make()
        result = invoke(["info", bag])
        assert_one_line_error(result, 3, f"two.mcap, listed in metadata.yaml, {said}")
        two.rmdir() if two.is_dir() and not two.is_symlink() else two.unlink()
    (tmp_path / "plain").mkdir()
    assert_one_line_error(invoke(["info", tmp_path / "plain"]), 3, "not a regular file")


def test_inject_and_detect_take_topic_fields_and_stamps(tmp_path) -> None:
    bag = write_bag(tmp_path / "vn", "vectornav", imus=4)
    out = tmp_path / "f.mcap"
    spec = "step:imu1.gyro.z,at=0.5s,amp=0.1rad/s"
    topics = [a for k in (3, 1, 0, 2) for a in ("--topic", f"/vn{k}/imu:imu")]
    result = invoke(["inject", bag, "--fault", spec, *topics, "--stamps", "header", "-o", out])
    assert result.code == 0, result.stderr
    _, block = read_array(out, topics=[f"/vn{k}/imu" for k in (3, 1, 0, 2)])
    _, before = read_array(bag, topics=[f"/vn{k}/imu" for k in (3, 1, 0, 2)])
    changed = np.flatnonzero(np.any(block.gyro != before.gyro, axis=2).any(axis=0))
    assert changed.tolist() == [1]  # imu1 = the 2nd topic given, /vn1/imu
    bad = invoke(["inject", bag, "--fault", spec, "--topic", "/vn0/imu:nope", "-o", out])
    assert_one_line_error(bad, 3, "custom_interfaces/msg/Vectornav")
    det = tmp_path / "d.mcap"
    result = invoke(["detect", bag, "-d", "glt", *topics, "--stamps", "log", "-o", det])
    assert result.code == 0, result.stderr
    bad = invoke(["detect", bag, "-d", "glt", "--topic", "/nope", "-o", det])
    assert_one_line_error(bad, 3, "/nope")
