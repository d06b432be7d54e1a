"""The console entry point: run the click group, turn every error into one line and an
exit code (``main``), and signals into a clean exit."""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import click

from imufdi_cli.cli.app import StdoutClosed, cli
from imufdi_cli.cli.ui import error_line as _err
from imufdi_cli.errors import EXIT_BAD_INPUT, EXIT_INTERNAL, EXIT_USAGE, ImufdiError


class Terminated(BaseException):
    """SIGTERM/SIGHUP (or SIGINT) turned into an exception, so that every ``with`` block
    unwinds: atomic outputs remove their temporary files, worker pools shut down.

    A BaseException, so that library code catching ``Exception`` (a campaign recording a
    failed run) does not swallow it.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


#: Signals that stop the CLI cleanly (exit 128 + signal number).
HANDLED_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


@contextmanager
def _signals_as_exceptions() -> Iterator[None]:
    """Install handlers raising :class:`Terminated` (the first signal only: further
    signals while cleaning up are ignored so the cleanup completes); restore on exit.
    A signal that is already ignored (``nohup`` ignores SIGHUP) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    raised = False

    def handler(signum: int, frame: Any) -> None:
        nonlocal raised
        if raised:
            return
        raised = True
        raise Terminated(signum)

    previous = {}
    for signum in HANDLED_SIGNALS:
        try:
            if signal.getsignal(signum) == signal.SIG_IGN:
                continue  # ignored by whoever started us (nohup, a background job): keep it
            previous[signum] = signal.signal(signum, handler)
        except (OSError, ValueError):  # pragma: no cover - platform without the signal
            continue
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def describe_exception(err: BaseException) -> str:
    """One non-empty line for an unexpected exception: its class and what it says."""
    text = " ".join(str(err).split())
    name = type(err).__name__
    if isinstance(err, MemoryError):
        return (
            "out of memory"
            + (f" ({text})" if text else "")
            + "; the input may declare sizes larger than it holds, or need more memory than"
            " this machine has"
        )
    if isinstance(err, OSError):
        reason = err.strerror or text or name
        where = err.filename if err.filename is not None else None
        return f"{where}: {reason}" if where is not None else f"{name}: {reason}"
    return f"{name}: {text}" if text else f"{name} (no message)"


def _json_took_the_argument(args: Sequence[str]) -> str:
    """A hint when a bare ``--json`` swallowed the command's argument (``info --json
    run.mcap``): ``--json`` takes an optional FILE, so it must come last or be given one."""
    for i, arg in enumerate(args[:-1]):
        following = args[i + 1]
        if arg == "--json" and following != "-" and not following.startswith("-"):
            return (
                f" (--json took {following!r} as its FILE: put --json last, or write"
                f" --json - for stdout)"
            )
    return ""


def _stdout_to_devnull() -> None:
    """Point file descriptor 1 (and ``sys.stdout``) at /dev/null."""
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    except (OSError, ValueError, AttributeError):  # no real stdout (tests): nothing buffered
        pass
    sys.stdout = open(os.devnull, "w")  # lives until exit


def _debug() -> bool:
    return os.environ.get("IMUFDI_DEBUG", "") not in ("", "0")


def _print_traceback_if_debug() -> None:
    """The current exception's traceback on stderr when IMUFDI_DEBUG is set (traceback is
    imported only then: start-up time)."""
    if _debug():
        import traceback

        traceback.print_exc()


def main(argv: Sequence[str] | None = None) -> None:
    """Console script: run the CLI, turning every error into one line and an exit code."""
    try:
        with _signals_as_exceptions():
            code = cli.main(
                args=list(argv) if argv is not None else None,
                prog_name="imufdi",
                standalone_mode=False,
            )
    except ImufdiError as err:
        _print_traceback_if_debug()
        _err(str(err) or type(err).__name__)
        sys.exit(err.exit_code)
    except Terminated as err:
        name = signal.Signals(err.signum).name
        _err("interrupted" if name == "SIGINT" else f"terminated by {name}")
        sys.exit(err.exit_code)
    except click.exceptions.Abort:
        _err("aborted")
        sys.exit(130)
    except click.ClickException as err:
        message = " ".join(err.format_message().split()) or type(err).__name__
        if isinstance(err, click.MissingParameter):
            message += _json_took_the_argument(list(argv) if argv is not None else sys.argv[1:])
        _err(message)
        sys.exit(EXIT_USAGE if err.exit_code == 2 else err.exit_code)
    except KeyboardInterrupt:
        _err("interrupted")
        sys.exit(130)
    except (BrokenPipeError, StdoutClosed):
        # the reader of our stdout went away (e.g. `| head`): not an error of ours. What
        # is still buffered for it must not be flushed at exit (that would print
        # "Exception ignored ... BrokenPipeError" and exit 120): stdout becomes /dev/null.
        _stdout_to_devnull()
        sys.exit(0)
    except (MemoryError, OSError) as err:
        _print_traceback_if_debug()
        _err(describe_exception(err))
        sys.exit(EXIT_BAD_INPUT)
    except Exception as err:  # a bug: one line, and the traceback only on request
        _print_traceback_if_debug()
        _err(
            f"internal error ({describe_exception(err)}); "
            "please report it with the output of IMUFDI_DEBUG=1"
        )
        sys.exit(EXIT_INTERNAL)
    sys.exit(code if isinstance(code, int) else 0)
