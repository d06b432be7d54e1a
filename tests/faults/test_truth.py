"""Tests of imufdi_cli.faults.truth: ground truth and metadata."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from imufdi_cli.array import ArrayConfig
from imufdi_cli.errors import FaultSpecError, TruthError
from imufdi_cli.faults import (
    FaultInjector,
    active_mask,
    fault_from_table,
    faults_from_metadata,
    parse_fault_spec,
)
from tests.faults.conftest import T0_NS

# --- ground truth ----------------------------------------------------------------------------


def test_active_mask_hand_made(array: ArrayConfig) -> None:
    faults = [
        parse_fault_spec("step:imu0.gyro.x,at=0.02s,until=0.04s,amp=1", array),
        parse_fault_spec("stuck:imu1.gyro,at=0.03s", array),
        parse_fault_spec("step:imu0.accel.x,at=0s,amp=1", array),  # other type: ignored
    ]
    t0 = 1000
    t_ns = t0 + np.arange(6) * 10_000_000  # 0, 10, ..., 50 ms
    ids = ["imu0.gyro.x", "imu0.gyro.y", "imu1.gyro.x", "imu1.gyro.z"]
    expected = np.array(
        [
            [0, 0, 0, 0],
            [0, 0, 0, 0],
            [1, 0, 0, 0],  # 20 ms: step starts (inclusive)
            [1, 0, 1, 1],  # 30 ms: stuck starts
            [0, 0, 1, 1],  # 40 ms: step ended (exclusive)
            [0, 0, 1, 1],
        ],
        dtype=bool,
    )
    assert_array_equal(active_mask(faults, ids, t_ns, t0), expected)
    assert active_mask([], ids, t_ns, t0).shape == (6, 4)


def test_truth_events_and_metadata_round_trip(array: ArrayConfig) -> None:
    faults = [
        parse_fault_spec("drift:imu1.accel.z,at=3s,until=8s,rate=0.01g/s", array),
        parse_fault_spec("step:imu0.gyro.x,at=2.5s,amp=0.9deg/s,id=bias", array),
    ]
    injector = FaultInjector(faults, array, seed=7, t0_ns=T0_NS)
    assert [f.id for f in injector.faults] == ["f0", "bias"]
    events = injector.truth_events()
    assert [(e["event"], e["fault_id"]) for e in events] == [
        ("start", "bias"),
        ("start", "f0"),
        ("end", "f0"),
    ]
    assert events[0]["t_ns"] == T0_NS + 2_500_000_000
    assert events[2]["t_ns"] == T0_NS + 8_000_000_000
    json.dumps(events)
    meta = injector.metadata()
    record = json.loads(meta["json"])
    assert record["seed"] == 7 and record["t0_ns"] == T0_NS
    assert faults_from_metadata(meta) == injector.faults


def test_previous_faults_are_kept_and_ids_unique(array: ArrayConfig) -> None:
    first = FaultInjector(
        [parse_fault_spec("step:imu0.gyro.x,at=1s,amp=1deg/s", array)],
        array,
        seed=1,
        t0_ns=0,
    )
    second = FaultInjector(
        [parse_fault_spec("stuck:imu1.gyro.x,at=2s", array)],
        array,
        seed=2,
        t0_ns=0,
        previous_metadata=first.metadata(),
    )
    assert [f.id for f in second.faults] == ["f1"]
    every = faults_from_metadata(second.metadata())
    assert [(f.id, f.model) for f in every] == [("f0", "step"), ("f1", "stuck")]
    record = json.loads(second.metadata()["json"])
    assert record["previous"][0]["seed"] == 1
    with pytest.raises(FaultSpecError, match="id 'f0' is already used"):
        FaultInjector(
            [parse_fault_spec("stuck:imu1.gyro.x,at=2s,id=f0", array)],
            array,
            seed=2,
            t0_ns=0,
            previous_metadata=first.metadata(),
        )


def test_bad_metadata_is_truth_error() -> None:
    with pytest.raises(TruthError):
        faults_from_metadata({"json": "not json"})
    with pytest.raises(TruthError):
        faults_from_metadata({"json": '{"faults": [{"model": "step"}]}'})
    with pytest.raises(TruthError):
        faults_from_metadata({})


def test_non_finite_values_rejected(array: ArrayConfig) -> None:
    with pytest.raises(FaultSpecError, match="amp: '1e999deg/s' is not a finite number"):
        parse_fault_spec("step:imu0.gyro.x,amp=1e999deg/s", array)
    with pytest.raises(FaultSpecError, match="at: inf is not a finite number"):
        fault_from_table(
            {"model": "step", "sensor": "imu0.gyro.x", "at": math.inf, "amp": 1.0},
            array,
            where="t",
        )


def test_apply_leaves_unfaulted_streams_and_empty_blocks(array: ArrayConfig) -> None:
    injector = FaultInjector(
        [parse_fault_spec("step:imu1.gyro.y,amp=1", array)], array, seed=0, t0_ns=0
    )
    values = np.arange(12.0).reshape(4, 3)
    t_ns = np.arange(4) * 10
    assert_array_equal(injector.apply(0, "gyro", t_ns, values), values)
    assert_array_equal(injector.apply(1, "accel", t_ns, values), values)
    assert injector.apply(1, "gyro", t_ns[:0], values[:0]).shape == (0, 3)
    assert_array_equal(injector.apply(1, "gyro", t_ns, values), values + np.array([0.0, 1.0, 0.0]))
    assert injector.affects(1, "gyro") and not injector.affects(1, "accel")


def test_reading_truth_loads_the_fault_models_only(fresh_python) -> None:
    # imufdi_cli.faults imports its submodules on first use: report reads the truth
    # (Fault, METADATA_NAME) without the injector, the spec grammar or the array model
    done = fresh_python(
        "import sys\n"
        "from imufdi_cli.faults import METADATA_NAME, Fault\n"
        "import imufdi_cli.report.truth\n"
        "print(sorted(m for m in sys.modules if m.startswith('imufdi_cli.faults')))\n"
        "print('imufdi_cli.array' in sys.modules)\n"
    )
    assert done.returncode == 0, done.stderr
    modules, array = done.stdout.split("\n")[:2]
    assert modules == "['imufdi_cli.faults', 'imufdi_cli.faults.models']"
    assert array == "False"
    import imufdi_cli.faults as faults

    assert all(getattr(faults, name) is not None for name in faults.__all__)
    with pytest.raises(AttributeError):
        faults.no_such_name  # noqa: B018
