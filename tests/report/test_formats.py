"""Report renderers on a hand-made report."""

from __future__ import annotations

import csv
import io
import json
import xml.etree.ElementTree as ET

import pytest

from imufdi_cli.report.formats import (
    format_value,
    table_columns,
    table_rows,
    to_csv,
    to_json,
    to_junit,
    to_markdown,
)
from imufdi_cli.report.gates import evaluate_gates, parse_gate
from tests.report.reports import KNOWN, hand_made_report


def test_renderers():
    report = hand_made_report()
    results = evaluate_gates(report, [parse_gate("glt.gyro.mar > 0.05", KNOWN)])
    data = json.loads(to_json(report, results))
    assert data["results"][0]["far"] == pytest.approx(0.04)
    assert data["gates"][0]["failed"] is True
    md = to_markdown(report, results)
    assert "| glt | gyro | 4.00 | 10.00 | 86.00 |" in md
    rows = list(csv.DictReader(io.StringIO(to_csv(report))))
    assert rows[0]["detector"] == "glt" and float(rows[0]["mar"]) == pytest.approx(0.1)
    suite = ET.fromstring(to_junit(report, results))
    assert suite.get("failures") == "1" and suite.find("testcase/failure") is not None
    suite = ET.fromstring(to_junit(report))
    assert suite.get("tests") == "1" and suite.find("testcase/failure") is None


def test_undefined_rendering():
    report = hand_made_report()
    report.entries[0].metrics.fir = None
    row = table_rows(report)[0]
    assert row[2 + [c[0] for c in table_columns(report)].index("fir")] == "undefined"
    assert format_value(None) == "undefined"


def test_a_fault_free_report_shows_what_the_alarms_cost_not_undefined_figures():
    report = hand_made_report(with_truth=False)
    assert json.loads(to_json(report))["results"][0]["mar"] is None
    names = [c[0] for c in table_columns(report)]
    assert "mar" not in names and "far" not in names
    assert names[:4] == ["alarm_rate", "alarm_events", "false_episodes", "false_episodes_per_hour"]
    row = dict(zip(names, table_rows(report)[0][2:]))
    # 47 alarms of 100 rows in 2 events, one episode (both runs isolate sensor 0, 50 rows
    # apart: joined); 1 s of rows at 100 Hz
    assert row["alarm_rate"] == "47.00" and row["alarm_events"] == "2"
    assert row["false_episodes"] == "1" and row["fault_free_hours"] == f"{1 / 3600:.3g}"
    assert row["false_episodes_per_hour"] == "3.6e+03"
    assert "undefined" not in row.values()
