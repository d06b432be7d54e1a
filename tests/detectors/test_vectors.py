"""The view of an array that px4-selector and ap-consistency share (detectors/vectors.py)."""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors.ap_consistency import ApConsistencyDetector
from imufdi_cli.detectors.px4_selector import Px4SelectorDetector
from imufdi_cli.detectors.vectors import CausalImuCheck
from imufdi_cli.log import ImuBlock


@pytest.mark.parametrize("cls", [Px4SelectorDetector, ApConsistencyDetector])
@pytest.mark.parametrize("types", ["gyro", "gyro,accel"])
def test_flush_gives_an_empty_block_per_tested_type(cls, types) -> None:
    """Causal checks hold nothing back: flush returns one empty block per tested type, with
    one score column per compared sensor, before and after process()."""
    assert cls.flush is CausalImuCheck.flush  # one implementation, not a copy per detector
    rng = np.random.default_rng(3)
    n, m = 200, 4
    data = ImuBlock(
        t_ns=np.arange(n) * 10_000_000,
        gyro=0.01 * rng.standard_normal((n, m, 3)),
        accel=np.array([0.0, 0.0, 9.81]) + 0.03 * rng.standard_normal((n, m, 3)),
    )
    detector = cls.from_params({"types": types})
    assert detector.flush() == {}  # nothing fitted, nothing tested
    detector.fit(data.slice(0, 100), ArrayConfig.co_aligned(m))
    rows = detector.process(data.slice(100, n))
    flushed = detector.flush()
    assert sorted(flushed) == sorted(types.split(","))
    for sensor_type, empty in flushed.items():
        assert len(empty) == 0
        assert empty.scores.shape == (0, rows[sensor_type].scores.shape[1]) == (0, 3 * m)
        assert len(rows[sensor_type]) == n - 100  # one row per input sample
