"""Per-chip calibration: synthetic arrays with known M, b; missing data errors/warnings."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig, ImuSpec
from imufdi_cli.calibrate import (
    STANDARD_GRAVITY,
    StaticInterval,
    calibrate_block,
    expected_normal_range,
    noise_spread,
)
from imufdi_cli.errors import CalibrationError, ImufdiError
from imufdi_cli.log import ImuBlock
from imufdi_cli.tomlfile import parse_toml

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


def test_expected_normal_range_matches_tabulated_values():
    # Tippett (1925) / standard d2 control-chart constants
    for n, d in ((2, 1.128), (5, 2.326), (10, 3.078), (20, 3.735)):
        assert abs(expected_normal_range(n) - d) < 1e-3
    assert expected_normal_range(1) == 0.0


def _orientation_log(rng, factor, *, orientations=6, seconds=60.0, m=8, sigma=(0.002, 0.02)):
    """Static orientations of an m-IMU board (identity calibration) whose imu1.gyro.z and
    imu2.accel.x noise sigma is ``factor`` times the nominal one in the last orientation."""
    array = _geometry(m)
    rot = array.rotations()
    n = int(seconds * RATE)
    gap = 10
    dirs = _directions(orientations, rng)
    accel, gyro, static, intervals = [], [], [], []
    for o, u in enumerate(dirs):
        start = len(static) / RATE
        g_sig = np.full((m, 3), sigma[0])
        a_sig = np.full((m, 3), sigma[1])
        if o == orientations - 1:
            g_sig[1, 2] *= factor
            a_sig[2, 0] *= factor
        f = np.einsum("kij,i->kj", rot, STANDARD_GRAVITY * u)  # R_k^T f
        accel.append(f[None] + a_sig[None] * rng.standard_normal((n, m, 3)))
        gyro.append(g_sig[None] * rng.standard_normal((n, m, 3)))
        static += [True] * n
        intervals.append(StaticInterval(start, (len(static) - 1) / RATE, u, orientation=o))
        accel.append(np.zeros((gap, m, 3)))
        gyro.append(np.zeros((gap, m, 3)))
        static += [False] * gap
    t_s = np.arange(len(static)) / RATE
    return array, np.concatenate(accel), np.concatenate(gyro), t_s, np.array(static), intervals


@pytest.mark.parametrize("seed", [3, 4])
def test_noise_spread_recovers_a_known_orientation_dependent_noise_factor(seed):
    """kappa of the axis whose sigma is 1.8x in one of 6 orientations is 1.8^2 = 3.24.

    ln s_jo has standard error se = sqrt(2 / nu), nu = 2 N^2 / (3 N - 1) (N = 5999
    differences): se = 0.0224. The estimator ``range - d_6 se`` of ln kappa then has mean
    ``ln F^2 + (d_5 / 2 - d_6) se`` (the low end is the minimum of 5 estimates, mean
    ``-d_5 se / 2``) and standard deviation at most ``sqrt(2) se`` (one estimate plus a
    minimum, whose variance is below one): 5 of them is the tolerance. Axes whose noise
    does not change: the range of 6 normals exceeds ``d_6 se`` by more than 4.5 se with
    probability < 1e-5, so kappa <= exp(4.5 se) on every one of them.
    """
    rng = np.random.default_rng(seed)
    factor = 1.8
    array, accel, gyro, t_s, static, intervals = _orientation_log(rng, factor)
    spread, tables = noise_spread(array, accel, gyro, t_s, static, intervals)
    count = 60.0 * RATE - 1
    se = np.sqrt(2.0 / (2 * count**2 / (3 * count - 1)))
    bias = (expected_normal_range(5) / 2 - expected_normal_range(6)) * se
    for sensor_type, (k, a) in (("gyro", (1, 2)), ("accel", (2, 0))):
        assert tables[sensor_type].shape == (6, 24)
        kappa = np.stack([spread[i][sensor_type] for i in range(8)])  # (m, 3)
        assert abs(np.log(kappa[k, a]) - (np.log(factor**2) + bias)) < 5 * np.sqrt(2) * se
        others = np.delete(kappa.ravel(), 3 * k + a)
        assert np.all(others >= 1.0) and np.all(others <= np.exp(4.5 * se))


def test_calibrate_writes_the_noise_spread_and_toml_keeps_it():
    rng = np.random.default_rng(11)
    array = _geometry()
    block, _ = _log(array, rng, orientations=6)
    result = calibrate_block(array, block)
    for sensor_type in ("gyro", "accel"):
        kappa = result.array.sensor_noise_spread(sensor_type)
        assert kappa is not None and kappa.shape == (12,)
        # constant noise: kappa ~ 1. Shortest interval N differences: se = sqrt(2 / nu)
        # of ln s_jo (0.06 here); the range of 6 normals exceeds d_6 se by 4.5 se with
        # probability < 1e-5, and with 12 sensors and 3 unknowns the per-sensor solution
        # inflates the error of v_o by up to ~1.3x: 6 se is the bound
        count = min(i.end_s - i.start_s for i in result.intervals) * RATE
        se = np.sqrt(2.0 / (2 * count**2 / (3 * count - 1)))
        assert np.all(kappa >= 1.0) and np.all(kappa <= np.exp(6 * se))
    again = ArrayConfig.from_dict(
        parse_toml(result.array.to_toml(), "round trip", ImufdiError), source="round trip"
    )
    assert_allclose(again.sensor_noise_spread("gyro"), result.array.sensor_noise_spread("gyro"))
    assert ArrayConfig.from_json(result.array.to_json()) == result.array


def _in_blocks(block: ImuBlock, size: int, repeats: int = 1):
    """``blocks()`` for :func:`calibrate_blocks`: ``block`` in pieces of ``size`` rows,
    ``repeats`` times end to end (later copies shifted in time)."""
    span = int(block.t_ns[-1] - block.t_ns[0]) + int(block.t_ns[1] - block.t_ns[0])

    def blocks():
        for k in range(repeats):
            for start in range(0, len(block), size):
                part = block.slice(start, start + size)
                yield ImuBlock(t_ns=part.t_ns + k * span, gyro=part.gyro, accel=part.accel)

    return blocks


def _assert_same_calibration(a, b):
    """Two calibrations of the same rows, summed in different orders: the same to 1e-9
    relative (their rounding; 1e-11 measured on the bundled cut), the jitter roots to
    2e-9 s (the root finder's tolerance xtol = 1e-9 s, on either side), the intervals
    and counts exactly."""
    assert [i.to_dict() for i in a.intervals] == [i.to_dict() for i in b.intervals]
    assert (a.orientations, a.clipped_rows, a.static_s, a.motion_s) == (
        b.orientations, b.clipped_rows, b.static_s, b.motion_s
    )  # fmt: skip
    assert a.warnings == b.warnings
    for x, y in zip(a.array.imus, b.array.imus):
        for s in ("gyro", "accel"):
            assert_allclose(x.calibration_of(s).matrix, y.calibration_of(s).matrix, rtol=1e-9)
            assert_allclose(
                x.calibration_of(s).bias, y.calibration_of(s).bias, rtol=1e-9, atol=1e-15
            )
            assert_allclose(x.noise[s], y.noise[s], rtol=1e-9)
            assert_allclose(x.noise_spread[s], y.noise_spread[s], rtol=1e-9)
    assert a.array.jitter.keys() == b.array.jitter.keys()
    for s in a.array.jitter:
        assert abs(a.array.jitter[s] - b.array.jitter[s]) <= 2e-9
    for s in a.residual_rms:
        # An RMS from sums of squares accumulated in a different order: its rounding is
        # relative to the largest residual of the sensor (cancellation), not to each one
        # (1.8e-12 rad/s measured on a 5.7e-4 rad/s residual beside a 0.19 one).
        scale = float(np.max(np.abs(a.residual_rms[s])))
        assert_allclose(a.residual_rms[s], b.residual_rms[s], rtol=1e-9, atol=1e-9 * scale)
    assert_allclose(a.time_offsets_s, b.time_offsets_s, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("size", [97, 1000])
def test_calibration_streamed_in_blocks_is_the_calibration_of_the_whole(size):
    """calibrate streams a log in blocks (memory independent of its length): any block
    size gives the calibration of the whole block in memory."""
    from imufdi_cli.calibrate import calibrate_blocks

    rng = np.random.default_rng(21)
    array = _geometry()
    block, _ = _log(array, rng)  # 12 orientations: a well-determined fit
    whole = calibrate_block(array, block)
    streamed = calibrate_blocks(array, _in_blocks(block, size))
    _assert_same_calibration(whole, streamed)
    assert whole.time_offsets_s  # the motion excites every axis: offsets were fitted


def test_calibration_memory_does_not_grow_with_the_log(monkeypatch):
    """Peak allocations (tracemalloc, which sees numpy's) of calibrating a log 5 times
    longer (the same 6 orientations, each interval and the motion 5 times longer) stay
    within 1.3x: calibrate keeps sums and spools its per-row values to disk, which it
    reads back SPOOL_CHUNK rows at a time and selects from in radix passes once more than
    SELECT_LIMIT values are left. Those two bound the memory of a long log (65,536 rows
    each); they are set below this test's 7,000-28,000 rows so that it sees that regime.
    (The accelerometer fit's own size grows with the number of static intervals, not
    rows.)"""
    import tracemalloc

    from imufdi_cli.calibrate import calibrate_blocks, passes

    monkeypatch.setattr(passes, "SPOOL_CHUNK", 1024)
    monkeypatch.setattr(passes, "SELECT_LIMIT", 1024)

    array = _geometry()
    warm, _ = _log(array, np.random.default_rng(4), orientations=6, motion_s=6.0)
    calibrate_blocks(array, _in_blocks(warm, 1024))  # first-use costs (caches, imports) out
    peaks = []
    for factor in (1, 5):
        rng = np.random.default_rng(5)
        block, _ = _log(array, rng, orientations=6, static_s=8.0 * factor, motion_s=6.0 * factor)
        tracemalloc.start()
        try:
            result = calibrate_blocks(array, _in_blocks(block, 1024))
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
        assert len(result.intervals) == 6
    assert peaks[1] <= 1.3 * peaks[0], peaks
