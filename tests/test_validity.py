"""Validity mask: flags, exclusion by consensus, held rows, calibration override, report rows."""

from __future__ import annotations

import numpy as np
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig, TriadCalibration
from imufdi_cli.log import ImuBlock
from imufdi_cli.validity import (
    CLIP_FRACTION,
    Conditioner,
    Runs,
    ValidityCounter,
    apply_calibration,
    flag_values,
    select_rows,
)

FS = np.radians(2000.0)


def _array(n=4, ranges=None):
    array = ArrayConfig.co_aligned(n, rate_hz=100.0)
    return array.with_range(ranges or {"gyro": FS, "accel": 16 * 9.80665})


def _block(n_rows=200, n_imus=4, seed=0):
    rng = np.random.default_rng(seed)
    rate = rng.standard_normal((n_rows, 3))
    gyro = rate[:, None, :] + 0.01 * rng.standard_normal((n_rows, n_imus, 3))
    accel = np.array([0, 0, 9.81]) + 0.02 * rng.standard_normal((n_rows, n_imus, 3))
    return ImuBlock(t_ns=np.arange(n_rows) * 10_000_000, gyro=gyro, accel=accel)


def test_flags():
    raw = np.array(
        [[0.0, np.nan, np.inf], [1e308, FS, CLIP_FRACTION * FS * 0.999], [-FS, 2 * FS, 1.0]]
    )
    clipped, invalid = flag_values(raw, "gyro", FS)
    assert invalid.tolist() == [[False, True, True], [True, False, False], [False, True, False]]
    assert clipped.tolist() == [[False, False, False], [False, True, False], [True, False, False]]
    # without a range only non-finite and absurd values flag
    clipped, invalid = flag_values(raw, "gyro", None)
    assert not clipped.any()
    assert invalid[1, 0] and not invalid[2, 1]


def test_validity_counter_counts_as_the_flags_whether_or_not_anything_is_flagged():
    # ValidityCounter skips flag_values when min and max show nothing can flag: the counts
    # must be those of the flags, for clean blocks and for each kind of flagged value
    array = _array()
    fs = array.range["gyro"]
    specials = [None, np.nan, np.inf, -np.inf, 2e3, -1.5 * fs, CLIP_FRACTION * fs, -0.999 * fs]
    for k, value in enumerate(specials):
        block = _block(n_rows=50, seed=k)
        if value is not None:
            block.gyro[7 + k, k % 4, k % 3] = value  # type: ignore[index]
        counter = ValidityCounter(array)
        counter.count(block)
        for s in ("gyro", "accel"):
            clipped, invalid = flag_values(block.get(s), s, array.range.get(s))
            assert counter.counts[s] == {
                "rows": 50,
                "clipped": int(clipped.any(axis=(1, 2)).sum()),
                "invalid": int(invalid.any(axis=(1, 2)).sum()),
            }, (value, s)
    # without ranges: only non-finite and absurd values count
    bare = ValidityCounter(ArrayConfig.co_aligned(4, rate_hz=100.0))
    block = _block(n_rows=20)
    block.gyro[3, 0, 0] = 5.0 * fs  # type: ignore[index]  (no range: not flagged)
    block.gyro[4, 1, 1] = 2e3  # type: ignore[index]  (absurd)
    bare.count(block)
    assert bare.counts["gyro"] == {"rows": 20, "clipped": 0, "invalid": 1}


def test_flagged_sensor_replaced_by_consensus_and_counted():
    array = _array()
    cond = Conditioner(array)
    block = _block()
    block.gyro[5, 2, 0] = np.nan
    block.gyro[7, 1, 1] = 1e308
    block.gyro[9, 3, 2] = FS  # clipped
    prepared, flags = cond.prepare(block)
    cond.fit(prepared, flags)
    out = cond.sanitize(prepared, flags)
    assert np.all(np.isfinite(out.gyro))
    h = array.measurement_matrix("gyro")
    for row in (5, 7, 9):
        y = array.select(out.gyro[row : row + 1], "gyro")[0] - cond.offsets["gyro"]
        residual = y - h @ np.linalg.lstsq(h, y, rcond=None)[0]
        j = {5: 6, 7: 4, 9: 11}[row]  # sensor index of the flagged value
        assert abs(residual[j]) < 1e-9  # it carries no parity residual
    # untouched elsewhere
    assert_allclose(out.gyro[:5], block.gyro[:5])
    counts = cond.counts["gyro"]
    assert (counts.rows, counts.invalid_rows, counts.clipped_rows, counts.held_rows) == (
        200,
        2,
        1,
        0,
    )
    assert counts.invalid_runs.intervals == [[50_000_000, 50_000_000], [70_000_000, 70_000_000]]


