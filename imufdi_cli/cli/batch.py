"""Commands that run whole pipelines: ``campaign``, ``demo``."""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click

from imufdi_cli.cli.app import cli, complete_dir, complete_file
from imufdi_cli.cli.ui import UI, common_options, make_console


@cli.command()
@click.argument("spec", shell_complete=complete_file)
@click.option(
    "-o",
    "--output",
    "results_dir",
    required=True,
    help="Results directory.",
    shell_complete=complete_dir,
)
@click.option(
    "--jobs",
    type=click.IntRange(min=1),
    help="Worker processes (default: all cores, the fastest on an idle machine; use 1 when "
    "other work keeps the cores busy, see docs/campaign.md).",
)
@click.option("--scheduler", help="dask scheduler: tcp://HOST:PORT or local:N.")
@click.option(
    "--resume", is_flag=True, help="Skip runs whose results are already in the directory."
)
@click.option(
    "--fail-if", "gates", multiple=True, help="Gate on the summary, e.g. 'glt.gyro.far > 0.08'."
)
@common_options(json_help="The campaign summary (summary.json of the results directory).")
def campaign(
    spec: str,
    results_dir: str,
    jobs: int | None,
    scheduler: str | None,
    resume: bool,
    gates: tuple[str, ...],
    ui: UI,
) -> None:
    """Run a fault-injection campaign: inject + detect + report over a matrix, in parallel.

    Progress and the summary go to stderr; the results to the directory.

    Example:


    \b
        imufdi campaign docs/campaigns/compare.toml -o results/ --jobs 2
        imufdi campaign spec.toml -o results/ --scheduler tcp://10.0.0.5:8786 --resume
    """
    from imufdi_cli.fileio import check_outputs

    check_outputs([spec], [("-o", results_dir), ("--json", ui.json_target)])
    code = run_campaign_cli(
        spec,
        results_dir,
        jobs=jobs,
        scheduler=scheduler,
        resume=resume,
        gates=list(gates),
        console=ui.live(),
    )
    summary = Path(results_dir) / "summary.json"
    if ui.json_target is not None and summary.is_file():
        ui.json(json.loads(summary.read_text(encoding="utf-8")))
    if code:
        sys.exit(code)


@cli.command()
@click.option(
    "--keep", "keep_dir", help="Keep the outputs in this directory.", shell_complete=complete_dir
)
@common_options(json_help="Summary: the steps with their commands, times and outputs.")
def demo(keep_dir: str | None, ui: UI) -> None:
    """Run the whole pipeline on the bundled sample log and print what it did.

    The outputs go to a temporary directory that is removed at the end, unless --keep DIR.

    Example:


    \b
        imufdi demo
        imufdi demo --keep demo_out/
    """
    from imufdi_cli.cli.demo import run_demo
    from imufdi_cli.fileio import check_outputs

    check_outputs([], [("--json", ui.json_target)])
    console = ui.product if ui.stdout_taken else make_console(sys.stdout, quiet=ui.quiet)
    result = run_demo(keep_dir, console=console)
    if not keep_dir:
        console.print(
            f"outputs removed with their temporary directory {result.directory};"
            " keep them with: imufdi demo --keep DIR"
        )
    ui.json(
        {
            "command": "demo",
            "directory": result.directory,
            "kept": bool(keep_dir),
            "steps": [
                {
                    "name": step.name,
                    "command_line": step.command,
                    "seconds": step.seconds,
                    "output": step.output,
                }
                for step in result.steps
            ],
        }
    )


def run_campaign_cli(
    spec_path: str,
    results_dir: str,
    *,
    jobs: int | None,
    scheduler: str | None,
    resume: bool,
    gates: Sequence[str],
    console: Any,
    progress: bool | None = None,
) -> int:
    """What ``imufdi campaign`` does; returns the exit code (0, or 1 when a gate fails).

    The closing line and the gates go to ``console``; the progress bar always goes to
    stderr: with ``progress=None`` only when stderr is a terminal and ``console`` is not
    quiet (rich's ``Console(quiet=True)``), ``False`` never (``--quiet``), ``True`` always.
    The bar is redrawn when runs finish, without a refresh thread (pool workers fork from
    a single-threaded process: :func:`~imufdi_cli.campaign.executors.start_method`).

    Raises CampaignFailedError (exit 3, or 4 on internal errors) when every run failed.
    """
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    from imufdi_cli.campaign import (
        check_all_failed,
        evaluate_summary_gates,
        load_spec,
        run_campaign,
        run_key,
    )
    from imufdi_cli.detectors import DETECTORS
    from imufdi_cli.report import parse_gate

    spec = load_spec(spec_path)
    for gate in gates:
        parse_gate(gate, DETECTORS)  # bad gates fail before any run
    if progress is None:
        progress = sys.stderr.isatty() and not getattr(console, "quiet", False)
    with Progress(
        TextColumn("[bold]campaign[/] {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("failed {task.fields[failed]}"),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        transient=False,
        auto_refresh=False,
        disable=not progress,
    ) as bar:
        task = bar.add_task(spec.name, total=len({run_key(r) for r in spec.runs}), failed=0)
        failed = 0

        def advance(done: int, total: int, result: dict[str, Any] | None) -> None:
            nonlocal failed
            if result is not None and not result["ok"]:
                failed += 1
            bar.update(task, completed=done, failed=failed, refresh=True)

        result = run_campaign(
            spec, results_dir, jobs=jobs, scheduler=scheduler, resume=resume, progress=advance
        )
    console.print(
        f"{result.total} runs ({result.executed} executed, {result.skipped} resumed, "
        f"{result.failed} failed) in {result.seconds:.1f} s -> {result.directory}"
    )
    check_all_failed(result)
    outcomes = evaluate_summary_gates(result.summary, gates)
    for _, failed_gate, message in outcomes:
        console.print(f"[{'red' if failed_gate else 'green'}]gate {message}[/]", markup=True)
    return 1 if any(f for _, f, _ in outcomes) else 0
