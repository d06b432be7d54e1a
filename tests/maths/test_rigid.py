"""Rigid-body lever-arm model: analytic cases (zero parity residual under any rigid motion)
and glt's false-alarm level on a rotating distributed array."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig, ImuSpec
from imufdi_cli.detectors.glt import GltDetector
from imufdi_cli.errors import ArrayTooSmallError
from imufdi_cli.log import ImuBlock
from imufdi_cli.maths.parity import parity_matrix
from imufdi_cli.maths.rigid import (
    accel_design,
    lever_arm_columns,
    observable_lever_arm,
    rigid_specific_force,
)

FLIP = np.array([[0.0, -1, 0], [-1, 0, 0], [0, 0, -1]])  # the MIMU4444 bottom face
MIMU4444 = np.array(  # IMU_positions.csv, metres
    [
        [-0.00945, 0.00945, 0.001],
        [-0.00945, 0.00945, -0.001],
        [-0.00945, -0.00945, 0.001],
        [-0.00945, -0.00945, -0.001],
        [0.00945, 0.00945, 0.001],
        [0.00945, 0.00945, -0.001],
        [0.00945, -0.00945, 0.001],
        [0.00945, -0.00945, -0.001],
    ]
)


def _board() -> ArrayConfig:
    imus = tuple(
        ImuSpec(rotation=np.eye(3) if k % 2 == 0 else FLIP, position=MIMU4444[k]) for k in range(8)
    )
    return ArrayConfig(imus=imus, rate_hz=62.5)


def _grid(offset: float = 0.0) -> ArrayConfig:
    x, y = np.meshgrid(np.arange(4) * 0.03, np.arange(3) * 0.03)
    positions = np.stack([x.ravel(), y.ravel(), np.zeros(12)], axis=1) + offset
    return ArrayConfig.co_aligned(12, 100.0, positions=positions)


def _rigid_measurements(array: ArrayConfig, rng: np.random.Generator, n: int) -> np.ndarray:
    """Accelerometer readings (n, n_s) of a rigid body in random fast motion, no noise."""
    f0 = rng.normal(0, 10, (n, 3))
    w = rng.normal(0, 15, (n, 3))  # up to ~50 rad/s
    w_dot = rng.normal(0, 500, (n, 3))
    body = rigid_specific_force(array.positions(), f0, w, w_dot)  # (n, m, 3)
    triads = np.einsum("kba,nkb->nka", array.rotations(), body)  # R_k^T f_k
    return array.select(triads, "accel")


def test_observable_columns_by_geometry():
    assert observable_lever_arm(ArrayConfig.co_aligned(4)).shape == (12, 0)  # co-located
    assert observable_lever_arm(_grid()).shape == (36, 6)  # planar: K's z column unseen
    assert observable_lever_arm(_grid(offset=0.7)).shape == (36, 6)  # a common offset too
    assert observable_lever_arm(_board()).shape == (24, 9)  # two faces 2 mm apart: 3-D
    design = accel_design(_board())
    assert design.shape == (24, 12)
    assert np.linalg.matrix_rank(design) == 12


def test_columns_are_h_times_r():
    array = _board()
    G = lever_arm_columns(array)
    H = array.measurement_matrix("accel")
    j = 7  # imu2.accel.y
    assert_allclose(G[j].reshape(3, 3), np.outer(H[j], MIMU4444[2]))


def test_rigid_motion_has_zero_parity_residual():
    rng = np.random.default_rng(3)
    for array in (_board(), _grid(), _grid(offset=0.2)):
        m = _rigid_measurements(array, rng, 200)
        plain = parity_matrix(array.measurement_matrix("accel")) @ m.T
        augmented = parity_matrix(accel_design(array)) @ m.T
        # lever terms reach metres per second squared; the augmented parity vector is
        # zero to rounding (measurements ~ 1e2 m/s^2, float64)
        assert np.abs(plain).max() > 1.0
        assert np.abs(augmented).max() < 1e-9 * np.abs(m).max()


def test_a_fault_still_shows():
    array = _board()
    rng = np.random.default_rng(4)
    m = _rigid_measurements(array, rng, 50)
    m[:, 5] += 0.5  # imu1.accel.z
    p = parity_matrix(accel_design(array)) @ m.T
    assert np.all(np.linalg.norm(p, axis=0) > 0.1)


def _rotating_block(array: ArrayConfig, n: int, sigma: float, seed: int) -> ImuBlock:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / array.rate_hz
    w = np.stack([3 * np.sin(2 * t), 2 * np.cos(3 * t), 1.5 * np.sin(t + 1)], axis=1)
    w_dot = np.gradient(w, t, axis=0)
    f0 = np.tile([0.0, 0.0, 9.81], (n, 1))
    body = rigid_specific_force(array.positions(), f0, w, w_dot)
    rot = array.rotations()
    accel = np.einsum("kba,nkb->nka", rot, body) + sigma * rng.standard_normal(body.shape)
    gyro = np.einsum("kba,nb->nka", rot, w) + 0.001 * rng.standard_normal(body.shape)
    return ImuBlock(t_ns=(t * 1e9).astype(np.int64), gyro=gyro, accel=accel)


def test_glt_holds_its_level_on_a_rotating_grid(scipy_stats):
    array = _grid()
    block = _rotating_block(array, 6000, 0.03, seed=11)
    calibration, rest = block.slice(0, 1000), block.slice(1000, 6000)
    alarms = {}
    for lever_arm in (True, False):
        det = GltDetector(alpha=0.01, lever_arm=lever_arm)
        det.fit(calibration, array)
        alarms[lever_arm] = int(np.count_nonzero(det.process(rest)["accel"].alarm))
    assert det.metadata()["params"]["lever_arm"] is False
    # with the model: at most the binomial 99.9 % quantile of alarms at 1.5 alpha (the
    # threshold accounts for the 1000-sample sigma estimate; 1.5 alpha leaves room for it)
    assert alarms[True] <= scipy_stats.binom.ppf(0.999, 5000, 0.015)
    # without it the lever terms (partly absorbed into the calibrated sigma) alarm on a
    # large share of the rows
    assert alarms[False] > 0.1 * 5000


def test_glt_reports_lever_arm_columns_and_untested_when_too_few():
    det = GltDetector()
    array = _board()
    det.fit(_rotating_block(array, 300, 0.03, seed=1), array)
    meta = det.metadata()
    assert meta["types"]["accel"]["lever_arm_columns"] == 9
    assert meta["types"]["gyro"]["lever_arm_columns"] == 0
    # 4 IMUs on a square: 12 accelerometers, 3 + 6 unknowns -> still 3 parity dimensions;
    # 3 IMUs at distinct points of a plane: 9 sensors, 9 unknowns -> untested
    three = ArrayConfig.co_aligned(3, positions=np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]))
    det = GltDetector(types="accel")
    with pytest.raises(ArrayTooSmallError, match="at least 4 sensors"):  # exit 3: the data
        det.fit(_rotating_block(three, 300, 0.03, seed=2), three)
    assert "accel" in det._untested and "lever_arm=false" in det._untested["accel"]


@pytest.mark.parametrize("name", ["bank", "pca-parity"])
def test_bank_and_pca_parity_hold_their_level_on_a_rotating_grid(scipy_stats, name):
    """The same rigid-body design in bank (array mode) and pca-parity: accelerometers of a
    rotating 12-IMU grid are tested and alarm at about alpha."""
    from imufdi_cli.detectors.bank import BankDetector
    from imufdi_cli.detectors.pca_parity import PcaParityDetector

    array = _grid()
    block = _rotating_block(array, 6000, 0.03, seed=12)
    det = BankDetector(alpha=0.01) if name == "bank" else PcaParityDetector(alpha=0.01)
    det.fit(block.slice(0, 1000), array)
    alarms = int(np.count_nonzero(det.process(block.slice(1000, 6000))["accel"].alarm))
    # binomial 99.9 % quantile at 2 alpha: room for the estimated sigma/bias of a 1000-sample
    # window and (pca-parity) the runs of a moving-window test; without the model the lever
    # terms alarm on most rows
    assert alarms <= scipy_stats.binom.ppf(0.999, 5000, 0.02)


def test_bias_tracker_uses_the_detector_design():
    """With the lever-arm design the tracker's residual is blind to the rotation: its
    tracked offset change stays at the noise level."""
    from imufdi_cli.detectors.tracking import BiasTracker

    array = _grid()
    block = _rotating_block(array, 3000, 0.03, seed=13)
    tracker = BiasTracker(5.0)
    tracker.fit(block.slice(0, 500), array, {"accel": accel_design(array)})
    tracker.apply(block.slice(500, 3000))
    change = np.abs(tracker.metadata()["accel"])
    plain = BiasTracker(5.0)
    plain.fit(block.slice(0, 500), array)
    plain.apply(block.slice(500, 3000))
    # tracked mean over ~5 s of 0.03 m/s^2 noise: ~0.03 / sqrt(500 / 2) ~ 2e-3 per sensor
    assert change.max() < 0.02
    assert np.abs(plain.metadata()["accel"]).max() > 5 * change.max()
