"""The habits every command shares (imufdi_cli.cli.ui): --json [FILE], -q/-v, summaries
on stderr, no ANSI off a terminal or with NO_COLOR, the progress bar's conditions."""

from __future__ import annotations

import io
import json
import os
import pty
import sys
import threading
from pathlib import Path
from typing import ClassVar

import pytest

from imufdi_cli.cli import cli as group
from imufdi_cli.cli import main, ui
from imufdi_cli.pipeline import SAMPLE_LOGS
from tests.cli.conftest import assert_one_line_error

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = SAMPLE_LOGS / "paper-table4.mcap"
ANSI = "\x1b["


def test_every_command_has_quiet_verbose_and_json():
    for name, command in group.commands.items():
        params = {p.name: p for p in command.params}
        assert {"quiet", "verbose", "json_target"} <= set(params), name
        assert params["json_target"].help and "stdout" in params["json_target"].help, name


def test_summary_on_stderr_stdout_clean(cli, tmp_path):
    result = cli(["simulate", "--preset", "paper-table4", "-o", tmp_path / "a.mcap"])
    assert result.code == 0 and result.stdout == b""
    assert result.stderr.startswith("simulate: 500 samples of 16 IMUs")
    assert ANSI not in result.stderr  # not a terminal: plain text


def test_json_to_stdout_and_to_a_file(cli, tmp_path):
    result = cli(["simulate", "--preset", "paper-table4", "-o", tmp_path / "a.mcap", "--json"])
    data = json.loads(result.out)
    assert data["command"] == "simulate" and data["samples"] == 500 and data["n_imus"] == 16
    # data on stdout, the summary in a file: both usable
    piped = cli(["simulate", "--preset", "paper-table4", "-o", "-", "--json", tmp_path / "s.json"])
    assert piped.code == 0 and piped.stdout.startswith(b"\x89MCAP0\r\n")
    assert json.loads((tmp_path / "s.json").read_text())["output"] == "-"


def test_json_and_data_both_on_stdout_is_a_usage_error(cli, tmp_path):
    result = cli(["simulate", "--preset", "paper-table4", "-o", "-", "--json", "-"])
    assert_one_line_error(result, 2, "would both write to stdout; give --json a file")
    assert result.stdout == b""
    result = cli(["detect", SAMPLE, "-d", "glt", "-o", "-", "--json"])
    assert_one_line_error(result, 2, "--json and -o - would both write to stdout")


def test_json_of_detect_inject_ingest_info(cli, tmp_path):
    faulty = tmp_path / "f.mcap"
    fault = "step:imu0.gyro.x,at=2.5s,amp=0.9deg/s"
    inject = json.loads(cli(["inject", SAMPLE, "--fault", fault, "-o", faulty, "--json"]).out)
    assert inject["faults"][0]["sensors"] == ["imu0.gyro.x"] or "imu0.gyro.x" in json.dumps(
        inject["faults"][0]
    )
    # alarms and isolation in the JSON, not episodes: no explanation
    args = ["detect", faulty, "-d", "glt", "--no-explain", "-o", tmp_path / "d.mcap", "--json"]
    detect = json.loads(cli(args).out)
    gyro = detect["detectors"]["glt"]["gyro"]
    assert gyro["samples"] == detect["samples"] and gyro["alarms"] <= gyro["samples"]
    assert max(gyro["isolated"], key=gyro["isolated"].get) == "imu0.gyro.x"
    # rates are written without float noise (12 significant digits at most)
    assert len(repr(gyro["alarm_rate"]).lstrip("0.").replace(".", "")) <= 12
    info = json.loads(cli(["info", faulty, "--json"]).out)
    assert info["n_imus"] == 16


def test_quiet_prints_nothing_but_errors(cli, tmp_path):
    out = tmp_path / "a.mcap"
    result = cli(["simulate", "--preset", "paper-table4", "-o", out, "-q"])
    assert result.code == 0 and result.stdout == b"" and result.stderr == ""
    result = cli(["info", out, "--quiet"])
    assert result.code == 0 and result.stdout == b"" and result.stderr == ""
    result = cli(["detect", out, "-d", "glt", "-q", "-o", tmp_path / "d.mcap"])
    assert result.code == 0 and result.stderr == ""
    failing = cli(["report", tmp_path / "d.mcap", "-q", "--fail-if", "glt.gyro.alarm_rate >= 0"])
    assert_one_line_error(failing, 1, "gate(s) failed")
    assert failing.stdout == b""


def test_verbose_adds_timing(cli, tmp_path):
    result = cli(["simulate", "--preset", "paper-table4", "-o", tmp_path / "a.mcap", "-v"])
    assert result.code == 0
    last = result.stderr.strip().splitlines()[-1]
    assert last.endswith(" s") and float(last[:-2]) >= 0


