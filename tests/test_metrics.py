"""Metric functions against hand-made truth/alarm sequences with known answers."""

from __future__ import annotations

import math

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


# --- out-of-sample FAR, decision time, isolation delay, recovery ----------------------------


def test_calibration_window_is_excluded_and_reported_apart():
    # 20 fault-free samples; the calibration window holds samples 0..9 with 4 alarms, the
    # rest 1 alarm: FAR 1/10 out of sample, 4/10 in sample.
    t = _t(20)
    alarm = np.zeros(20, bool)
    alarm[[1, 2, 3, 5, 15]] = True
    m = compute_metrics(t, alarm, np.full(20, -1), n_sensors=2, calibration_ns=(0, 10 * MS10))
    assert m.samples == 20 and m.calibration_samples == 10 and m.fault_free_samples == 10
    assert m.far == pytest.approx(1 / 10)
    assert m.far_calibration == pytest.approx(4 / 10)
    assert m.alarm_rate == pytest.approx(1 / 10)
    assert m.alarm_events == 1  # the events inside the window do not count
    # without the window: every sample counts, as older logs are reported
    m_all = compute_metrics(t, alarm, np.full(20, -1), n_sensors=2)
    assert m_all.far == pytest.approx(5 / 20) and m_all.far_calibration is None


def test_calibration_exclusion_streams_like_one_call():
    from imufdi_cli.metrics import MetricsAccumulator

    rng = np.random.default_rng(3)
    t = _t(500)
    alarm = rng.random(500) < 0.2
    isolated = np.where(alarm, rng.integers(0, 3, 500), -1)
    fault = FaultWindow("f", (2,), 300 * MS10, 400 * MS10)
    whole = compute_metrics(
        t, alarm, isolated, n_sensors=3, faults=[fault], calibration_ns=(0, 100 * MS10)
    )
    acc = MetricsAccumulator(3, [fault], calibration_ns=(0, 100 * MS10))
    for start in range(0, 500, 37):  # uneven chunks
        part = slice(start, start + 37)
        acc.update(t[part], alarm[part], isolated[part])
    assert acc.result().to_dict() == whole.to_dict()


def test_delays_are_at_decision_time():
    # fault on sensor 0 from sample 10; first alarm at sample 12, its decision available
    # 5 samples later (a detector that looks ahead): delay 0.07 s, latency 0.05 s
    t = _t(30)
    decided = t + 5 * MS10
    alarm = np.zeros(30, bool)
    alarm[12:] = True
    fault = FaultWindow("f", (0,), 10 * MS10)
    m = compute_metrics(
        t, alarm, np.zeros(30, int), n_sensors=2, faults=[fault], decided_ns=decided
    )
    assert m.detection_delay_s == pytest.approx(0.07)
    assert m.decision_latency_s == pytest.approx(0.05)
    causal = compute_metrics(t, alarm, np.zeros(30, int), n_sensors=2, faults=[fault])
    assert causal.detection_delay_s == pytest.approx(0.02)
    assert causal.decision_latency_s == 0.0


def test_isolation_delay_waits_for_the_faulty_sensor():
    # a chance alarm isolated to healthy sensor 1 at sample 11, then sensor 0 from sample 15
    t = _t(30)
    alarm = np.zeros(30, bool)
    alarm[11] = True
    alarm[15:] = True
    isolated = np.full(30, -1)
    isolated[11] = 1
    isolated[15:] = 0
    fault = FaultWindow("f", (0,), 10 * MS10)
    m = compute_metrics(t, alarm, isolated, n_sensors=2, faults=[fault])
    assert m.detection_delay_s == pytest.approx(0.01)
    assert m.isolation_delay_s == pytest.approx(0.05)
    assert m.faults[0].isolation_delay_s == pytest.approx(0.05)
    # with a set of isolated sensors the fault's own sensor must be in the set
    iso_set = np.zeros((30, 2), bool)
    iso_set[11, 1] = True
    iso_set[18:, :] = True
    m_set = compute_metrics(t, alarm, isolated, n_sensors=2, faults=[fault], isolated_set=iso_set)
    assert m_set.isolation_delay_s == pytest.approx(0.08)
    never = compute_metrics(t, alarm, np.where(alarm, 1, -1), n_sensors=2, faults=[fault])
    assert never.isolation_delay_s is None and never.detection_delay_s is not None


