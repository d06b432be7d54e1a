"""report --plot figures (imufdi_cli.plots): scale choice, which sensors are drawn, the
direction of isolation scores, stable colours, and a PNG that is written."""

from __future__ import annotations

import numpy as np
import pytest

from imufdi_cli import plots
from imufdi_cli.report import Report, ReportEntry


def entry(scores, isolated, alarm, faulty, name="pca-parity") -> ReportEntry:
    n = len(alarm)
    return ReportEntry(
        detector=name,
        sensor_type="gyro",
        sensor_ids=[f"imu{j}.gyro.x" for j in range(scores.shape[1])],
        metrics=None,  # type: ignore[arg-type]  # not drawn
        t_ns=np.arange(n, dtype=np.int64) * 10_000_000,
        statistic=np.linspace(1.0, 2.0, n),
        threshold=np.ones(n),
        alarm=np.asarray(alarm, bool),
        scores=scores,
        faulty=faulty,
        isolated=np.asarray(isolated, np.int64),
    )


def test_log_scale_when_statistic_and_threshold_differ_by_orders():
    assert plots.use_log_scale(np.array([900.0, 1100.0]), np.array([70.0, 70.0]))  # woa case
    assert not plots.use_log_scale(np.array([40.0, 140.0]), np.array([71.0]))  # glt case
    assert plots.use_log_scale(np.array([0.01, 5.0]), np.array([np.inf]))  # spans > 100
    assert not plots.use_log_scale(np.array([0.0, -1.0]), np.array([1.0]))  # nothing > 0


def test_smaller_is_worse_is_read_from_the_isolation_decisions():
    rng = np.random.default_rng(0)
    scores = rng.uniform(1.0, 1.5, size=(50, 6))
    scores[25:, 2] = 0.1  # pca-parity: the faulty sensor has the smallest angle
    alarm = np.arange(50) >= 25
    isolated = np.where(alarm, 2, -1)
    faulty = np.zeros((50, 6), bool)
    faulty[25:, 2] = True
    e = entry(scores, isolated, alarm, faulty)
    assert plots.smaller_is_worse(e)
    flipped = entry(-scores + 3.0, isolated, alarm, faulty, name="glt")  # largest = worst
    assert not plots.smaller_is_worse(flipped)


def test_suspects_are_the_faulty_then_the_wrongly_isolated():
    scores = np.zeros((10, 5))
    alarm = np.ones(10, bool)
    isolated = np.array([3] * 6 + [1] * 3 + [-1])
    faulty = np.zeros((10, 5), bool)
    faulty[:, 1] = True
    assert plots.suspects(entry(scores, isolated, alarm, faulty)) == [1, 3]
    none = np.zeros((10, 5), bool)
    assert plots.suspects(entry(scores, isolated, alarm, none)) == [3]  # the worst false one


@pytest.mark.draws  # run early, on one worker (tests/conftest.py)
def test_plot_report_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    rng = np.random.default_rng(1)
    scores = rng.uniform(1.0, 1.5, size=(200, 8))
    scores[100:, 4] = 0.2
    alarm = np.arange(200) >= 100
    faulty = np.zeros((200, 8), bool)
    faulty[100:, 4] = True
    e = entry(scores, np.where(alarm, 4, -1), alarm, faulty)
    report = Report(source="synthetic", has_truth=True, faults=[], entries=[e], notes=[], t0_ns=0)
    path = tmp_path / "r.png"
    plots.plot_report(report, str(path))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_time_zero_is_the_log_start_detect_recorded():
    e = entry(np.zeros((3, 2)), [-1] * 3, [False] * 3, np.zeros((3, 2), bool))
    report = Report(source="s", has_truth=False, faults=[], entries=[e], notes=[], t0_ns=10**10)
    assert plots.origin_ns(report, e) == 10**10  # older logs: the first status sample
    report.records["pca-parity"] = {"t0_ns": 0}  # detect --start 10s: status from 10 s
    assert plots.origin_ns(report, e) == 0
