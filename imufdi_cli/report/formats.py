"""Renderers of a :class:`~imufdi_cli.report.model.Report`: table rows, JSON, Markdown (the
layout of Li et al. Table 4), CSV, JUnit XML, the ROC CSV of ``--roc`` and the explained
episodes (rows, Markdown, CSV)."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from imufdi_cli.jsonout import dumps as json_dumps
from imufdi_cli.metrics import AmplitudeFigure
from imufdi_cli.report.gates import GateResult
from imufdi_cli.report.model import Report

#: Columns of the tables: (metric, header, scale, format)
TABLE_COLUMNS: list[tuple[str, str, float, str]] = [
    ("far", "FAR %", 100.0, "{:.2f}"),
    ("mar", "MAR %", 100.0, "{:.2f}"),
    ("accuracy", "Accuracy %", 100.0, "{:.2f}"),
    ("fir", "FIR %", 100.0, "{:.2f}"),
    ("detection_delay_s", "Delay s", 1.0, "{:.3f}"),
    ("isolation_delay_s", "Iso delay s", 1.0, "{:.3f}"),
    ("decision_latency_s", "Latency s", 1.0, "{:.3f}"),
    ("recovery_delay_s", "Recovery s", 1.0, "{:.3f}"),
    ("far_calibration", "FAR cal %", 100.0, "{:.2f}"),
    ("alarm_rate", "Alarm %", 100.0, "{:.2f}"),
    ("alarm_events", "Events", 1.0, "{:.0f}"),
    ("false_episodes_per_hour", "False ep/h", 1.0, "{:.3g}"),
    ("false_episodes_per_hour_upper95", "upper 95 %", 1.0, "{:.3g}"),
    ("fault_free_hours", "Tested h", 1.0, "{:.3g}"),
]
#: The columns of a log without faults (no faulty sample on any channel): what the alarms
#: cost, instead of a row of undefined truth-based figures.
FAULT_FREE_COLUMNS: list[tuple[str, str, float, str]] = [
    ("alarm_rate", "Alarm %", 100.0, "{:.2f}"),
    ("alarm_events", "Events", 1.0, "{:.0f}"),
    ("false_episodes", "Episodes", 1.0, "{:.0f}"),
    ("false_episodes_per_hour", "Episodes/h", 1.0, "{:.3g}"),
    ("false_episodes_per_hour_upper95", "upper 95 %", 1.0, "{:.3g}"),
    ("mtbfa_h", "MTBFA h", 1.0, "{:.3g}"),
    ("mtbfa_h_lower95", "lower 95 %", 1.0, "{:.3g}"),
    ("fault_free_hours", "Tested h", 1.0, "{:.3g}"),
    ("decision_latency_s", "Latency s", 1.0, "{:.3f}"),
]
#: Columns of runs under a false-alarm budget: the optimal test's delay and the ratio.
REFERENCE_COLUMNS: list[tuple[str, str, float, str]] = [
    ("reference_delay_s", "Ref delay s", 1.0, "{:.3f}"),
    ("delay_ratio", "Delay/ref", 1.0, "{:.2f}"),
]
#: Extra columns with --match-budget.
BUDGET_COLUMNS: list[tuple[str, str, float, str]] = [
    ("mar_at_budget", "MAR@budget %", 100.0, "{:.2f}"),
    ("fir_at_budget", "FIR@budget %", 100.0, "{:.2f}"),
    ("detection_delay_s_at_budget", "Delay@budget s", 1.0, "{:.3f}"),
    ("isolation_delay_s_at_budget", "Iso delay@budget s", 1.0, "{:.3f}"),
    ("threshold_scale_at_budget", "Scale@budget", 1.0, "{:.3g}"),
]
#: Extra columns with --match-far.
MATCHED_COLUMNS: list[tuple[str, str, float, str]] = [
    ("mar_at_far", "MAR@FAR %", 100.0, "{:.2f}"),
    ("fir_at_far", "FIR@FAR %", 100.0, "{:.2f}"),
    ("detection_delay_at_far_s", "Delay@FAR s", 1.0, "{:.3f}"),
    ("threshold_scale_at_far", "Scale@FAR", 1.0, "{:.3g}"),
]


#: Columns the terminal table leaves out (they stay in Markdown, CSV, JSON and JUnit).
CONSOLE_OMITS = {"far_calibration", "alarm_rate"}


def fault_free(report: Report) -> bool:
    """Whether no channel of the report has a faulty sample (no truth, or faults on none
    of the tested sensors, or none outside the calibration window)."""
    return all(e.metrics.faulty_samples == 0 for e in report.entries)


def table_columns(report: Report, *, console: bool = False) -> list[tuple[str, str, float, str]]:
    """The columns of this report's tables: the papers' figures with the false alarm
    episodes, or on a log without faults (:func:`fault_free`) the alarm rate and episodes
    per hour with their bounds; the reference delays of runs under a budget; matched-FAR
    columns with ``--match-far``, matched-budget ones with ``--match-budget``
    (``console``: the narrower terminal table)."""
    quiet = fault_free(report)
    columns = list(FAULT_FREE_COLUMNS if quiet else TABLE_COLUMNS)
    if console and not quiet:  # the rate and its bound in one cell: "64.3 [135]"
        columns = [c for c in columns if c[0] not in CONSOLE_OMITS and c[0] != BOUND]
        columns = [CONSOLE_RATE if c[0] == CONSOLE_RATE[0] else c for c in columns]
    if not quiet and any(e.metrics.reference_delay_s is not None for e in report.entries):
        columns += REFERENCE_COLUMNS
    if report.match_far is not None and not quiet:
        columns += MATCHED_COLUMNS
    if report.match_budget is not None:
        budget = [c for c in BUDGET_COLUMNS if not (console and c[0] == "fir_at_budget")]
        columns += budget[-1:] if quiet else budget
    return columns


#: The upper bound's column, and the console's one cell for the rate with its bound.
BOUND = "false_episodes_per_hour_upper95"
CONSOLE_RATE = ("false_episodes_per_hour", "False ep/h [95 %]", 1.0, "{:.3g}")


def _cell(metrics: Any, column: tuple[str, str, float, str]) -> str:
    name, _, scale, fmt = column
    text = format_value(metrics.value(name), scale, fmt)
    if column is CONSOLE_RATE and metrics.value(BOUND) is not None:
        text += f" [{format_value(metrics.value(BOUND), 1.0, fmt)}]"
    return text


def format_value(value: float | None, scale: float = 1.0, fmt: str = "{:.4g}") -> str:
    """Format a figure for tables; undefined values read ``undefined``."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "undefined"
    return fmt.format(value * scale)


