"""campaign.driver: progress on stderr only (never stdout), silent when asked, default jobs."""

from __future__ import annotations

import io
import textwrap

import pytest
from rich.console import Console

from imufdi_cli.campaign.driver import default_jobs
from imufdi_cli.cli.batch import run_campaign_cli

SPEC = """
[campaign]
seeds = [0]
calibrate = "0s:0.6s"
metrics = ["far", "mar", "detection_probability"]

[[base]]
preset = "paper-table4"
options = { duration = "1s" }

[[fault]]
model = "step"
sensor = "imu0.gyro.x"
at = "0.7s"
amp = ["0.3deg/s", "0.9deg/s"]

[[detector]]
name = "glt"
"""


@pytest.mark.parametrize("progress", [True, False, None])
def test_progress_goes_to_stderr_and_the_summary_to_the_console(tmp_path, capsys, progress):
    spec = tmp_path / "spec.toml"
    spec.write_text(textwrap.dedent(SPEC))
    summary = io.StringIO()
    console = Console(file=summary, width=200)
    code = run_campaign_cli(
        str(spec),
        str(tmp_path / "out"),
        jobs=1,
        scheduler=None,
        resume=False,
        gates=[],
        console=console,
        progress=progress,
    )
    assert code == 0
    captured = capsys.readouterr()
    assert captured.out == ""  # never stdout
    assert "2 runs (2 executed, 0 resumed, 0 failed)" in summary.getvalue()
    if progress:
        assert "campaign" in captured.err and "2/2" in captured.err
    else:  # --quiet, or stderr not a terminal (pytest captures it)
        assert captured.err == ""


def test_a_quiet_console_silences_the_bar_too(tmp_path, capsys, monkeypatch):
    spec = tmp_path / "spec.toml"
    spec.write_text(textwrap.dedent(SPEC))
    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)
    run_campaign_cli(
        str(spec),
        str(tmp_path / "out"),
        jobs=1,
        scheduler=None,
        resume=False,
        gates=[],
        console=Console(file=io.StringIO(), quiet=True),
    )
    assert capsys.readouterr().err == ""


def test_default_jobs_is_the_usable_cores():
    import os

    assert default_jobs() == len(os.sched_getaffinity(0))