def _run_on_terminal(args: list[str]) -> str:
    """Run imufdi in this process with stdout and stderr on a pseudo-terminal (a real
    terminal device: ``isatty()`` is true, as in a shell); everything it printed. A thread
    drains the terminal while the command writes, so a long output cannot fill its buffer.
    (In this process rather than a fresh ``python -m imufdi_cli``, 0.3 s of CPU each: the
    console is built per command from the stream and the environment, which is what this
    checks; ``tests/cli/test_main.py`` runs ``python -m imufdi_cli`` itself.)"""
    master, slave = pty.openpty()
    chunks: list[bytes] = []

    def drain() -> None:
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the writing side is closed
                break
            if not data:
                break
            chunks.append(data)

    reader = threading.Thread(target=drain)
    reader.start()
    saved = sys.stdin, sys.stdout, sys.stderr
    terminal = open(slave, "w", encoding="utf-8", errors="replace", buffering=1)
    sys.stdin, sys.stdout, sys.stderr = io.StringIO(), terminal, terminal
    try:
        main([*args])
    except SystemExit:
        pass
    finally:
        sys.stdin, sys.stdout, sys.stderr = saved
        terminal.close()  # closes the slave: the reader sees EIO once it read everything
        reader.join(timeout=60)
        os.close(master)
    return b"".join(chunks).decode("utf-8", "replace")


def test_no_color_means_no_escape_codes_on_a_terminal(monkeypatch):
    monkeypatch.delenv("NO_COLOR", raising=False)
    monkeypatch.setenv("TERM", "xterm-256color")
    args = ["info", str(SAMPLE)]
    styled = _run_on_terminal(args)
    assert "paper-table4.mcap" in styled and ANSI in styled  # the test can fail
    monkeypatch.setenv("NO_COLOR", "1")
    plain = _run_on_terminal(args)
    assert "paper-table4.mcap" in plain and ANSI not in plain
    monkeypatch.chdir(ROOT)
    error = _run_on_terminal(["info", "missing.mcap"])
    assert "imufdi: error: missing.mcap: no such file" in error and ANSI not in error


class RecordingBar(ui.DelayedBar):
    made: ClassVar[list[RecordingBar]] = []

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        RecordingBar.made.append(self)


@pytest.fixture
def bars(monkeypatch):
    RecordingBar.made = []
    monkeypatch.setattr(ui, "DelayedBar", RecordingBar)
    monkeypatch.setattr(ui, "PROGRESS_DELAY_S", 0.0)
    return RecordingBar.made


#: the progress tests watch the reading loop, not the episodes: no explanation (about
#: 0.07 s of CPU per run on SAMPLE; explained episodes: tests/test_detect.py, episodes/)
DETECT = ["detect", SAMPLE, "-d", "glt", "--no-explain"]


def test_no_progress_bar_when_stderr_is_not_a_terminal(cli, bars, tmp_path):
    result = cli([*DETECT, "-o", tmp_path / "d.mcap"])
    assert result.code == 0 and bars == []
    assert f"detect {SAMPLE}" not in result.stderr  # the bar's description


def test_progress_bar_on_a_terminal_and_not_with_quiet(cli, bars, monkeypatch, tmp_path):
    monkeypatch.setattr(ui, "stderr_is_terminal", lambda: True)
    result = cli([*DETECT, "-o", tmp_path / "d.mcap"])
    assert result.code == 0 and len(bars) == 1
    assert bars[0].calls > 0 and bars[0].started and bars[0].bar is None  # stopped
    result = cli([*DETECT, "-q", "-o", tmp_path / "e.mcap"])
    assert result.code == 0 and len(bars) == 1  # --quiet: no new bar


def test_progress_bar_waits_before_appearing():
    bar = ui.DelayedBar("work", "s", delay=3600.0)
    bar.update(1.0, 10.0)
    bar.update(2.0, None)
    assert bar.calls == 2 and not bar.started
    bar.stop()
    assert bar.amount(2.0, None) == "2 s" and bar.amount(2.0, 10.0) == "2/10 s"
    assert ui.DelayedBar("x", "B").amount(1.5 * 2**20, 20 * 2**20) == "1.5/20.0 MiB"


def test_shell_completion_completes_detectors_and_presets(cli, monkeypatch):
    # the entry point in this process with the shell's variables (click reads them from the
    # environment at each call; `python -m imufdi_cli` itself: test_main.test_python_dash_m)
    monkeypatch.setenv("_IMUFDI_COMPLETE", "bash_complete")
    monkeypatch.setenv("COMP_WORDS", "imufdi detect x -d woa")
    monkeypatch.setenv("COMP_CWORD", "4")
    done = cli([])
    assert done.code == 0 and done.out.split() == ["plain,woa-mvmd-glt"]
    monkeypatch.setenv("COMP_WORDS", "imufdi simulate --preset paper")
    monkeypatch.setenv("COMP_CWORD", "3")
    done = cli([])
    assert done.code == 0 and done.out.split() == ["plain,paper-table4"]


def test_a_bare_json_before_the_argument_is_explained(cli, tmp_path):
    result = cli(["info", "--json", SAMPLE])
    assert_one_line_error(result, 2, f"--json took '{SAMPLE}' as its FILE: put --json last")
    assert json.loads(cli(["info", "--json", "-", SAMPLE]).out)["n_imus"] == 16


def test_a_summary_is_written_in_one_piece(monkeypatch):
    """Pipeline stages share stderr: each writes its summary with a single write, so
    their lines cannot interleave (short of the terminal's own limits)."""
    import io as _io

    class Counting(_io.StringIO):
        writes = 0

        def write(self, text):
            Counting.writes += 1
            return super().write(text)

    err = Counting()
    monkeypatch.setattr(sys, "stderr", err)
    out = ui.UI()
    out.summary.print("detect: first line")
    out.warn(["second", "third"])
    assert err.getvalue() == "" and Counting.writes == 0  # nothing before the end
    out.flush()
    assert Counting.writes == 1
    assert err.getvalue().splitlines() == [
        "detect: first line",
        "warning: second",
        "warning: third",
    ]
