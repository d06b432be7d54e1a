"""Tests of imufdi_cli.faults.injector: model effects, statistics, streaming."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.array import ArrayConfig
from imufdi_cli.faults import (
    FaultInjector,
    parse_fault_spec,
)
from imufdi_cli.log import ImuBlock, iter_blocks
from tests.faults.conftest import DEG, T0_NS, G, make_block, rel_s

# --- models: exact effects ----------------------------------------------------------------


def _inject(array: ArrayConfig, specs: list[str], block: ImuBlock, seed: int = 0) -> ImuBlock:
    faults = [parse_fault_spec(s, array) for s in specs]
    return FaultInjector(faults, array, seed=seed, t0_ns=T0_NS).apply_block(block)


def test_step_exact(array: ArrayConfig) -> None:
    block = make_block(1000)
    out = _inject(array, ["step:imu0.gyro.x,at=2.5s,until=7s,amp=0.9deg/s"], block)
    t = rel_s(block)
    expected = np.where((t >= 2.5) & (t < 7.0), 0.9 * DEG, 0.0)
    assert_allclose(out.gyro[:, 0, 0] - block.gyro[:, 0, 0], expected, atol=1e-12, rtol=0)
    # nothing else touched
    untouched = np.ones(block.gyro.shape, bool)
    untouched[:, 0, 0] = False
    assert_array_equal(out.gyro[untouched], block.gyro[untouched])
    assert_array_equal(out.accel, block.accel)
    assert_array_equal(out.mag, block.mag)


def test_drift_exact(array: ArrayConfig) -> None:
    block = make_block(1000)
    out = _inject(array, ["drift:imu1.accel,at=3s,until=8s,rate=0.01g/s"], block)
    t = rel_s(block)
    ramp = np.where((t >= 3.0) & (t < 8.0), 0.01 * G * (t - 3.0), 0.0)
    assert_allclose(
        out.accel[:, 1, :] - block.accel[:, 1, :], ramp[:, None] * np.ones(3), atol=1e-12, rtol=0
    )


def test_stuck_exact(array: ArrayConfig) -> None:
    block = make_block(600)
    out = _inject(array, ["stuck:imu2.gyro.y,at=2s,until=4s"], block)
    t = rel_s(block)
    window = (t >= 2.0) & (t < 4.0)
    last_before = np.flatnonzero(t < 2.0)[-1]
    assert_array_equal(out.gyro[window, 2, 1], block.gyro[last_before, 2, 1])
    assert_array_equal(out.gyro[~window, 2, 1], block.gyro[~window, 2, 1])


def test_stuck_from_log_start_freezes_first_sample(array: ArrayConfig) -> None:
    block = make_block(50)
    out = _inject(array, ["stuck:imu0.mag"], block)
    assert_array_equal(out.mag[:, 0, :], np.broadcast_to(block.mag[0, 0, :], (50, 3)))


def test_scale_exact(array: ArrayConfig) -> None:
    block = make_block(500)
    out = _inject(array, ["scale:imu3.accel.z,at=1s,factor=1.02"], block)
    t = rel_s(block)
    expected = np.where(t >= 1.0, 0.02 * block.accel[:, 3, 2], 0.0)
    assert_allclose(out.accel[:, 3, 2] - block.accel[:, 3, 2], expected, atol=1e-12, rtol=0)


def test_faults_on_same_sensor_compose_in_order(array: ArrayConfig) -> None:
    block = make_block(300)
    out = _inject(array, ["scale:imu0.gyro.x,factor=2", "step:imu0.gyro.x,at=1s,amp=1rad/s"], block)
    t = rel_s(block)
    assert_allclose(out.gyro[:, 0, 0], 2 * block.gyro[:, 0, 0] + (t >= 1.0), atol=1e-12)


# --- models: statistics ---------------------------------------------------------------------


@pytest.mark.slow
def test_noise_growth_sigma_ratio() -> None:
    sigma0 = 0.02
    n = 200_000
    array = ArrayConfig.co_aligned(2, noise={"accel": sigma0})
    rng = np.random.default_rng(5)
    t_ns = T0_NS + np.arange(n, dtype=np.int64) * 10_000_000
    accel = rng.normal(0.0, sigma0, (n, 2, 3))
    block = ImuBlock(t_ns=t_ns, accel=accel)
    out = _inject(array, ["noise:imu0.accel.x,at=100s,factor=3"], block, seed=11)
    t = rel_s(block)
    ratio = out.accel[t >= 100, 0, 0].std() / accel[t >= 100, 0, 0].std()
    assert abs(ratio / 3.0 - 1.0) < 0.05
    assert_array_equal(out.accel[t < 100, 0, 0], accel[t < 100, 0, 0])


def test_noise_added_sigma() -> None:
    array = ArrayConfig.co_aligned(1)
    block = ImuBlock(t_ns=np.arange(40_000) * 10_000_000, gyro=np.zeros((40_000, 1, 3)))
    faults = [parse_fault_spec("noise:imu0.gyro.z,sigma=0.5deg/s", array)]
    out = FaultInjector(faults, array, seed=3, t0_ns=0).apply_block(block)
    added = out.gyro[:, 0, 2]
    # sample std of 40000 normals: relative standard error 1/sqrt(2N) = 0.35 %
    assert abs(added.std() / (0.5 * DEG) - 1.0) < 0.02
    assert abs(added.mean()) < 4 * 0.5 * DEG / math.sqrt(40_000)


def test_spikes_rate_and_amplitude() -> None:
    array = ArrayConfig.co_aligned(1)
    n, rate = 100_000, 2.0  # 1000 s at 100 Hz
    block = ImuBlock(t_ns=np.arange(n) * 10_000_000, gyro=np.zeros((n, 1, 3)))
    faults = [parse_fault_spec(f"spikes:imu0.gyro,rate={rate}Hz,amp=1deg/s", array)]
    out = FaultInjector(faults, array, seed=9, t0_ns=0).apply_block(block).gyro[:, 0, :]
    assert set(np.unique(np.abs(out))) <= {0.0, DEG}
    counts = np.count_nonzero(out, axis=0)
    p = -math.expm1(-rate * 0.01)
    expected = n * p  # width 1: one faulty sample per event
    assert np.all(np.abs(counts - expected) < 4 * math.sqrt(expected * (1 - p)))
    positive = np.count_nonzero(out > 0)
    assert abs(positive / counts.sum() - 0.5) < 4 * 0.5 / math.sqrt(counts.sum())


def test_spikes_width() -> None:
    array = ArrayConfig.co_aligned(1)
    n = 20_000
    block = ImuBlock(t_ns=np.arange(n) * 10_000_000, gyro=np.zeros((n, 1, 3)))
    faults = [parse_fault_spec("spikes:imu0.gyro.x,rate=0.5Hz,amp=1rad/s,width=5", array)]
    out = FaultInjector(faults, array, seed=2, t0_ns=0).apply_block(block).gyro[:, 0, 0]
    on = out != 0
    starts = np.flatnonzero(on & ~np.concatenate([[False], on[:-1]]))
    ends = np.flatnonzero(on & ~np.concatenate([on[1:], [False]]))
    lengths = ends - starts + 1
    assert starts.size > 50
    assert np.all(lengths[ends < n - 1] >= 5)  # bursts may merge, never shorter than width
    assert_array_equal(np.abs(out[on]), 1.0)


# --- determinism and streaming -------------------------------------------------------------

_MIXED = [
    "noise:imu0.gyro.x,at=0.3s,until=4s,sigma=0.2deg/s",
    "spikes:imu1.gyro,at=0.5s,rate=20Hz,amp=1deg/s,width=3",
    "stuck:imu2.accel.z,at=1.05s,until=3s",
    "drift:imu3.mag.y,at=0.2s,rate=1uT/s",
    "step:imu0.gyro.x,at=1s,amp=0.1rad/s",
]


@pytest.mark.parametrize("block_size", [1, 7, 64, 333])
def test_block_splits_do_not_change_output(array: ArrayConfig, block_size: int) -> None:
    block = make_block(500)
    faults = [parse_fault_spec(s, array) for s in _MIXED]
    whole = FaultInjector(faults, array, seed=42, t0_ns=T0_NS).apply_block(block)
    injector = FaultInjector(faults, array, seed=42, t0_ns=T0_NS)
    pieces = ImuBlock.concatenate(injector.apply_block(b) for b in iter_blocks(block, block_size))
    for name in ("gyro", "accel", "mag"):
        assert_array_equal(getattr(pieces, name), getattr(whole, name))


def test_seed_determinism(array: ArrayConfig) -> None:
    block = make_block(300)
    faults = [parse_fault_spec(s, array) for s in _MIXED]
    a = FaultInjector(faults, array, seed=1, t0_ns=T0_NS).apply_block(block)
    b = FaultInjector(faults, array, seed=1, t0_ns=T0_NS).apply_block(block)
    c = FaultInjector(faults, array, seed=2, t0_ns=T0_NS).apply_block(block)
    assert_array_equal(a.gyro, b.gyro)
    assert not np.array_equal(a.gyro, c.gyro)


def test_apply_does_not_modify_input(array: ArrayConfig) -> None:
    block = make_block(200)
    before = block.copy()
    _inject(array, _MIXED, block)
    assert_array_equal(block.gyro, before.gyro)
    assert_array_equal(block.accel, before.accel)
