"""What the commands print and where: summaries, products, JSON, warnings, progress.

The habits every command shares (docs/user-guide.md, "Output conventions"):

- a command's **product** (``info``'s description, ``report``'s table) goes to stdout,
  or to stderr when stdout already carries data (``-o -``, ``--json -``);
- a **summary** of what a command did goes to stderr, written in one piece at the end, so
  the stages of a shell pipeline neither mix their lines nor pollute the data stream;
- ``--json [FILE]`` writes the command's machine-readable summary to FILE, or to stdout
  when FILE is ``-`` or left out; it is a usage error when stdout already carries data;
- ``-q/--quiet``: nothing but errors (and the outputs asked for); ``-v/--verbose``: more
  detail (timings, full lists);
- no ANSI escapes at all when the stream is not a terminal or ``NO_COLOR`` is set;
- a progress bar on stderr for work that lasts longer than :data:`PROGRESS_DELAY_S`, only
  when stderr is a terminal and not with ``--quiet``.
"""

from __future__ import annotations

import functools
import io
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import IO, TYPE_CHECKING, Any

import click

from imufdi_cli.cli.plain import PLAIN_WIDTH, PlainTable, plain_safe

if TYPE_CHECKING:  # rich is imported when a console is made (start-up time)
    from rich.console import Console

#: version of the ``--json`` objects: raised when a key is renamed or removed or changes
#: meaning (adding keys keeps it); every object carries it as ``format_version``
JSON_FORMAT_VERSION = 1

#: seconds of work before the progress bar appears (short commands never show one)
PROGRESS_DELAY_S = 2.0


def no_color() -> bool:
    """True when the user asked for no colour (https://no-color.org: NO_COLOR set and not
    empty)."""
    return bool(os.environ.get("NO_COLOR", ""))


def is_terminal(stream: IO[Any]) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def stderr_is_terminal() -> bool:
    """Whether stderr is a terminal (the progress bar's condition; tests replace it)."""
    return is_terminal(sys.stderr)


def make_console(stream: IO[Any], file: IO[str] | None = None, *, quiet: bool = False) -> Console:
    """A rich console rendering for ``stream`` (colour and width follow it) that writes to
    ``file`` (default: the stream itself). Styles only on a terminal without NO_COLOR;
    elsewhere plain text (no escape codes), wide enough that tables are not cut."""
    from rich.console import Console

    terminal = is_terminal(stream)
    styled = terminal and not no_color()
    width = shutil.get_terminal_size((120, 24)).columns if terminal else PLAIN_WIDTH
    return Console(
        file=file if file is not None else stream,
        force_terminal=terminal,  # a progress bar still redraws with NO_COLOR, uncoloured
        color_system="auto" if styled else None,
        no_color=not styled,
        highlight=False,
        soft_wrap=True,
        width=width,
        emoji=False,
        quiet=quiet,
    )


def print_table(console: Console, table: PlainTable) -> None:
    """Print ``table`` on a console made by :func:`make_console`: when the console is not a
    terminal and the table renders as plain text (:meth:`PlainTable.render`), that text,
    which is what rich would print, is written without rich's layout; otherwise rich
    prints :meth:`PlainTable.to_rich` (a terminal: styles, its width; or a deferral)."""
    text = None if console.is_terminal else table.render(console.width)
    if text is None:
        console.print(table.to_rich())
    elif not console.quiet:
        console.file.write(text)
        console.file.flush()


def error_line(message: str) -> None:
    """One non-empty line on stderr: ``imufdi: error: MESSAGE`` (red on a terminal)."""
    from rich.markup import escape

    message = " ".join(str(message).split()) or "unknown error (no message)"
    if is_terminal(sys.stderr) and not no_color():
        make_console(sys.stderr).print(f"[bold red]imufdi: error:[/] {escape(message)}")
    else:
        sys.stderr.write(f"imufdi: error: {message}\n")
        sys.stderr.flush()


