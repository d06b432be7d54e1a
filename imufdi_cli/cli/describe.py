"""``imufdi info``: describe a log."""

from __future__ import annotations

import json
from typing import Any

import click
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from imufdi_cli.cli.app import cli, stamps_option, time_source, topic_option
from imufdi_cli.cli.ui import UI, common_options


@cli.command()
@click.argument("log")
@topic_option
@stamps_option
@click.option("--strict", is_flag=True, help="A truncated or corrupt input is an error (exit 3).")
@common_options(json_help="The description as JSON instead of tables.")
def info(log: str, topics: tuple[str, ...], stamps: str, strict: bool, ui: UI) -> None:
    """Describe a log: topics, IMUs, rate, duration, gaps, array, faults, detectors.

    The description goes to stdout (with --json: the JSON), warnings to stderr.

    Example:


    \b
        imufdi info run.mcap
        imufdi info run.mcap --json | jq .n_imus
    """
    from imufdi_cli.fileio import check_input, check_outputs

    check_input(log)
    check_outputs([log], [("--json", ui.json_target)])
    summary = log_info_summary(log, topics, stamps, strict)
    ui.warn(summary.get("warnings", []))
    if ui.json_target is not None:
        ui.json(summary)
        if ui.json_target == "-":
            return
    render_info(ui.product, summary)


def log_info_summary(
    log: str, topics: tuple[str, ...], stamps: str, strict: bool
) -> dict[str, Any]:
    from imufdi_cli.pipeline import log_info

    return log_info(
        log, topics=list(topics) or None, time_source=time_source(stamps), strict=strict
    )


def _has_cal(imu: dict[str, Any]) -> bool:
    return any(key.endswith(("_matrix", "_bias")) for key in imu)


def render_info(console: Console, s: dict[str, Any]) -> None:
    """The tables of ``imufdi info`` (warnings are printed separately)."""
    console.print(f"[bold]{escape(str(s['source']))}[/]")
    head = Table(show_header=False, box=None)
    head.add_column(style="bold")
    head.add_column()
    for key in ("n_imus", "n_samples", "duration_s", "start_ns"):
        if key in s:
            value = s[key]
            head.add_row(key, f"{value:.6g}" if isinstance(value, float) else str(value))
    if s.get("rate_hz") is not None:
        head.add_row("rate_hz", f"{s['rate_hz']:.6g}  ({s.get('rate_method', '')})")
    if s.get("time_source"):
        head.add_row("stamps", "header.stamp" if s["time_source"] == "header" else "log time")
    fields = {t: f for t, f in s.get("imu_fields", {}).items() if f}
    for topic, path in fields.items():
        head.add_row("imu field", f"{topic}: {path}")
    gaps = s.get("gaps") or {}
    if gaps:
        text = f"{gaps.get('count', 0)}"
        if gaps.get("count"):
            text += (
                f" ({gaps['missing_samples']} samples missing of {gaps['expected_samples']}"
                f" expected; longest {gaps['longest_s']:.6g} s)"
            )
        head.add_row("gaps (all topics)", text)
    ingest = s.get("ingest")
    if ingest:
        labels = (
            ("frames_ok", "frames ok"),
            ("frames_lost", "lost"),
            ("frames_bad_checksum", "bad checksum"),
            ("frames_truncated", "truncated"),
            ("duplicates", "duplicates"),
            ("bytes_dropped", "bytes dropped"),
        )
        parts = [f"{label} {ingest[key]}" for key, label in labels if key in ingest]
        head.add_row("capture (ingest)", ", ".join(parts))
    for key, value in s.get("alignment", {}).items():
        if isinstance(value, dict):
            nonzero = {k: v for k, v in value.items() if v}
            total = sum(v for v in value.values() if isinstance(v, (int, float)))
            detail = ", ".join(f"{k}: {v}" for k, v in nonzero.items()) if nonzero else ""
            text = f"{total}" + (f" ({detail})" if detail and key != "messages" else "")
        else:
            text = str(value)
        head.add_row(f"alignment.{key}", text)
    console.print(head)
    topics = Table(title="topics")
    for col in ("topic", "schema", "encoding", "messages"):
        topics.add_column(col)
    for t in s.get("topics", []):
        topics.add_row(
            t["topic"], str(t.get("schema")), t["message_encoding"], str(t["message_count"])
        )
    console.print(topics)
    array = s.get("array")
    if array:
        source = "metadata" if s.get("array_from_metadata") else "inferred"
        console.print(
            escape(
                f"array ({source}): {len(array['imu'])} IMUs, noise "
                + (json.dumps(array.get("noise")) if array.get("noise") else "not given")
                + (", per-IMU calibration" if any(_has_cal(imu) for imu in array["imu"]) else "")
                + (f", range {json.dumps(array['range'])}" if array.get("range") else "")
            )
        )
    for sensor_type, counts in s.get("validity", {}).items():
        console.print(
            f"{sensor_type}: {counts.get('clipped', 0)} clipped and {counts.get('invalid', 0)}"
            f" invalid of {counts.get('rows', 0)} samples (at ingest)"
        )
    for fault in s.get("faults", []):
        console.print(escape(f"fault {fault.get('id', '')}: {fault.get('spec') or fault}"))
    for name, det in s.get("detectors", {}).items():
        console.print(escape(f"detector {name}: {json.dumps(det.get('params', {}))}"))
        for sensor_type, counts in det.get("validity", {}).items():
            console.print(
                f"  {sensor_type}: {counts.get('clipped', 0)} clipped, {counts.get('invalid', 0)}"
                f" invalid samples excluded from the tests"
            )
