"""Report renderers and --fail-if gates on a hand-made report."""

from __future__ import annotations

import csv
import io
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from imufdi_cli import report as rep
from imufdi_cli.errors import GateError
from imufdi_cli.metrics import FaultWindow, compute_metrics

KNOWN = ["glt", "pca-parity"]


def _report(with_truth: bool = True) -> rep.Report:
    n = 100
    t = np.arange(n, dtype=np.int64) * 10_000_000
    faulty = np.zeros((n, 3), bool)
    if with_truth:
        faulty[50:, 0] = True
    alarm = np.zeros(n, bool)
    alarm[[3, 4]] = True  # 2 false alarms of 50 fault-free samples: FAR 4 %
    alarm[55:] = True  # 5 of 50 faulty samples missed: MAR 10 %
    isolated = np.where(alarm, 0, -1)
    isolated[60] = 2  # one false isolation of 45 detected faulty samples
    windows = [FaultWindow("f0", (0,), 50 * 10_000_000)] if with_truth else []
    metrics = compute_metrics(t, alarm, isolated, faulty, windows)
    entry = rep.ReportEntry(
        detector="glt",
        sensor_type="gyro",
        sensor_ids=["imu0.gyro.x", "imu1.gyro.x", "imu2.gyro.x"],
        metrics=metrics,
        t_ns=t,
        statistic=np.where(alarm, 10.0, 1.0),
        threshold=np.full(n, 6.6),
        alarm=alarm,
        scores=np.zeros((n, 3)),
        faulty=faulty,
    )
    return rep.Report(
        source="x.mcap",
        has_truth=with_truth,
        faults=[{"id": "f0", "spec": "step:imu0.gyro.x,at=0.5s,amp=1deg/s"}] if with_truth else [],
        entries=[entry],
        notes=[],
        t0_ns=0,
    )


def test_parse_gate_forms():
    gate = rep.parse_gate("glt.gyro.far > 0.01", KNOWN)
    assert (gate.detector, gate.sensor_type, gate.metric, gate.op, gate.value) == (
        "glt",
        "gyro",
        "far",
        ">",
        0.01,
    )
    assert rep.parse_gate("*.accel.mar>=5%", KNOWN).value == pytest.approx(0.05)
    assert rep.parse_gate(" pca-parity.*.detection_delay_s <= 1e-1 ", KNOWN).op == "<="


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("glt.gyro.far", "not of the form"),
        ("glt.gyro.far >> 1", "not of the form"),
        ("glt.gyro.far > abc", "not of the form"),
        ("nope.gyro.far > 1", "unknown detector 'nope'; valid: glt, pca-parity"),
        ("glt.baro.far > 1", "unknown sensor type 'baro'"),
        ("glt.gyro.speed > 1", "unknown metric 'speed'"),
    ],
)
def test_parse_gate_errors(text, fragment):
    with pytest.raises(GateError, match=fragment.replace("(", r"\(")) as info:
        rep.parse_gate(text, KNOWN)
    assert info.value.exit_code == 2
    assert "\n" not in str(info.value)


def test_evaluate_gates_pass_fail_and_undefined():
    report = _report()
    gates = [
        rep.parse_gate("glt.gyro.far > 0.05", KNOWN),  # 0.04: passes
        rep.parse_gate("glt.gyro.mar > 0.05", KNOWN),  # 0.10: fails
        rep.parse_gate("glt.*.fir >= 2%", KNOWN),  # 1/45 = 2.2 %: fails
    ]
    results = rep.evaluate_gates(report, gates)
    assert [r.failed for r in results] == [False, True, True]
    assert results[0].actual == pytest.approx(0.04)
    assert results[1].actual == pytest.approx(0.10)
    assert results[2].actual == pytest.approx(1 / 45)
    # undefined metric fails the gate
    no_truth = _report(with_truth=False)
    no_truth.entries[0].metrics.mar = None
    (undefined,) = rep.evaluate_gates(no_truth, [rep.parse_gate("glt.gyro.mar > 0.5", KNOWN)])
    assert undefined.failed and "undefined" in undefined.message


def test_gate_naming_absent_results_is_usage_error():
    with pytest.raises(GateError, match=r"no results for pca-parity\.gyro.*present: glt\.gyro"):
        rep.evaluate_gates(_report(), [rep.parse_gate("pca-parity.gyro.far > 0.1", KNOWN)])


def test_renderers():
    report = _report()
    results = rep.evaluate_gates(report, [rep.parse_gate("glt.gyro.mar > 0.05", KNOWN)])
    data = json.loads(rep.to_json(report, results))
    assert data["results"][0]["far"] == pytest.approx(0.04)
    assert data["gates"][0]["failed"] is True
    md = rep.to_markdown(report, results)
    assert "| glt | gyro | 4.00 | 10.00 | 86.00 |" in md
    rows = list(csv.DictReader(io.StringIO(rep.to_csv(report))))
    assert rows[0]["detector"] == "glt" and float(rows[0]["mar"]) == pytest.approx(0.1)
    suite = ET.fromstring(rep.to_junit(report, results))
    assert suite.get("failures") == "1" and suite.find("testcase/failure") is not None
    suite = ET.fromstring(rep.to_junit(report))
    assert suite.get("tests") == "1" and suite.find("testcase/failure") is None


def test_undefined_rendering():
    report = _report(with_truth=False)
    row = rep.table_rows(report)[0]
    assert row[3] == "undefined"  # MAR without faulty samples
    assert json.loads(rep.to_json(report))["results"][0]["mar"] is None
    assert rep.format_value(None) == "undefined"


def test_plot_series_keep_every_alarm_when_decimating(monkeypatch):
    """The kept sample's alarm is the OR of the alarms since the previous kept sample,
    for any block sizes and after any number of halvings."""
    monkeypatch.setattr(rep, "PLOT_POINTS", 50)
    rng = np.random.default_rng(3)
    for _ in range(100):
        n = int(rng.integers(1, 2000))
        alarm = rng.random(n) < rng.choice([0.001, 0.01, 0.2])
        t = np.arange(n)
        series = rep._Series()
        pos = 0
        while pos < n:
            k = int(rng.integers(1, 300))
            series.add({"t_ns": t[pos : pos + k], "alarm": alarm[pos : pos + k]})
            pos += k
        kept = series.arrays()
        t_kept = kept["t_ns"]
        assert t_kept[0] == 0 and np.all(np.diff(t_kept) == series.stride)
        assert t_kept.size <= 2 * 50 + 300
        expected = [
            alarm[(t_kept[i - 1] + 1 if i else 0) : t_kept[i] + 1].any() for i in range(t_kept.size)
        ]
        assert kept["alarm"].tolist() == expected
        assert series.pending_alarm == bool(alarm[t_kept[-1] + 1 :].any())
