"""imufdi detect: annotated output, pass-through, pipelines, bad parameters exit 2."""

from __future__ import annotations

import pytest

from imufdi_cli.mcapio import McapSource, read_status
from tests.cli.conftest import assert_one_line_error


def test_detect_writes_status_and_copies_input(cli, tmp_path, faulty_log):
    out = tmp_path / "d.mcap"
    # status and the copied input, not episodes: no explanation (tests/test_detect.py)
    args = ["detect", faulty_log, "-d", "glt", "-d", "pca-parity", "--no-explain"]
    result = cli([*args, "-o", out])
    assert result.code == 0, result.stderr
    status = read_status(str(out))
    assert {("glt", "gyro"), ("glt", "accel"), ("pca-parity", "gyro")} <= set(status)
    assert len(status[("glt", "gyro")].t_ns) == 500

    # every input message is in the output, byte for byte
    def payloads(path):
        with McapSource(str(path)) as src:
            found = []
            for batch in src.batches():
                for i in range(len(batch)):
                    if src.channels[int(batch.channel_id[i])].topic.endswith("/data_raw"):
                        found.append(batch.payload(i))
            return found

    assert payloads(faulty_log) == payloads(out)


def test_pipeline_stdin_stdout(cli, faulty_log):
    args = ["detect", "-", "-d", "glt", "--no-explain", "-o", "-"]  # the pipe, not episodes
    result = cli(args, stdin=faulty_log.read_bytes())
    assert result.code == 0, result.stderr
    report = cli(["report", "-", "--json", "-"], stdin=result.stdout)
    assert report.code == 0, report.stderr
    assert b'"detector": "glt"' in report.stdout


def test_rerun_replaces_own_channels(cli, tmp_path, detected_log):
    from imufdi_cli.mcapio.events import EVENTS_TOPIC, read_events

    out = tmp_path / "again.mcap"
    # without explanation: the input's events (with its episodes) must go all the same
    assert cli(["detect", detected_log, "-d", "glt", "--no-explain", "-o", out]).code == 0
    with McapSource(str(out)) as src:
        for _ in src.batches():
            pass
        topics = [c.topic for c in src.channels.values()]
    assert topics.count("/imufdi/glt/gyro") == 1
    assert topics.count("/imufdi/events") == 1
    kinds = {event["event"] for _, event in read_events(str(out), EVENTS_TOPIC)}
    assert "alarm_start" in kinds and "episode" not in kinds


@pytest.mark.parametrize(
    ("args", "code", "fragment"),
    [
        (["-d", "nope"], 2, "nope"),
        (["-d", "glt", "--param", "glt.alpha=2"], 2, "glt.alpha"),
        (["-d", "glt", "--param", "glt.bogus=1"], 2, "glt.bogus"),
        (["-d", "glt", "--param", "pca-parity.window=3"], 2, "not selected"),
        (["-d", "glt", "--param", "alpha"], 2, "DETECTOR.KEY=VALUE"),
        (["-d", "glt", "--calibrate", "3s:1s"], 2, "--calibrate"),
        (["-d", "glt", "--calibrate", "100s:200s"], 3, "calibration"),
    ],
)
def test_bad_arguments(cli, tmp_path, faulty_log, args, code, fragment):
    out = tmp_path / "x.mcap"
    assert_one_line_error(cli(["detect", faulty_log, *args, "-o", out]), code, fragment)
    assert not out.exists()


@pytest.mark.parametrize("detector", ["glt", "cnn-map", "px4-selector", "bank", "woa-mvmd-glt"])
def test_a_single_imu_log_is_bad_data_for_every_detector(cli, tmp_path, detector):
    """One situation, one exit code: 3 (the data cannot be checked), with what to do."""
    log = tmp_path / "one.mcap"
    assert cli(["simulate", "--imus", "1", "--duration", "3s", "-o", log]).code == 0
    out = tmp_path / "d.mcap"
    result = cli(["detect", log, "-d", detector, "-o", out])
    assert_one_line_error(result, 3, "`imufdi info LOG` shows its IMUs")
    assert "bank mode=marg" in result.stderr
    assert "health checks each IMU alone" in result.stderr  # the detector that applies
    assert not out.exists()


@pytest.mark.parametrize("detector", ["noise-glr", "pca-parity"])
def test_too_small_log_for_noise_glr_and_pca_parity_names_detector_and_hint(
    cli, tmp_path, detector
):
    """These two need 4+ redundant sensor axes of a type; one IMU has 3: exit 3, one line
    naming the detector, with the same hint as the other detectors."""
    log = tmp_path / "one.mcap"
    assert cli(["simulate", "--imus", "1", "--duration", "3s", "-o", log]).code == 0
    out = tmp_path / "d.mcap"
    result = cli(["detect", log, "-d", detector, "-o", out])
    assert_one_line_error(result, 3, f"imufdi: error: {detector}: nothing to test")
    assert "`imufdi info LOG` shows its IMUs" in result.stderr
    assert "bank mode=marg" in result.stderr
    assert not out.exists()


def test_false_alarms_budget_detects_without_the_per_sample_noise(cli, tmp_path, faulty_log):
    import json

    per_sample = cli(["detect", faulty_log, "-d", "glt", "--no-explain", "-o", tmp_path / "a.mcap"])
    assert per_sample.code == 0
    # the papers' per-sample test: a warning naming the way out
    assert "--false-alarms 1/h" in per_sample.stderr and "3,600" in per_sample.stderr
    out = tmp_path / "b.mcap"
    budget = cli(
        ["detect", faulty_log, "-d", "glt", "--false-alarms", "1/h", "-o", out, "--json", "-"]
    )
    assert budget.code == 0, budget.stderr
    assert "--false-alarms" not in budget.stderr
    gyro = json.loads(budget.stdout)["detectors"]["glt"]["gyro"]
    assert gyro["events"] == 1  # the 0.9 deg/s step, nothing else
    status = read_status(str(out), "glt")[("glt", "gyro")]
    first = int(status.alarm.argmax())
    assert status.alarm.any() and 2.5 <= (status.t_ns[first] - status.t_ns[0]) / 1e9 <= 2.55
    assert status.isolated[first] == 0  # imu0.gyro.x


@pytest.mark.parametrize(
    ("rate", "fragment"),
    [("1/m", "is not a frequency"), ("-1/h", "must be >= 0"), ("fast", "cannot read")],
)
def test_false_alarms_bad_rate_is_a_usage_error(cli, tmp_path, faulty_log, rate, fragment):
    result = cli(
        ["detect", faulty_log, "-d", "glt", "--false-alarms", rate, "-o", tmp_path / "x.mcap"]
    )
    assert_one_line_error(result, 2, fragment)
    assert not (tmp_path / "x.mcap").exists()
