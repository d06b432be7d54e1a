"""imufdi demo runs the whole pipeline on the bundled sample."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from imufdi_cli.pipeline import SAMPLE_LOGS


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


def test_the_sample_logs_are_package_data_and_the_commands_name_them(cli, tmp_path, monkeypatch):
    """The demo's inputs are inside the package (installed with it: a wheel carries them)
    and the ingest command it prints names the bundled capture by a path valid from any
    directory (run here from an empty one)."""
    import imufdi_cli

    package = Path(imufdi_cli.__file__).resolve().parent
    assert SAMPLE_LOGS.parent == package and (SAMPLE_LOGS / "paper-table4.cap").is_file()
    monkeypatch.chdir(tmp_path)
    result = cli(["demo", "--json", tmp_path / "demo.json", "-q"])
    assert result.code == 0, result.stderr
    ingest = json.loads((tmp_path / "demo.json").read_text())["steps"][0]
    words = shlex.split(ingest["command_line"])
    assert ingest["name"] == "ingest" and words[:2] == ["imufdi", "ingest"]
    assert Path(words[2]).is_file() and Path(words[2]).samefile(SAMPLE_LOGS / "paper-table4.cap")