def test_no_consensus_holds_the_row():
    array = _array()
    cond = Conditioner(array)
    block = _block()
    block.gyro[20:23, :, 0] = FS  # every x gyro clipped: x not observable
    prepared, flags = cond.prepare(block)
    cond.fit(prepared, flags)
    out = cond.sanitize(prepared, flags)
    assert cond.counts["gyro"].held_rows == 3
    held = array.select(out.gyro[20:23], "gyro") - cond.offsets["gyro"]
    h = array.measurement_matrix("gyro")
    x_prev = np.linalg.lstsq(
        h, array.select(out.gyro[19:20], "gyro")[0] - cond.offsets["gyro"], rcond=None
    )[0]
    assert_allclose(held, np.tile(h @ x_prev, (3, 1)), atol=1e-12)
    assert cond.counts["gyro"].clipped_runs.intervals == [[200_000_000, 220_000_000]]


def test_calibration_override_maps_through_raw():
    rng = np.random.default_rng(1)
    base = _array(2)
    cal_a = [{"gyro": TriadCalibration(np.eye(3) * 1.01, rng.standard_normal(3))} for _ in range(2)]
    cal_b = [
        {
            "gyro": TriadCalibration(
                np.eye(3) + 0.01 * rng.standard_normal((3, 3)), rng.standard_normal(3)
            )
        }
        for _ in range(2)
    ]
    log_array, new_array = base.with_calibration(cal_a), base.with_calibration(cal_b)
    raw = _block(50, 2)
    logged = apply_calibration(raw, log_array)  # what ingest --array writes
    prepared, _ = Conditioner(log_array, new_array).prepare(logged)
    assert_allclose(prepared.gyro, apply_calibration(raw, new_array).gyro, atol=1e-12)


def test_runs_merge_across_blocks():
    runs = Runs()
    runs.add(np.array([0, 1, 2, 3]), np.array([False, True, False, True]))
    runs.add(np.array([4, 5, 6]), np.array([True, False, True]))
    assert runs.intervals == [[1, 1], [3, 4], [6, 6]]


def test_select_rows_window_and_exclusions():
    t = np.arange(100) * 1_000_000_000 + 5_000_000_000
    record = {
        "t0_ns": 0,
        "validity": {
            "types": {"gyro": {"clipped_ns": [[t[10], t[12]]], "invalid_ns": [[t[50], t[50]]]}}
        },
    }
    sel = select_rows(t, record, "gyro", (10.0, 60.0))  # rows 5..54 (log time 5 s .. 104 s)
    assert sel.keep.sum() == 50 - 4 and (sel.clipped, sel.invalid, sel.excluded) == (3, 1, 4)
    assert select_rows(t, None, "gyro", None).keep.all()
    assert select_rows(t, record, "accel").keep.all()


def test_clipped_accelerometer_of_a_rotating_board_replaced_with_its_lever_arm_terms():
    """12 IMUs on a grid in fast rotation: a clipped accelerometer sample is replaced by
    the rigid-body consensus (maths/rigid.py), i.e. its true value to the noise, not
    the specific force at the centre."""
    from imufdi_cli.maths.rigid import accel_design, rigid_specific_force

    x, y = np.meshgrid(np.arange(4) * 0.05, np.arange(3) * 0.05)
    positions = np.stack([x.ravel(), y.ravel(), np.zeros(12)], axis=1)
    array = ArrayConfig.co_aligned(12, 100.0, positions=positions).with_range(
        {"gyro": FS, "accel": 16 * 9.80665}
    )
    rng = np.random.default_rng(3)
    n = 300
    w = rng.normal(0, 8, (n, 3))
    body = rigid_specific_force(
        positions, np.tile([0, 0, 9.81], (n, 1)), w, rng.normal(0, 300, (n, 3))
    )
    accel = body + 0.002 * rng.standard_normal(body.shape)
    truth = accel[150, 11, 0]
    accel[150, 11, 0] = 16 * 9.80665  # clipped
    block = ImuBlock(t_ns=np.arange(n) * 10_000_000, gyro=w[:, None, :].repeat(12, 1), accel=accel)
    cond = Conditioner(array)
    prepared, flags = cond.prepare(block)
    cond.fit(prepared, flags)
    out = cond.sanitize(prepared, flags)
    # 35 valid sensors estimate 9 unknowns: the replacement's error is about the noise
    assert abs(out.accel[150, 11, 0] - truth) < 0.01
    # and it carries no residual in the rigid-body model
    a = accel_design(array)
    y_row = array.select(out.accel[150:151], "accel")[0] - cond.offsets["accel"]
    residual = y_row - a @ np.linalg.lstsq(a, y_row, rcond=None)[0]
    assert abs(residual[33]) < 1e-9