def table_rows(report: Report, *, console: bool = False) -> list[list[str]]:
    """Rows (detector, type, columns of :func:`table_columns`) as strings."""
    columns = table_columns(report, console=console)
    return [
        [e.detector, e.sensor_type] + [_cell(e.metrics, c) for c in columns] for e in report.entries
    ]


def to_json(
    report: Report,
    gate_results: Sequence[GateResult] = (),
    head: dict[str, Any] | None = None,
) -> str:
    """The report as JSON text; ``head`` (``format_version``, ``command``) comes first."""
    data = {
        **(head or {}),
        "source": report.source,
        "has_truth": report.has_truth,
        "match_far": report.match_far,
        "match_budget": report.match_budget,
        "faults": report.faults,
        "results": [
            {
                "detector": e.detector,
                "sensor_type": e.sensor_type,
                **e.metrics.to_dict(),
                **e.validity,
            }
            for e in report.entries
        ],
        "gates": [
            {
                "gate": r.gate.text,
                "target": r.target,
                "actual": r.actual,
                "failed": r.failed,
            }
            for r in gate_results
        ],
        "notes": report.notes,
        "episodes": report.episodes,
        "episode_scores": report.episode_scores,
    }
    return json_dumps(data)


def to_markdown(report: Report, gate_results: Sequence[GateResult] = ()) -> str:
    header = ["Detector", "Sensor"] + [h for _, h, _, _ in table_columns(report)]
    lines = [
        f"# imufdi report: `{report.source}`",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(report)]
    if report.faults:
        lines += ["", "## Injected faults", ""]
        lines += [f"- `{f.get('spec', f.get('id', '?'))}`" for f in report.faults]
    per_fault = [(e, f) for e in report.entries for f in e.metrics.faults]
    if per_fault:
        lines += [
            "",
            "## Per fault",
            "",
            "| Fault | Detector | Sensor | Detected | Delay s | Iso delay s | Recovery s"
            " | Isolated to it % | Estimated size (/ true) | Reference delay s | Delay / reference |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {f.fault_id} | {e.detector} | {e.sensor_type} | {'yes' if f.detected else 'no'} | "
            f"{format_value(f.detection_delay_s, 1.0, '{:.3f}')} | "
            f"{format_value(f.isolation_delay_s, 1.0, '{:.3f}')} | "
            f"{format_value(f.recovery_delay_s, 1.0, '{:.3f}')} | "
            f"{format_value(f.isolated_correctly, 100.0, '{:.1f}')} | "
            f"{format_amplitudes(f.amplitudes, e.sensor_type)} | "
            f"{_reference(f.reference_delay_s, '{:.3f}')} | {_reference(f.delay_ratio, '{:.2f}')} |"
            for e, f in per_fault
        ]
    lines += _episodes_markdown(report)
    if gate_results:
        lines += ["", "## Gates", ""]
        lines += [f"- {'❌' if r.failed else '✅'} {r.message}" for r in gate_results]
    if report.notes:
        lines += [""] + [f"> {note}" for note in report.notes]
    return "\n".join(lines) + "\n"


