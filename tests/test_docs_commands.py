"""Every ``imufdi`` command in the README's and the guides' shell blocks runs as written.

Each fenced ``bash`` block of :data:`DOCS` is cut into commands (backslash continuations
and ``|`` lines joined, ``&&`` and ``|`` split), and each ``imufdi`` invocation in it is

- parsed by the real click commands (options and their values valid, nothing run);
- checked for its inputs: every input file or directory is shipped in the repository, or
  written by an earlier command of the same document, or the comment above the command
  (or at its end) says where it comes from: the reader's own ("your board's capture",
  "other.mcap: yours");
- a campaign (long) says its run time in its comment.

The slow run then executes, in a temporary directory holding links to the repository's
``imufdi_cli`` (its ``sample_logs``), ``docs`` and ``tests``, every command whose inputs are shipped or made by
the commands before it, in the documents' order: each must exit 0 (or 1, a failed
``--fail-if`` gate, for a command with gates). Commands needing the reader's own files,
campaigns (their run time is given) and ``pip``/``pytest`` set-up lines are not run.
"""

from __future__ import annotations

import functools
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import click
import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "docs/guide.md", "docs/flight-controllers.md")
#: options whose value is a file the command writes
OUTPUTS = {
    "-o",
    "--output",
    "--json",
    "--markdown",
    "--plot",
    "--junit",
    "--episodes-csv",
    "--capture",
    "--keep",
}
#: options whose value is a file the command reads
INPUTS = {"--layout", "--array", "--faults"}
#: commands too long to run in the tests: they must say how long they take
LONG = {"campaign"}
RUN_TIME = re.compile(r"\b\d+(\.\d+)?\s*(s|min|minutes|h|hours)\b")


@dataclass
class Command:
    doc: str
    line: int
    text: str
    comment: str
    invocations: list[list[str]] = field(default_factory=list)

    def __str__(self) -> str:
        return f"{self.doc}:{self.line}: {self.text}"


def _blocks(text: str) -> list[tuple[int, list[str]]]:
    blocks, current, start = [], None, 0
    for number, line in enumerate(text.splitlines(), 1):
        if current is None and re.match(r"^```(bash|sh|shell|console)\s*$", line):
            current, start = [], number + 1
        elif current is not None and line.startswith("```"):
            blocks.append((start, current))
            current = None
        elif current is not None:
            current.append(line)
    return blocks


def _commands(doc: str) -> list[Command]:
    out: list[Command] = []
    for start, lines in _blocks((REPO / doc).read_text()):
        comment: list[str] = []
        pending: list[str] = []
        first = start
        after_command = False
        for offset, raw in enumerate([*lines, ""]):
            line = raw.rstrip()
            stripped = line.strip()
            if pending and (pending[-1].endswith("\\") or stripped.startswith("|")):
                pending[-1] = pending[-1].rstrip("\\")
                pending.append(stripped)
                continue
            if pending:
                out.append(_command(doc, first, " ".join(pending), " ".join(comment)))
                pending, after_command = [], True
            # a comment covers the commands under it up to a blank line or the next comment
            if stripped.startswith("#"):
                if after_command:
                    comment, after_command = [], False
                comment.append(stripped)
            elif stripped:
                pending, first = [stripped], start + offset
            else:
                comment, after_command = [], False
    return out


def _command(doc: str, line: int, text: str, comment: str) -> Command:
    code, _, inline = text.partition(" # ")
    command = Command(doc, line, code.strip(), f"{comment} {inline}".strip())
    for part in re.split(r"\s*(?:\|\||&&|\|)\s*", command.text):
        words = shlex.split(part)
        while words and re.match(r"^[A-Z_]+=", words[0]):
            words = words[1:]  # VAR=value prefixes
        if words and words[0] == "imufdi":
            command.invocations.append(words[1:])
    return command


ALL = [c for doc in DOCS for c in _commands(doc) if c.invocations]


@functools.cache
def _group_context() -> click.Context:
    """The ``imufdi`` group's context, as the console script makes it (its settings, e.g.
    ``-h``, are inherited: a context without them would make click cache other help
    options on the commands)."""
    from imufdi_cli.cli import cli

    return cli.context_class(cli, info_name="imufdi", **cli.context_settings)


def _click_command(name: str) -> click.Command:
    from imufdi_cli.cli import cli

    command = cli.get_command(_group_context(), name)
    assert command is not None, f"no imufdi command {name!r}"
    return command


