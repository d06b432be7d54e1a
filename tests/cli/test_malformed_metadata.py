"""Malformed imufdi.* metadata records and array files: one line and exit 3 (or 2 for a
user's array file), a warning where the record is only descriptive; never exit 4, never
a RecursionError, inputs unchanged."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from tests.cli.conftest import assert_one_line_error

DEEP = "[" * 100_000 + "]" * 100_000
HOSTILE = {"null": "null", "list": "[]", "number": "5", "string": '"x"', "deep": DEEP}
FAULT = "step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"


@pytest.fixture(scope="module")
def detected_log(tmp_path_factory) -> Path:
    """A small detected log with truth (4 IMUs, 3 s): every record these tests break."""
    from tests.cli.conftest import invoke

    base = tmp_path_factory.mktemp("meta")
    steps = [
        ["simulate", "--imus", "4", "--duration", "3s", "-o", base / "a.mcap"],
        ["inject", base / "a.mcap", "--fault", FAULT, "-o", base / "f.mcap"],
        ["detect", base / "f.mcap", "-d", "glt", "--no-explain", "-o", base / "d.mcap"],
    ]
    for argv in steps:
        made = invoke(argv)
        assert made.code == 0, made.stderr
    return base / "d.mcap"


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def with_record(source: Path, target: Path, name: str, text: str | None) -> Path:
    """A copy of ``source`` (through the mcap package) whose metadata record ``name``
    holds ``{"json": text}`` (None: ``{"other": "x"}``, no ``json`` entry)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(source, "rb") as stream, open(target, "wb") as out:
        reader = make_reader(stream)
        writer = Writer(out)
        writer.start("ros2", "test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages():
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time
            )
        for record in reader.iter_metadata():
            if record.name != name:
                writer.add_metadata(record.name, record.metadata)
        writer.add_metadata(name, {"json": text} if text is not None else {"other": "x"})
        writer.finish()
    return target


def _argv(command: str, log: Path, out: Path) -> list:
    if command == "inject":
        return ["inject", log, "--fault", FAULT, "-o", out / "o.mcap"]
    if command == "detect":
        return ["detect", log, "-d", "glt", "--no-explain", "-o", out / "o.mcap"]
    if command == "calibrate":
        return ["calibrate", log, "--min-static", "1s", "-o", out / "o.toml"]
    return [command, log]


@pytest.mark.parametrize("value", ["null", "string", "deep"])  # the others: tests/test_metadata.py
@pytest.mark.parametrize(
    ("record", "command"),
    [
        ("imufdi.faults", "info"),
        ("imufdi.faults", "report"),
        ("imufdi.faults", "inject"),
        ("imufdi.detect.glt", "info"),
        ("imufdi.detect.glt", "report"),
    ],
)
def test_a_malformed_record_is_bad_input_naming_it(
    cli, detected_log, tmp_path, record, command, value
):
    log = with_record(detected_log, tmp_path / "m.mcap", record, HOSTILE[value])
    before = sha(log)
    out = tmp_path / "out"
    out.mkdir()
    result = cli(_argv(command, log, out))
    assert_one_line_error(result, 3, f"{record} metadata: ")
    if value == "deep":
        assert "nested 100000 levels deep" in result.stderr
    assert sha(log) == before
    assert list(out.iterdir()) == []


@pytest.mark.parametrize("value", ["list", "deep"])
@pytest.mark.parametrize("command", ["info", "detect", "inject", "calibrate"])
def test_a_malformed_array_record_is_a_warning_and_the_array_is_inferred(
    cli, detected_log, tmp_path, command, value
):
    log = with_record(detected_log, tmp_path / "m.mcap", "imufdi.array", HOSTILE[value])
    out = tmp_path / "out"
    out.mkdir()
    result = cli(_argv(command, log, out))
    assert "Traceback" not in result.stderr and result.code in (0, 3), result.stderr
    if result.code == 3:  # calibrate: the short log has no static interval; still one line
        assert command == "calibrate"
        assert_one_line_error(result, 3, "static interval")
    else:
        assert "warning: imufdi.array metadata: " in result.stderr
        assert "the array is inferred from the topics" in result.stderr


@pytest.mark.parametrize("value", ["number", "deep"])
def test_a_malformed_ingest_record_is_a_warning_in_info(cli, detected_log, tmp_path, value):
    log = with_record(detected_log, tmp_path / "m.mcap", "imufdi.ingest", HOSTILE[value])
    result = cli(["info", log])
    assert result.code == 0, result.stderr
    assert "warning: imufdi.ingest metadata: " in result.stderr


@pytest.mark.parametrize("command", ["info", "report", "inject"])
def test_a_faults_record_without_json_is_bad_input(cli, detected_log, tmp_path, command):
    log = with_record(detected_log, tmp_path / "m.mcap", "imufdi.faults", None)
    out = tmp_path / "out"
    out.mkdir()
    result = cli(_argv(command, log, out))
    assert_one_line_error(result, 3, "imufdi.faults metadata has no 'json' entry")
    assert list(out.iterdir()) == []


def test_a_bad_fault_in_a_record_is_named(cli, detected_log, tmp_path):
    text = (
        '{"t0_ns": 1, "faults": [{"model": "step", "sensors": ["imu0.gyro.x"],'
        ' "at_s": "x", "params": {}}]}'
    )
    log = with_record(detected_log, tmp_path / "m.mcap", "imufdi.faults", text)
    result = cli(["report", log])
    assert_one_line_error(
        result, 3, "imufdi.faults metadata: faults[0].at_s: expected a finite number"
    )


# --- array files given by the user (exit 2: a usage error naming the key) ----------------


@pytest.mark.parametrize("value", ['"x"', "[1]", "{ a = 1 }"])
@pytest.mark.parametrize("command", ["detect", "ingest", "calibrate"])
def test_an_array_file_with_a_bad_rate_is_a_usage_error(cli, table4_log, tmp_path, command, value):
    array = tmp_path / "array.toml"
    array.write_text(f'rate_hz = {value}\n[[imu]]\ngyro_axes = "xyz"\n')
    capture = tmp_path / "c.bin"
    capture.write_bytes(b"\0" * 64)
    argv = {
        "detect": ["detect", table4_log, "-d", "glt", "--array", array, "-o", tmp_path / "o.mcap"],
        "ingest": ["ingest", capture, "--array", array, "-o", tmp_path / "o.mcap"],
        "calibrate": ["calibrate", table4_log, "--array", array, "-o", tmp_path / "o.toml"],
    }[command]
    result = cli(argv)
    assert_one_line_error(result, 2, "rate_hz")
    assert not (tmp_path / "o.mcap").exists() and not (tmp_path / "o.toml").exists()