def _reference(value: float | None, fmt: str) -> str:
    """A reference delay cell: ``-`` when there is none (no budget, another fault model)."""
    return "-" if value is None else fmt.format(value)


# --- episodes ---------------------------------------------------------------------------

#: display unit of an episode's size: (sensor type, size name) -> (scale from SI, unit)
_SIZE_UNITS = {
    ("gyro", "amp"): (180.0 / math.pi, "deg/s"),
    ("gyro", "rate"): (180.0 / math.pi, "deg/s^2"),
    ("gyro", "value"): (180.0 / math.pi, "deg/s"),
    ("accel", "amp"): (1.0, "m/s^2"),
    ("accel", "rate"): (1.0, "m/s^3"),
    ("accel", "value"): (1.0, "m/s^2"),
    ("mag", "amp"): (1e6, "uT"),
    ("mag", "rate"): (1e6, "uT/s"),
    ("mag", "value"): (1e6, "uT"),
    ("gyro", "duration"): (1.0, "s"),
    ("accel", "duration"): (1.0, "s"),
    ("mag", "duration"): (1.0, "s"),
}


def format_amplitudes(figures: Sequence[AmplitudeFigure], sensor_type: str) -> str:
    """``imu0.gyro.z 28.5 deg/s (0.995); ...``: each faulty sensor's estimated size in
    display units, and its ratio to the injected one when known; ``-`` when none."""
    parts = []
    for a in figures:
        scale, unit = _SIZE_UNITS.get((sensor_type, a.size_name), (1.0, "SI"))
        ratio = "" if a.ratio is None else f" ({a.ratio:.3f})"
        parts.append(f"{a.sensor} {a.estimate * scale:.4g} {unit}{ratio}")
    return "; ".join(parts) or "-"


def format_size(episode: dict[str, Any]) -> str:
    """``0.91 deg/s [0.88, 0.94]``: the best fit's size and interval in display units."""
    fits = episode.get("fits") or []
    if not fits or fits[0].get("model") in (None, "none"):
        return "-"
    fit = fits[0]
    name = fit.get("size_name", "")
    if name == "factor":
        scale, unit = 1.0, "x"
    else:
        scale, unit = _SIZE_UNITS.get((episode["sensor_type"], name), (1.0, "SI"))

    def num(value: float | None) -> str:
        return "?" if value is None else f"{value * scale:.3g}"

    if fit.get("model") == "stuck":
        return f"at {num(fit.get('size'))} {unit}"
    return f"{num(fit.get('size'))} {unit} [{num(fit.get('low'))}, {num(fit.get('high'))}]"


