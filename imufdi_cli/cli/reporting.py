"""``imufdi report``: metrics, renderers, CI gates."""

from __future__ import annotations

import sys
from typing import Any

import click

from imufdi_cli.cli.app import TIME_POINT_HELP, cli, complete_file, start_end
from imufdi_cli.cli.plain import PlainTable
from imufdi_cli.cli.ui import UI, common_options, error_line
from imufdi_cli.errors import EXIT_GATE_FAILED


@cli.command()
@click.argument("log", shell_complete=complete_file)
@click.option(
    "--markdown",
    "md_out",
    help="Write a Markdown table here (- for stdout).",
    shell_complete=complete_file,
)
@click.option(
    "--csv", "csv_out", help="Write a CSV table here (- for stdout).", shell_complete=complete_file
)
@click.option(
    "--junit",
    "junit_out",
    help="Write JUnit XML (one test case per gate).",
    shell_complete=complete_file,
)
@click.option(
    "--plot",
    "plot_out",
    help="Write a PNG of statistics (alarms marked) and isolation scores (needs matplotlib).",
    shell_complete=complete_file,
)
@click.option(
    "--episodes-csv",
    "episodes_out",
    help="Write the explained alarm episodes as CSV (docs/episodes.md).",
)
@click.option("--fail-if", "gates", multiple=True, help="Gate, e.g. 'glt.gyro.far > 0.01'.")
@click.option(
    "--persist",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Detection delay counts the first run of this many alarms; recovery needs this"
    " many quiet samples after the last alarm.",
)
@click.option(
    "--match-far",
    "match_far",
    metavar="RATE",
    help="Also report MAR, FIR and delay with each detector's threshold scaled to this"
    " out-of-sample FAR (e.g. 1% or 0.01).",
)
@click.option(
    "--match-budget",
    "match_budget",
    metavar="RATE",
    help="Also report MAR, FIR and delays with each detector's threshold scaled so that"
    " the fault-free tested time raises this many false alarm episodes (e.g. 1/h).",
)
@click.option(
    "--roc",
    "roc_out",
    metavar="FILE",
    help="Write the threshold sweep (FAR, MAR, FIR, delay per scale) as CSV; with --plot"
    " also FILE's name with .png.",
    shell_complete=complete_file,
)
@click.option("--start", help=f"Score samples from this time: {TIME_POINT_HELP}.")
@click.option("--end", help="Score samples before this time (the same forms as --start).")
@common_options(json_help="The whole report (metrics, gates, notes, episodes).")
def report(
    log: str,
    md_out: str | None,
    csv_out: str | None,
    junit_out: str | None,
    plot_out: str | None,
    episodes_out: str | None,
    gates: tuple[str, ...],
    persist: int,
    match_far: str | None,
    match_budget: str | None,
    roc_out: str | None,
    start: str | None,
    end: str | None,
    ui: UI,
) -> None:
    """Metrics per detector and sensor type: FAR, MAR, accuracy, FIR, delays.

    FAR counts samples outside the calibration window; delays are at decision time;
    false alarm episodes are counted per hour of fault-free tested time, with their 95 %
    upper bound. --match-far compares detectors at one per-sample false-alarm rate,
    --match-budget at one rate of false episodes per hour (docs/metrics.md).
    --fail-if gates exit with code 1 when any fails (CI regression on recorded data).
    The table goes to stdout (to stderr when an output is -).

    Example:


    \b
        imufdi report out.mcap --markdown table.md --fail-if 'glt.gyro.far > 0.08' --fail-if 'glt.gyro.mar > 0.35'
        imufdi report out.mcap --match-far 1% --roc roc.csv --plot figures.png
        imufdi report recorded.mcap --fail-if 'glt.gyro.false_episodes_per_hour_upper95 > 2'
    """
    from imufdi_cli import report as rep
    from imufdi_cli.errors import UsageError
    from imufdi_cli.fileio import (
        atomic_path,
        check_input,
        check_outputs,
        derived_output,
        write_text,
    )

    target = None if match_far is None else rep.parse_far(match_far)
    budget = None if match_budget is None else rep.parse_budget(match_budget)
    check_input(log)
    # with --plot, --roc FILE also writes FILE's name with .png: an output like the others
    roc_png = derived_output(roc_out, ".png") if plot_out and roc_out and roc_out != "-" else None
    outputs = [
        ("--json", ui.json_target),
        ("--markdown", md_out),
        ("--csv", csv_out),
        ("--junit", junit_out),
        ("--plot", plot_out),
        ("--roc", roc_out),
        ("--episodes-csv", episodes_out),
        ("--roc (its .png figure with --plot)", roc_png),
    ]
    if plot_out == "-":
        raise UsageError("--plot writes a PNG file; give it a file name")
    ui.data_to_stdout(md_out, csv_out, junit_out, roc_out, episodes_out)
    check_outputs([log], outputs)
    parsed = []
    if gates:  # (the detector registry only for gates)
        from imufdi_cli.detectors import DETECTORS

        parsed = [rep.parse_gate(g, DETECTORS) for g in gates]  # bad gates fail before reading
    if plot_out:
        from imufdi_cli.plots import pyplot

        pyplot()  # no matplotlib: a usage error before any work or any output
    with ui.progress(f"report {log}") as progress:
        result = rep.build_report(
            log,
            persist=persist,
            match_far=target,
            match_budget=budget,
            keep_series=plot_out is not None,
            keep_roc=roc_out is not None,
            window=start_end(start, end),
            progress=progress,
        )
    window = start_end(start, end)
    if (
        window is not None
        and result.entries
        and all(e.metrics.samples == 0 for e in result.entries)
    ):
        ui.warn(
            [
                f"--start/--end holds no status sample (--start {start or '0'}, --end"
                f" {end or 'the end'}; the status starts at {_status_start(result)}):"
                " nothing was scored"
            ]
        )
    gate_results = rep.evaluate_gates(result, parsed)
    ui.print_table(report_table(result))
    for table in episode_tables(result, limit=None if ui.verbose else 12):
        ui.print_table(table)
    if result.notes:  # in the product, after the tables
        ui.note(result.notes, product=True)
    if episodes_out:
        write_text(episodes_out, rep.to_episodes_csv(result))
    if ui.json_target:
        write_text(ui.json_target, rep.to_json(result, gate_results, head=ui.json_object({})))
    if md_out:
        write_text(md_out, rep.to_markdown(result, gate_results))
    if csv_out:
        write_text(csv_out, rep.to_csv(result))
    if junit_out:
        write_text(junit_out, rep.to_junit(result, gate_results))
    if roc_out:
        write_text(roc_out, rep.to_roc_csv(result))
    if plot_out:
        from imufdi_cli import plots

        with atomic_path(plot_out, suffix=".png") as tmp:  # matplotlib wants the extension
            plots.plot_report(result, tmp)
        if roc_png is not None:
            with atomic_path(roc_png, suffix=".png") as tmp:
                plots.plot_roc(result, tmp)
    failed = [r for r in gate_results if r.failed]
    if gate_results:  # rich only when there are gate lines to print
        from rich.markup import escape

    for r in gate_results:
        style = "red" if r.failed else "green"
        ui.product.print(f"[{style}]gate {escape(r.message)}[/]")
    if failed:
        ui.flush()  # the table before the error line
        # the line names each failed gate with its figure, so that it makes sense alone
        # (under -q nothing else was printed)
        where = "" if ui.quiet else "; the report above shows every figure"
        error_line(
            f"{len(failed)} of {len(gate_results)} gate(s) failed: "
            + "; ".join(_failed_gate(r) for r in failed)
            + f" (exit 1{where})"
        )
        sys.exit(EXIT_GATE_FAILED)


