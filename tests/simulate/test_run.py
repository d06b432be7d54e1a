"""Tests of imufdi_cli.simulate.run: reproducibility, kinematic consistency, error models."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.array import ArrayConfig
from imufdi_cli.log import ImuBlock
from imufdi_cli.simulate import (
    CHUNK_SAMPLES,
    DEFAULT_T0_NS,
    AttitudeMotion,
    SensorErrors,
    SimConfig,
    StaticMotion,
    SwingMotion,
    TurntableMotion,
    VehicleMotion,
    preset,
    rotation_from_euler,
    simulate,
    simulate_block,
    true_motion,
)
from imufdi_cli.units import STANDARD_GRAVITY
from tests.simulate.conftest import sigma_interval

# --- reproducibility ------------------------------------------------------------------------


def test_same_seed_same_arrays_and_block_size_invariance() -> None:
    config = preset("wearable12", seed=7, duration=2.0 * CHUNK_SAMPLES / 100 + 1)
    _, whole = simulate_block(config)
    _, again = simulate_block(config)
    assert_array_equal(whole.gyro, again.gyro)
    assert_array_equal(whole.accel, again.accel)
    for block_size in (1, 997, CHUNK_SAMPLES, 10_000, 10 * config.n_samples):
        if block_size == 1:
            config_small = replace(config, duration_s=0.5)
            _, small = simulate(config_small, block_size=1)
            joined = ImuBlock.concatenate(small)
            assert_array_equal(joined.gyro, whole.gyro[:50])
            continue
        _, blocks = simulate(config, block_size=block_size)
        pieces = list(blocks)
        assert all(len(p) == block_size for p in pieces[:-1])
        joined = ImuBlock.concatenate(pieces)
        assert_array_equal(joined.t_ns, whole.t_ns)
        assert_array_equal(joined.gyro, whole.gyro)
        assert_array_equal(joined.accel, whole.accel)
    _, other = simulate_block(replace(config, seed=8))
    assert not np.array_equal(other.gyro, whole.gyro)


def test_timestamps() -> None:
    config = preset("paper-table4", rate="300Hz", duration=1.0)
    _, block = simulate_block(config)
    index = np.arange(300)
    expected = DEFAULT_T0_NS + np.round(index * 1e9 / 300).astype(np.int64)
    assert_array_equal(block.t_ns, expected)
    assert block.t_ns.dtype == np.int64
    shifted = preset("paper-table4", t0_ns=0)
    _, block0 = simulate_block(shifted)
    assert block0.t_ns[0] == 0 and block0.t_ns[1] == 10_000_000


# --- kinematic consistency ------------------------------------------------------------------

MOTIONS_TO_CHECK = [
    StaticMotion(attitude_rpy=(0.1, -0.2, 0.3)),
    TurntableMotion(rate=(0.3, -0.2, 0.5)),
    SwingMotion(start=0.5, ramp=0.7),
    VehicleMotion(),
    AttitudeMotion(),
    preset("quadrotor-marg").motion,
    preset("conical6").motion,
]


def _log_so3(matrices: np.ndarray) -> np.ndarray:
    """Rotation vectors of rotation matrices (angles well below pi)."""
    cos_angle = np.clip((np.trace(matrices, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos_angle)
    vee = np.stack(
        [
            matrices[..., 2, 1] - matrices[..., 1, 2],
            matrices[..., 0, 2] - matrices[..., 2, 0],
            matrices[..., 1, 0] - matrices[..., 0, 1],
        ],
        axis=-1,
    )
    factor = np.where(angle < 1e-8, 0.5, angle / (2.0 * np.sin(np.maximum(angle, 1e-300))))
    return factor[..., None] * vee


@pytest.mark.parametrize("motion", MOTIONS_TO_CHECK, ids=lambda m: type(m).__name__)
def test_attitude_integrates_angular_rate(motion) -> None:
    t = np.linspace(0.0, 9.0, 401)
    h = 1e-5
    state = motion.evaluate(t)
    before, after = motion.evaluate(t - h), motion.evaluate(t + h)
    # C(t-h)^T C(t+h) = exp(2h [w]x) + O(h^3)
    increment = np.einsum("nji,njk->nik", before.attitude, after.attitude)
    rate_fd = _log_so3(increment) / (2 * h)
    assert_allclose(rate_fd, state.angular_rate, atol=1e-6)
    accel_fd = (after.angular_rate - before.angular_rate) / (2 * h)
    assert_allclose(accel_fd, state.angular_acceleration, atol=1e-4)
    # specific force: dv/dt = C f + g
    accel_nav = (after.velocity - before.velocity) / (2 * h)
    gravity = np.array([0.0, 0.0, -STANDARD_GRAVITY])
    expected = np.einsum("nij,nj->ni", state.attitude, state.specific_force) + gravity
    assert_allclose(accel_nav, expected, atol=1e-4)
    # attitudes are rotations
    gram = np.einsum("nji,njk->nik", state.attitude, state.attitude)
    assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-12)


def test_static_level_body_measures_plus_g() -> None:
    state = StaticMotion().evaluate(np.zeros(3))
    assert_allclose(state.specific_force, [[0, 0, STANDARD_GRAVITY]] * 3)
    assert_allclose(state.angular_rate, 0.0)


def test_noise_free_co_aligned_gyro_equals_body_rate_and_lever_arms() -> None:
    positions = np.array([[0, 0, 0], [0.05, 0, 0], [0, -0.04, 0.02], [0.03, 0.03, -0.03]])
    array = ArrayConfig.co_aligned(4, 200.0, positions=positions)
    config = SimConfig(array=array, duration_s=3.0, motion=SwingMotion(), errors={})
    _, block = simulate_block(config)
    state = true_motion(config)
    assert block.gyro is not None and block.accel is not None
    for k in range(4):
        assert_array_equal(block.gyro[:, k], state.angular_rate)
    # lever arm: IMU k's accel minus the origin's = C^T d2/dt2 (C r_k), by finite differences
    h = 1e-4
    t = state.t_s
    before, after = config.motion.evaluate(t - h), config.motion.evaluate(t + h)
    for k in range(1, 4):
        r = positions[k]
        second = (
            after.attitude @ r - 2 * (state.attitude @ r) + before.attitude @ r
        ) / h**2  # nav frame
        expected = np.einsum("nji,nj->ni", state.attitude, second)
        assert_allclose(block.accel[:, k] - block.accel[:, 0], expected, atol=2e-3)


def test_rotated_imu_measures_rotated_quantities() -> None:
    base = preset("quadrotor-marg", gyro_noise=0, accel_noise=0, mag_noise=0)
    rotation = rotation_from_euler(0.3, -0.5, 1.2)
    imu = replace(base.array.imus[0], rotation=rotation)
    config = replace(base, array=ArrayConfig(imus=(imu,), rate_hz=100.0))
    _, block = simulate_block(config)
    _, reference = simulate_block(base)
    for name in ("gyro", "accel", "mag"):
        body = reference.get(name)[:, 0]  # type: ignore[index]
        assert_allclose(block.get(name)[:, 0], body @ rotation, atol=1e-15 * 1e9)  # type: ignore[index]


# --- error models ---------------------------------------------------------------------------


def test_bias_random_walk_grows_with_sqrt_time() -> None:
    array = ArrayConfig.co_aligned(50, 100.0, sensors=("gyro",))
    errors = {"gyro": SensorErrors(bias_random_walk=0.01)}
    config = SimConfig(array=array, duration_s=100.0, motion=StaticMotion(), errors=errors)
    _, block = simulate_block(config)
    assert block.gyro is not None
    # after T seconds the walk has std 0.01 * sqrt(T)
    low, high = sigma_interval(0.01 * 10.0, 150)
    assert low <= block.gyro[-1].std() <= high
    # continuous across internal chunks: steps are all small
    steps = np.diff(block.gyro, axis=0)
    assert np.abs(steps).max() < 6 * 0.01 / 10


def test_scale_factor_and_misalignment() -> None:
    array = ArrayConfig.co_aligned(200, 100.0, sensors=("gyro",))
    errors = {"gyro": SensorErrors(scale_factor_sigma=1e-3)}
    motion = TurntableMotion(rate=(1.0, 0.0, 0.0))
    config = SimConfig(array=array, duration_s=0.05, motion=motion, errors=errors)
    _, block = simulate_block(config)
    assert block.gyro is not None
    scale = block.gyro[0, :, 0] - 1.0
    low, high = sigma_interval(1e-3, scale.size)
    assert low <= scale.std() <= high
    assert_allclose(block.gyro[:, :, 1:], 0.0, atol=1e-15)
    mis = replace(config, errors={"gyro": SensorErrors(misalignment_sigma=1e-3)})
    _, block_m = simulate_block(mis)
    assert block_m.gyro is not None
    # small rotation exp([d]x) moves x onto y by d_z and onto z by -d_y; norm is kept
    assert_allclose(np.linalg.norm(block_m.gyro[0], axis=-1), 1.0, rtol=1e-12)
    low, high = sigma_interval(1e-3, 400)
    assert low <= block_m.gyro[0, :, 1:].std() <= high
