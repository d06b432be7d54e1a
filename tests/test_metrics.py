"""Metric functions against hand-made truth/alarm sequences with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from imufdi_cli.metrics import (
    FaultWindow,
    compute_metrics,
    mean_metrics,
    persistent,
    rising_edges,
)

MS10 = 10_000_000  # 10 ms in ns: 100 Hz


def _t(n: int) -> np.ndarray:
    return np.arange(n, dtype=np.int64) * MS10


def test_far_mar_fir_hand_made():
    # 10 samples, 2 sensors; fault on sensor 1 from sample 5 on.
    t = _t(10)
    faulty = np.zeros((10, 2), bool)
    faulty[5:, 1] = True
    alarm = np.array([0, 1, 0, 0, 0, 0, 1, 1, 1, 0], bool)
    isolated = np.array([-1, 0, -1, -1, -1, -1, 1, 0, 1, -1])
    m = compute_metrics(t, alarm, isolated, faulty, [FaultWindow("f0", (1,), 5 * MS10)])
    assert m.fault_free_samples == 5 and m.faulty_samples == 5
    assert m.far == pytest.approx(1 / 5)
    assert m.mar == pytest.approx(2 / 5)
    assert m.accuracy == pytest.approx(1 - 1 / 5 - 2 / 5)
    assert m.detected_faulty == 3
    assert m.fir == pytest.approx(1 / 3)  # sample 7 isolated to healthy sensor 0
    assert m.isolation_accuracy == pytest.approx(2 / 3)
    assert m.detection_delay_s == pytest.approx(0.01)  # onset at 5, first alarm at 6
    assert m.recovery_delay_s is None  # fault never ends
    assert m.alarm_events == 2
    assert m.faults[0].detected and m.faults[0].isolated_correctly == pytest.approx(2 / 3)


def test_paper_table4_accuracy_identity():
    # FAR 4.98 %, MAR 26.58 % -> accuracy 68.44 % (Li et al. Table 4, GLT row)
    n_free, n_faulty = 10_000, 10_000
    t = _t(n_free + n_faulty)
    faulty = np.zeros((t.size, 1), bool)
    faulty[n_free:, 0] = True
    alarm = np.zeros(t.size, bool)
    alarm[:498] = True  # 4.98 % of fault-free samples
    alarm[n_free + 2658 :] = True  # 26.58 % of faulty samples missed
    m = compute_metrics(t, alarm, np.zeros(t.size, int), faulty)
    assert_allclose([m.far, m.mar, m.accuracy], [0.0498, 0.2658, 0.6844], atol=1e-12)


def test_undefined_values_are_none_not_zero():
    t = _t(20)
    # no faulty samples: MAR, FIR, accuracy, delays undefined
    m = compute_metrics(t, np.zeros(20, bool), np.full(20, -1), np.zeros((20, 3), bool))
    assert m.far == 0.0
    assert m.mar is None and m.fir is None and m.accuracy is None
    assert m.detection_delay_s is None and m.recovery_delay_s is None
    # faulty samples but never detected: FIR undefined, delay undefined, MAR = 1
    faulty = np.zeros((20, 3), bool)
    faulty[10:, 2] = True
    m = compute_metrics(
        t, np.zeros(20, bool), np.full(20, -1), faulty, [FaultWindow("f", (2,), 10 * MS10)]
    )
    assert m.mar == 1.0 and m.fir is None and m.detection_delay_s is None
    assert m.faults[0].detected is False and m.faults[0].isolated_correctly is None
    # every sample faulty: FAR undefined
    faulty = np.ones((20, 1), bool)
    m = compute_metrics(t, np.ones(20, bool), np.zeros(20, int), faulty)
    assert m.far is None and m.mar == 0.0 and m.fir == 0.0 and m.accuracy is None


def test_recovery_delay_and_persistence():
    t = _t(30)
    faulty = np.zeros((30, 1), bool)
    faulty[10:20, 0] = True
    alarm = np.zeros(30, bool)
    alarm[11] = True  # a one-sample blip
    alarm[14:23] = True  # persists, clears at 23 (3 samples after the end at 20)
    fault = FaultWindow("f", (0,), 10 * MS10, 20 * MS10)
    m = compute_metrics(t, alarm, np.zeros(30, int), faulty, [fault])
    assert m.detection_delay_s == pytest.approx(0.01)
    assert m.recovery_delay_s == pytest.approx(0.03)
    m3 = compute_metrics(t, alarm, np.zeros(30, int), faulty, [fault], persist=3)
    # the blip does not count; the run 14..16 is known to persist at sample 16
    assert m3.detection_delay_s == pytest.approx(0.06)


def test_alarm_after_fault_end_is_not_a_detection():
    t = _t(30)
    faulty = np.zeros((30, 1), bool)
    faulty[10:15, 0] = True
    alarm = np.zeros(30, bool)
    alarm[20] = True
    m = compute_metrics(
        t, alarm, np.zeros(30, int), faulty, [FaultWindow("f", (0,), 10 * MS10, 15 * MS10)]
    )
    assert m.faults[0].detected is False
    assert m.false_alarms == 1 and m.false_alarm_events_per_hour is not None


def test_two_simultaneous_faults_isolation_counts_either_sensor():
    t = _t(4)
    faulty = np.array([[1, 1, 0], [1, 1, 0], [1, 1, 0], [1, 1, 0]], bool)
    isolated = np.array([0, 1, 2, -1])
    m = compute_metrics(t, np.ones(4, bool), isolated, faulty)
    assert m.false_isolations == 1 and m.unisolated == 1
    assert m.fir == pytest.approx(1 / 4)


def test_helpers():
    assert rising_edges(np.array([1, 1, 0, 1, 0, 1], bool)).tolist() == [0, 3, 5]
    assert rising_edges(np.zeros(0, bool)).size == 0
    assert persistent(np.array([1, 1, 0, 1, 1, 1, 0], bool), 2).tolist() == [
        True,
        False,
        False,
        True,
        True,
        False,
        False,
    ]
    assert mean_metrics([0.1, None, 0.3]) == (pytest.approx(0.2), pytest.approx(0.1414213), 2)
    assert mean_metrics([None, None]) == (None, None, 0)


def test_value_lookup():
    t = _t(10)
    faulty = np.zeros((10, 1), bool)
    faulty[5:] = True
    m = compute_metrics(
        t, faulty[:, 0].copy(), np.zeros(10, int), faulty, [FaultWindow("f", (0,), 5 * MS10)]
    )
    assert m.value("detection_rate") == 1.0
    assert m.value("detection_probability") == 1.0
    with pytest.raises(KeyError):
        m.value("nonsense")


def test_faulty_matrix_from_windows():
    from imufdi_cli.metrics import faulty_matrix

    t = _t(6)
    windows = [FaultWindow("a", (0,), 2 * MS10, 4 * MS10), FaultWindow("b", (1, 2), 5 * MS10)]
    expected = np.zeros((6, 3), bool)
    expected[2:4, 0] = True
    expected[5:, 1:] = True
    assert (faulty_matrix(t, windows, 3) == expected).all()
