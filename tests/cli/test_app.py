"""The imufdi group loads each command's module on demand, and lists them all."""

from __future__ import annotations

import json
import subprocess
import sys

from imufdi_cli.cli import cli
from imufdi_cli.cli.app import COMMAND_MODULES


def test_command_table_matches_the_commands() -> None:
    defined = {name: command.callback.__module__ for name, command in cli.commands.items()}
    assert defined == COMMAND_MODULES


def _modules_after(
    args: list[str], prefixes: tuple[str, ...] = ("imufdi_cli.cli.",)
) -> tuple[list[str], str]:
    probe = (
        "import runpy, sys, json\n"
        f"sys.argv = ['imufdi', *{args!r}]\n"
        "try:\n    runpy.run_module('imufdi_cli', run_name='__main__')\n"
        "except SystemExit:\n    pass\n"
        "sys.stderr.write('\\n' + json.dumps(sorted(m for m in sys.modules"
        f" if m.startswith({prefixes!r}))))\n"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stderr.strip().splitlines()[-1]), done.stdout


def test_a_command_imports_only_its_own_module(table4_log) -> None:
    loaded, out = _modules_after(["info", str(table4_log)])
    assert "/imu15/data_raw" in out
    others = set(COMMAND_MODULES.values()) - {"imufdi_cli.cli.describe"}
    assert "imufdi_cli.cli.describe" in loaded
    assert not others & set(loaded)


def test_info_does_not_import_what_reading_does_not_need(table4_log) -> None:
    """Start-up time: ``imufdi info`` compiles neither the writer, the pipeline nor the
    bag-directory reader, and imports no thread pool, TOML parser or hashlib."""
    unneeded = (
        "imufdi_cli.mcapio.writer",
        "imufdi_cli.mcapio.imu_writer",
        "imufdi_cli.pipeline",
        "imufdi_cli.mcapio.bagdir",
        "concurrent",
        "tomllib",
        "secrets",
        "scipy",
        "rich",
    )
    loaded, out = _modules_after(["info", str(table4_log)], ("imufdi_cli.mcapio.", *unneeded))
    assert "/imu15/data_raw" in out
    assert "imufdi_cli.mcapio.summary" in loaded
    assert not {m.split(".")[0] if not m.startswith("imufdi") else m for m in loaded} & set(
        unneeded
    )


def test_help_lists_every_command() -> None:
    _, out = _modules_after(["--help"])
    section = out.split("Commands:\n")[1].split("\n\n")[0]
    listed = [line.split()[0] for line in section.splitlines()]
    assert listed == sorted(COMMAND_MODULES)
