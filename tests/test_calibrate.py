"""Per-chip calibration: synthetic arrays with known M, b; missing data errors/warnings."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig, ImuSpec
from imufdi_cli.calibrate import STANDARD_GRAVITY, calibrate_block
from imufdi_cli.errors import CalibrationError
from imufdi_cli.log import ImuBlock

RATE = 100.0
FLIP = np.array([[0.0, -1, 0], [-1, 0, 0], [0, 0, -1]])  # the MIMU4444 bottom face


def _geometry(m=4):
    imus = tuple(ImuSpec(rotation=np.eye(3) if k % 2 == 0 else FLIP) for k in range(m))
    return ArrayConfig(imus=imus, rate_hz=RATE)


def _directions(n, rng):
    u = rng.standard_normal((n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _truth(array, rng, size):
    """M_k = I + P_k with the gauge of calibrate: mean_k R_k M_k R_k^T = I (gyro) or
    symmetric P_k (accel: no common rotation)."""
    rot = array.rotations()
    perturb = [size * rng.standard_normal((3, 3)) for _ in rot]
    mean = sum(r @ p @ r.T for r, p in zip(rot, perturb)) / len(rot)
    perturb = [p - r.T @ mean @ r for r, p in zip(rot, perturb)]
    return [np.eye(3) + p for p in perturb]


def _log(array, rng, *, orientations=12, static_s=8.0, motion_s=20.0, noise=(0.002, 0.02)):
    """Raw samples: static orientations joined by 2 s moves, then motion on all axes."""
    m = array.n_imus
    rot = array.rotations()
    acc_m = [
        np.eye(3) + (p + p.T) / 2 for p in (0.01 * rng.standard_normal((3, 3)) for _ in range(m))
    ]
    gyr_m = _truth(array, rng, 0.01)
    acc_b = 0.3 * rng.standard_normal((m, 3))
    gyr_b = 0.03 * rng.standard_normal((m, 3))
    f_body, w_body = [], []
    dirs = _directions(orientations, rng)
    n_static, n_move = int(static_s * RATE), int(2 * RATE)
    for i, u in enumerate(dirs):
        f_body.append(np.tile(STANDARD_GRAVITY * u, (n_static, 1)))
        w_body.append(np.zeros((n_static, 3)))
        nxt = dirs[(i + 1) % len(dirs)]
        s = np.linspace(0, 1, n_move)[:, None]
        path = (1 - s) * u + s * nxt
        f_body.append(STANDARD_GRAVITY * path / np.linalg.norm(path, axis=1, keepdims=True))
        w_body.append(np.tile(np.cross(u, nxt), (n_move, 1)))
    t = np.arange(int(motion_s * RATE)) / RATE
    w = np.stack(
        [
            2.0 * np.sin(2 * np.pi * 0.7 * t),
            1.5 * np.sin(2 * np.pi * 1.1 * t + 1),
            2.5 * np.sin(2 * np.pi * 0.5 * t + 2),
        ],
        1,
    )
    w_body.append(w)
    f_body.append(np.tile([0, 0, STANDARD_GRAVITY], (len(t), 1)) + rng.standard_normal((len(t), 3)))
    f_body, w_body = np.concatenate(f_body), np.concatenate(w_body)
    n = len(f_body)
    gyro = np.empty((n, m, 3))
    accel = np.empty((n, m, 3))
    for k in range(m):
        gyro[:, k] = (w_body @ rot[k]) @ np.linalg.inv(gyr_m[k]).T + gyr_b[k]
        accel[:, k] = (f_body @ rot[k]) @ np.linalg.inv(acc_m[k]).T + acc_b[k]
    gyro += noise[0] * rng.standard_normal(gyro.shape)
    accel += noise[1] * rng.standard_normal(accel.shape)
    block = ImuBlock(t_ns=(np.arange(n) * 1e9 / RATE).astype(np.int64), gyro=gyro, accel=accel)
    return block, (acc_m, acc_b, gyr_m, gyr_b)


def test_recovers_known_calibration():
    rng = np.random.default_rng(7)
    array = _geometry()
    block, (acc_m, acc_b, gyr_m, gyr_b) = _log(array, rng)
    result = calibrate_block(array, block)
    assert len(result.intervals) == 12 and result.orientations == 12
    assert result.coverage > 0.3
    assert not result.warnings
    # accel: per-interval mean noise sigma = 0.02/sqrt(650) ~ 8e-4 m/s^2 per axis; the
    # tolerances are 10 sigma (b, m/s^2) and 10 sigma / g (M)
    for k, imu in enumerate(result.array.imus):
        assert_allclose(imu.calibration_of("accel").matrix, acc_m[k], atol=8e-4)
        assert_allclose(imu.calibration_of("accel").bias, acc_b[k], atol=8e-3)
        assert_allclose(imu.calibration_of("gyro").matrix, gyr_m[k], atol=2e-3)
        assert_allclose(imu.calibration_of("gyro").bias, gyr_b[k], atol=5e-4)
    before, after = result.residual_rms["accel"]
    assert after < 0.01 * before
    assert after < 5e-3
    # per-sensor noise at rest: 12 intervals of ~7 s (8,000+ rows); the relative standard
    # error of a residual-based sigma is ~ sqrt(Var(sigma^2 est) / 4) ~ 1 % here: 6 %
    # tolerance is 6 standard errors
    assert_allclose(result.array.sensor_noise("gyro"), 0.002, rtol=0.06)
    assert_allclose(result.array.sensor_noise("accel"), 0.02, rtol=0.06)


def test_few_orientations_and_no_motion_warn_and_estimate_biases_only():
    rng = np.random.default_rng(3)
    array = _geometry()
    block, _ = _log(array, rng, orientations=3, motion_s=0.0)
    result = calibrate_block(array, block)
    assert result.orientations == 3
    text = " ".join(result.warnings)
    assert "only 3 orientation(s)" in text and "biases only" in text
    for imu in result.array.imus:
        assert_allclose(imu.calibration_of("accel").matrix, np.eye(3))


def test_no_static_interval_is_bad_input():
    rng = np.random.default_rng(0)
    array = _geometry()
    n = 3000
    gyro = rng.standard_normal((n, 1, 3)).repeat(4, axis=1)
    accel = 5 * rng.standard_normal((n, 1, 3)).repeat(4, axis=1)
    block = ImuBlock(t_ns=(np.arange(n) * 1e7).astype(np.int64), gyro=gyro, accel=accel)
    with pytest.raises(CalibrationError, match="no static interval of at least 5 s"):
        calibrate_block(array, block)


def test_needs_accelerometers():
    block = ImuBlock(t_ns=np.arange(10), gyro=np.zeros((10, 4, 3)))
    with pytest.raises(CalibrationError, match="needs accelerometers"):
        calibrate_block(_geometry(), block)


def test_time_offsets_recovered_on_synthetic_motion():
    """Chips sampling a smooth rotation dt_k late: w_k(t) = w(t + dt_k); the regression on
    the consensus angular acceleration recovers dt_k - mean(dt) (the second-order term
    w_ddot dt^2 / 2 is ~1e-4 of the first at these rates: tolerance 2 % of the offsets)."""
    from imufdi_cli.calibrate import time_offsets

    array = _geometry(4)
    t = np.arange(2000) / RATE
    dt = np.array([0.002, -0.001, 0.0005, -0.0015])

    def rate(time):
        return np.stack(
            [2 * np.sin(2 * np.pi * 0.7 * time), np.cos(2 * np.pi * 1.1 * time), np.sin(time)],
            axis=-1,
        )

    rot = array.rotations()
    gyro = np.stack([rate(t + dt[k]) @ rot[k] for k in range(4)], axis=1)  # R_k^T w
    offsets, explained = time_offsets(array, gyro, t, np.ones(len(t), bool))
    assert_allclose(offsets, dt - dt.mean(), atol=0.02 * np.abs(dt).max())
    assert np.all(explained > 0.99)
    # no offset: nothing to explain
    same = np.stack([rate(t) @ rot[k] for k in range(4)], axis=1)
    offsets, _ = time_offsets(array, same, t, np.ones(len(t), bool))
    assert_allclose(offsets, 0.0, atol=1e-9)