def test_recovery_waits_until_alarms_stop_for_good():
    # fault 10..20; alarms flicker after the end: 20, 22, 25 on, then quiet to the end
    t = _t(40)
    alarm = np.zeros(40, bool)
    alarm[12:21] = True
    alarm[[22, 25]] = True
    fault = FaultWindow("f", (0,), 10 * MS10, 20 * MS10)
    m = compute_metrics(t, alarm, np.zeros(40, int), n_sensors=1, faults=[fault])
    assert m.recovery_delay_s == pytest.approx(0.06)  # first sample after the last alarm: 26
    # --persist 20: 14 quiet samples (26..39) are not enough, recovery undefined
    m20 = compute_metrics(t, alarm, np.zeros(40, int), n_sensors=1, faults=[fault], persist=20)
    assert m20.recovery_delay_s is None
    # an alarm that comes back more than 0.1 s (the merge gap) after the clearing is a new
    # episode (a false alarm), not a late recovery; one within 0.1 s is flicker
    t80 = _t(80)
    alarm80 = np.zeros(80, bool)
    alarm80[12:21] = True
    alarm80[[22, 25, 60]] = True
    m80 = compute_metrics(t80, alarm80, np.zeros(80, int), n_sensors=1, faults=[fault])
    assert m80.recovery_delay_s == pytest.approx(0.06)
    assert m80.false_alarms == 4  # 20 (the fault ends at 20), 22, 25 and 60
    alarm80[35] = True  # 9 samples (0.09 s) after the clearing at 26: still the episode
    m80 = compute_metrics(t80, alarm80, np.zeros(80, int), n_sensors=1, faults=[fault])
    assert m80.recovery_delay_s == pytest.approx(0.16)
    # the recovery episode ends at the next onset: alarms of the next fault do not count
    second = FaultWindow("g", (0,), 30 * MS10)
    alarm2 = alarm.copy()
    alarm2[31:] = True
    m2 = compute_metrics(t, alarm2, np.zeros(40, int), n_sensors=1, faults=[fault, second])
    assert m2.faults[0].recovery_delay_s == pytest.approx(0.06)
    # and the recovery is stamped at decision time too
    late = compute_metrics(
        t, alarm, np.zeros(40, int), n_sensors=1, faults=[fault], decided_ns=t + 3 * MS10
    )
    assert late.recovery_delay_s == pytest.approx(0.09)


def test_recovery_streams_across_chunks():
    from imufdi_cli.metrics import MetricsAccumulator

    t = _t(40)
    alarm = np.zeros(40, bool)
    alarm[12:21] = True
    alarm[[22, 25]] = True
    fault = FaultWindow("f", (0,), 10 * MS10, 20 * MS10)
    for size in (1, 3, 7, 40):
        acc = MetricsAccumulator(1, [fault], persist=2)
        for start in range(0, 40, size):
            part = slice(start, start + size)
            acc.update(t[part], alarm[part], np.zeros(len(t[part]), int))
        result = acc.result()
        assert result.recovery_delay_s == pytest.approx(0.06)
        assert result.detection_delay_s == pytest.approx(0.03)  # run 12, 13 known at 13


def test_detection_rate_is_one_minus_mar_and_rate_after_first_detection_is_apart():
    t = _t(20)
    alarm = np.zeros(20, bool)
    alarm[15:] = True  # fault from 10: detected late
    fault = FaultWindow("f", (0,), 10 * MS10)
    m = compute_metrics(t, alarm, np.zeros(20, int), n_sensors=1, faults=[fault])
    assert m.value("detection_rate") == pytest.approx(0.5)
    assert m.to_dict()["detection_rate"] == pytest.approx(0.5)
    assert m.rate_after_first_detection == pytest.approx(1.0)


