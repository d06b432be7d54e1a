"""imufdi info: summary, JSON, and bad input (exit 3, one line)."""

from __future__ import annotations

import json

from imufdi_cli.mcapio import McapWriter
from tests.cli.conftest import assert_one_line_error


def test_info_table_and_json(cli, table4_log):
    result = cli(["info", table4_log])
    assert result.code == 0, result.stderr
    assert "/imu15/data_raw" in result.out
    data = json.loads(cli(["info", table4_log, "--json"]).out)
    assert data["n_imus"] == 16
    assert abs(data["rate_hz"] - 100.0) < 1e-6
    assert abs(data["duration_s"] - 5.0) < 0.02


def test_info_shows_faults_and_detectors(cli, detected_log):
    data = json.loads(cli(["info", detected_log, "--json"]).out)
    assert data["faults"][0]["sensors"] == ["imu0.gyro.x"]
    assert "glt" in data["detectors"]


def test_missing_file(cli, tmp_path):
    assert_one_line_error(cli(["info", tmp_path / "nope.mcap"]), 3, "no such file")


def test_not_mcap(cli, tmp_path):
    path = tmp_path / "x.mcap"
    path.write_bytes(b"this is not an mcap file at all" * 10)
    assert_one_line_error(cli(["info", path]), 3, str(path))


def test_no_imu_channel(cli, tmp_path):
    path = tmp_path / "empty.mcap"
    with McapWriter(str(path)) as writer:
        channel = writer.register_json_channel("/other", "Other")
        writer.add_json(channel, 1, {"a": 1})
    assert_one_line_error(cli(["info", path]), 3, "Imu")


def test_truncated_warns_or_fails_with_strict(cli, tmp_path, table4_log):
    data = table4_log.read_bytes()
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[: len(data) * 2 // 3])
    result = cli(["info", path])
    assert result.code == 0, result.stderr
    assert "warning" in result.out.lower() or "warning" in result.stderr.lower()
    out = tmp_path / "d.mcap"
    assert_one_line_error(cli(["detect", path, "-d", "glt", "--strict", "-o", out]), 3, "truncated")
    assert not out.exists()


def _damaged_second_chunk(log) -> tuple[bytes, int]:
    """The log with one byte of its second chunk's compressed records altered."""
    data = bytearray(log.read_bytes())
    position, chunks = 8, []
    while data[position] != 0x0F:  # up to DataEnd
        length = int.from_bytes(data[position + 1 : position + 9], "little")
        chunks += [position] if data[position] == 0x06 else []
        position += 9 + length
    data[chunks[1] + 500] ^= 0x10
    return bytes(data), chunks[1]


def test_corrupt_chunk_is_skipped_with_its_offset_or_fails_with_strict(cli, tmp_path, table4_log):
    data, offset = _damaged_second_chunk(table4_log)
    path = tmp_path / "bad.mcap"
    path.write_bytes(data)
    result = cli(["info", path])
    assert result.code == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and f"chunk at byte {offset} skipped: " in warnings[0]
    assert_one_line_error(cli(["info", "--strict", "-"], stdin=data), 3, f"chunk at byte {offset}")


def test_info_shows_capture_losses_and_one_rate(cli, tmp_path):
    """A capture with lost frames: info shows the ingest counts, the gaps where every topic
    misses samples, and one rate saying how it was measured."""
    capture, log = tmp_path / "cap.bin", tmp_path / "cap.mcap"
    sim = ["simulate", "--preset", "paper-table4", "--imus", "4", "--duration", "3s"]
    assert cli([*sim, "-o", tmp_path / "s.mcap", "--capture", capture, "--corrupt"]).code == 0
    assert cli(["ingest", capture, "-o", log]).code == 0
    data = json.loads(cli(["info", log, "--json"]).out)
    ingest = data["ingest"]
    assert ingest["frames_lost"] > 0 and ingest["frames_bad_checksum"] > 0
    # every frame lost or dropped leaves a hole in all topics at once
    holes = ingest["frames_lost"] + ingest["frames_bad_checksum"] + ingest["frames_truncated"]
    assert 0 < data["gaps"]["missing_samples"] <= holes
    assert data["gaps"]["expected_samples"] == data["n_samples"] + data["gaps"]["missing_samples"]
    assert data["alignment"]["gaps"] == {f"/imu{k}/data_raw": 0 for k in range(4)}
    assert abs(data["rate_hz"] - 100.0) < 1e-6  # not (N - 1) / duration, which gaps bias
    assert "missing" in data["rate_method"] and "header stamps" in data["rate_method"]
    text = cli(["info", log]).out
    assert f"lost {ingest['frames_lost']}" in text
    assert f"{data['gaps']['missing_samples']} samples missing" in text
    assert text.count(" Hz") == 0  # one rate, in the rate_hz row
    assert "rate_hz" in text and "aligned samples" in text


def test_ingest_start_time_anchors_device_time(cli, tmp_path):
    capture = tmp_path / "cap.bin"
    sim = ["simulate", "--preset", "paper-table4", "--imus", "4", "--duration", "1s"]
    assert cli([*sim, "-o", tmp_path / "s.mcap", "--capture", capture]).code == 0
    device, anchored = tmp_path / "device.mcap", tmp_path / "anchored.mcap"
    assert cli(["ingest", capture, "-o", device]).code == 0
    assert (
        cli(["ingest", capture, "-o", anchored, "--start-time", "2024-05-01T12:00:00Z"]).code == 0
    )
    a = json.loads(cli(["info", device, "--json"]).out)
    b = json.loads(cli(["info", anchored, "--json"]).out)
    assert b["start_ns"] == 1_714_564_800_000_000_000
    assert a["start_ns"] < 10**18  # the device's clock: near the 1970 epoch
    assert b["duration_s"] == a["duration_s"] and b["n_samples"] == a["n_samples"]
    unix = tmp_path / "unix.mcap"
    assert cli(["ingest", capture, "-o", unix, "--start-time", "1714564800.5"]).code == 0
    assert json.loads(cli(["info", unix, "--json"]).out)["start_ns"] == 1_714_564_800_500_000_000
    result = cli(["ingest", capture, "-o", tmp_path / "x.mcap", "--start-time", "noon"])
    assert_one_line_error(result, 2, "--start-time")
    assert not (tmp_path / "x.mcap").exists()
