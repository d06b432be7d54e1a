"""imufdi report: tables and files, gates exit 0/1/2, no-truth logs."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

from tests.cli.conftest import assert_one_line_error


def test_report_table_and_files(cli, tmp_path, detected_log):
    files = {k: tmp_path / f"r.{k}" for k in ("json", "md", "csv", "xml")}
    result = cli(
        [
            "report",
            detected_log,
            "--json",
            files["json"],
            "--markdown",
            files["md"],
            "--csv",
            files["csv"],
            "--junit",
            files["xml"],
        ]
    )
    assert result.code == 0, result.stderr
    assert "FAR %" in result.out and "glt" in result.out
    data = json.loads(files["json"].read_text())
    gyro = next(r for r in data["results"] if r["detector"] == "glt" and r["sensor_type"] == "gyro")
    assert 0.0 <= gyro["far"] <= 0.2 and 0.0 <= gyro["mar"] <= 0.6
    assert data["faults"][0]["spec"].startswith("step:imu0.gyro.x")
    assert "| glt | gyro |" in files["md"].read_text()
    assert files["csv"].read_text().startswith("detector,sensor_type")
    ET.fromstring(files["xml"].read_text())


def test_gates(cli, detected_log, tmp_path):
    ok = cli(["report", detected_log, "--fail-if", "glt.gyro.far > 0.5"])
    assert ok.code == 0, ok.stderr
    junit = tmp_path / "g.xml"
    bad = cli(["report", detected_log, "--fail-if", "glt.gyro.far >= 0", "--junit", junit])
    assert bad.code == 1
    assert "glt.gyro.far" in bad.stderr
    assert ET.fromstring(junit.read_text()).get("failures") == "1"


def test_gate_usage_errors(cli, detected_log):
    assert_one_line_error(
        cli(["report", detected_log, "--fail-if", "glt.gyro.far"]), 2, "not of the form"
    )
    assert_one_line_error(
        cli(["report", detected_log, "--fail-if", "nope.gyro.far > 1"]), 2, "unknown detector"
    )
    assert_one_line_error(
        cli(["report", detected_log, "--fail-if", "glt.gyro.speed > 1"]), 2, "unknown metric"
    )
    assert_one_line_error(
        cli(["report", detected_log, "--fail-if", "pca-parity.gyro.far > 1"]), 2, "no results"
    )


def test_no_truth(cli, tmp_path, table4_log):
    out = tmp_path / "d.mcap"
    assert cli(["detect", table4_log, "-d", "glt", "-o", out]).code == 0
    result = cli(["report", out, "--json", "-"])
    assert result.code == 0
    data = json.loads(result.stdout)
    assert data["has_truth"] is False and data["results"][0]["far"] is None
    assert "need truth" in result.stderr  # note goes to stderr when stdout carries JSON


def test_report_without_detection_is_bad_input(cli, table4_log):
    assert_one_line_error(cli(["report", table4_log]), 3, "imufdi detect")


def test_plot(cli, tmp_path, detected_log):
    png = tmp_path / "p.png"
    assert cli(["report", detected_log, "--plot", png]).code == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
