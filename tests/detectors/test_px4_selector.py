"""px4-selector: the firmware recursion sample by sample, isolation rules, streaming, CLI."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.array import ArrayConfig, ImuSpec
from imufdi_cli.detectors.base import NO_ISOLATION, NOT_ISOLABLE, DetectionBlock, parse_params
from imufdi_cli.detectors.px4_selector import (
    Px4SelectorDetector,
    accumulate_excess,
    smooth_deviation,
)
from imufdi_cli.errors import ArrayTooSmallError, DetectorConfigError
from imufdi_cli.log import ImuBlock
from imufdi_cli.mcapio import read_status
from tests.cli.conftest import assert_one_line_error, invoke

DT_NS = 10_000_000


def make(**raw: Any) -> Px4SelectorDetector:
    return Px4SelectorDetector(**parse_params(Px4SelectorDetector.PARAMS, raw, "px4-selector"))


def block(n: int, m: int, rng: np.random.Generator, start: int = 0) -> ImuBlock:
    gyro = 0.01 * rng.standard_normal((n, m, 3))
    accel = np.array([0.0, 0.0, 9.81]) + 0.03 * rng.standard_normal((n, m, 3))
    return ImuBlock(t_ns=(start + np.arange(n)) * DT_NS, gyro=gyro, accel=accel)


def reference_loop(values: np.ndarray, rate: float, angle: float, dt: float) -> np.ndarray:
    """The firmware's per-update loop, written plainly: returns max_i E_i per sample."""
    m = values.shape[1]
    diff = np.zeros((m, 3))
    accumulated = np.zeros(m)
    out = []
    for x in values:
        mean = x.mean(axis=0)
        for i in range(m):
            diff[i] = 0.95 * diff[i] + 0.05 * (x[i] - mean)
            accumulated[i] += (np.linalg.norm(diff[i]) - rate) * min(dt, 0.02)
            accumulated[i] = max(accumulated[i], 0.0)
        out.append(accumulated.max())
    return np.array(out)


def test_lindley_recursion_matches_loop() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(-0.1, 1.0, (500, 4))
    start = np.array([0.0, 2.0, 0.5, 10.0])
    expected = np.empty_like(x)
    state = start.copy()
    for t, row in enumerate(x):
        state = np.maximum(state + row, 0.0)
        expected[t] = state
    assert_allclose(accumulate_excess(x, start), expected, atol=1e-9)


def test_smoothing_matches_loop_and_continues_across_blocks() -> None:
    rng = np.random.default_rng(4)
    x = rng.standard_normal((300, 2, 3))
    expected = np.empty_like(x)
    d = np.zeros((2, 3))
    for t, row in enumerate(x):
        d = 0.95 * d + 0.05 * row
        expected[t] = d
    first = smooth_deviation(x[:120], np.zeros((2, 3)), 0.05)
    second = smooth_deviation(x[120:], first[-1], 0.05)
    assert_allclose(np.concatenate([first, second]), expected, atol=1e-12)


def test_step_alarm_time_and_isolation_match_the_firmware_loop() -> None:
    rng = np.random.default_rng(5)
    array = ArrayConfig.co_aligned(4)
    data = block(2000, 4, rng)
    assert data.gyro is not None
    data.gyro[1000:, 2, 1] += math.radians(20.0)
    det = make(bias=False)
    det.fit(data.slice(0, 200), array)
    out = det.process(data)["gyro"]
    expected = reference_loop(data.gyro, math.radians(7.0), math.radians(15.0), 0.01)
    assert_allclose(out.statistic, expected, atol=1e-9)
    first = int(np.argmax(out.alarm))
    assert first == int(np.argmax(expected > math.radians(15.0)))
    assert not out.alarm[:1000].any()
    assert out.isolated[first] == 2 * 3 + 1  # imu2.gyro.y
    # a 20 deg/s step on one of 4 IMUs: the deviation filter converges to 15 deg/s = f (m-1)/m
    assert_allclose(out.amplitude[-1], math.radians(20.0), rtol=0.05)
    assert out.isolated[~out.alarm].tolist() == [NO_ISOLATION] * int((~out.alarm).sum())