def test_per_fault_amplitudes_median_for_a_step_and_slope_for_a_drift():
    """Analytic: a step's estimate is the median amplitude where its sensor is isolated
    (rows without an alarm or isolated elsewhere are ignored); a drift's is the slope of the
    amplitude against time, unchanged by a lag (the estimate shifted by 0.5 s)."""
    from imufdi_cli.metrics import MetricsAccumulator

    n = 1000
    t = _t(n)
    t_s = t * 1e-9
    step = FaultWindow("s", (0,), 200 * MS10, None, "step", 0.5)
    drift = FaultWindow("d", (2,), 300 * MS10, None, "drift", 0.1)
    alarm = t >= 200 * MS10
    isolated_set = np.zeros((n, 3), bool)
    isolated_set[200:, 0] = True
    isolated_set[350:, 2] = True
    amplitudes = np.full((n, 3), np.nan)
    amplitudes[:, 0] = 0.5 + 0.01 * np.sin(np.arange(n))  # symmetric wiggle: median 0.5
    amplitudes[:, 1] = 7.0  # a healthy sensor: not part of any fault's figure
    amplitudes[:, 2] = 0.1 * (t_s - 3.0 - 0.5)  # the drift lagged by 0.5 s
    amplitudes[600:610, 0] = 100.0  # outliers the median ignores...
    isolated_set[600:610, 0] = True
    alarm[900:] = False  # ...and rows without alarm that would bias the slope
    amplitudes[900:, 2] = -50.0
    acc = MetricsAccumulator(3, [step, drift], sensor_ids=["a", "b", "c"])
    for lo in range(0, n, 97):  # streaming in uneven blocks
        hi = min(lo + 97, n)
        acc.update(
            t[lo:hi],
            alarm[lo:hi],
            np.full(hi - lo, -1),
            isolated_set=isolated_set[lo:hi],
            amplitudes=amplitudes[lo:hi],
        )
    figures = {f.fault_id: f.amplitudes for f in acc.result().faults}
    (a_step,) = figures["s"]
    assert (a_step.sensor, a_step.size_name, a_step.true) == ("a", "amp", 0.5)
    # 10 outliers in 700 move the median by 5 ranks: 5/700 of the quantile range, times
    # the arcsine spread at its centre, pi x 0.01: 2.2e-4
    assert a_step.estimate == pytest.approx(0.5, abs=3e-4)
    assert a_step.samples == 700
    (a_drift,) = figures["d"]
    assert (a_drift.sensor, a_drift.size_name, a_drift.samples) == ("c", "rate", 550)
    assert a_drift.estimate == pytest.approx(0.1, rel=1e-9)
    assert a_drift.ratio == pytest.approx(1.0, rel=1e-9)
    # without per-sensor amplitudes there is no figure
    plain = compute_metrics(t, alarm, np.zeros(n, int), faults=[step], n_sensors=3)
    assert plain.faults[0].amplitudes == []


def test_per_fault_amplitude_median_in_bounded_memory():
    """Beyond 2 x AMPLITUDE_POINTS samples the median comes from an evenly decimated copy:
    memory stays bounded and, for a smooth distribution, the median is still right to a
    fraction of the spread."""
    from imufdi_cli.metrics import AMPLITUDE_POINTS, MetricsAccumulator

    rng = np.random.default_rng(0)
    n = 10 * AMPLITUDE_POINTS
    values = rng.normal(2.0, 0.1, n)
    acc = MetricsAccumulator(1, [FaultWindow("f", (0,), 0, None, "step", 2.0)])
    for lo in range(0, n, 4999):
        hi = min(lo + 4999, n)
        k = hi - lo
        acc.update(_t(n)[lo:hi], np.ones(k, bool), np.zeros(k, int), amplitudes=values[lo:hi, None])
    track = acc.states[0].amplitudes[0]
    assert track.n_kept <= 2 * AMPLITUDE_POINTS
    (figure,) = acc.result().faults[0].amplitudes
    assert figure.samples == n
    # the decimated median's std is about 1.25 sigma / sqrt(kept) = 0.001; 5 of them
    assert figure.estimate == pytest.approx(float(np.median(values)), abs=0.005)


# --- false alarm episodes per hour and the matched budget --------------------------------


