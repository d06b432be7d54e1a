"""Flight-controller logs (PX4 ULog, ArduPilot DataFlash) -> IMU array MCAP.

The logs here are written by tests/capture/fclog_files.py from the format specifications;
each is read back with pyulog or pymavlink, the libraries PX4 and ArduPilot maintain, and
the ingested values must equal theirs bit for bit (float32 log values widened to float64:
exact). The public logs are in test_fclog_real.py.
"""

from __future__ import annotations

import functools
import itertools
import json
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_array_equal

from imufdi_cli.errors import FlightLogError, UsageError
from imufdi_cli.fclog import ingest_flight_log, sniff_format
from imufdi_cli.fclog.align import NearestAligner
from imufdi_cli.fclog.streams import gps_to_unix_us
from imufdi_cli.mcapio import McapSource, read_array
from tests.cli.conftest import assert_one_line_error, invoke

from .fclog_files import (
    AP_FORMATS,
    ap_imu_messages,
    dataflash_bytes,
    px4_imu_samples,
    ulog_bytes,
)

pyulog = pytest.importorskip("pyulog")
DFReader = pytest.importorskip("pymavlink.DFReader")

T0_US = 20_000_000


def _triads(n: int, m: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Gyro and accel (n, m, 3) as float32 values (what the logs store)."""
    rng = np.random.default_rng(seed)
    gyro = rng.normal(0.0, 0.02, (n, m, 3)).astype(np.float32).astype(np.float64)
    accel = (rng.normal(0.0, 0.1, (n, m, 3)) + np.array([0.0, 0.0, -9.81])).astype(np.float32)
    return gyro, accel.astype(np.float64)


def _record(path) -> dict:
    with McapSource(path) as source:
        return json.loads(source.metadata["imufdi.ingest"]["json"])


def _px4_log(tmp_path, name="log.ulg", *, n=400, m=3, period_us=2500, seed=0, **kwargs):
    t = T0_US + np.arange(n, dtype=np.int64) * period_us
    gyro, accel = _triads(n, m, seed)
    offsets = kwargs.pop("offsets_us", (0, 310, 1170)[:m])
    vehicle_imu = kwargs.pop("vehicle_imu", False)
    samples = px4_imu_samples(t, gyro, accel, offsets_us=offsets, vehicle_imu=vehicle_imu)
    extra = kwargs.pop("extra", [])
    path = tmp_path / name
    path.write_bytes(ulog_bytes(sorted(samples + extra, key=_ulog_time), **kwargs))
    return path, t, gyro, accel, offsets


def _ulog_time(sample) -> int:
    values = sample[2]
    return int(values.get("timestamp_sample", values["timestamp"]))


# --- recognising the format -------------------------------------------------------------


def test_formats_are_recognised_by_their_first_bytes():
    assert sniff_format(b"ULog\x01\x12\x35\x01" + bytes(8)) == "px4-ulog"
    assert sniff_format(b"\xa3\x95\x80\x80Y") == "ardupilot-dataflash"
    assert sniff_format(b"\xaa\x55\x01\x10") is None
    assert sniff_format(b"ULog") is None  # too short to be sure
    assert sniff_format(b"") is None


def test_ingest_recognises_a_ulog_whatever_its_name_and_refuses_capture_options(tmp_path):
    path, *_ = _px4_log(tmp_path, "flight.dat")
    result = invoke(["ingest", path, "-o", tmp_path / "out.mcap"])
    assert result.code == 0, result.stderr
    assert read_array(tmp_path / "out.mcap")[0].n_imus == 3
    bad = invoke(
        ["ingest", path, "--layout", "mpu6500-array", "--rate", "5Hz", "-o", tmp_path / "b.mcap"]
    )
    assert_one_line_error(
        bad, 2, "is a PX4 ULog (recognised by its content): --layout, --rate apply"
    )
    assert not (tmp_path / "b.mcap").exists()


def test_imu_data_is_refused_for_a_capture_and_a_capture_error_names_flight_logs(tmp_path):
    capture = tmp_path / "noise.cap"
    capture.write_bytes(bytes(range(256)) * 4)
    result = invoke(["ingest", capture, "--imu-data", "sensor", "-o", tmp_path / "a.mcap"])
    assert_one_line_error(result, 2, "--imu-data applies to flight-controller logs only")
    result = invoke(["ingest", capture, "-o", tmp_path / "a.mcap"])
    assert_one_line_error(result, 3, "nor is")
    assert "PX4 ULog or an ArduPilot DataFlash log" in result.stderr


def test_a_log_on_stdin_is_recognised_and_converted(tmp_path):
    path, *_ = _px4_log(tmp_path)
    result = invoke(["ingest", "-", "-o", tmp_path / "stdin.mcap"], stdin=path.read_bytes())
    assert result.code == 0, result.stderr
    invoke(["ingest", path, "-o", tmp_path / "file.mcap"])
    a, b = read_array(tmp_path / "stdin.mcap")[1], read_array(tmp_path / "file.mcap")[1]
    assert_array_equal(a.t_ns, b.t_ns)
    assert_array_equal(a.gyro, b.gyro)
    messages = tmp_path / "messages.ulg"
    messages.write_bytes(b"\xa3\x95\x80" + bytes(10))
    cut = invoke(["ingest", "-", "-o", tmp_path / "cut.mcap"], stdin=messages.read_bytes())
    assert_one_line_error(cut, 3, "")


# --- PX4 ----------------------------------------------------------------------------------


def test_px4_sensor_topics_equal_pyulog_and_are_stamped_when_the_last_value_exists(tmp_path):
    path, t, _, _, offsets = _px4_log(tmp_path)
    out = tmp_path / "out.mcap"
    result = ingest_flight_log(path, out)
    array, block = read_array(out)
    assert array.n_imus == 3 and array.sensor_types() == ["gyro", "accel"]
    assert array.rate_hz == pytest.approx(400.0)
    log = pyulog.ULog(str(path))
    for k in range(3):
        for topic, sensor in (("sensor_gyro", block.gyro), ("sensor_accel", block.accel)):
            data = log.get_dataset(topic, k).data
            reference = np.column_stack([data[a] for a in "xyz"]).astype(np.float64)
            assert_array_equal(sensor[:, k], reference)  # every sample kept, in order
    # each array sample is stamped when its last value exists: the latest IMU's time
    assert_array_equal(block.t_ns, (t + max(offsets)) * 1000)
    record = result.record
    assert record["imu_data"] == "sensor" and record["n_imus"] == 3
    assert record["alignment"]["max_skew_us"] == max(offsets)
    assert record["rate"]["testable"] is True
    assert record["imus"][1] == ["sensor_gyro 1", "sensor_accel 1"]


def test_px4_vehicle_imu_is_delta_over_interval_and_matches_pyulog(tmp_path):
    path, _, gyro, _, _ = _px4_log(tmp_path, vehicle_imu=True, period_us=5000, n=200)
    out = tmp_path / "out.mcap"
    result = ingest_flight_log(path, out)
    assert result.record["imu_data"] == "vehicle_imu"
    block = read_array(out)[1]
    data = pyulog.ULog(str(path)).get_dataset("vehicle_imu", 2).data
    dt = data["delta_angle_dt"].astype(np.float64) * 1e-6
    reference = np.column_stack([data[f"delta_angle[{j}]"] for j in range(3)]) / dt[:, None]
    assert_array_equal(block.gyro[:, 2], reference)
    # float32 deltas of a float32 value times 5 ms, divided again: within 2 ulp of it
    np.testing.assert_allclose(block.gyro[:, 2], gyro[:, 2], rtol=3e-7, atol=1e-12)


def test_auto_takes_the_faster_source_and_imu_data_chooses(tmp_path):
    """sensor_* at 1 Hz and vehicle_imu at 200 Hz: auto takes vehicle_imu; --imu-data
    sensor takes the 1 Hz topics and says they are too sparse."""
    n = 400
    t = T0_US + np.arange(n, dtype=np.int64) * 5000
    gyro, accel = _triads(n, 3, 3)
    fast = px4_imu_samples(t, gyro, accel, vehicle_imu=True)
    slow = px4_imu_samples(t[::200], gyro[::200], accel[::200])
    path = tmp_path / "both.ulg"
    path.write_bytes(ulog_bytes(sorted(fast + slow, key=_ulog_time)))
    assert ingest_flight_log(path, tmp_path / "a.mcap").record["imu_data"] == "vehicle_imu"
    sparse = ingest_flight_log(path, tmp_path / "b.mcap", imu_data="sensor")
    assert sparse.record["imu_data"] == "sensor"
    assert not sparse.record["rate"]["testable"]
    with pytest.raises(UsageError, match="valid: auto, sensor, vehicle_imu"):
        ingest_flight_log(path, tmp_path / "c.mcap", imu_data="raw")


def test_a_default_profile_log_is_too_sparse_and_info_and_detect_say_what_to_log(tmp_path):
    path, *_ = _px4_log(tmp_path, n=20, period_us=1_000_000)
    out = tmp_path / "sparse.mcap"
    result = invoke(["ingest", path, "-o", out])
    assert result.code == 0
    assert "too low to test" in result.stderr and "logger_topics.txt" in result.stderr
    info = invoke(["info", out])
    assert info.code == 0
    assert "3 IMUs at 1, 1, 1 Hz (too low to test)" in info.out
    assert "SDLOG_PROFILE" in info.stderr
    as_json = json.loads(invoke(["info", out, "--json", "-"]).stdout)
    assert as_json["flight_log"]["testable"] is False
    detect = invoke(["detect", out, "-d", "glt", "-o", tmp_path / "det.mcap"])
    assert_one_line_error(detect, 3, "at 1 Hz, too low to test (at least 10 Hz per IMU)")
    assert "sensor_accel 0" in detect.stderr
    assert not (tmp_path / "det.mcap").exists()


def test_px4_utc_comes_from_the_gps_time(tmp_path):
    utc = 1_700_000_000_000_000
    gps_t = T0_US + 123_456
    gps = [("vehicle_gps_position", 0, {"timestamp": gps_t, "time_utc_usec": utc})]
    path, t, *_ = _px4_log(tmp_path, extra=gps, offsets_us=(0, 0, 0))
    out = tmp_path / "utc.mcap"
    result = ingest_flight_log(path, out)
    block = read_array(out)[1]
    assert int(block.t_ns[0]) == (int(t[0]) + utc - gps_t) * 1000
    assert result.record["utc"]["start"] == "2023-11-14T22:13:19.876544Z"
    moved = ingest_flight_log(path, tmp_path / "moved.mcap", start_time_ns=2 * 10**18)
    assert int(read_array(tmp_path / "moved.mcap")[1].t_ns[0]) == 2 * 10**18
    assert moved.record["parameters_of_ingest"]["start_time_ns"] == 2 * 10**18


@pytest.mark.parametrize("sync", [True, False])
def test_px4_corruption_is_skipped_counted_and_refused_when_strict(tmp_path, sync):
    path, t, *_ = _px4_log(
        tmp_path, sync_every=40 if sync else 0, garbage_after=500, dropout_after=100
    )
    out = tmp_path / "out.mcap"
    result = ingest_flight_log(path, out)
    counts = result.record["counts"]
    assert counts["corrupt_bytes"] > 0 and counts["dropouts"] == 1 and counts["dropout_ms"] == 10
    block = read_array(out)[1]
    # the samples after the corruption are read again (with sync messages, from the next one)
    assert block.t_ns[-1] == (t[-1] + 1170) * 1000
    assert len(block) >= len(t) - (40 if sync else 2)
    with pytest.raises(FlightLogError, match=r"strict: the log is damaged \(corrupt bytes"):
        ingest_flight_log(path, tmp_path / "strict.mcap", strict=True)
    assert not (tmp_path / "strict.mcap").exists()


def test_px4_truncated_log_and_small_chunks(tmp_path):
    path, t, *_ = _px4_log(tmp_path, truncate=11)
    whole = ingest_flight_log(path, tmp_path / "a.mcap")
    assert whole.record["counts"]["truncated"] is True
    ingest_flight_log(path, tmp_path / "b.mcap", chunk_size=997)
    a, b = read_array(tmp_path / "a.mcap")[1], read_array(tmp_path / "b.mcap")[1]
    assert_array_equal(a.t_ns, b.t_ns)
    assert_array_equal(a.accel, b.accel)
    assert len(a) == len(t) - 1  # the cut message's sample is incomplete


def test_not_a_flight_log_and_no_imu_data(tmp_path):
    other = tmp_path / "x.ulg"
    other.write_bytes(b"not a log at all")
    with pytest.raises(FlightLogError, match="neither a PX4 ULog nor an ArduPilot"):
        ingest_flight_log(other, tmp_path / "x.mcap")
    gps_only = tmp_path / "gps.ulg"
    gps_only.write_bytes(
        ulog_bytes([("vehicle_gps_position", 0, {"timestamp": 1, "time_utc_usec": 2})])
    )
    with pytest.raises(FlightLogError, match=r"holds no per-IMU data.*logger_topics\.txt"):
        ingest_flight_log(gps_only, tmp_path / "gps.mcap")
    assert not (tmp_path / "gps.mcap").exists()


def test_array_override_must_match_the_imu_count(tmp_path):
    from imufdi_cli.array import ArrayConfig

    path, *_ = _px4_log(tmp_path)
    with pytest.raises(UsageError, match="--array has 2 IMUs, this PX4 ULog 3"):
        ingest_flight_log(path, tmp_path / "a.mcap", array=ArrayConfig.co_aligned(2))
    positions = np.array([[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]])
    given = ArrayConfig.co_aligned(3, rate_hz=400.0, positions=positions)
    ingest_flight_log(path, tmp_path / "b.mcap", array=given)
    assert_array_equal(read_array(tmp_path / "b.mcap")[0].positions(), positions)


# --- ArduPilot ---------------------------------------------------------------------------


def _ap_log(tmp_path, messages, name="log.bin", **kwargs):
    path = tmp_path / name
    path.write_bytes(dataflash_bytes(messages, **kwargs))
    return path


def _pymavlink(path, kind):
    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    out = []
    while True:
        message = reader.recv_match(type=kind)
        if message is None:
            return out
        out.append(message)


def test_ardupilot_imu_instances_equal_pymavlink_and_utc_from_gps(tmp_path):
    n, m = 300, 3
    t = T0_US + np.arange(n, dtype=np.int64) * 2500
    gyro, accel = _triads(n, m, 7)
    gps = ("GPS", {"TimeUS": T0_US + 1000, "Status": 3, "GMS": 302_400_000, "GWk": 2290})
    params = [
        ("PARM", {"Name": p, "Value": v})
        for p, v in (("INS_POS2_X", 0.05), ("LOG_BITMASK", 176126))
    ]
    path = _ap_log(
        tmp_path,
        [
            *params,
            ("MSG", {"Message": "ArduCopter V4.5.7 (2a3dc4b7)"}),
            gps,
            *ap_imu_messages(t, gyro, accel),
        ],
    )
    out = tmp_path / "ap.mcap"
    result = ingest_flight_log(path, out)
    array, block = read_array(out)
    assert array.n_imus == 3 and array.rate_hz == pytest.approx(400.0)
    assert_array_equal(array.positions()[1], [float(np.float32(0.05)), 0.0, 0.0])  # as logged
    reference = _pymavlink(path, "IMU")
    for k in range(m):
        mine = [r for r in reference if r.I == k]
        assert_array_equal(block.gyro[:, k], [[r.GyrX, r.GyrY, r.GyrZ] for r in mine])
        assert_array_equal(block.accel[:, k], [[r.AccX, r.AccY, r.AccZ] for r in mine])
    utc_us = gps_to_unix_us(2290, 302_400_000) - (T0_US + 1000)
    assert_array_equal(block.t_ns, (t + utc_us) * 1000)
    # GPS week 2290, Wednesday noon, less 18 leap seconds, 1 ms before the GPS message
    assert result.record["utc"]["start"] == "2023-11-29T11:59:41.999000Z"
    assert result.record["system"]["firmware"].startswith("ArduCopter V4.5.7")
    assert result.record["parameters"]["LOG_BITMASK"] == 176126


def test_gps_time_to_utc_uses_the_leap_seconds_of_the_date():
    from datetime import datetime, timedelta, timezone

    def unix_us(moment):
        return round((moment - datetime(1970, 1, 1, tzinfo=timezone.utc)).total_seconds() * 1e6)

    gps_epoch = datetime(1980, 1, 6, tzinfo=timezone.utc)
    # 2014 (GPS - UTC = 16 s), 2016 (17 s), 2017 and later (18 s)
    for week, leap in ((1782, 16), (1900, 17), (1973, 18), (2290, 18)):
        expected = unix_us(gps_epoch + timedelta(weeks=week, seconds=100 - leap))
        assert gps_to_unix_us(week, 100_000) == expected


def test_ardupilot_old_style_imu2_messages(tmp_path):
    n = 100
    t = T0_US + np.arange(n, dtype=np.int64) * 20_000
    gyro, accel = _triads(n, 2, 8)
    messages = ap_imu_messages(t, gyro, accel, old_style=True)
    path = _ap_log(tmp_path, messages, formats={"IMU": AP_FORMATS["IMU2"]})
    out = tmp_path / "old.mcap"
    result = ingest_flight_log(path, out)
    assert result.record["imus"] == [["IMU 0"], ["IMU 1"]]
    block = read_array(out)[1]
    second = _pymavlink(path, "IMU2")
    assert_array_equal(block.gyro[:, 1], [[r.GyrX, r.GyrY, r.GyrZ] for r in second])


def _raw_messages(n_acc, m, *, gyro_factor=2, post_filter=False, seed=9):
    t_acc = T0_US + np.arange(n_acc, dtype=np.int64) * 1000
    t_gyr = T0_US + np.arange(n_acc * gyro_factor, dtype=np.int64) * (1000 // gyro_factor) + 7
    rng = np.random.default_rng(seed)
    out = []
    for k in range(m):
        for ts in t_acc.tolist():
            out.append(
                (
                    ts,
                    "ACC",
                    {
                        "TimeUS": ts + 50,
                        "I": k,
                        "SampleUS": ts,
                        "AccX": float(rng.normal()),
                        "AccY": 0.0,
                        "AccZ": -9.8,
                    },
                )
            )
        for ts in t_gyr.tolist():
            for copy in (0, 1) if post_filter else (0,):
                out.append(
                    (
                        ts,
                        "GYR",
                        {
                            "TimeUS": ts + 50,
                            "I": k + copy * m,
                            "SampleUS": ts,
                            "GyrX": float(rng.normal()),
                            "GyrY": 0.0,
                            "GyrZ": 0.0,
                        },
                    )
                )
    out.sort(key=lambda r: r[0])
    return [(name, values) for _, name, values in out]


def test_ardupilot_raw_gyro_faster_than_accel_is_taken_nearest_on_the_accel_grid(tmp_path):
    n = 500
    path = _ap_log(tmp_path, _raw_messages(n, 2))
    out = tmp_path / "raw.mcap"
    result = ingest_flight_log(path, out)
    assert result.record["imu_data"] == "raw"
    assert result.record["alignment"]["reference"] == "ACC 0"
    block = read_array(out)[1]
    assert read_array(out)[0].rate_hz == pytest.approx(1000.0)
    gyros = [r for r in _pymavlink(path, "GYR") if r.I == 1]
    g_t = np.array([r.SampleUS for r in gyros])
    accels = [r for r in _pymavlink(path, "ACC") if r.I == 1]
    a_t = np.array([r.SampleUS for r in accels])
    nearest = np.argmin(np.abs(g_t[None, :] - a_t[:, None]), axis=1)
    assert_array_equal(block.gyro[:, 1, 0], [gyros[i].GyrX for i in nearest])
    assert_array_equal(block.accel[:, 1, 0], [r.AccX for r in accels])
    assert result.record["alignment"]["unused"]["GYR 1"] == n  # every other gyro sample


def test_ardupilot_gyro_only_raw_logging_and_post_filter_copies(tmp_path):
    """INS_RAW_LOG_OPT = 9 (all gyros, before and after the filters): GYR instances 2, 3
    are copies of 0, 1 after the filters; auto prefers IMU (gyro and accel) to gyro-only
    raw data, --imu-data raw takes the gyros."""
    n = 200
    raw = [m for m in _raw_messages(n, 2, post_filter=True) if m[0] == "GYR"]
    t = T0_US + np.arange(n // 8, dtype=np.int64) * 8000
    gyro, accel = _triads(len(t), 2, 1)
    params = [
        ("PARM", {"Name": p, "Value": v})
        for p, v in (("INS_GYR_ID", 1), ("INS_GYR2_ID", 2), ("INS_RAW_LOG_OPT", 9))
    ]
    messages = params + sorted(raw + ap_imu_messages(t, gyro, accel), key=lambda r: r[1]["TimeUS"])
    path = _ap_log(tmp_path, messages)
    assert ingest_flight_log(path, tmp_path / "a.mcap").record["imu_data"] == "imu"
    result = ingest_flight_log(path, tmp_path / "b.mcap", imu_data="raw")
    assert result.record["sensors"] == ["gyro"] and result.record["n_imus"] == 2
    assert any("GYR 2 is the post-filter copy of instance 0" in w for w in result.warnings)
    assert read_array(tmp_path / "b.mcap")[0].sensor_types() == ["gyro"]


def test_ardupilot_batch_sampler_is_described_not_aligned(tmp_path):
    n = 120
    t = T0_US + np.arange(n, dtype=np.int64) * 2500
    gyro, accel = _triads(n, 2, 2)
    batches = [
        (
            "ISBH",
            {
                "TimeUS": T0_US + 10,
                "N": seq,
                "type": seq % 2,
                "instance": seq // 2,
                "mul": 1000,
                "smp_cnt": 32,
                "SampleUS": T0_US + seq * 1000,
                "smp_rate": 1000.0,
            },
        )
        for seq in range(4)
    ]
    data = [
        (
            "ISBD",
            {
                "TimeUS": T0_US + 20,
                "N": 0,
                "seqno": 0,
                "x": list(range(32)),
                "y": [0] * 32,
                "z": [0] * 32,
            },
        )
    ]
    path = _ap_log(tmp_path, batches + data + ap_imu_messages(t, gyro, accel))
    result = ingest_flight_log(path, tmp_path / "a.mcap")
    assert result.record["batch_sampler"] == {
        "imu0.accel": {"batches": 1, "samples": 32, "rate_hz": 1000.0},
        "imu0.gyro": {"batches": 1, "samples": 32, "rate_hz": 1000.0},
        "imu1.accel": {"batches": 1, "samples": 32, "rate_hz": 1000.0},
        "imu1.gyro": {"batches": 1, "samples": 32, "rate_hz": 1000.0},
    }
    only = _ap_log(tmp_path, batches + data, name="batches.bin")
    with pytest.raises(
        FlightLogError, match=r"only the batch sampler's bursts .*, one sensor at a time"
    ):
        ingest_flight_log(only, tmp_path / "b.mcap")


def test_ardupilot_garbage_is_skipped_and_chunks_do_not_change_the_samples(tmp_path):
    n = 300
    t = T0_US + np.arange(n, dtype=np.int64) * 2500
    gyro, accel = _triads(n, 2, 4)
    path = _ap_log(tmp_path, ap_imu_messages(t, gyro, accel), garbage_after=101, truncate=5)
    whole = ingest_flight_log(path, tmp_path / "a.mcap")
    # the 7 garbage bytes and the 49 of the last IMU message (54 bytes) cut by 5
    assert whole.record["counts"]["corrupt_bytes"] == 7 + (54 - 5)
    assert whole.record["counts"]["truncated"] is True
    ingest_flight_log(path, tmp_path / "b.mcap", chunk_size=333)
    a, b = read_array(tmp_path / "a.mcap")[1], read_array(tmp_path / "b.mcap")[1]
    assert_array_equal(a.t_ns, b.t_ns)
    assert_array_equal(a.gyro, b.gyro)
    assert len(a) == n - 1  # the last sample of IMU 1 is cut: that array sample is dropped
    assert_array_equal(a.gyro[:, 0], gyro[:-1, 0])
    with pytest.raises(FlightLogError, match="strict"):
        ingest_flight_log(path, tmp_path / "c.mcap", strict=True)


def test_ingest_detect_report_on_an_ardupilot_log(tmp_path):
    n = 1500
    t = T0_US + np.arange(n, dtype=np.int64) * 10_000
    gyro, accel = _triads(n, 3, 11)
    path = _ap_log(tmp_path, ap_imu_messages(t, gyro, accel))
    mcap = tmp_path / "ap.mcap"
    assert invoke(["ingest", path, "-o", mcap]).code == 0
    info = json.loads(invoke(["info", mcap, "--json", "-"]).stdout)
    assert info["n_imus"] == 3 and info["rate_hz"] == pytest.approx(100.0)
    assert info["flight_log"]["imu_rates_hz"] == [100.0, 100.0, 100.0]
    detected = tmp_path / "det.mcap"
    assert invoke(["detect", mcap, "-d", "glt", "-o", detected]).code == 0
    report = invoke(["report", detected, "--json", "-"])
    assert report.code == 0, report.stderr


# --- alignment ---------------------------------------------------------------------------


def test_aligner_takes_each_sample_once_and_drops_gaps():
    aligner = NearestAligner([3, 3], 0, 5000)
    grid = np.arange(0, 100_000, 10_000)
    other = np.delete(grid + 3000, 4)  # one sample missing
    aligner.add(0, grid, np.repeat(grid[:, None], 3, axis=1))
    aligner.add(1, other, np.repeat(other[:, None], 3, axis=1))
    stamps, values = aligner.pop(final=True)
    assert_array_equal(stamps, np.delete(grid, 4) + 3000)
    assert_array_equal(values[1][:, 0], other)
    assert aligner.counts.dropped == 1
    # a slower second stream: each of its samples serves the nearest grid time only
    slow = NearestAligner([3, 3], 0, 5000)
    slow.add(0, grid, np.zeros((10, 3)))
    slow.add(1, grid[::2] + 1000, np.zeros((5, 3)))
    stamps, _ = slow.pop(final=True)
    assert_array_equal(stamps, grid[::2] + 1000)


def test_aligner_streaming_equals_one_pass():
    rng = np.random.default_rng(5)
    times = [np.sort(rng.integers(0, 2_000_000, 400)) + o for o in (0, 700, 2100)]
    times = [np.unique(t) for t in times]
    values = [rng.normal(size=(t.shape[0], 3)) for t in times]

    def run(pieces):
        aligner = NearestAligner([3, 3, 3], 0, 2500)
        out_t, out_v = [], []
        edges = np.linspace(0, 2_100_000, pieces + 1)
        for lo, hi in itertools.pairwise(edges):
            for s in range(3):
                keep = (times[s] >= lo) & (times[s] < hi)
                aligner.add(s, times[s][keep], values[s][keep])
            t, v = aligner.pop()
            out_t.append(t)
            out_v.append(v[2])
        t, v = aligner.pop(final=True)
        return np.concatenate([*out_t, t]), np.concatenate([*out_v, v[2]])

    one_t, one_v = run(1)
    many_t, many_v = run(37)
    assert one_t.shape[0] > 50
    assert_array_equal(one_t, many_t)
    assert_array_equal(one_v, many_v)


@functools.cache
def _pristine(kind: str) -> bytes:
    n = 60
    t = T0_US + np.arange(n, dtype=np.int64) * 5000
    gyro, accel = _triads(n, 3, 12)
    if kind == "ulog":
        gps = [
            (
                "vehicle_gps_position",
                0,
                {"timestamp": T0_US, "time_utc_usec": 1_700_000_000_000_000},
            )
        ]
        samples = px4_imu_samples(t, gyro, accel, offsets_us=(0, 90, 180)) + gps
        return ulog_bytes(sorted(samples, key=_ulog_time), sync_every=25)
    ap = [("GPS", {"TimeUS": T0_US, "GMS": 1000, "GWk": 2200}), *ap_imu_messages(t, gyro, accel)]
    return dataflash_bytes(ap)


@pytest.mark.slow
@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.sampled_from(["ulog", "dataflash"]),
    st.lists(
        st.tuples(
            st.sampled_from(["set", "cut", "insert", "truncate"]),
            st.floats(0, 1),
            st.binary(min_size=1, max_size=40),
        ),
        min_size=1,
        max_size=8,
    ),
    st.integers(min_value=64, max_value=4096),
)
def test_damaged_logs_give_samples_or_an_imufdi_error(tmp_path, kind, edits, chunk):
    """Whatever the bytes (flipped, cut, inserted, truncated anywhere, the header and the
    formats included): an MCAP or a one-line imufdi error (and no output), never another
    exception, and no numpy warning (signalling NaNs, huge values)."""
    from imufdi_cli.errors import ImufdiError

    data = bytearray(_pristine(kind))
    for op, where, payload in edits:
        at = int(where * (len(data) - 1))
        if op == "set":
            data[at : at + len(payload)] = payload
        elif op == "cut":
            del data[at : at + len(payload)]
        elif op == "insert":
            data[at:at] = payload
        else:
            del data[max(at, 8) :]
    folder = Path(tempfile.mkdtemp(dir=tmp_path))  # one per example
    path = folder / "damaged.log"
    path.write_bytes(bytes(data))
    out = folder / "damaged.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            result = ingest_flight_log(path, out, chunk_size=chunk)
        except ImufdiError as err:
            assert "\n" not in str(err)
            assert not out.exists()
            return
    assert read_array(out)[1].n_imus == result.n_imus


def test_a_corrupt_instance_number_is_left_out_not_fatal(tmp_path):
    """A damaged ``I`` column makes a stream of one sample (IMU 7): it is left out, with a
    note, and the real IMUs are ingested."""
    n = 100
    t = T0_US + np.arange(n, dtype=np.int64) * 5000
    gyro, accel = _triads(n, 2, 13)
    messages = ap_imu_messages(t, gyro, accel)
    messages[51][1]["I"] = 7
    result = ingest_flight_log(_ap_log(tmp_path, messages), tmp_path / "a.mcap")
    assert result.n_imus == 2
    assert any("IMU 7" in w and "left out" in w for w in result.warnings)
