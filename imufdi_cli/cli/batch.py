"""Commands that run whole pipelines: ``campaign``, ``demo``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

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
    from imufdi_cli.campaign import run_campaign_cli
    from imufdi_cli.fileio import check_outputs

    check_outputs([spec], [("--json", ui.json_target)])
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
    from imufdi_cli.fileio import check_outputs
    from imufdi_cli.pipeline import run_demo

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