def test_false_episodes_per_hour_of_fault_free_tested_time():
    # 1 h at 100 Hz minus a 20-minute hole (nothing tested): 40 min of rows. Three false
    # runs, the second two 0.5 s apart on the same sensor (one episode), a fault from
    # 30 min whose alarms end 0.2 s after it (the same episode: not a false one), and a
    # false run inside the calibration window (not counted)
    t = _t(360_000)
    t = np.concatenate([t[:120_000], t[240_000:]])  # rows 120,000-240,000 missing
    alarm = np.zeros(t.size, bool)
    isolated = np.full(t.size, -1)
    for start, length, sensor in [(50, 3, 1), (30_000, 5, 2), (30_055, 4, 2), (100_000, 2, 0)]:
        alarm[start : start + length] = True
        isolated[start : start + length] = sensor
    fault_from = 180_000 - 120_000  # row of 30 min
    alarm[fault_from + 30 : fault_from + 500 + 20] = True
    isolated[fault_from + 30 : fault_from + 500 + 20] = 3
    fault = FaultWindow("f", (3,), int(t[fault_from]), int(t[fault_from + 500]))
    m = compute_metrics(
        t,
        alarm,
        isolated,
        n_sensors=4,
        faults=[fault],
        calibration_ns=(0, 10 * MS10 * 100),
        episode_gaps=(10, 100),
    )
    assert m.false_episodes == 2  # the joined pair and the run at row 100,000
    hours = (t.size - 1000 - 500) * 0.01 / 3600  # rows outside the calibration and fault
    assert m.fault_free_hours == pytest.approx(hours, rel=1e-12)
    assert m.false_episodes_per_hour == pytest.approx(2 / hours, rel=1e-12)
    assert m.false_episodes_per_hour_upper95 == pytest.approx(6.2957936 / hours, rel=1e-6)
    assert m.mtbfa_h == pytest.approx(hours / 2, rel=1e-12)
    assert m.mtbfa_h_lower95 == pytest.approx(1 / m.false_episodes_per_hour_upper95)
    assert m.value("false_episodes_per_hour_upper95") == m.false_episodes_per_hour_upper95


def test_episodes_need_the_joining_rule_and_a_quiet_log_has_no_mean_time_between():
    t = _t(1000)
    quiet = compute_metrics(t, np.zeros(1000, bool), np.full(1000, -1), n_sensors=3, episode_gaps=(10, 100))  # fmt: skip
    assert quiet.false_episodes == 0 and quiet.false_episodes_per_hour == 0.0
    assert quiet.mtbfa_h is None and quiet.mtbfa_h_lower95 == pytest.approx(10 / 3600 / 2.9957, rel=1e-4)  # fmt: skip
    unknown = compute_metrics(t, np.zeros(1000, bool), np.full(1000, -1), n_sensors=3)
    assert unknown.false_episodes is None and unknown.false_episodes_per_hour is None


def test_rows_not_scored_take_part_in_episodes_but_not_in_figures():
    from imufdi_cli.metrics import MetricsAccumulator

    t = _t(400)
    alarm = np.zeros(400, bool)
    alarm[[100, 101, 105, 300]] = True  # one run from 100 (105 within the merge gap), one at 300
    isolated = np.where(alarm, 0, -1)
    scored = np.ones(400, bool)
    scored[98:103] = False  # the first run starts on an excluded (clipped) row
    acc = MetricsAccumulator(2, episode_gaps=(10, 30))
    acc.update(t, alarm, isolated, scored=scored)
    m = acc.result()
    assert m.samples == 395 and m.false_alarms == 2  # rows 105 and 300
    assert m.false_episodes == 1  # 105 is not an episode of its own; 300 is (200 rows on)


