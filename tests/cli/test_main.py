"""The entry point: version, help, python -m, usage errors are one line with exit 2."""

from __future__ import annotations

import runpy
import subprocess
import sys
from pathlib import Path

from imufdi_cli import __version__
from tests.cli.conftest import assert_one_line_error


def test_version(cli):
    result = cli(["--version"])
    assert result.code == 0 and __version__ in result.out


def test_help_lists_every_command(cli):
    result = cli(["--help"])
    assert result.code == 0
    for name in (
        "simulate",
        "ingest",
        "info",
        "inject",
        "tune",
        "detect",
        "report",
        "campaign",
        "demo",
    ):
        assert name in result.out
    assert "Exit codes" in result.out


def test_python_dash_m():
    done = subprocess.run(
        [sys.executable, "-m", "imufdi_cli", "--version"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0 and __version__ in done.stdout


def test_unknown_command_is_usage_error(cli):
    assert_one_line_error(cli(["frobnicate"]), 2, "No such command 'frobnicate'")


def test_unknown_option_is_usage_error(cli):
    result = cli(["report", "x.mcap", "--bogus"])
    # click's words: "No such option '--bogus'" from 8.4, "No such option: --bogus" before
    assert_one_line_error(result, 2, "No such option")
    assert "--bogus" in result.stderr


def test_cli_docs_match_help():
    # the generator's render() in this process (the commands' help does not depend on the
    # interpreter; a fresh one cost about 0.4 s of CPU): what `gen_cli_docs.py --check` compares
    tool = runpy.run_path(str(Path(__file__).resolve().parents[2] / "tools" / "gen_cli_docs.py"))
    current = tool["DOC"].read_text(encoding="utf-8")
    assert current == tool["render"](), "docs/cli.md is out of date: run tools/gen_cli_docs.py"