def test_two_imus_detect_but_cannot_isolate() -> None:
    rng = np.random.default_rng(6)
    array = ArrayConfig.co_aligned(2)
    data = block(1500, 2, rng)
    assert data.accel is not None
    data.accel[500:, 1, 0] += 5.0  # 2.5 m/s^2 from the mean, 1.5 over EKF2_SEL_IMU_ACC
    det = make()
    det.fit(data.slice(0, 200), array)
    out = det.process(data.slice(200, 1500))["accel"]
    assert out.alarm.any()
    assert set(out.isolated[out.alarm].tolist()) == {NOT_ISOLABLE}
    # accumulated velocity error: about (2.5 - 1) m/s^2 * t > 2 m/s -> ~1.3 s + filter lag
    first = int(np.argmax(out.alarm)) + 200
    assert 500 + 120 <= first <= 500 + 170


def test_rotated_imus_are_compared_in_the_body_frame() -> None:
    rng = np.random.default_rng(7)
    flip = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # x/y swapped, z flipped
    imus = tuple(ImuSpec(rotation=flip if k % 2 else np.eye(3)) for k in range(4))
    array = ArrayConfig(imus=imus)
    rate_body = np.array([0.5, -0.3, 1.0])  # 57 deg/s about z: large against the thresholds
    gyro = np.stack([flip.T @ rate_body if k % 2 else rate_body for k in range(4)])
    gyro = np.broadcast_to(gyro, (1000, 4, 3)) + 0.005 * rng.standard_normal((1000, 4, 3))
    accel = np.array([0.0, 0.0, 9.81]) + 0.02 * rng.standard_normal((1000, 4, 3))
    data = ImuBlock(t_ns=np.arange(1000) * DT_NS, gyro=gyro, accel=accel)
    det = make(bias=False)
    det.fit(data.slice(0, 100), array)
    out = det.process(data)
    assert not out["gyro"].alarm.any()
    assert out["gyro"].statistic.max() == 0.0


def test_block_size_does_not_change_rows() -> None:
    rng = np.random.default_rng(8)
    array = ArrayConfig.co_aligned(5)
    data = block(1200, 5, rng)
    assert data.gyro is not None
    data.gyro[600:, 4, 2] += math.radians(15.0)
    whole = make()
    whole.fit(data.slice(0, 100), array)
    expected = whole.process(data)
    pieces = make()
    pieces.fit(data.slice(0, 100), array)
    parts = [pieces.process(data.slice(i, i + 37)) for i in range(0, 1200, 37)]
    for sensor_type in ("gyro", "accel"):
        joined = DetectionBlock.concatenate([p[sensor_type] for p in parts])
        assert_allclose(joined.statistic, expected[sensor_type].statistic, atol=1e-12)
        assert_array_equal(joined.isolated, expected[sensor_type].isolated)
    assert pieces.lookahead_samples == 0
    assert len(pieces.flush()["gyro"]) == 0


def test_defaults_are_the_firmware_parameters() -> None:
    det = make()
    assert_allclose(det.rate_threshold, math.radians(7.0))  # EKF2_SEL_IMU_RAT
    assert_allclose(det.angle_threshold, math.radians(15.0))  # EKF2_SEL_IMU_ANG
    assert det.accel_threshold == 1.0  # EKF2_SEL_IMU_ACC
    assert det.velocity_threshold == 2.0  # EKF2_SEL_IMU_VEL
    assert make(rate_threshold="3deg/s").rate_threshold == pytest.approx(math.radians(3.0))
    assert make(velocity_threshold="1m/s").velocity_threshold == 1.0


