"""The ``imufdi`` command line: thin click commands over the library.

Each command parses its options, calls one library function and renders the result with
rich (:mod:`imufdi_cli.cli.ui`: summaries on stderr, products on stdout, ``--json [FILE]``,
``-q``/``-v``, NO_COLOR, the progress bar). Data go to ``-o`` (``-`` = stdout), so
commands compose in pipelines::

    imufdi ingest cap.bin -o - | imufdi inject - --fault ... -o - | imufdi detect - -d glt -o - | imufdi report -

Commands by group (each module imported when its command runs, :data:`.app.COMMAND_MODULES`):
:mod:`~imufdi_cli.cli.data` (simulate, ingest, inject),
:mod:`~imufdi_cli.cli.describe` (info), :mod:`~imufdi_cli.cli.detection` (detect, tune,
calibrate), :mod:`~imufdi_cli.cli.reporting` (report), :mod:`~imufdi_cli.cli.batch`
(campaign, demo); the entry point and signal handling in :mod:`~imufdi_cli.cli.entry`.

Exit codes: 0 ok, 1 a CI gate failed, 2 usage error, 3 bad input data (or an I/O error
such as a full disk), 4 internal error; 130 interrupted (SIGINT), 143 terminated (SIGTERM),
129 hung up (SIGHUP): 128 + the signal number, after removing any partial output.
"""

from __future__ import annotations

import os

# The maths works on thin matrices (tens of sensors) where multi-threaded BLAS only adds
# contention on small machines (10-20x slower measured on 2 cores under load); campaigns
# get their parallelism from processes. Users can still override these.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from typing import TYPE_CHECKING, Any  # noqa: E402

from imufdi_cli.cli.entry import (  # noqa: E402
    HANDLED_SIGNALS,
    Terminated,
    describe_exception,
    main,
)

if TYPE_CHECKING:
    from imufdi_cli.cli.app import cli


def __getattr__(name: str) -> Any:
    """``cli``: the click group with every command loaded (tools, tests, embedding); the
    console script (:func:`main`) loads only the command it runs."""
    if name == "cli":
        from imufdi_cli.cli.app import cli, load_all_commands

        load_all_commands()
        return cli
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["HANDLED_SIGNALS", "Terminated", "cli", "describe_exception", "main"]
