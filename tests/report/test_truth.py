"""Ground truth and calibration windows read from the metadata records of a log."""

from __future__ import annotations

import json

import pytest

from imufdi_cli.errors import McapInputError, TruthError
from imufdi_cli.report.truth import TruthWindow, calibration_windows, truth_windows

T0 = 1_700_000_000_000_000_000


def _faults_record(runs: list[dict]) -> dict[str, dict[str, str]]:
    """An ``imufdi.faults`` record: the last run, the earlier ones under ``previous``."""
    *previous, last = runs
    return {"imufdi.faults": {"json": json.dumps({**last, "previous": previous})}}


def _fault(fault_id, model, sensors, at_s, until_s=None, **params):
    return {
        "id": fault_id,
        "model": model,
        "sensors": sensors,
        "at_s": at_s,
        "until_s": until_s,
        "params": params,
        "spec": f"{model}:{','.join(sensors)}",
    }


def test_no_faults_record_is_no_truth():
    assert truth_windows({}) is None
    assert truth_windows({"imufdi.detect.glt": {"json": "{}"}}) is None


def test_windows_are_absolute_and_carry_the_size_of_steps_and_drifts():
    """Times are each run's t0 plus the fault's offsets, the runs in order (earlier runs
    first); the size is a step's amp or a drift's rate, none for the other models."""
    runs = [
        {"t0_ns": T0, "faults": [_fault("a", "step", ["imu0.gyro.x"], 1.5, 3.0, amp=0.01)]},
        {
            "t0_ns": T0 + 7,
            "faults": [
                _fault("b", "drift", ["imu1.accel.z"], 0.25, rate=0.2),
                _fault("c", "stuck", ["imu2.gyro.x", "imu2.gyro.y"], 2.0),
            ],
        },
    ]
    truth = truth_windows(_faults_record(runs))
    assert truth is not None
    assert truth.windows == [
        TruthWindow("a", ("imu0.gyro.x",), T0 + 1_500_000_000, T0 + 3_000_000_000, "step", 0.01),
        TruthWindow("b", ("imu1.accel.z",), T0 + 7 + 250_000_000, None, "drift", 0.2),
        TruthWindow("c", ("imu2.gyro.x", "imu2.gyro.y"), T0 + 7 + 2_000_000_000, None, "stuck"),
    ]
    assert [d["id"] for d in truth.descriptions] == ["a", "b", "c"]
    assert truth.descriptions[0]["params"] == {"amp": 0.01}


@pytest.mark.parametrize(
    "record",
    ["not json", json.dumps({"faults": []}), json.dumps({"t0_ns": "x", "faults": []})],
)
def test_a_malformed_faults_record_is_bad_input(record):
    with pytest.raises(TruthError, match=r"imufdi\.faults metadata: ") as info:
        truth_windows({"imufdi.faults": {"json": record}})
    assert info.value.exit_code == 3


def test_calibration_windows_per_detector():
    metadata = {
        "imufdi.detect.glt": {"json": json.dumps({"calibration_window_ns": [10, 20]})},
        "imufdi.detect.bank": {"json": json.dumps({"calibration_window_ns": None})},
        "imufdi.detect.old": {"json": json.dumps({"alpha": 0.01})},  # recorded none
        "imufdi.faults": {"json": json.dumps({"calibration_window_ns": [1, 2]})},
    }
    assert calibration_windows(metadata) == {"glt": (10, 20), "bank": None}


@pytest.mark.parametrize(
    ("record", "fragment"),
    [
        ({"calibration_window_ns": [5]}, "calibration_window_ns: expected a list of 2"),
        ({"calibration_window_ns": ["a", 2]}, r"calibration_window_ns\[0\]: expected a 64-bit"),
        ("{", "not valid JSON"),  # unreadable: the window would silently count as tested
        (None, "expected an object, got null"),
        ([], "expected an object, got a list"),
        ({"t0_ns": 1e400}, "t0_ns: expected a 64-bit integer or null, got the number inf"),
        ("[" * 100_000 + "]" * 100_000, "JSON nested 100000 levels deep; at most 64"),
    ],
)
def test_a_malformed_detect_record_is_bad_input(record, fragment):
    text = record if isinstance(record, str) else json.dumps(record)
    metadata = {"imufdi.detect.glt": {"json": text}}
    with pytest.raises(McapInputError, match=r"imufdi\.detect\.glt metadata: " + fragment):
        calibration_windows(metadata)
