"""Tests of imufdi_cli.simulate.presets: preset figures, other presets, construction."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.errors import UsageError
from imufdi_cli.log import ImuBlock
from imufdi_cli.simulate import (
    CONE_HALF_ANGLE,
    PRESETS,
    SwingMotion,
    TurntableMotion,
    config_from_options,
    euler_from_rotation,
    make_motion,
    preset,
    rotation_from_euler,
    simulate,
    simulate_block,
    true_block,
    true_motion,
)
from imufdi_cli.units import STANDARD_GRAVITY
from tests.simulate.conftest import DEG, binomial_interval, sigma_interval

# --- paper-table4 ---------------------------------------------------------------------------


def test_paper_table4_figures(scipy_stats) -> None:
    config = preset("paper-table4", seed=3, duration=20.0)  # longer: tighter intervals
    array, block = simulate_block(config)
    truth = true_block(config)
    assert array.n_imus == 16 and array.rate_hz == 100.0
    assert block.gyro is not None and block.accel is not None and truth.gyro is not None
    assert block.mag is None
    gyro_error = block.gyro - truth.gyro
    outlier = np.abs(gyro_error) > 0.6 * DEG  # 4 sigma of the white noise
    n_channels = gyro_error.size
    low, high = binomial_interval(0.001 + 2 * scipy_stats.norm.sf(4), n_channels)
    assert low <= outlier.mean() <= high
    # outliers have amplitude exactly +-1 deg/s on top of the noise
    residual = np.abs(gyro_error[outlier]) - 1.0 * DEG
    assert np.all(np.abs(residual) < 0.8 * DEG)
    clean = gyro_error[~outlier]
    low, high = sigma_interval(0.15 * DEG, clean.size, p=1e-3)
    # truncating at 4 sigma removes a negligible part of the variance (< 0.2 %)
    assert low * 0.995 <= clean.std() <= high
    accel_error = block.accel - true_block(config).accel
    low, high = sigma_interval(0.02, accel_error.size)
    assert low <= accel_error.std() <= high
    # turntable: 10 deg/s on each body axis (co-aligned: IMU axes = body axes)
    assert_allclose(block.gyro.mean(axis=(0, 1)), 10.0 * DEG, atol=6 * 0.15 * DEG / 100)
    assert_allclose(truth.gyro, 10.0 * DEG, rtol=1e-12)
    # nominal noise is carried in the ArrayConfig for detectors
    assert_allclose(array.noise["gyro"], 0.15 * DEG)
    assert_allclose(array.noise["accel"], 0.02)


def test_paper_table4_defaults() -> None:
    config = preset("paper-table4")
    assert config.n_samples == 500 and config.duration_s == 5.0
    gyro = config.errors["gyro"]
    assert gyro.outlier_probability == 0.001
    assert_allclose(gyro.outlier_amplitude, 1.0 * DEG)
    assert PRESETS["paper-table4"].faults["step"] == ("step:imu0.gyro.x,at=2.5s,amp=0.9deg/s",)


def test_outliers_off_and_chip_biases() -> None:
    config = preset("paper-table4", seed=1, outliers=False)
    _, block = simulate_block(config)
    assert block.gyro is not None
    error = block.gyro - true_block(config).gyro
    assert np.abs(error).max() < 6 * 0.15 * DEG
    # switching outliers off leaves the white noise draw unchanged
    _, with_outliers = simulate_block(preset("paper-table4", seed=1))
    assert with_outliers.gyro is not None
    same = with_outliers.gyro == block.gyro
    assert same.mean() > 0.99 and not same.all()
    biased = preset("paper-table4", seed=1, outliers=False, chip_biases="0.5deg/s", duration=50)
    _, block_b = simulate_block(biased)
    assert block_b.gyro is not None
    bias = (block_b.gyro - true_block(biased).gyro).mean(axis=0)  # (16, 3)
    low, high = sigma_interval(0.5 * DEG, bias.size)
    assert low <= bias.std() <= high
    # constant: first and second half give the same bias
    half = len(block_b) // 2
    first = (block_b.gyro[:half] - true_block(biased, 0, half).gyro).mean(axis=0)
    assert_allclose(first, bias, atol=6 * 0.15 * DEG / math.sqrt(half))


# --- other presets --------------------------------------------------------------------------


def test_conical6_geometry_and_motion() -> None:
    config = preset("conical6")
    array, block = simulate_block(config)
    h = array.measurement_matrix("gyro")
    assert h.shape == (6, 3)
    assert_allclose(np.degrees(np.arccos(h[:, 2])), 54.7356, atol=1e-4)
    assert_allclose(CONE_HALF_ANGLE, math.acos(1 / math.sqrt(3)))
    azimuth = np.degrees(np.arctan2(h[:, 1], h[:, 0])) % 360
    assert_allclose(azimuth, [0, 60, 120, 180, 240, 300], atol=1e-9)
    assert array.sensor_ids("gyro") == [f"imu{k}.gyro.z" for k in range(6)]
    assert not array.has("accel") and block.accel is None
    assert block.gyro is not None and np.isnan(block.gyro[:, :, :2]).all()
    measured = array.select(block.gyro, "gyro")
    state = true_motion(config)
    assert np.abs(state.angular_rate[:100]).max() == 0.0  # static first second
    assert np.abs(state.angular_rate[150:]).max() > 30 * DEG  # tens of deg/s later
    # fault-free parity residual (errors only) stays far below the 0.5 deg/s fault
    _, _, vt = np.linalg.svd(h.T)
    parity = vt[3:]  # (3, 6), V H = 0
    residual = (measured - measured[:100].mean(axis=0)) @ parity.T
    assert np.abs(residual).max() < 0.25 * DEG
    assert residual[100:].std() < 1.5 * residual[:100].std()


def test_wearable12_lever_arms() -> None:
    config = preset("wearable12", seed=2)
    array, block = simulate_block(config)
    assert array.n_imus == 12 and config.n_samples == 3000
    positions = array.positions()
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    assert distance[~np.eye(12, dtype=bool)].min() >= 0.03 - 1e-12
    assert block.accel is not None
    difference = block.accel[:, 0] - block.accel[:, 11]
    assert np.abs(difference).max() > 20 * 0.03  # lever arms dominate the noise
    accel_error = block.accel - true_block(config).accel
    low, high = sigma_interval(0.03, accel_error.size)
    assert low <= accel_error.std() <= high
    assert np.abs(true_motion(config).angular_rate).max() > 60 * DEG


def test_quadrotor_set_points_and_magnetometer() -> None:
    config = preset("quadrotor-marg", accel_noise=0, mag_noise=0, gyro_noise=0)
    _, block = simulate_block(config)
    state = true_motion(config)
    assert block.accel is not None and block.mag is not None
    set_points = {
        50: (-25, -35, -10),  # 0.5 s
        300: (0, 0, 0),  # 3 s
        800: (10, -20, 5),  # 8 s
    }
    field = np.array([0.5, 0.0, math.sqrt(3) / 2]) * 50e-6
    for index, rpy in set_points.items():
        attitude = rotation_from_euler(*np.radians(rpy))
        assert_allclose(np.degrees(euler_from_rotation(state.attitude[index])), rpy, atol=1e-9)
        # at rest the accelerometer measures -gravity in the body frame
        assert_allclose(block.accel[index, 0], attitude.T @ [0, 0, STANDARD_GRAVITY], atol=1e-12)
        assert_allclose(block.mag[index, 0], attitude.T @ field, atol=1e-18)
        assert_allclose(state.angular_rate[index], 0.0, atol=1e-15)
    # noise figures
    noisy = preset("quadrotor-marg", seed=4, duration=100)
    _, noisy_block = simulate_block(noisy)
    truth = true_block(noisy)
    for name, sigma in (("gyro", 0.01), ("accel", 0.002 * 9.80665), ("mag", 0.0007 * 50e-6)):
        error = noisy_block.get(name) - truth.get(name)  # type: ignore[operator]
        low, high = sigma_interval(sigma, error.size)
        assert low <= error.std() <= high, name


# --- construction and validation ------------------------------------------------------------


def test_config_from_options_free_and_preset() -> None:
    config = config_from_options(
        None, imus=4, rate="1kHz", duration="2s", motion="turntable", seed=1
    )
    assert config.array.n_imus == 4 and config.rate_hz == 1000.0 and config.n_samples == 2000
    assert isinstance(config.motion, TurntableMotion)
    assert config.seed == 1
    config = config_from_options(
        None, motion="turntable", motion_params={"rate": "0,0,90deg/s"}, gyro_noise="0.1deg/s"
    )
    assert_allclose(config.motion.rate, (0, 0, math.pi / 2))  # type: ignore[attr-defined]
    assert_allclose(config.errors["gyro"].noise, 0.1 * DEG)
    from_preset = config_from_options("conical6", seed=2, duration="3s", imus=None)
    assert from_preset.name == "conical6" and from_preset.duration_s == 3.0


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"preset_name": "nope"}, "valid: conical6, paper-table4, quadrotor-marg, wearable12"),
        ({"motion": "spin"}, "valid: attitude, static, swing, turntable, vehicle"),
        ({"rate": "10deg"}, "rate"),
        ({"duration": -1}, "duration must be > 0"),
        ({"imus": 0}, "--imus"),
        ({"colour": "red"}, "unknown simulation option 'colour'"),
        ({"motion": "turntable", "motion_params": {"speed": 1}}, "valid: rate"),
        ({"outliers": 2.0}, "outliers"),
        ({"seed": -3}, "seed"),
    ],
)
def test_config_from_options_errors(kwargs, fragment) -> None:
    with pytest.raises(UsageError, match=None) as info:
        config_from_options(**kwargs)
    assert fragment in str(info.value)


def test_make_motion_parses_units() -> None:
    motion = make_motion("swing", amplitude="20deg", frequency_hz="2Hz", start="1s")
    assert isinstance(motion, SwingMotion)
    assert_allclose(motion.amplitude, (20 * DEG,) * 3)
    assert motion.start == 1.0
    with pytest.raises(UsageError, match="valid: attitude"):
        make_motion("warp")


def test_preset_overrides() -> None:
    config = preset("paper-table4", n_imus=5, rate=200, noise_scale=2.0)
    assert config.array.n_imus == 5 and config.rate_hz == 200.0
    assert_allclose(config.errors["gyro"].noise, 0.3 * DEG)
    assert_allclose(config.array.noise["gyro"], 0.3 * DEG)
    with pytest.raises(UsageError, match="valid: duration"):
        preset("paper-table4", speed=3)
    with pytest.raises(UsageError, match="n_imus"):
        preset("paper-table4", n_imus=0)


def test_every_preset_runs_and_lists_faults() -> None:
    for name, info in PRESETS.items():
        assert info.name == name and info.source and info.faults
        for specs in info.faults.values():
            assert all(spec.split(":")[0] in {"step", "drift", "noise"} for spec in specs)
        config = preset(name, duration=0.2)
        array, block = simulate_block(config)
        assert len(block) == 20 and block.n_imus == array.n_imus


def test_paper_table4_plain_glt_lands_near_the_paper_row(scipy_stats) -> None:
    """docs/simulate.md: a per-sample GLT at alpha = 0.01 with the 0.9 deg/s step on imu0.gyro.x
    gives FAR ~ 5 %, MAR ~ 27 %, FIR ~ 4 % (Li et al. Table 4, GLT row: 4.98, 26.58)."""
    far, mar, fir = [], [], []
    for seed in range(20):
        config = preset("paper-table4", seed=seed)
        array, block = simulate_block(config)
        assert block.gyro is not None
        h = array.measurement_matrix("gyro")
        measured = array.select(block.gyro, "gyro")
        onset = 250  # 2.5 s
        measured[onset:, 0] += 0.9 * DEG
        left, _, _ = np.linalg.svd(h)
        parity_matrix = left[:, 3:].T  # (n-3, n), V H = 0, V V^T = I
        parity = measured @ parity_matrix.T
        statistic = (parity**2).sum(axis=1) / (0.15 * DEG) ** 2
        alarm = statistic > scipy_stats.chi2.ppf(0.99, parity_matrix.shape[0])
        isolation = ((parity @ parity_matrix) ** 2 / (parity_matrix**2).sum(axis=0)).argmax(1)
        far.append(alarm[:onset].mean())
        mar.append((~alarm[onset:]).mean())
        fir.append((isolation[onset:][alarm[onset:]] != 0).mean())
    assert 0.035 <= np.mean(far) <= 0.065
    assert 0.22 <= np.mean(mar) <= 0.33
    assert 0.02 <= np.mean(fir) <= 0.07


@settings(max_examples=25, deadline=None)
@given(
    block_size=st.integers(min_value=1, max_value=300),
    n_imus=st.integers(min_value=1, max_value=5),
    rate=st.sampled_from(["50Hz", "100", "0.2kHz", "333Hz"]),
    seed=st.integers(min_value=0, max_value=2**32),
)
def test_options_and_block_size_property(block_size, n_imus, rate, seed) -> None:
    config = config_from_options(
        None, imus=n_imus, rate=rate, duration="0.6s", motion="vehicle", seed=seed
    )
    expected_rate = {"50Hz": 50.0, "100": 100.0, "0.2kHz": 200.0, "333Hz": 333.0}[rate]
    assert config.rate_hz == expected_rate
    assert config.n_samples == round(0.6 * expected_rate)
    _, whole = simulate_block(config)
    _, blocks = simulate(config, block_size=block_size)
    joined = ImuBlock.concatenate(blocks)
    assert whole.gyro is not None and whole.gyro.shape == (config.n_samples, n_imus, 3)
    assert_array_equal(joined.gyro, whole.gyro)
    assert_array_equal(joined.accel, whole.accel)
    assert np.all(np.diff(whole.t_ns) > 0)


def test_describe_is_json_and_block_size_is_checked() -> None:
    import json

    for name in PRESETS:
        described = json.loads(json.dumps(preset(name, seed=5).describe()))
        assert described["name"] == name and described["seed"] == 5
    quadrotor = preset("quadrotor-marg").describe()
    assert quadrotor["motion"] == "attitude"
    assert_allclose(quadrotor["moves"][1][2], np.radians([10, -20, 5]))
    with pytest.raises(UsageError, match="block_size"):
        simulate(preset("paper-table4"), block_size=0)
