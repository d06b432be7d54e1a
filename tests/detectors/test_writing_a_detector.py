"""docs/writing-a-detector.md: its example module plus its registry line is a working detector."""

from __future__ import annotations

import ast
import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from imufdi_cli.array import ArrayConfig
from imufdi_cli.detectors import DETECTORS, Detector, DetectorBase, detector_class, make_detector
from imufdi_cli.errors import DetectorConfigError
from imufdi_cli.log import ImuBlock

DOC = Path(__file__).resolve().parents[2] / "docs" / "writing-a-detector.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), flags=re.S)


@pytest.fixture
def registered(monkeypatch: pytest.MonkeyPatch) -> str:
    """The doc's module under its documented name, and the doc's registry line."""
    module_code, registry_line = _python_blocks()
    entry = ast.literal_eval("{" + registry_line.strip() + "}")
    (name, location), *_ = entry.items()
    module_name = location.partition(":")[0]
    module = types.ModuleType(module_name)
    monkeypatch.setitem(sys.modules, module_name, module)
    exec(compile(module_code, str(DOC), "exec"), module.__dict__)
    monkeypatch.setitem(DETECTORS, name, location)
    return str(name)


def _block(array: ArrayConfig, n: int, rng: np.random.Generator, step_at: int | None) -> ImuBlock:
    """Six co-aligned gyros turning at 0.3 rad/s about z, sigma 0.01 rad/s; a 0.1 rad/s
    step on imu2's x axis from ``step_at``."""
    gyro = np.tile([0.0, 0.0, 0.3], (n, 6, 1)) + 0.01 * rng.standard_normal((n, 6, 3))
    if step_at is not None:
        gyro[step_at:, 2, 0] += 0.1
    return ImuBlock(t_ns=np.arange(n) * 10_000_000, gyro=gyro)


def test_doc_example_is_one_module_plus_one_registry_line(registered: str) -> None:
    cls = detector_class(registered)
    assert issubclass(cls, DetectorBase)
    detector = make_detector(registered, {"alpha": "0.001", "types": "gyro"})
    assert isinstance(detector, Detector)
    with pytest.raises(DetectorConfigError, match=r"unknown parameter residual-z\.beta"):
        make_detector(registered, {"beta": "1"})
    with pytest.raises(DetectorConfigError, match="valid: gyro, accel, mag"):
        make_detector(registered, {"types": "baro"})


def test_doc_example_detects_and_isolates_a_step_at_its_false_alarm_level(
    scipy_stats, registered: str
) -> None:
    array = ArrayConfig.co_aligned(6, 100.0, sensors=("gyro",))
    rng = np.random.default_rng(2101)
    alpha, n_quiet, n_fault = 0.01, 4000, 200
    detector = make_detector(registered, {"alpha": alpha, "types": "gyro"})
    detector.fit(_block(array, 1000, rng, None), array)
    out = detector.process(_block(array, n_quiet + n_fault, rng, n_quiet))["gyro"]
    assert len(out) == n_quiet + n_fault
    # Bonferroni: P(alarm) <= alpha per fault-free sample (a little above with estimated
    # mean/std from 1000 samples); 1e-6 upper binomial tail of 1.5 alpha
    assert out.alarm[:n_quiet].sum() <= scipy_stats.binom.ppf(1 - 1e-6, n_quiet, 1.5 * alpha)
    # 0.1 rad/s = 10 sigma; residual (5/6) 10 = 8.3 sigma vs a 3.8-sigma threshold: always
    assert out.alarm[n_quiet:].all()
    sensor = array.sensor_ids("gyro").index("imu2.gyro.x")
    assert (out.isolated[n_quiet:] == sensor).all()
    assert set(detector.flush()) == {"gyro"}
    assert detector.metadata()["params"] == {"alpha": alpha, "types": "gyro"}