class UI:
    """The output side of one command run (see the module docstring).

    Parameters
    ----------
    quiet : bool
        Print nothing but errors.
    verbose : int
        Extra detail (0 none).
    json_target : str or None
        ``--json`` value: a path, ``-`` for stdout, or None.
    command : str or None
        The command's name, written as ``command`` in its ``--json`` object.
    """

    def __init__(
        self,
        quiet: bool = False,
        verbose: int = 0,
        json_target: str | None = None,
        command: str | None = None,
    ):
        self.command = command
        self.quiet = quiet
        self.verbose = 0 if quiet else verbose
        self.json_target = json_target
        self.started = time.perf_counter()
        self._stdout_taken = json_target == "-"
        self._summary_buffer = io.StringIO()
        self._product_buffer = io.StringIO()
        self._summary: Console | None = None
        self._product: Console | None = None

    # --- where things go ---------------------------------------------------------------

    def data_to_stdout(self, *outputs: str | None, labels: Sequence[str] = ()) -> None:
        """Declare the command's data outputs; any ``-`` takes stdout. Raises UsageError
        when ``--json -`` would share stdout with them."""
        from imufdi_cli.errors import UsageError

        taken = [labels[i] if i < len(labels) else "-o" for i, o in enumerate(outputs) if o == "-"]
        if taken and self.json_target == "-":
            raise UsageError(
                f"--json and {taken[0]} - would both write to stdout; give --json a file"
                " (--json summary.json) or send the data to a file"
            )
        if taken:
            self._stdout_taken = True

    @property
    def stdout_taken(self) -> bool:
        return self._stdout_taken

    @property
    def summary(self) -> Console:
        """Console for the summary (stderr, written in one piece by :meth:`flush`)."""
        if self._summary is None:
            self._summary = make_console(sys.stderr, self._summary_buffer, quiet=self.quiet)
        return self._summary

    @property
    def product(self) -> Console:
        """Console for the command's human product: stdout, or stderr when stdout carries
        data (buffered like the summary)."""
        if self._product is None:
            if self._stdout_taken:
                self._product = self.summary
            else:
                self._product = make_console(sys.stdout, self._product_buffer, quiet=self.quiet)
        return self._product

    def product_is_plain(self) -> bool:
        """Whether the product console would render without styles at
        :data:`~imufdi_cli.cli.plain.PLAIN_WIDTH` (its stream is not a terminal), so that
        text from :mod:`imufdi_cli.cli.plain` is what rich would print."""
        return not is_terminal(sys.stderr if self._stdout_taken else sys.stdout)

    def write_product(self, text: str) -> None:
        """Add ready-rendered plain ``text`` to the product (nothing with ``--quiet``), in
        order with what the product console prints."""
        if self.quiet:
            return
        if self._stdout_taken:
            self._summary_buffer.write(text)
        else:
            self._product_buffer.write(text)

    def print_table(self, table: PlainTable, *, summary: bool = False) -> None:
        """Print ``table`` in the product (or with ``summary``, in the summary), in order
        with what that console prints: as plain text (:meth:`PlainTable.render`, what rich
        would print) when the stream is not a terminal and the table renders, without
        making the console (rich is not imported for it); else through rich, as
        :func:`print_table`."""
        if self.quiet:
            return
        plain = not is_terminal(sys.stderr) if summary else self.product_is_plain()
        text = table.render() if plain else None
        if text is None:
            (self.summary if summary else self.product).print(table.to_rich())
        elif summary:
            self._summary_buffer.write(text)
        else:
            self.write_product(text)

    def live(self) -> Console:
        """Console writing straight to stderr (commands that show steps as they go)."""
        return make_console(sys.stderr, quiet=self.quiet)

    def warn(self, warnings: Sequence[str], console: Console | None = None) -> None:
        for warning in warnings:
            if console is not None or not self._plain_line("warning", warning):
                (console or self.summary).print(f"[yellow]warning:[/] {_escape(warning)}")

    def note(
        self, notes: Sequence[str], console: Console | None = None, *, product: bool = False
    ) -> None:
        """Notes on the summary (stderr), on ``console``, or with ``product`` in the
        product (after what it holds)."""
        for text in notes:
            if console is None and self._plain_line("note", text, product):
                continue
            target = console or (self.product if product else self.summary)
            target.print(f"[yellow]note:[/] {_escape(text)}")

    def _plain_line(self, label: str, text: str, product: bool = False) -> bool:
        """Write ``label: text`` to the summary (or the product) as plain text, which is
        what its console prints when its stream is not a terminal, without importing rich
        (about 40 ms: a report without ground truth has a note); False when rich must
        print it (a terminal, or text rich would not print as it is: :func:`plain_safe`)."""
        plain = self.product_is_plain() if product else not is_terminal(sys.stderr)
        if not plain or not plain_safe(str(text)):
            return False
        if product:
            self.write_product(f"{label}: {text}\n")
        elif not self.quiet:
            self._summary_buffer.write(f"{label}: {text}\n")
        return True

    def json(self, data: Any) -> None:
        """Write the machine-readable summary to ``--json``'s target (if given)."""
        if self.json_target is None:
            return
        from imufdi_cli.fileio import write_text
        from imufdi_cli.jsonout import dumps

        write_text(self.json_target, dumps(self.json_object(data)))

    def json_object(self, data: dict[str, Any]) -> dict[str, Any]:
        """``data`` headed by ``format_version`` (:data:`JSON_FORMAT_VERSION`) and
        ``command`` (this command's name), the two keys every ``--json`` object starts
        with."""
        rest = {k: v for k, v in data.items() if k not in ("format_version", "command")}
        return {"format_version": JSON_FORMAT_VERSION, "command": self.command, **rest}

    def flush(self) -> None:
        """Write the product (stdout) and the summary (stderr), each in one piece."""
        if self.verbose and not self.quiet:
            self.summary.print(f"[dim]{time.perf_counter() - self.started:.2f} s[/]")
        for buffer, stream in (
            (self._product_buffer, sys.stdout),
            (self._summary_buffer, sys.stderr),
        ):
            text = buffer.getvalue()
            if text:
                stream.write(text)
                stream.flush()
            buffer.seek(0)
            buffer.truncate()

    # --- progress ----------------------------------------------------------------------

    @contextmanager
    def progress(self, description: str, unit: str = "s") -> Iterator[Callable[..., None] | None]:
        """A progress callback ``(done, total)`` rendered as a bar on stderr once the work
        has lasted :data:`PROGRESS_DELAY_S`; None (no bar) with ``--quiet`` or when stderr
        is not a terminal."""
        if self.quiet or not stderr_is_terminal():
            yield None
            return
        bar = DelayedBar(description, unit)
        try:
            yield bar.update
        finally:
            bar.stop()


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(str(text))


