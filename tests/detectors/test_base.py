"""Tests of the detector output :class:`DetectionBlock` (per-sensor isolation and amplitude)."""

from __future__ import annotations

import numpy as np
from numpy.testing import assert_array_equal

from imufdi_cli.detectors.base import NO_ISOLATION, NOT_ISOLABLE, DetectionBlock


def _block(isolated: list[int], amplitude: list[float], **extra: np.ndarray) -> DetectionBlock:
    n = len(isolated)
    return DetectionBlock(
        statistic=np.zeros(n),
        threshold=np.ones(n),
        alarm=np.asarray(isolated) != NO_ISOLATION,
        isolated=np.asarray(isolated, dtype=np.int32),
        amplitude=np.asarray(amplitude, dtype=np.float64),
        scores=np.zeros((n, 3)),
        **extra,
    )


def test_amplitude_set_defaults_to_the_isolated_sensors_amplitude() -> None:
    block = _block([NO_ISOLATION, 2, NOT_ISOLABLE, 0], [np.nan, 0.5, 0.7, -1.0])
    expected = np.full((4, 3), np.nan)
    expected[1, 2] = 0.5
    expected[3, 0] = -1.0
    assert_array_equal(block.amplitude_set(), expected)  # NOT_ISOLABLE: no sensor, NaN


def test_amplitude_set_returns_the_per_sensor_amplitudes_when_given() -> None:
    amplitudes = np.array([[0.1, np.nan, 0.3]])
    block = _block([0], [0.1], amplitudes=amplitudes)
    assert_array_equal(block.amplitude_set(), amplitudes)


def test_concatenate_keeps_per_sensor_amplitudes_and_fills_the_others() -> None:
    with_set = _block([0], [0.1], amplitudes=np.array([[0.1, np.nan, 0.3]]))
    without = _block([1], [0.2])
    both = DetectionBlock.concatenate([with_set, without])
    assert both.amplitudes is not None
    assert_array_equal(both.amplitudes, [[0.1, np.nan, 0.3], [np.nan, 0.2, np.nan]])
    neither = DetectionBlock.concatenate([without, without])
    assert neither.amplitudes is None
    assert_array_equal(neither.amplitude_set()[:, 1], [0.2, 0.2])
