"""``imufdi info``: describe a log."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

import click

from imufdi_cli.cli.app import cli, complete_file, stamps_option, time_source, topic_option
from imufdi_cli.cli.plain import PLAIN_WIDTH, PlainTable, plain_safe
from imufdi_cli.cli.ui import UI, common_options

if TYPE_CHECKING:
    from rich.console import Console


@cli.command()
@click.argument("log", shell_complete=complete_file)
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
    text = render_info_plain(summary) if ui.product_is_plain() else None
    if text is not None:
        ui.write_product(text)
    else:
        render_info(ui.product, summary)


def log_info_summary(
    log: str, topics: tuple[str, ...], stamps: str, strict: bool
) -> dict[str, Any]:
    from imufdi_cli.info import log_info

    return log_info(
        log, topics=list(topics) or None, time_source=time_source(stamps), strict=strict
    )


def _has_cal(imu: dict[str, Any]) -> bool:
    return any(key.endswith(("_matrix", "_bias")) for key in imu)


#: one part of the description: ("bold" | "text", line) or ("table", PlainTable)
Part = tuple[str, Any]


def info_parts(s: dict[str, Any]) -> list[Part]:
    """What ``imufdi info`` prints, in order, as plain lines and tables (no markup)."""
    parts: list[Part] = [("bold", str(s["source"])), ("table", _head_table(s))]
    topics = PlainTable(("topic", "schema", "encoding", "messages"), title="topics")
    for t in s.get("topics", []):
        topics.add_row(
            t["topic"], str(t.get("schema")), t["message_encoding"], str(t["message_count"])
        )
    parts.append(("table", topics))
    array = s.get("array")
    if array:
        source = "metadata" if s.get("array_from_metadata") else "inferred"
        parts.append(
            (
                "text",
                f"array ({source}): {len(array['imu'])} IMUs, noise "
                + (json.dumps(array.get("noise")) if array.get("noise") else "not given")
                + (", per-IMU calibration" if any(_has_cal(imu) for imu in array["imu"]) else "")
                + (f", range {json.dumps(array['range'])}" if array.get("range") else ""),
            )
        )
    fc = s.get("flight_log")
    if fc:
        parts.append(("text", _flight_log_line(fc)))
    for sensor_type, counts in s.get("validity", {}).items():
        parts.append(
            (
                "text",
                f"{sensor_type}: {counts.get('clipped', 0)} clipped and"
                f" {counts.get('invalid', 0)} invalid of {counts.get('rows', 0)} samples"
                " (at ingest)",
            )
        )
    for fault in s.get("faults", []):
        parts.append(("text", f"fault {fault.get('id', '')}: {fault.get('spec') or fault}"))
    for name, det in s.get("detectors", {}).items():
        parts.append(("text", f"detector {name}: {json.dumps(det.get('params', {}))}"))
        for sensor_type, counts in det.get("validity", {}).items():
            parts.append(
                (
                    "text",
                    f"  {sensor_type}: {counts.get('clipped', 0)} clipped,"
                    f" {counts.get('invalid', 0)} invalid samples excluded from the tests",
                )
            )
    return parts


def _flight_log_line(fc: dict[str, Any]) -> str:
    """``flight log: PX4 ULog (PX4, CUBEORANGE, v1.11.2), vehicle_imu: 3 IMUs at 2, 2, 2 Hz``."""
    names = {"px4-ulog": "PX4 ULog", "ardupilot-dataflash": "ArduPilot DataFlash"}
    system = fc.get("system") or {}
    words = [
        system[k] for k in ("sys_name", "ver_hw", "version", "firmware", "board") if system.get(k)
    ]
    rates = ", ".join(f"{r:.4g}" for r in fc.get("imu_rates_hz") or [])
    text = (
        f"flight log: {names.get(str(fc.get('format')), fc.get('format'))}"
        + (f" ({', '.join(words)})" if words else "")
        + f", {fc.get('imu_data')}: {fc.get('n_imus')} IMUs at {rates} Hz"
        + ("" if fc.get("testable", True) else " (too low to test)")
        + (
            f"; UTC from GPS, start {fc['utc_start']}"
            if fc.get("utc_start")
            else "; no UTC (no GPS time)"
        )
    )
    return text


def _head_table(s: dict[str, Any]) -> PlainTable:
    """The key/value table at the top of ``imufdi info``."""
    head = PlainTable(("key", "value"), boxed=False, bold_first=True)
    for key in ("n_imus", "n_samples", "duration_s", "start_ns"):
        if key in s:
            value = s[key]
            head.add_row(key, f"{value:.6g}" if isinstance(value, float) else str(value))
    if s.get("start_ns") is not None:
        if s.get("start_utc"):
            head.add_row("start (UTC)", s["start_utc"])
            head.add_row("end (UTC)", s.get("end_utc") or "")
        else:  # stamps from boot (a flight controller, a capture card)
            head.add_row(
                "start (UTC)",
                "not a calendar time (stamps count from boot or an epoch of the"
                " device's own); --start/--end take seconds from the log start",
            )
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
    return head


def render_info(console: Console, s: dict[str, Any]) -> None:
    """The tables of ``imufdi info`` on a rich console (warnings are printed separately)."""
    from rich.markup import escape

    for kind, payload in info_parts(s):
        if kind == "table":
            console.print(payload.to_rich())
        elif kind == "bold":
            console.print(f"[bold]{escape(payload)}[/]")
        else:
            console.print(escape(payload))


def render_info_plain(s: dict[str, Any], width: int = PLAIN_WIDTH) -> str | None:
    """``imufdi info``'s description as rich prints it on a plain console of ``width``
    columns, without importing rich; None when only rich can render it exactly."""
    out = []
    for kind, payload in info_parts(s):
        if kind == "table":
            text = payload.render(width)
            if text is None:
                return None
            out.append(text)
        elif plain_safe(payload):
            out.append(payload + "\n")
        else:
            return None
    return "".join(out)