class DelayedBar:
    """A rich progress bar on stderr that starts only after :data:`PROGRESS_DELAY_S` of
    work and disappears when the work ends (the summary follows)."""

    def __init__(self, description: str, unit: str, delay: float | None = None) -> None:
        self.description = description
        self.unit = unit
        self.delay = PROGRESS_DELAY_S if delay is None else delay
        self.t0 = time.monotonic()
        self.bar: Any = None
        self.task: Any = None
        self.calls = 0
        self.started = False

    def _start(self) -> None:
        from rich.progress import (
            BarColumn,
            Progress,
            TaskProgressColumn,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.bar = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TaskProgressColumn(),
            TextColumn("{task.fields[amount]}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=make_console(sys.stderr),
            transient=True,
        )
        self.task = self.bar.add_task(self.description, total=None, amount="")
        self.bar.start()
        self.started = True

    def update(self, done: float, total: float | None) -> None:
        self.calls += 1
        if self.bar is None:
            if time.monotonic() - self.t0 < self.delay:
                return
            self._start()
        self.bar.update(self.task, completed=done, total=total, amount=self.amount(done, total))

    def amount(self, done: float, total: float | None) -> str:
        """``12/60 s`` of log time, or ``1.5/20.0 MiB`` of a capture (total when known)."""
        if self.unit == "B":
            scale, unit, fmt = 2.0**-20, "MiB", "{:.1f}"
        else:
            scale, unit, fmt = 1.0, self.unit, "{:.0f}"
        text = fmt.format(done * scale)
        if total is not None:
            text += "/" + fmt.format(total * scale)
        return f"{text} {unit}"

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


# --- options every command shares --------------------------------------------------------


def common_options(*, json_help: str | None = None) -> Callable[[Callable[..., Any]], Any]:
    """Add ``-q/--quiet``, ``-v/--verbose`` and (with ``json_help``) ``--json [FILE]`` to a
    command; the command receives a :class:`UI` as ``ui`` and its buffered output is
    written when it returns (also when it exits with a gate failure)."""

    def decorate(fn: Callable[..., Any]) -> Any:
        @functools.wraps(fn)
        def wrapper(*args: Any, quiet: bool, verbose: int, **kwargs: Any) -> Any:
            json_target = kwargs.pop("json_target", None)
            ui = UI(
                quiet=quiet,
                verbose=verbose,
                json_target=json_target,
                command=click.get_current_context().info_name,
            )
            try:
                return fn(*args, ui=ui, **kwargs)
            finally:
                ui.flush()

        options = [
            click.option(
                "-q",
                "--quiet",
                is_flag=True,
                help="Print nothing but errors (and the outputs asked for).",
            ),
            click.option("-v", "--verbose", count=True, help="More detail: timings, full lists."),
        ]
        if json_help is not None:
            options.append(
                click.option(
                    "--json",
                    "json_target",
                    metavar="[FILE]",
                    is_flag=False,
                    flag_value="-",
                    default=None,
                    help=json_help + " Written to FILE, or to stdout with - or no FILE"
                    " (then put --json last or give -).",
                )
            )
        for option in reversed(options):
            wrapper = option(wrapper)
        return wrapper

    return decorate