EPISODE_COLUMNS = [
    "detector",
    "sensor_type",
    "start_s",
    "duration_s",
    "decided_start_s",
    "sensor",
    "fault_class",
    "size",
    "runner_up_class",
    "peak_ratio",
    "runner_up_sensor",
    "runner_up_share",
    "alarms",
    "match",
    "fault_id",
    "detector_amplitude",
]


def episode_rows(report: Report) -> list[dict[str, Any]]:
    """One flat row per listed episode (times in seconds from the log's first sample)."""
    rows = []
    for e in report.episodes:
        fits = e.get("fits") or []
        rows.append(
            {
                "detector": e["detector"],
                "sensor_type": e["sensor_type"],
                "start_s": (e["start_ns"] - report.t0_ns) * 1e-9,
                "duration_s": e.get("duration_s"),
                "decided_start_s": (e["decided_start_ns"] - report.t0_ns) * 1e-9,
                "sensor": (e.get("sensors") or [None])[0],
                "fault_class": e.get("fault_class"),
                "size": format_size(e),
                "runner_up_class": fits[1]["model"] if len(fits) > 1 else None,
                "peak_ratio": e.get("peak_ratio"),
                "runner_up_sensor": e.get("runner_up"),
                "runner_up_share": e.get("runner_up_share"),
                "alarms": e.get("alarms"),
                "match": e.get("match"),
                "fault_id": e.get("fault_id"),
                # the detector's own estimate for the episode's sensor, SI (None: none)
                "detector_amplitude": e.get("amplitude"),
            }
        )
    return rows