def test_matched_budget_scales_the_threshold_until_false_episodes_fall_to_the_target():
    # 2 h at 10 Hz of fault-free rows with ratios drawn so that the episodes thin out with
    # the threshold, then a fault whose ratio rises to 8 x the threshold
    rng = np.random.default_rng(3)
    n_free, n_fault = 72_000, 200
    ratio = np.concatenate([rng.exponential(0.12, n_free), np.full(n_fault, 8.0)])
    t = np.arange(ratio.size, dtype=np.int64) * 100_000_000
    fault = FaultWindow("f", (0,), int(t[n_free]))
    isolated = np.zeros(ratio.size, int)
    m = compute_metrics(
        t,
        ratio >= 1,
        np.where(ratio >= 1, isolated, -1),
        n_sensors=2,
        faults=[fault],
        statistic=ratio,
        threshold=np.ones(ratio.size),
        episode_gaps=(1, 10),
        match_budget=1.0,
    )
    own = m.false_episodes_per_hour
    assert own is not None and own > 1.0  # the detector's own threshold raises more
    scale = m.threshold_scale_at_budget
    assert scale is not None and scale > 1.0
    # at the matched scale the exceedances of the fault-free ratios are about 2 in 2 h
    assert 0.5 <= np.count_nonzero(ratio[:n_free] >= scale) <= 6
    assert m.mar_at_budget == 0.0 and m.detection_delay_s_at_budget == 0.0
    assert m.target_budget_per_hour == 1.0


def test_a_statistic_that_grew_in_a_fault_is_not_a_false_episode_at_a_higher_threshold():
    # a sequential test's statistic grows through a fault (rows 1000-1099) and on after
    # it, while the detector's own episode stays open (to row 1199): at 10 x its threshold
    # the statistic first crosses after the fault's end, yet it is the fault's episode. A
    # later excursion to 20 x on fault-free rows is a false episode up to 20 x.
    from imufdi_cli.metrics import MetricsAccumulator
    from imufdi_cli.sweep import BUDGET_LOG_SCALES

    n = 5000
    t = np.arange(n, dtype=np.int64) * 100_000_000  # 10 Hz
    ratio = np.full(n, 0.1)
    ratio[1000:1200] = np.geomspace(1.0, 50.0, 200)
    ratio[3000:3010] = 20.0
    alarm = ratio >= 1.0
    fault = FaultWindow("f", (0,), int(t[1000]), int(t[1100]))
    acc = MetricsAccumulator(2, [fault], episode_gaps=(1, 10))
    acc.update(t, alarm, np.where(alarm, 0, -1), statistic=ratio, threshold=np.ones(n))
    counts = acc.budget_curve().false_episodes
    scale = 10**BUDGET_LOG_SCALES
    assert counts[(scale > 1.5) & (scale < 19)].tolist() == [1] * int(np.sum((scale > 1.5) & (scale < 19)))  # fmt: skip
    assert counts[scale > 21].sum() == 0
    assert acc.result().false_episodes == 1  # the detector's own: the excursion at 3000


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 10, 101, 1000])
def test_the_amplitude_median_is_numpys(n: int) -> None:
    """metrics.accumulator._median gives np.median's float (not a close one)."""
    from imufdi_cli.metrics.accumulator import _median

    rng = np.random.default_rng(n)
    for values in (rng.normal(size=n), rng.integers(-3, 3, size=n).astype(float)):
        assert _median(values) == float(np.median(values))
    assert math.isnan(_median(np.array([1.0, np.nan, 2.0])))
    assert math.isnan(_median(np.array([])))


def test_the_amplitude_median_does_not_import_numpy_ma(fresh_python) -> None:
    probe = (
        "import sys\n"
        "import numpy as np\n"
        "from imufdi_cli.metrics.accumulator import _median\n"
        "_median(np.arange(10.0))\n"
        "print('numpy.ma' in sys.modules)\n"
    )
    done = fresh_python(probe)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"


def _loop_recovery(t, decided, alarm, persist, merge_gap_ns, state):
    """The recovery bookkeeping as a plain loop over the rows (reference): ``state`` is
    [quiet_from_ns, quiet_from_t, quiet, recovered_ns]."""
    position = 0
    size = int(t.size)
    for a in [*np.flatnonzero(alarm).tolist(), size]:
        if a > position:
            if state[0] is None:
                state[0], state[1], state[2] = int(decided[position]), int(t[position]), 0
            state[2] += a - position
        if a == size:
            return
        if state[1] is not None and state[2] >= persist and t[a] - state[1] > merge_gap_ns:
            state[3] = state[0]
            return
        state[0] = state[1] = None
        state[2] = 0
        position = a + 1


def _loop_detection(decided, on, persist, run):
    """The first row where a run of alarms reaches ``persist`` (reference loop)."""
    for j, flag in enumerate(on.tolist()):
        run = run + 1 if flag else 0
        if run >= persist:
            return int(decided[j]), run
    return None, run


