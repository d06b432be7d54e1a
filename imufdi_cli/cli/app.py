"""The ``imufdi`` click group and the option helpers its commands share."""

from __future__ import annotations

from importlib import import_module

import click

from imufdi_cli._version import __version__

#: command name -> the module whose ``@cli.command()`` defines it. A command's module is
#: imported when that command is run or listed (``--help``, completion), so that
#: ``imufdi info`` does not pay for compiling the others (start-up time, docs/performance.md);
#: tests/cli/test_app.py checks that this table matches the commands.
COMMAND_MODULES: dict[str, str] = {
    "calibrate": "imufdi_cli.cli.detection",
    "campaign": "imufdi_cli.cli.batch",
    "demo": "imufdi_cli.cli.batch",
    "detect": "imufdi_cli.cli.detection",
    "info": "imufdi_cli.cli.describe",
    "ingest": "imufdi_cli.cli.data",
    "inject": "imufdi_cli.cli.data",
    "report": "imufdi_cli.cli.reporting",
    "simulate": "imufdi_cli.cli.data",
    "tune": "imufdi_cli.cli.detection",
}


def load_all_commands() -> None:
    """Import every command's module (``cli.commands`` is then complete)."""
    for module in sorted(set(COMMAND_MODULES.values())):
        import_module(module)


def start_end(start: str | None, end: str | None) -> tuple[float, float | None] | None:
    """``--start``/``--end`` as a window, or None: seconds from the first sample, or
    :class:`~imufdi_cli.units.UnixTime` for ISO 8601 and Unix times (resolved against the
    log's first sample where it is read)."""
    from imufdi_cli.errors import UsageError
    from imufdi_cli.units import UnixTime, parse_time_point

    if start is None and end is None:
        return None
    start_s = parse_time_point(start, name="--start") if start is not None else 0.0
    end_s = parse_time_point(end, name="--end") if end is not None else None
    if not isinstance(start_s, UnixTime) and start_s < 0:
        raise UsageError(f"--start {start!r}: need a time >= 0 s from the log start")
    comparable = end_s is not None and isinstance(start_s, UnixTime) == isinstance(end_s, UnixTime)
    if comparable and end_s is not None and end_s <= start_s:
        raise UsageError(f"--start {start!r} / --end {end!r}: need START < END")
    return start_s, end_s


def time_source(stamps: str) -> str:
    """--stamps choice -> ImuArrayReader time source."""
    return "log_time" if stamps == "log" else stamps


def time_range(text: str, name: str) -> tuple[float, float | None]:
    """A ``START:END`` option (e.g. ``--calibrate 0s:2s``) in seconds."""
    from imufdi_cli.units import parse_time_range

    return parse_time_range(text, name=name)


def complete_file(ctx: click.Context, param: click.Parameter, incomplete: str) -> list[object]:
    """Shell completion of a file (or directory) argument: the shell lists the names
    (``imufdi info s<TAB>``); a rosbag2 directory is an input too."""
    from click.shell_completion import CompletionItem

    return [CompletionItem(incomplete, type="file")]


def complete_dir(ctx: click.Context, param: click.Parameter, incomplete: str) -> list[object]:
    """Shell completion of a directory argument (campaign results, demo --keep)."""
    from click.shell_completion import CompletionItem

    return [CompletionItem(incomplete, type="dir")]


#: what --start and --end accept (help text)
TIME_POINT_HELP = (
    "seconds from the log start (30s, 2min), an ISO 8601 UTC time"
    " (2023-11-14T22:13:30Z) or a Unix time (1700000010)"
)

#: options shared by every command that reads Imu topics (info, inject, detect)
topic_option = click.option(
    "--topic",
    "topics",
    multiple=True,
    help="Imu topic to use, in array order (repeatable); /TOPIC:FIELD picks the"
    " sensor_msgs/msg/Imu field FIELD of a larger message.",
)
stamps_option = click.option(
    "--stamps",
    type=click.Choice(["auto", "header", "log"]),
    default="auto",
    show_default=True,
    help="Imu time: header.stamp, MCAP log time, or auto (header; log time when the Imu has"
    " no header or all-zero stamps, with a warning).",
)

EXIT_CODES_TEXT = (
    "Exit codes: 0 ok, 1 CI gate failed, 2 usage error, 3 bad input data or I/O error,"
    " 4 internal error, 130/143 interrupted/terminated."
)


class StdoutClosed(Exception):
    """The reader of our stdout went away (``imufdi simulate -o - | head -c1``).

    Raised in place of the BrokenPipeError a write to stdout gives, so that click's own
    handling of that error (exit 1, the "gate failed" code) does not apply: the console
    script ends quietly with exit 0 (docs/guide.md, "Output conventions").
    """


class Group(click.Group):
    """The ``imufdi`` group: commands from :data:`COMMAND_MODULES`, imported on demand."""

    def invoke(self, ctx: click.Context) -> object:
        try:
            return super().invoke(ctx)
        except BrokenPipeError:
            raise StdoutClosed from None

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(self.commands) | set(COMMAND_MODULES))

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in self.commands and cmd_name in COMMAND_MODULES:
            import_module(COMMAND_MODULES[cmd_name])
        return super().get_command(ctx, cmd_name)

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        formatter.write_paragraph()
        formatter.write_text(
            "Every command: -q/--quiet, -v/--verbose, --json [FILE] (machine-readable"
            " summary; - or no FILE: stdout); summaries on stderr; NO_COLOR honoured."
            ' Shell completion: eval "$(_IMUFDI_COMPLETE=bash_source imufdi)"'
            " (zsh_source, fish_source)."
        )
        formatter.write_paragraph()
        formatter.write_text(EXIT_CODES_TEXT)


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="imufdi")
def cli() -> None:
    """Fault detection and isolation for redundant MEMS IMU arrays, on MCAP logs.

    Example:


    \b
        imufdi simulate --preset paper-table4 --seed 1 -o run.mcap
        imufdi inject run.mcap --fault step:imu0.gyro.x,at=2.5s,amp=0.9deg/s -o faulty.mcap
        imufdi detect faulty.mcap -d glt -o detected.mcap
        imufdi report detected.mcap --fail-if 'glt.gyro.far > 0.08'
    """
