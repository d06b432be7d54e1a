"""Generate docs/cli.md from the click commands' help text (the single source of truth).

python tools/gen_cli_docs.py            # rewrite docs/cli.md
python tools/gen_cli_docs.py --check    # exit 1 if docs/cli.md is out of date (tests do this)
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

DOC = Path(__file__).resolve().parent.parent / "docs" / "cli.md"


def render() -> str:
    from imufdi_cli.cli import cli

    parts = [
        "# Command-line reference",
        "",
        "Generated from the commands' help text by `python tools/gen_cli_docs.py`;",
        "a test fails when this file and `imufdi COMMAND --help` disagree.",
        "",
        "Exit codes for every command: `0` ok, `1` a `--fail-if` gate failed, `2` usage error,",
        "`3` bad input data (or an I/O error such as a full disk), `4` internal error;",
        "`130` interrupted (SIGINT), `143` terminated (SIGTERM), `129` hung up (SIGHUP).",
        "Errors are one line on stderr. No output is ever one of the command's inputs.",
        "",
        "Every command takes `-q/--quiet`, `-v/--verbose` and `--json [FILE]` (its",
        "machine-readable summary; `-` or no FILE: stdout), prints summaries on stderr and no",
        'escape codes off a terminal or with `NO_COLOR`: docs/guide.md, "Output conventions".',
        "",
    ]
    ctx = click.Context(
        cli, info_name="imufdi", terminal_width=100, max_content_width=100, **cli.context_settings
    )
    parts += ["## imufdi", "", "```text", cli.get_help(ctx).rstrip(), "```", ""]
    for name in sorted(cli.commands):
        command = cli.commands[name]
        sub = click.Context(
            command,
            info_name=name,
            parent=ctx,
            terminal_width=100,
            max_content_width=100,
            **cli.context_settings,
        )
        parts += [f"## imufdi {name}", "", "```text", command.get_help(sub).rstrip(), "```", ""]
    return "\n".join(parts)


def main() -> int:
    text = render()
    if "--check" in sys.argv:
        current = DOC.read_text(encoding="utf-8") if DOC.exists() else ""
        if current != text:
            print("docs/cli.md is out of date: run python tools/gen_cli_docs.py", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
