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
    assert "| glt | gyro |" in (tmp_path / "report.md").read_text()