def test_bad_configurations_name_the_problem() -> None:
    with pytest.raises(DetectorConfigError, match="types"):
        make(types="mag")
    with pytest.raises(ArrayTooSmallError, match="at least 2 IMUs"):  # exit 3: the data
        make().fit(block(100, 1, np.random.default_rng(0)), ArrayConfig.co_aligned(1))
    partial = ArrayConfig(
        imus=(ImuSpec(), ImuSpec(axes={"gyro": ("x", "y"), "accel": ("x", "y", "z"), "mag": ()}))
    )
    with pytest.raises(DetectorConfigError, match="imu1 has only 2 of 3 axes"):
        make().fit(block(100, 2, np.random.default_rng(0)), partial)


def test_cli_detect_and_report(tmp_path: Any) -> None:
    clean, faulty, detected = (str(tmp_path / f) for f in ("c.mcap", "f.mcap", "d.mcap"))
    args = ["simulate", "--preset", "paper-table4", "--seed", "2", "--duration", "5s"]
    assert invoke([*args, "-o", clean]).code == 0
    fault = "step:imu3.gyro.x,amp=30deg/s,at=3s"
    assert invoke(["inject", clean, "--fault", fault, "-o", faulty]).code == 0
    result = invoke(["detect", faulty, "-d", "px4-selector", "-o", detected])
    assert result.code == 0, result.stderr
    status = read_status(detected)[("px4-selector", "gyro")]
    assert status.alarm.any() and not status.alarm[:300].any()
    result = invoke(["report", detected, "--json", "-"])
    assert result.code == 0, result.stderr
    assert "px4-selector" in result.out
    bad = invoke(["detect", faulty, "-d", "px4-selector", "--param", "px4-selector.smoothing=2"])
    assert_one_line_error(bad, 2, "px4-selector.smoothing")


# --- under a false-alarm budget ----------------------------------------------------------


def test_a_budget_scales_both_thresholds_by_one_factor() -> None:
    from imufdi_cli.faults import FaultInjector, parse_fault_spec
    from imufdi_cli.simulate import preset, simulate_block

    array, log = simulate_block(preset("paper-table4", seed=5, duration=30.0))
    fault = parse_fault_spec("step:imu3.gyro.y,at=10s,amp=0.9deg/s", array)
    log = FaultInjector([fault], array, seed=5, t0_ns=int(log.t_ns[0])).apply_block(log)
    det = make(false_alarms="1/h")
    det.fit(log.slice(0, 200), array)
    meta = det.metadata()["types"]["gyro"]
    scale = meta["budget"]["threshold_scale"]
    assert 0 < scale < 0.05  # the firmware's 7 deg/s comes down to the noise's level
    assert meta["rate_threshold"] == pytest.approx(math.radians(7.0) * scale)
    assert meta["threshold"] == pytest.approx(math.radians(15.0) * scale)
    # the scaled rate threshold sits above the smoothed deviation's mean (|d| ~ 1.6 x
    # 0.16 sigma of the deviation from the 16-IMU mean): E does not drift up
    sigma = math.radians(0.15) * math.sqrt(15 / 16)
    assert meta["rate_threshold"] > 1.6 * math.sqrt(0.05 / 1.95) * sigma
    out = det.process(log)["gyro"]
    t = (log.t_ns - log.t_ns[0]) * 1e-9
    assert not out.alarm[t < 10.0].any()
    first = t[np.flatnonzero(out.alarm)[0]]
    assert 10.0 < first < 11.0  # measured ~0.4 s on tuning seeds
    assert (out.isolated[out.alarm] == 3 * 3 + 1).mean() > 0.99
    assert det.calibration_warnings() == []
    assert make().metadata()["params"]["false_alarms_per_hour"] == 0.0


def test_a_budget_warns_where_the_imus_disagree_beyond_their_noise() -> None:
    from imufdi_cli.simulate import preset, simulate_block

    array, log = simulate_block(preset("wearable12", seed=6, duration=20.0))
    det = make(false_alarms="1/h")
    det.fit(log.slice(0, 200), array)
    det.process(log)
    notes = det.calibration_warnings()
    assert len(notes) == 1 and notes[0].startswith("px4-selector: accel:")
    assert "lever arms" in notes[0] and "\n" not in notes[0]
