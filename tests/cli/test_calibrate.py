"""imufdi calibrate / detect --array / --start --end / validity, on the real MIMU4444 sample.

imufdi_cli/sample_logs/mimu4444-exp1-cut.bin is 300 s of exp_1 (10 static orientations, then hand
motion with gyro clipping) of the MIT-licensed MIMU4444 recordings (imufdi_cli/sample_logs/README.md).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from imufdi_cli.array import ArrayConfig
from imufdi_cli.calibrate import find_static
from imufdi_cli.mcapio import read_array, read_status, write_array
from imufdi_cli.pipeline import SAMPLE_LOGS
from tests.cli.conftest import assert_one_line_error

SAMPLES = SAMPLE_LOGS
CUT = SAMPLES / "mimu4444-exp1-cut.bin"
FRAMES = 18750  # (1,987,504 - 4 prefix bytes) / 106


@pytest.fixture
def real_log(mimu4444_cut_log):
    """The cut ingested by ``imufdi ingest`` with the layout and the uncalibrated array
    (tests/conftest.py: once per test process, shared with cnn-map's tests)."""
    return mimu4444_cut_log


@pytest.fixture(scope="module")
def real_block(mimu4444_cut_log):
    """``read_array`` of the ingested cut (array, block), read once per module and only
    read by the tests (about 0.19 s of CPU a read)."""
    return read_array(str(mimu4444_cut_log))


def test_ingest_every_frame(cli, real_log, real_block):
    info = cli(["info", real_log])
    assert info.code == 0, info.stderr
    assert "gyro: 563 clipped and 0 invalid of 18750 samples" in info.out
    array, block = real_block
    assert len(block) == FRAMES
    assert CUT.stat().st_size == 4 + 106 * FRAMES
    # full scale from the layout: int16 at 16.4 LSB/(deg/s) and 2048 LSB/g
    assert array.range["gyro"] == pytest.approx(np.radians(32768 / 16.4))
    assert array.range["accel"] == pytest.approx(16 * 9.80665)


def test_calibrate_improves_triad_agreement(cli, real_log, tmp_path):
    out = tmp_path / "cal.toml"
    result = cli(["calibrate", real_log, "-o", out, "--json"])
    assert result.code == 0, result.stderr
    figures = json.loads(result.out)
    assert figures["orientations"] == 10 and figures["coverage"] > 0.9
    before, after = figures["residual_rms"]["accel"]
    assert before > 0.1 and after < 0.01  # m/s^2, interval means at rest
    assert figures["residual_rms"]["gyro"][1] < figures["residual_rms"]["gyro"][0]
    assert figures["clipped_rows"] > 0  # the motion phase saturates the gyros
    cal = ArrayConfig.load(out)
    assert cal.calibrated and cal.range
    # the committed calibration is what calibrate writes for the sample, to rounding: M and
    # b are least-squares fits over 18,750 samples (~1e-15 of their unit scale apart between
    # numpy's AVX-512, AVX2 and SSE4.2 loops, OpenBLAS kernels and numpy 2.0 / 2.4:
    # measured at most 3.6e-15), the noise levels and jitter ratios of sums; 1e-9 bounds that
    # with room, while a change of the estimators (a divisor n - 1 for n, a sample more or
    # less in an interval) moves them by more than 1e-5
    committed = ArrayConfig.load(SAMPLES / "mimu4444-calibrated.toml")
    for new, old in zip(cal.imus, committed.imus):
        for s in ("gyro", "accel"):
            np.testing.assert_allclose(
                new.calibration_of(s).matrix, old.calibration_of(s).matrix, atol=1e-9
            )
            np.testing.assert_allclose(
                new.calibration_of(s).bias, old.calibration_of(s).bias, atol=1e-9
            )
            np.testing.assert_allclose(new.noise[s], old.noise[s], rtol=1e-9)
    # per-IMU noise at rest, after calibration (the board: gyro 0.1-0.6 deg/s, accel
    # 0.03-0.12 m/s^2 per axis)
    assert np.all(
        (np.degrees(cal.sensor_noise("gyro")) > 0.05) & (np.degrees(cal.sensor_noise("gyro")) < 1)
    )
    assert np.all((cal.sensor_noise("accel") > 0.01) & (cal.sensor_noise("accel") < 0.2))
    # chip time offsets: a diagnostic; on this board none (< 0.1 ms, explaining < 5 %)
    assert np.all(np.abs(figures["time_offsets_s"]) < 1e-4)
    # sampling-time jitter, fitted on the cut's 45 s of hand motion so that glt's
    # per-sample test holds 1 % there (exp_1 in full: gyro 1.42 ms, accel 2.63 ms)
    assert set(figures["jitter_s"]) == {"gyro", "accel"}
    assert cal.jitter == pytest.approx(committed.jitter, rel=1e-9)
    assert 5e-4 < cal.jitter["gyro"] < 5e-3 and 5e-4 < cal.jitter["accel"] < 1e-2
    moments = cli(["calibrate", real_log, "-o", tmp_path / "m.toml", "--jitter-fit", "moments"])
    assert moments.code == 0, moments.stderr
    # moments match the mean, not the tail: a smaller sigma_t than the level fit
    assert ArrayConfig.load(tmp_path / "m.toml").jitter["gyro"] < cal.jitter["gyro"]
    assert max(figures["time_offset_explained"]) < 0.05


def test_calibrate_reads_stdin_in_passes(cli, real_log, tmp_path):
    """calibrate reads its log once per pass: stdin is spooled to a temporary file."""
    piped = cli(
        ["calibrate", "-", "--jitter-fit", "off", "-o", tmp_path / "p.toml"],
        stdin=real_log.read_bytes(),
    )
    assert piped.code == 0, piped.stderr
    direct = cli(["calibrate", real_log, "--jitter-fit", "off", "-o", tmp_path / "d.toml"])
    assert direct.code == 0, direct.stderr
    assert (tmp_path / "p.toml").read_text() == (tmp_path / "d.toml").read_text()


def test_calibrate_start_end_and_missing_static(cli, real_log, tmp_path):
    # the last 40 s are hand motion only: no static interval -> exit 3 naming it
    result = cli(["calibrate", real_log, "--start", "260s", "-o", tmp_path / "c.toml"])
    assert_one_line_error(result, 3, "no static interval")
    assert not (tmp_path / "c.toml").exists()
    base = tmp_path / "base.toml"
    base.write_text((SAMPLES / "mimu4444-array.toml").read_text())
    result = cli(["calibrate", real_log, "--array", base, "-o", base])
    assert_one_line_error(result, 2, "inputs are never modified")
    assert base.read_text() == (SAMPLES / "mimu4444-array.toml").read_text()
    # --jitter-fit off on this run too (one calibration fewer than a run of its own on the
    # whole cut: about 0.45 s of CPU): the level fit gives this window a jitter of 0.1 s
    # for both types (no jitter holds the level in its motion), off none
    result = cli(
        ["calibrate", real_log, "--end", "60s", "--jitter-fit", "off", "-o", tmp_path / "c.toml"]
    )
    assert result.code == 0, result.stderr
    assert "only 2 orientation(s)" in result.stderr and "warning" in result.stderr
    assert ArrayConfig.load(tmp_path / "c.toml").jitter == {}


def test_singular_calibration_is_usage_error_naming_the_imu(cli, real_log, tmp_path):
    text = (SAMPLES / "mimu4444-calibrated.toml").read_text()
    bad = tmp_path / "bad.toml"
    lines = text.splitlines()
    idx = [i for i, line in enumerate(lines) if line.startswith("accel_matrix")][3]
    lines[idx] = "accel_matrix = [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]"
    bad.write_text("\n".join(lines))
    result = cli(["detect", real_log, "-d", "glt", "--array", bad, "-o", tmp_path / "d.mcap"])
    assert_one_line_error(result, 2, "imu3 accel calibration: matrix is singular")
    result = cli(["calibrate", real_log, "--array", bad, "-o", tmp_path / "c.toml"])
    assert_one_line_error(result, 2, "imu3 accel calibration")
    negative = tmp_path / "negative.toml"
    negative.write_text(text.replace("gyro = 0.00", "gyro = -0.00", 1))
    result = cli(["detect", real_log, "-d", "glt", "--array", negative, "-o", tmp_path / "d.mcap"])
    assert_one_line_error(result, 2, "jitter.gyro: must be finite and >= 0")


@pytest.mark.slow
def test_detect_holds_its_level_on_the_real_sample(cli, real_log, real_block, tmp_path):
    """Calibrated array, 10 s bias calibration: static alarm rate near alpha = 1 %."""
    out = tmp_path / "d.mcap"
    result = cli(
        [
            "detect", real_log, "-d", "glt", "-d", "pca-parity",
            "--array", SAMPLES / "mimu4444-calibrated.toml", "--calibrate", "0s:10s",
            "--start", "10s", "-o", out,
        ]
    )  # fmt: skip
    assert result.code == 0, result.stderr
    assert "563 clipped" in result.stderr
    array, block = real_block
    t = block.t_s()
    _, static = find_static(array, block.accel, block.gyro, t, np.ones(len(t), bool))
    status = read_status(str(out))
    from imufdi_cli.validity import flag_values

    clipped = np.zeros(len(t), dtype=bool)
    for s in ("gyro", "accel"):
        c, i = flag_values(block.get(s), s, array.range.get(s))
        clipped |= (c | i).any(axis=(1, 2))
    for (detector, sensor_type), arrays in status.items():
        rel = (arrays.t_ns - block.t_ns[0]) / 1e9
        rows = np.interp(rel, t, static.astype(float)) > 0.5
        rate = arrays.alarm[rows].mean()
        # the per-orientation target is 5 % (docs/real-arrays.md): the sample's static rows must hold it
        assert rate <= 0.05, (detector, sensor_type, rate)
        # motion after the last static interval (clipped rows not scored): the jitter was
        # fitted on this very motion (in-sample; out of sample: docs/real-arrays.md)
        moving = (rel > 262.0) & ~(np.interp(rel, t, clipped.astype(float)) > 0)
        assert np.count_nonzero(moving) > 1500
        rate = arrays.alarm[moving].mean()
        assert rate <= 0.05, (detector, sensor_type, "motion", rate)


def test_detect_window_and_report_window(cli, real_log, real_block, tmp_path):
    # the window's rows and samples, not its episodes: no explanation (about 0.16 s of CPU
    # on this log; the explanation and --no-explain: tests/test_detect.py, tests/episodes/)
    out = tmp_path / "d.mcap"
    args = ["detect", real_log, "-d", "glt", "--calibrate", "0s:10s", "--no-explain"]
    result = cli([*args, "--start", "20s", "--end", "50s", "-o", out])
    assert result.code == 0, result.stderr
    status = read_status(str(out))[("glt", "gyro")]
    _, block = real_block
    rel = block.t_s()
    assert len(status.t_ns) == np.count_nonzero((rel >= 20) & (rel < 50))
    assert abs(len(status.t_ns) - 30 * 62.5) <= 1
    report = cli(["report", out, "--start", "30s", "--json", "-"])
    assert report.code == 0, report.stderr
    entry = json.loads(report.out)["results"][0]
    assert entry["samples"] == np.count_nonzero((rel >= 30) & (rel < 50))
    bad = cli([*args, "--start", "50s", "--end", "20s", "-o", tmp_path / "x.mcap"])
    assert_one_line_error(bad, 2, "--start")


def test_huge_and_nan_values_are_flagged_not_a_crash(cli, tmp_path):
    """1e308 in a gyro, NaN in an accel (also in the calibration window): exit 0, counted."""
    rng = np.random.default_rng(0)
    array = ArrayConfig.co_aligned(4, rate_hz=100.0)
    n = 1000
    from imufdi_cli.log import ImuBlock

    gyro = 0.002 * rng.standard_normal((n, 4, 3))
    accel = np.array([0, 0, 9.81]) + 0.02 * rng.standard_normal((n, 4, 3))
    gyro[500, 1, 2] = 1e308
    gyro[50, 0, 0] = 1e308  # inside the calibration window too
    gyro[600, 2, 0] = -np.inf
    accel[100, 0, 1] = np.nan
    accel[700:705, 3, :] = np.nan
    log = tmp_path / "bad.mcap"
    write_array(str(log), array, ImuBlock(t_ns=np.arange(n) * 10_000_000, gyro=gyro, accel=accel))
    out = tmp_path / "d.mcap"
    detectors = ["-d", "glt", "-d", "pca-parity", "-d", "bank", "-d", "noise-glr"]
    result = cli(["detect", log, *detectors, "-o", out])
    assert result.code == 0, result.stderr
    assert "3 invalid" in result.stderr and "6 invalid" in result.stderr
    report = cli(["report", out, "--json", "-"])
    assert report.code == 0, report.stderr
    entries = {(e["detector"], e["sensor_type"]): e for e in json.loads(report.out)["results"]}
    assert entries[("glt", "gyro")]["invalid"] == 3
    assert entries[("glt", "accel")]["invalid"] == 6  # row 100 (calibration window) too
    assert entries[("glt", "accel")]["alarm_rate"] < 0.05
    for command in (
        ["tune", log, "--segment", "0s:1s", "--param", "population=3", "--param", "iterations=2"],
        ["inject", log, "--fault", "scale:imu1.gyro.z,at=4s,factor=2", "-o", tmp_path / "i.mcap"],
        ["calibrate", log, "-o", tmp_path / "c.toml"],
    ):
        result = cli(command)
        assert result.code in (0, 3), (command, result.stderr)
        assert "Traceback" not in result.stderr and "internal error" not in result.stderr
