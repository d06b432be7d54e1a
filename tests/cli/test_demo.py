"""imufdi demo runs the whole pipeline on the bundled sample."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_demo_keep(cli, tmp_path):
    result = cli(["demo", "--keep", tmp_path])
    assert result.code == 0, result.stderr
    for name in ("faulty.mcap", "detected.mcap", "report.md"):
        assert (tmp_path / name).exists()
    assert "imufdi inject" in result.out and "imufdi detect" in result.out
    assert f"outputs kept in {tmp_path}" in result.out
    assert "| glt | gyro |" in (tmp_path / "report.md").read_text()
    # quiet: nothing on stdout or stderr, the summary in the JSON file
    keep = tmp_path / "quiet"
    result = cli(["demo", "--keep", keep, "--json", tmp_path / "demo.json", "-q"])
    assert result.code == 0 and result.stdout == b"" and result.stderr == ""
    summary = json.loads((tmp_path / "demo.json").read_text())
    assert summary["kept"] is True and [s["name"] for s in summary["steps"]][-1] == "report"


def test_demo_says_where_its_outputs_went(cli, tmp_path):
    result = cli(["demo", "--json", tmp_path / "demo.json"])
    assert result.code == 0, result.stderr
    assert "keep them with: imufdi demo --keep DIR" in result.out
    summary = json.loads((tmp_path / "demo.json").read_text())
    assert summary["kept"] is False and [s["name"] for s in summary["steps"]][-1] == "report"