@pytest.mark.parametrize("seed", range(40))
def test_recovery_and_detection_runs_are_those_of_a_loop_over_the_rows(seed):
    # the accumulator finds them with numpy, block by block: the same rows as a loop
    from imufdi_cli.metrics import MetricsAccumulator

    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 120))
    t = np.cumsum(rng.integers(1, 3, n)).astype(np.int64) * MS10
    decided = t + rng.integers(0, 3, n) * MS10
    alarm = rng.random(n) < rng.choice([0.05, 0.3, 0.7, 0.95])
    persist = int(rng.integers(1, 5))
    start, end = int(t[n // 4]), int(t[n // 2])
    fault = FaultWindow("f", (0,), start, end)
    acc = MetricsAccumulator(1, [fault], persist=persist)
    cuts = np.sort(rng.choice(np.arange(1, n), size=min(n - 1, 4), replace=False))
    for part in np.split(np.arange(n), cuts):
        acc.update(t[part], alarm[part], np.zeros(part.size, int), decided_ns=decided[part])
    st = acc.states[0]
    inside = (t >= start) & (t < end)
    want_detected, _ = _loop_detection(decided[inside], alarm[inside], persist, 0)
    assert st.detected_ns == want_detected
    state = [None, None, 0, None]
    after = t >= end
    _loop_recovery(t[after], decided[after], alarm[after], persist, acc.merge_gap_ns, state)
    assert st.recovered_ns == state[3]
    if state[3] is None:
        assert (st.quiet_from_ns, st.quiet_from_t, st.quiet) == tuple(state[:3])


def _scored(seed: int, **options):
    """Metrics of one random channel with three faults, fed in blocks of 37 rows."""
    from imufdi_cli.metrics import MetricsAccumulator

    rng = np.random.default_rng(seed)
    n, n_s = 400, 5
    t = _t(n)
    alarm = rng.random(n) < 0.4
    isolated = np.where(alarm, rng.integers(-2, n_s, n), -1)
    scores = rng.normal(size=(n, n_s))
    scores[rng.random((n, n_s)) < 0.1] = np.nan
    scores[rng.random((n, n_s)) < 0.05] = np.inf
    amplitude = np.where(isolated >= 0, rng.normal(size=n), np.nan)
    faults = [
        FaultWindow("a", (1,), 50 * MS10, 150 * MS10, "step", 1.0),
        FaultWindow("b", (3, 4), 200 * MS10, 300 * MS10, "drift", 0.5),
    ]
    acc = MetricsAccumulator(n_s, faults, episode_gaps=(10, 100))
    statistic = rng.gamma(2.0, size=n)
    for s in range(0, n, 37):
        part = slice(s, s + 37)
        k = len(t[part])
        amplitudes = np.full((k, n_s), np.nan)
        rows = np.flatnonzero(isolated[part] >= 0)
        amplitudes[rows, isolated[part][rows]] = amplitude[part][rows]
        given = {
            "amplitudes": amplitudes,
            "amplitude": amplitude[part],
            "scores": scores[part],
            "best_score": None,
        }
        if options.get("compact_amplitudes"):
            given["amplitudes"] = None
        else:
            given["amplitude"] = None
        if options.get("best_score"):
            from imufdi_cli.sweep import best_columns

            given["best_score"] = best_columns(scores[part])
            given["scores"] = None
        acc.update(
            t[part],
            alarm[part],
            isolated[part],
            statistic=statistic[part],
            threshold=np.ones(k),
            scored=rng.random(k) < 0.95,
            **given,
        )
    return acc.result()


@pytest.mark.parametrize("seed", range(5))
def test_amplitude_on_the_isolated_column_and_best_score_give_the_same_figures(seed):
    # update(amplitude=) in place of the (k, n) amplitudes holding it on the isolated
    # column, and update(best_score=) in place of the scores: the same metrics
    reference = _scored(seed)
    for options in ({"compact_amplitudes": True}, {"best_score": True}):
        got = _scored(seed, **options)
        assert repr(got) == repr(reference)
    assert any(f.amplitudes for f in reference.faults)