def _status_start(result: Any) -> str:
    """When the log's status starts: ISO 8601 UTC for calendar stamps, else the raw ns."""
    from imufdi_cli.units import UNIX_TIME_MIN_S, utc_iso

    t0 = int(result.t0_ns)
    return utc_iso(t0) if t0 >= UNIX_TIME_MIN_S * 1e9 else f"{t0} ns (not a calendar time)"


def _failed_gate(result: Any) -> str:
    """``glt.gyro.far > 0.08 (actual 0.12)``: a failed gate and the figure that failed it."""
    actual = result.actual
    figure = "undefined" if actual is None else f"{actual:.6g}"
    return f"{result.gate.text} (actual {figure})"


def report_table(result: Any) -> PlainTable:
    """``imufdi report``'s figure table: detector, sensor and the console's columns
    (right-justified)."""
    from imufdi_cli import report as rep

    columns = rep.table_columns(result, console=True)
    table = PlainTable(
        ("detector", "sensor", *(header for _, header, _, _ in columns)),
        title=f"imufdi report: {result.source}",
        justify=("left", "left", *("right" for _ in columns)),
    )
    for row in rep.table_rows(result, console=True):
        table.add_row(*row)
    return table


def episode_tables(result: Any, limit: int | None = 12) -> list[PlainTable]:
    """The episode figures per detector and type, and the ``limit`` strongest episodes
    (none without episode scores)."""
    from imufdi_cli import report as rep

    if not result.episode_scores:
        return []
    columns = ("detector.type", "episodes", "false / h", "class right %", "covered %")
    table = PlainTable(
        columns, title="alarm episodes (docs/episodes.md)", justify=("right",) * len(columns)
    )
    for key, score in result.episode_scores.items():
        table.add_row(
            key,
            str(score["episodes"]),
            rep.format_value(score.get("false_episodes_per_hour"), 1.0, "{:.3g}"),
            rep.format_value(score.get("class_accuracy"), 100.0, "{:.1f}"),
            rep.format_value(score.get("coverage"), 100.0, "{:.1f}"),
        )
    rows = sorted(rep.episode_rows(result), key=lambda r: -(r["peak_ratio"] or 0.0))[:limit]
    detail = PlainTable(
        (
            "detector",
            "start s",
            "dur s",
            "sensor",
            "class",
            "size [90 %]",
            "runner-up",
            "peak",
            "match",
        ),
        title=f"strongest {len(rows)} episodes",
    )
    for r in rows:
        detail.add_row(
            f"{r['detector']}.{r['sensor_type']}",
            f"{r['start_s']:.2f}",
            rep.format_value(r["duration_s"], 1.0, "{:.2f}"),
            r["sensor"] or "-",
            r["fault_class"] or "-",
            r["size"],
            r["runner_up_class"] or "-",
            rep.format_value(r["peak_ratio"], 1.0, "{:.3g}"),
            r["match"] or "-",
        )
    return [table, detail]
