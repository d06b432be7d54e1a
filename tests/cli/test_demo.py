"""imufdi demo runs the whole pipeline on the bundled sample."""

from __future__ import annotations

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


def test_demo_says_where_its_outputs_went(cli, tmp_path):
    import json

    result = cli(["demo", "--keep", tmp_path, "--json", tmp_path / "demo.json", "-q"])
    assert result.code == 0 and result.stdout == b"" and result.stderr == ""
    summary = json.loads((tmp_path / "demo.json").read_text())
    assert summary["kept"] is True and [s["name"] for s in summary["steps"]][-1] == "report"
    result = cli(["demo"])
    assert result.code == 0, result.stderr
    assert "keep them with: imufdi demo --keep DIR" in result.out