def _files(args: list[str]) -> tuple[list[str], list[str]]:
    """(inputs, outputs) of one invocation: positional arguments and input options' values
    are inputs, output options' values outputs (``-`` is neither)."""
    command = _click_command(args[0])
    takes_value = {}
    for param in command.params:
        if isinstance(param, click.Option):
            for opt in param.opts + param.secondary_opts:
                takes_value[opt] = not param.is_flag and not param.count
    inputs, outputs = [], []
    words = args[1:]
    i = 0
    while i < len(words):
        word = words[i]
        name, eq, inline = word.partition("=")
        if word.startswith("-") and word != "-":
            optional = name == "--json"  # --json [FILE]
            value = inline if eq else None
            if value is None and takes_value.get(name) and i + 1 < len(words):
                nxt = words[i + 1]
                if not optional or nxt == "-" or not nxt.startswith("-"):
                    value, i = nxt, i + 1
            if value not in (None, "-"):
                if name in OUTPUTS:
                    outputs.append(value)
                elif name in INPUTS:
                    inputs.append(value)
        elif word != "-":
            inputs.append(word)
        i += 1
    return inputs, outputs


@functools.cache
def _made_before() -> dict[int, set[str]]:
    """For each command of ALL (by index): the files earlier commands of its document wrote."""
    made: dict[str, set[str]] = {}
    before = {}
    for k, command in enumerate(ALL):
        known = made.setdefault(command.doc, set())
        before[k] = set(known)
        for args in command.invocations:
            known.update(p.rstrip("/") for p in _files(args)[1])
    return before


def _shipped(path: str) -> bool:
    return (REPO / path).exists()


@pytest.mark.parametrize("index", range(len(ALL)), ids=[f"{c.doc}:{c.line}" for c in ALL])
def test_every_command_parses_and_names_its_inputs(index):
    command = ALL[index]
    for args in command.invocations:
        click_command = _click_command(args[0])
        try:
            click_command.make_context(args[0], list(args[1:]), parent=_group_context())
        except click.UsageError as err:
            pytest.fail(f"{command}: {err.format_message()}")
        inputs, _ = _files(args)
        made = _made_before()[index]
        foreign = [p for p in inputs if not _shipped(p) and p.rstrip("/") not in made]
        if foreign:
            assert "your" in command.comment.lower(), (
                f"{command}: {', '.join(foreign)} is neither shipped nor made by an earlier"
                " command, and the comment does not say where it comes from"
            )
        if args[0] in LONG:
            assert RUN_TIME.search(command.comment), f"{command}: give its run time"


def test_the_documents_hold_the_commands_they_should():
    docs = {c.doc for c in ALL}
    assert docs == set(DOCS)
    names = {args[0] for c in ALL for args in c.invocations}
    assert {
        "simulate",
        "ingest",
        "info",
        "inject",
        "detect",
        "report",
        "calibrate",
        "campaign",
    } <= names


@functools.cache
def _runnable() -> list[Command]:
    out: list[Command] = []
    made_in: dict[str, set[str]] = {}
    for command in ALL:
        made = made_in.setdefault(command.doc, set())
        files = [_files(args) for args in command.invocations]
        names = {args[0] for args in command.invocations}
        ok = not names & LONG and all(
            _shipped(p) or p.rstrip("/") in made for inputs, _ in files for p in inputs
        )
        if ok:
            out.append(command)
            made.update(p.rstrip("/") for _, outputs in files for p in outputs)
    return out


def test_the_runnable_commands_are_most_of_them():
    # what needs the reader's own log: ingest of their flight log, their bag, their other
    # log and nightly log (and what is derived from those), the campaign (run time given)
    assert len(_runnable()) >= 16, [str(c) for c in _runnable()]


@pytest.mark.slow
@pytest.mark.parametrize("doc", DOCS)
def test_runnable_commands_run_as_written(doc, tmp_path):
    """A document's runnable commands, in its order (a command may read what the ones
    before it wrote), in a directory holding links to the shipped files."""
    for name in ("imufdi_cli", "docs", "tests"):  # imufdi_cli/sample_logs: the shipped logs
        (tmp_path / name).symlink_to(REPO / name)
    env = {**os.environ, "PYTHONPATH": str(REPO), "MPLBACKEND": "Agg", "NO_COLOR": "1"}
    failures = []
    for command in (c for c in _runnable() if c.doc == doc):
        script = (
            f'imufdi() {{ "{sys.executable}" -m imufdi_cli "$@"; }}\n'
            "set -o pipefail\n" + re.sub(r"^pip install [^&]*&&\s*", "", command.text)
            # set-up steps of the README (installing the package) are not doc commands
        )
        result = subprocess.run(
            ["bash", "-c", script],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        allowed = {0, 1} if "--fail-if" in command.text else {0}
        if result.returncode not in allowed:
            failures.append(f"{command}: exit {result.returncode}: {result.stderr.strip()[-500:]}")
    assert not failures, "\n".join(failures)
