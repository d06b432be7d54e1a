"""Public flight-controller logs: ingest, info, detect and report, values against pyulog and
pymavlink on the same log.

The logs are not in the repository (their licences and provenance are listed in
docs/flight-controllers.md, with the commands that fetch them); these tests read them from
the directory ``IMUFDI_FCLOG_DIR`` names and skip, saying so, when it is not set. Each
file is checked against its SHA-256 first, so a different file fails instead of passing
for the wrong reason.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from imufdi_cli.fclog import ingest_flight_log
from imufdi_cli.mcapio import read_array
from tests.cli.conftest import assert_one_line_error, invoke

pyulog = pytest.importorskip("pyulog")
DFReader = pytest.importorskip("pymavlink.DFReader")

#: name -> (SHA-256, format, IMUs, imu data ingest chooses, testable)
LOGS: dict[str, tuple[str, str, int, str, bool]] = {
    "px4-cubeorange-3imu.ulg": (
        "68d1020f688109f027dba08d2950247cc0ae34aaefdcf37e4a7d60838f3e1aa3",
        "px4-ulog",
        3,
        "vehicle_imu",
        False,
    ),
    "px4-sitl-3imu.ulg": (
        "32f564608d46caf5a4cbb1cb0cd0dc839fb9512b06c6d1384fb96ec3d6c9173d",
        "px4-ulog",
        3,
        "vehicle_imu",
        False,
    ),
    "ardupilot-sitl-2imu.bin": (
        "a51f040b2ad7f55185c1da5705f226f51469b86562c4ff76d05c99e0e52c2bf4",
        "ardupilot-dataflash",
        2,
        "imu",
        True,
    ),
    "ardupilot-pixhawk4-2imu.bin": (
        "0e45308b9d9f8c9d7167bb10b11f3e98212d5d5c3b42ed811aaa9e356fb02656",
        "ardupilot-dataflash",
        2,
        "imu",
        True,
    ),
    "ardupilot-pxf-2imu.bin": (
        "9968d91604d7b6edaca4d1f7403b5cae1bbb430f9e0a31095457d02e73ebcd6b",
        "ardupilot-dataflash",
        2,
        "imu",
        True,
    ),
}


def _log(name: str) -> Path:
    folder = os.environ.get("IMUFDI_FCLOG_DIR")
    if not folder:
        pytest.skip("IMUFDI_FCLOG_DIR is not set (docs/flight-controllers.md: the public logs)")
    path = Path(folder) / name
    if not path.is_file():
        pytest.skip(f"{name} is not in IMUFDI_FCLOG_DIR={folder}")
    assert hashlib.sha256(path.read_bytes()).hexdigest() == LOGS[name][0], (
        f"{name}: not the published file"
    )
    return path


def _in_order(ours: np.ndarray, reference: np.ndarray) -> None:
    """Every row of ``ours`` is a row of ``reference``, in the reference's order (the
    alignment drops rows, never changes or reorders them)."""
    at = 0
    for row in ours:
        hits = np.flatnonzero((reference[at:] == row).all(axis=1))
        assert hits.size, f"row {row} is not in the reference after index {at}"
        at += int(hits[0]) + 1


@pytest.mark.parametrize("name", sorted(LOGS))
def test_public_log_ingests_with_the_imus_and_rates_it_holds(name, tmp_path):
    path = _log(name)
    _, fmt, n_imus, source, testable = LOGS[name]
    out = tmp_path / "log.mcap"
    result = invoke(["ingest", path, "-o", out, "--json", "-"])
    assert result.code == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["format"] == fmt and summary["n_imus"] == n_imus
    assert summary["imu_data"] == source and summary["testable"] is testable
    info = json.loads(invoke(["info", out, "--json", "-"]).stdout)
    assert info["n_imus"] == n_imus
    assert info["flight_log"]["imu_rates_hz"] == summary["imu_rates_hz"]
    if not testable:
        assert any("too low to test" in w for w in info["warnings"])


@pytest.mark.parametrize("name", [n for n in sorted(LOGS) if LOGS[n][1] == "px4-ulog"])
def test_px4_values_equal_pyulog(name, tmp_path):
    path = _log(name)
    out = tmp_path / "log.mcap"
    result = ingest_flight_log(path, out)
    block = read_array(out)[1]
    log = pyulog.ULog(str(path))
    for k in range(block.n_imus):
        data = log.get_dataset("vehicle_imu", k).data
        dt = data["delta_angle_dt"].astype(np.float64) * 1e-6
        gyro = np.column_stack([data[f"delta_angle[{j}]"] for j in range(3)]) / dt[:, None]
        dv = data["delta_velocity_dt"].astype(np.float64) * 1e-6
        accel = np.column_stack([data[f"delta_velocity[{j}]"] for j in range(3)]) / dv[:, None]
        _in_order(
            np.concatenate([block.gyro[:, k], block.accel[:, k]], axis=1),
            np.concatenate([gyro, accel], axis=1),
        )
    # UTC: the first GPS time against its timestamp, as Flight Review computes it
    gps = log.get_dataset("vehicle_gps_position").data
    first = int(np.flatnonzero(gps["time_utc_usec"] > 0)[0])
    offset_us = int(gps["time_utc_usec"][first]) - int(gps["timestamp"][first])
    assert result.record["utc"]["offset_us"] == offset_us
    # the sensor_accel/sensor_gyro instances at 1 Hz are counted and described too
    names = {s["name"]: s for s in result.record["streams"]}
    assert {f"sensor_gyro {k}" for k in range(3)} <= set(names)


def test_px4_sparse_log_detect_says_which_logging_gives_full_rate(tmp_path):
    path = _log("px4-cubeorange-3imu.ulg")
    out = tmp_path / "log.mcap"
    assert invoke(["ingest", path, "-o", out]).code == 0
    detect = invoke(["detect", out, "-d", "glt", "-o", tmp_path / "det.mcap"])
    assert_one_line_error(detect, 3, "too low to test")
    assert "SDLOG_PROFILE" in detect.stderr and "logger_topics.txt" in detect.stderr


@pytest.mark.parametrize("name", [n for n in sorted(LOGS) if LOGS[n][1] == "ardupilot-dataflash"])
def test_ardupilot_values_and_utc_equal_pymavlink(name, tmp_path):
    path = _log(name)
    out = tmp_path / "log.mcap"
    result = ingest_flight_log(path, out)
    block = read_array(out)[1]
    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    rows: dict[int, list] = {}
    stamps: dict[int, list] = {}
    while True:
        message = reader.recv_match(type=["IMU", "IMU2", "IMU3"])
        if message is None:
            break
        kind = message.get_type()
        k = int(getattr(message, "I", 0 if kind == "IMU" else int(kind[-1]) - 1))
        rows.setdefault(k, []).append(
            [message.GyrX, message.GyrY, message.GyrZ, message.AccX, message.AccY, message.AccZ]
        )
        stamps.setdefault(k, []).append(message._timestamp)
    for k in range(block.n_imus):
        ours = np.concatenate([block.gyro[:, k], block.accel[:, k]], axis=1)
        assert_array_equal(ours, np.asarray(rows[k]))  # every sample, nothing dropped
    utc = result.record["utc"]
    if utc is not None:
        # pymavlink's clock subtracts 18 leap seconds whatever the date: these logs are
        # from 2017 on, where that is right; float seconds since 1970 hold 0.24 us
        assert abs(block.t_ns[0] / 1e9 - stamps[0][0]) < 2e-6


def test_ardupilot_real_log_detect_and_report_run(tmp_path):
    path = _log("ardupilot-pxf-2imu.bin")
    out = tmp_path / "log.mcap"
    assert invoke(["ingest", path, "-o", out]).code == 0
    detected = tmp_path / "det.mcap"
    result = invoke(["detect", out, "-d", "glt", "-d", "ap-consistency", "-o", detected])
    assert result.code == 0, result.stderr
    report = invoke(["report", detected, "--json", "-"])
    assert report.code == 0, report.stderr
    assert json.loads(report.stdout)
