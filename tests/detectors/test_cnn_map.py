"""cnn-map: training, model files, streaming invariance, errors, wearable12 noise growth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from imufdi_cli.detectors.base import DetectionBlock, parse_params
from imufdi_cli.detectors.cnn_map import CnnMapDetector, MappingNetwork, gamma_shape, input_windows
from imufdi_cli.errors import CalibrationError, DetectorConfigError
from imufdi_cli.faults import FaultInjector, parse_fault_spec
from imufdi_cli.log import iter_blocks
from imufdi_cli.simulate import preset, simulate_block

FAST = {"epochs": "6", "patience": "3"}


def make(params: dict | None = None) -> CnnMapDetector:
    return CnnMapDetector(**parse_params(CnnMapDetector.PARAMS, params or {}, "cnn-map"))


def wearable12(seed: int, duration: float = 30.0, factor: float | None = 3.0):
    array, block = simulate_block(preset("wearable12", seed=seed, duration=duration))
    if factor is not None:
        spec = f"noise:imu0.accel.x,at=12s,until=18s,factor={factor}"
        faults = [parse_fault_spec(spec, array)]
        block = FaultInjector(faults, array, seed=seed, t0_ns=int(block.t_ns[0])).apply_block(block)
    return array, block


def run(detector, array, block, calibrate=(0.0, 10.0), block_size=250):
    t = block.t_s()
    detector.fit(block.mask((t >= calibrate[0]) & (t < calibrate[1])), array)
    outs = [detector.process(b) for b in iter_blocks(block, block_size)]
    return DetectionBlock.concatenate([o["accel"] for o in outs])


@pytest.fixture(scope="module")
def short_log():
    return wearable12(1, duration=8.0, factor=None)


def test_input_windows_end_at_their_sample():
    body = np.arange(5 * 2 * 3, dtype=float).reshape(5, 2, 3)
    windows = input_windows(body, 3)
    assert windows.shape == (3, 2, 3, 3)
    assert_array_equal(windows[1, 1], body[1:4, 1])


def test_gamma_shape_of_chi2_means():
    rng = np.random.default_rng(0)
    energies = rng.chisquare(10, 200_000) / 10  # gamma(5, 1/5): shape 5
    assert_allclose(gamma_shape(energies), 5.0, rtol=0.02)


def test_block_size_invariance_and_json_metadata(short_log):
    array, block = short_log
    a = run(make(FAST), array, block, (0.0, 6.0), block_size=97)
    b = run(make(FAST), array, block, (0.0, 6.0), block_size=1000)
    assert len(a) == len(block)
    assert_allclose(a.statistic, b.statistic, rtol=1e-9, atol=1e-12)
    assert_array_equal(a.alarm, b.alarm)
    assert_array_equal(a.isolated, b.isolated)
    assert a.scores.shape == (len(block), 36)
    # first L - 1 samples: no full input window, calibrated mean energy
    assert_allclose(a.statistic[:10], 1.0)
    detector = make(FAST)
    run(detector, array, block, (0.0, 6.0))
    meta = json.loads(json.dumps(detector.metadata()))
    assert meta["detector"] == "cnn-map"
    training = meta["training"]
    assert len(training["train_loss"]) == training["epochs_run"] == len(training["holdout_loss"])
    assert training["mae_rad_s"] > 0
    assert meta["gyro_screening"] == "glt"
    assert len(meta["excluded_gyros"]) <= 36 - 3


def test_training_reduces_the_loss(short_log):
    array, block = short_log
    detector = make({"epochs": "15", "patience": "15"})
    t = block.t_s()
    detector.fit(block.mask(t < 6.0), array)
    training = detector.metadata()["training"]
    assert training["train_loss"][-1] < 0.8 * training["train_loss"][0]
    assert training["train_mae_rad_s"] < training["reference_rms_rad_s"]


def test_saved_model_reproduces_the_network(short_log, tmp_path):
    array, block = short_log
    first = make(FAST)
    t = block.t_s()
    first.fit(block.mask(t < 6.0), array)
    path = tmp_path / "model.npz"
    first.save_model(path)
    second = make({"model": str(path)})
    second.fit(block.mask(t < 6.0), array)
    assert first.mapping is not None and second.mapping is not None
    for w1, w2 in zip(first.mapping.weights, second.mapping.weights):
        assert_array_equal(w1, w2)
    windows = input_windows(first._body_accel(block), first.input_length)[:50]
    assert_allclose(first._predict(windows), second._predict(windows), rtol=1e-12)
    # the metadata copy of the weights loads too
    import base64

    blob = base64.b64decode(first.metadata()["model_npz_base64"])
    loaded = MappingNetwork.from_npz_bytes(blob, "metadata")
    assert_array_equal(loaded.weights[-1], first.mapping.weights[-1])


def test_bad_model_file_and_params(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not an npz")
    array, block = wearable12(0, duration=4.0, factor=None)
    with pytest.raises(DetectorConfigError, match="cnn-map"):
        make({"model": str(bad)}).fit(block, array)
    with pytest.raises(DetectorConfigError, match="cannot read"):
        make({"model": str(tmp_path / "missing.npz")}).fit(block, array)
    with pytest.raises(DetectorConfigError, match="valid: relu, tanh"):
        make({"activation": "sigmoid"})
    with pytest.raises(DetectorConfigError, match="unknown parameter"):
        make({"layers": "3"})


def test_short_calibration_is_rejected():
    array, block = wearable12(0, duration=4.0, factor=None)
    with pytest.raises(CalibrationError, match="--calibrate"):
        make(FAST).fit(block.slice(0, 60), array)


def test_model_trained_at_another_rate_is_rejected(short_log, tmp_path):
    array, block = short_log
    detector = make(FAST)
    detector.fit(block.mask(block.t_s() < 6.0), array)
    assert detector.mapping is not None
    detector.mapping.rate_hz = 200.0
    path = tmp_path / "m.npz"
    detector.save_model(path)
    with pytest.raises(DetectorConfigError, match="200 Hz"):
        make({"model": str(path)}).fit(block, array)


@pytest.mark.slow
def test_wearable12_noise_growth_is_detected_on_imu0():
    array, block = wearable12(1)
    out = run(make(), array, block)
    t = block.t_s()
    fault = (t >= 12.0) & (t < 18.0)
    free = (t >= 10.0) & ~fault
    assert out.alarm[fault].mean() > 0.8
    assert out.alarm[free].mean() < 0.1
    hits = np.flatnonzero(out.alarm & fault)
    assert t[hits[0]] - 12.0 < 0.5
    # isolated to an accelerometer of IMU 0 (sensors 0-2) most of the time
    assert np.isin(out.isolated[out.alarm & fault], [0, 1, 2]).mean() > 0.8
