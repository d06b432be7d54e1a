"""Slow bias tracking: follows a parity offset with its time constant, leaves the consensus."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors import make_detector
from imufdi_cli.detectors.tracking import GATE_SIGMA, BiasTracker
from imufdi_cli.errors import DetectorConfigError
from imufdi_cli.log import ImuBlock

RATE = 100.0


def _block(n, seed, sigma=0.01, offset=0.0):
    rng = np.random.default_rng(seed)
    gyro = sigma * rng.standard_normal((n, 6, 3))
    gyro[:, 2, 1] += offset
    return ImuBlock(t_ns=(np.arange(n) * 1e7).astype(np.int64), gyro=gyro)


def test_off_is_identity():
    tracker = BiasTracker(0.0)
    array = ArrayConfig.co_aligned(6, RATE, sensors=("gyro",))
    block = _block(100, 0)
    tracker.fit(block, array)
    assert tracker.apply(block) is block


def test_small_offset_tracked_with_its_time_constant_and_consensus_kept():
    array = ArrayConfig.co_aligned(6, RATE, sensors=("gyro",))
    tau = 2.0
    tracker = BiasTracker(tau)
    tracker.fit(_block(2000, 1), array)
    offset = 0.01  # 1 sigma: inside the gate, so the average is exactly exponential
    block = _block(3000, 2, offset=offset)  # 30 s = 15 tau
    out = tracker.apply(block)
    h = array.measurement_matrix("gyro")
    y, y_out = array.select(block.gyro, "gyro"), array.select(out.gyro, "gyro")
    pinv = np.linalg.pinv(h)
    assert_allclose(y_out @ pinv.T, y @ pinv.T, atol=1e-12)  # consensus unchanged
    projector = np.eye(h.shape[0]) - h @ pinv
    expected = projector[:, 7] * offset  # parity image of the offset on imu2.gyro.y
    assert_allclose(y[-500:].mean(0) - y_out[-500:].mean(0), expected, atol=2e-3)
    # after one tau about 1 - 1/e of it is removed (noise of the estimate: sigma dt/tau)
    removed = (y - y_out)[int(tau * RATE)] @ expected / (expected @ expected)
    assert removed == pytest.approx(1 - np.exp(-1), abs=0.1)


def test_large_step_absorbed_no_faster_than_the_gate():
    array = ArrayConfig.co_aligned(6, RATE, sensors=("gyro",))
    tau = 10.0
    tracker = BiasTracker(tau)
    tracker.fit(_block(2000, 3), array)
    block = _block(500, 4, offset=1.0)  # 100 sigma
    out = tracker.apply(block)
    correction = array.select(block.gyro, "gyro") - array.select(out.gyro, "gyro")
    # each step moves every sensor's estimate by at most GATE_SIGMA sigma_j dt / tau, and
    # the projection does not lengthen it: |correction| <= N dt / tau * GATE_SIGMA |sigma|
    residual = array.select(_block(2000, 3).gyro, "gyro")
    h = array.measurement_matrix("gyro")
    sigma = (residual - residual @ np.linalg.pinv(h).T @ h.T).std(axis=0)
    bound = GATE_SIGMA * np.linalg.norm(sigma) * len(block) / (tau * RATE)
    assert np.linalg.norm(correction[-1]) <= bound
    assert np.argmax(np.abs(correction[-1])) == 7  # imu2.gyro.y, the offset sensor


def test_detectors_take_the_parameter():
    for name in ("glt", "pca-parity"):
        det = make_detector(name, {"track_bias": "60s"})
        assert det.tracker.tau_s == 60.0  # type: ignore[attr-defined]
        assert det.metadata()["params"]["track_bias"] == 60.0
        with pytest.raises(DetectorConfigError, match="track_bias"):
            make_detector(name, {"track_bias": "-1s"})
