"""Report renderers on a hand-made report."""

from __future__ import annotations

import csv
import io
import json
import xml.etree.ElementTree as ET

import pytest

from imufdi_cli.report.formats import (
    format_value,
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
    report = hand_made_report(with_truth=False)
    row = table_rows(report)[0]
    assert row[3] == "undefined"  # MAR without faulty samples
    assert json.loads(to_json(report))["results"][0]["mar"] is None
    assert format_value(None) == "undefined"