def to_episodes_csv(report: Report) -> str:
    """The listed episodes, one CSV row each (:data:`EPISODE_COLUMNS`)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(EPISODE_COLUMNS)
    for row in episode_rows(report):
        writer.writerow(["" if row[k] is None else row[k] for k in EPISODE_COLUMNS])
    return out.getvalue()


def _episodes_markdown(report: Report) -> list[str]:
    if not report.episode_scores:
        return []
    lines = ["", "## Alarm episodes", ""]
    if report.has_truth:
        lines += [
            "| Detector | Sensor | Episodes | Matched | False | False / h | Class right %"
            " | 90 % interval covers % |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for key, score in report.episode_scores.items():
            detector, sensor_type = key.split(".", 1)
            lines.append(
                f"| {detector} | {sensor_type} | {score['episodes']} | {score['matched']} | "
                f"{score['false']} | {format_value(score['false_episodes_per_hour'], 1, '{:.3g}')} | "
                f"{format_value(score['class_accuracy'], 100.0, '{:.1f}')} | "
                f"{format_value(score['coverage'], 100.0, '{:.1f}')} |"
            )
    lines += [
        "",
        "| Detector | Sensor | Start s | Duration s | Isolated | Class | Size [90 % interval]"
        " | Detector's amplitude | Runner-up class | Peak stat/threshold | Match |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in episode_rows(report):
        scale, unit = _SIZE_UNITS.get((row["sensor_type"], "amp"), (1.0, "SI"))
        amplitude = row["detector_amplitude"]
        lines.append(
            f"| {row['detector']} | {row['sensor_type']} | {row['start_s']:.3f} | "
            f"{format_value(row['duration_s'], 1.0, '{:.3f}')} | {row['sensor'] or '-'} | "
            f"{row['fault_class'] or '-'} | {row['size']} | "
            f"{'-' if amplitude is None else f'{amplitude * scale:.4g} {unit}'} | "
            f"{row['runner_up_class'] or '-'} | "
            f"{format_value(row['peak_ratio'], 1.0, '{:.3g}')} | "
            f"{row['match'] or '-'}{' ' + row['fault_id'] if row['fault_id'] else ''} |"
        )
    omitted = sum(s.get("omitted", 0) for s in report.episode_scores.values())
    if omitted:
        lines += ["", f"> {omitted} more episodes counted but not listed"]
    return lines


CSV_FIELDS = [
    "detector",
    "sensor_type",
    "samples",
    "fault_free_samples",
    "faulty_samples",
    "calibration_samples",
    "far",
    "far_calibration",
    "mar",
    "detection_rate",
    "accuracy",
    "fir",
    "isolation_accuracy",
    "detection_delay_s",
    "isolation_delay_s",
    "decision_latency_s",
    "recovery_delay_s",
    "rate_after_first_detection",
    "alarm_rate",
    "alarm_events",
    "false_alarm_events_per_hour",
    "false_episodes",
    "false_episodes_per_hour",
    "false_episodes_per_hour_upper95",
    "mtbfa_h",
    "mtbfa_h_lower95",
    "fault_free_hours",
    "reference_delay_s",
    "delay_ratio",
    "target_far",
    "mar_at_far",
    "fir_at_far",
    "detection_delay_at_far_s",
    "threshold_scale_at_far",
    "target_budget_per_hour",
    "mar_at_budget",
    "fir_at_budget",
    "detection_delay_s_at_budget",
    "isolation_delay_s_at_budget",
    "threshold_scale_at_budget",
]


def to_csv(report: Report) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_FIELDS)
    for e in report.entries:
        data = {"detector": e.detector, "sensor_type": e.sensor_type, **e.metrics.to_dict()}
        writer.writerow(["" if data[k] is None else data[k] for k in CSV_FIELDS])
    return out.getvalue()


def to_junit(report: Report, gate_results: Sequence[GateResult] = ()) -> str:
    """JUnit XML: one test case per gate (or per detector/type when no gates are given)."""
    # (imported here: xml.sax.saxutils pulls in urllib, http and email, 20-50 ms)
    from xml.sax.saxutils import escape, quoteattr

    cases = []
    if gate_results:
        for r in gate_results:
            body = (
                f"<failure message={quoteattr(r.message)}>{escape(r.message)}</failure>"
                if r.failed
                else ""
            )
            cases.append(
                f'  <testcase classname="imufdi.gates" name={quoteattr(r.target + " " + r.gate.op + " " + format(r.gate.value, "g"))}>{body}</testcase>'
            )
    else:
        for e in report.entries:
            summary = ", ".join(
                f"{h}={format_value(e.metrics.value(m), s, f)}"
                for m, h, s, f in table_columns(report)
            )
            cases.append(
                f'  <testcase classname="imufdi.{escape(e.detector)}" name="{escape(e.sensor_type)}">'
                f"<system-out>{escape(summary)}</system-out></testcase>"
            )
    failures = sum(r.failed for r in gate_results)
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<testsuite name="imufdi" tests="{len(cases)}" failures="{failures}" errors="0">\n'
        + "\n".join(cases)
        + "\n</testsuite>\n"
    )


ROC_FIELDS = [
    "detector",
    "sensor_type",
    "threshold_scale",
    "far",
    "mar",
    "fir",
    "detection_delay_s",
]


def to_roc_csv(report: Report) -> str:
    """The swept curves (``--roc``): one row per histogram edge where FAR or MAR changes
    (plus the first and last edge), per detector and sensor type; empty cells are undefined."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(ROC_FIELDS)
    for e in report.entries:
        if e.roc is None:
            continue
        far, mar = e.roc["far"], e.roc["mar"]
        change = np.ones(far.size, dtype=bool)
        change[1:-1] = (np.diff(np.nan_to_num(far, nan=-1.0))[:-1] != 0) | (
            np.diff(np.nan_to_num(mar, nan=-1.0))[:-1] != 0
        )
        for k in np.flatnonzero(change).tolist():
            row = [e.detector, e.sensor_type, f"{10 ** e.roc['log10_scale'][k]:.6g}"]
            for name in ("far", "mar", "fir", "detection_delay_s"):
                v = float(e.roc[name][k])
                row.append("" if math.isnan(v) else f"{v:.6g}")
            writer.writerow(row)
    return out.getvalue()
