"""``imufdi report``: metrics of an annotated log, renderers and CI gates.

:func:`build_report` reads the detector status channels and the ground truth of an
annotated MCAP and computes the metrics of DESIGN.md §7 per detector and sensor type.
Renderers turn a :class:`Report` into JSON, Markdown (the layout of Li et al. Table 4), CSV
and JUnit XML; :func:`parse_gate` / :func:`evaluate_gates` implement ``--fail-if``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import operator
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, BinaryIO
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from imufdi_cli.errors import GateError, McapInputError
from imufdi_cli.metrics import (
    METRIC_NAMES,
    FaultWindow,
    Metrics,
    compute_metrics,
    faulty_matrix,
)

# --- building --------------------------------------------------------------------------


@dataclass
class ReportEntry:
    """Metrics of one detector on one sensor type."""

    detector: str
    sensor_type: str
    sensor_ids: list[str]
    metrics: Metrics
    t_ns: np.ndarray = field(repr=False)
    statistic: np.ndarray = field(repr=False)
    threshold: np.ndarray = field(repr=False)
    alarm: np.ndarray = field(repr=False)
    scores: np.ndarray = field(repr=False)
    faulty: np.ndarray = field(repr=False)


@dataclass
class Report:
    """Everything ``imufdi report`` shows."""

    source: str
    has_truth: bool
    faults: list[dict[str, Any]]
    entries: list[ReportEntry]
    notes: list[str]
    t0_ns: int

    def entry(self, detector: str, sensor_type: str) -> ReportEntry | None:
        for item in self.entries:
            if item.detector == detector and item.sensor_type == sensor_type:
                return item
        return None


@dataclass(frozen=True)
class TruthWindow:
    """An injected fault with absolute times, as recorded in ``imufdi.faults``."""

    fault_id: str
    sensors: tuple[str, ...]
    start_ns: int
    end_ns: int | None


@dataclass
class Truth:
    windows: list[TruthWindow]
    descriptions: list[dict[str, Any]]


def truth_windows(metadata: dict[str, dict[str, str]]) -> Truth | None:
    """Ground truth of a log from its ``imufdi.faults`` record (None when there is none).

    Each injection run records its log start ``t0_ns``; fault times are relative to it.
    """
    from imufdi_cli.errors import TruthError
    from imufdi_cli.faults import METADATA_NAME, Fault

    record_meta = metadata.get(METADATA_NAME)
    if record_meta is None:
        return None
    try:
        record = json.loads(record_meta["json"])
        runs = [*record.get("previous", []), record]
        windows = []
        descriptions = []
        for run in runs:
            t0 = int(run["t0_ns"])
            for item in run.get("faults", []):
                fault = Fault.from_dict(item)
                end = None if fault.until_ns is None else t0 + fault.until_ns
                windows.append(TruthWindow(fault.id, tuple(fault.sensors), t0 + fault.at_ns, end))
                descriptions.append(fault.to_dict())
    except (KeyError, TypeError, ValueError) as err:
        raise TruthError(f"{METADATA_NAME} metadata is malformed ({err})") from err
    return Truth(windows=windows, descriptions=descriptions)


def build_report(source: str | BinaryIO, *, persist: int = 1) -> Report:
    """Compute the report of an annotated log.

    Parameters
    ----------
    source : path, ``"-"`` or binary stream
        An MCAP written by ``imufdi detect``.
    persist : int
        Detection delays count the first alarm persisting this many samples.
    """
    from imufdi_cli.mcapio import McapSource, read_status

    name = source if isinstance(source, str) else "<stream>"
    # one pass: read_status streams every batch, so the source's metadata (wherever the
    # records sit, even in a stream from stdin) is complete afterwards
    with McapSource(source) as src:
        status = read_status(src)
        metadata = dict(src.metadata)
        problems = list(src.warnings)
    if not status:
        raise McapInputError(
            f"{name}: no detector status channels (/imufdi/<detector>/<type>); "
            "run `imufdi detect` on the log first" + (f"; {problems[0]}" if problems else "")
        )
    truth = truth_windows(metadata)
    # a damaged log is reported on what could be read, and says so
    notes: list[str] = [f"input: {problem}" for problem in problems]
    has_truth = truth is not None
    if not has_truth:
        notes.append(
            "no ground truth in this log (inject faults with `imufdi inject`): "
            "FAR, MAR, FIR and delays need truth; alarm statistics only"
        )
    t0_candidates = [int(arrs.t_ns[0]) for arrs in status.values() if len(arrs.t_ns)]
    t0_ns = min(t0_candidates) if t0_candidates else 0
    entries = []
    for (detector, sensor_type), arrays in sorted(status.items()):
        ids = list(arrays.sensor_ids)
        windows: list[FaultWindow] = []
        if truth is not None:
            windows = [
                FaultWindow(
                    w.fault_id, tuple(ids.index(s) for s in w.sensors), w.start_ns, w.end_ns
                )
                for w in truth.windows
                if all(s in ids for s in w.sensors)
            ]
        faulty = faulty_matrix(arrays.t_ns, windows, len(ids))
        metrics = compute_metrics(
            arrays.t_ns,
            arrays.alarm,
            arrays.isolated,
            faulty,
            windows,
            persist=persist,
            isolated_set=arrays.isolated_set,
        )
        if not has_truth:
            metrics.far = metrics.mar = metrics.accuracy = None
            metrics.fir = metrics.isolation_accuracy = None
            metrics.false_alarm_events_per_hour = None
        entries.append(
            ReportEntry(
                detector=detector,
                sensor_type=sensor_type,
                sensor_ids=ids,
                metrics=metrics,
                t_ns=arrays.t_ns,
                statistic=arrays.statistic,
                threshold=arrays.threshold,
                alarm=arrays.alarm,
                scores=arrays.scores,
                faulty=faulty,
            )
        )
    return Report(
        source=name,
        has_truth=has_truth,
        faults=[] if truth is None else truth.descriptions,
        entries=entries,
        notes=notes,
        t0_ns=t0_ns,
    )


# --- gates -----------------------------------------------------------------------------

OPERATORS: dict[str, Callable[[float, float], bool]] = {
    ">": operator.gt,
    ">=": operator.ge,
    "<": operator.lt,
    "<=": operator.le,
    "==": operator.eq,
    "!=": operator.ne,
}
_GATE = re.compile(
    r"^\s*([A-Za-z0-9_*-]+)\.([A-Za-z*]+)\.([A-Za-z_]+)\s*(>=|<=|==|!=|>|<)\s*"
    r"([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*(%?)\s*$"
)


@dataclass(frozen=True)
class Gate:
    """``DETECTOR.TYPE.METRIC OP VALUE``: fails when the comparison is true."""

    text: str
    detector: str
    sensor_type: str
    metric: str
    op: str
    value: float


@dataclass
class GateResult:
    gate: Gate
    target: str  # "glt.gyro"
    actual: float | None
    failed: bool
    message: str


def parse_gate(text: str, known_detectors: Iterable[str]) -> Gate:
    """Parse a ``--fail-if`` expression (e.g. ``glt.gyro.far > 0.01`` or ``*.accel.mar >= 5%``).

    Raises GateError (exit 2) naming what is wrong and the valid choices.
    """
    match = _GATE.match(text)
    if match is None:
        raise GateError(
            f"--fail-if {text!r} is not of the form DETECTOR.TYPE.METRIC OP NUMBER "
            "(e.g. 'glt.gyro.far > 0.01'; OP one of > >= < <= == !=)"
        )
    detector, sensor_type, metric, op, number, percent = match.groups()
    known = sorted(known_detectors)
    if detector != "*" and detector not in known:
        raise GateError(
            f"--fail-if {text!r}: unknown detector {detector!r}; valid: {', '.join(known)}, *"
        )
    if sensor_type not in ("gyro", "accel", "mag", "*"):
        raise GateError(
            f"--fail-if {text!r}: unknown sensor type {sensor_type!r}; valid: gyro, accel, mag, *"
        )
    if metric not in METRIC_NAMES:
        raise GateError(
            f"--fail-if {text!r}: unknown metric {metric!r}; valid: {', '.join(METRIC_NAMES)}"
        )
    value = float(number) / (100.0 if percent else 1.0)
    return Gate(text.strip(), detector, sensor_type, metric, op, value)


def evaluate_gates(report: Report, gates: Sequence[Gate]) -> list[GateResult]:
    """Evaluate gates; a gate naming results absent from the log raises GateError.

    A gate whose metric is undefined on this log (e.g. MAR without faulty samples) fails:
    a CI gate must not pass on a figure that could not be computed.
    """
    results = []
    for gate in gates:
        matched = [
            e
            for e in report.entries
            if gate.detector in ("*", e.detector) and gate.sensor_type in ("*", e.sensor_type)
        ]
        if not matched:
            present = ", ".join(f"{e.detector}.{e.sensor_type}" for e in report.entries)
            raise GateError(
                f"--fail-if {gate.text!r}: no results for {gate.detector}.{gate.sensor_type} "
                f"in this log (present: {present or 'none'})"
            )
        for entry in matched:
            actual = entry.metrics.value(gate.metric)
            target = f"{entry.detector}.{entry.sensor_type}.{gate.metric}"
            if actual is None:
                results.append(
                    GateResult(gate, target, None, True, f"{target} is undefined on this log")
                )
                continue
            failed = OPERATORS[gate.op](actual, gate.value)
            verdict = "FAILED" if failed else "passed"
            results.append(
                GateResult(
                    gate,
                    target,
                    actual,
                    failed,
                    f"{verdict}: {target} = {actual:.6g} (fail if {gate.op} {gate.value:g})",
                )
            )
    return results


# --- renderers -------------------------------------------------------------------------

#: Columns of the tables: (metric, header, scale, format)
TABLE_COLUMNS: list[tuple[str, str, float, str]] = [
    ("far", "FAR %", 100.0, "{:.2f}"),
    ("mar", "MAR %", 100.0, "{:.2f}"),
    ("accuracy", "Accuracy %", 100.0, "{:.2f}"),
    ("fir", "FIR %", 100.0, "{:.2f}"),
    ("detection_delay_s", "Delay s", 1.0, "{:.3f}"),
    ("recovery_delay_s", "Recovery s", 1.0, "{:.3f}"),
    ("alarm_rate", "Alarm %", 100.0, "{:.2f}"),
    ("alarm_events", "Events", 1.0, "{:.0f}"),
]


def format_value(value: float | None, scale: float = 1.0, fmt: str = "{:.4g}") -> str:
    """Format a figure for tables; undefined values read ``undefined``."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "undefined"
    return fmt.format(value * scale)


def table_rows(report: Report) -> list[list[str]]:
    """Rows (detector, type, columns of TABLE_COLUMNS) as strings."""
    return [
        [e.detector, e.sensor_type]
        + [format_value(e.metrics.value(m), s, f) for m, _, s, f in TABLE_COLUMNS]
        for e in report.entries
    ]


def to_json(report: Report, gate_results: Sequence[GateResult] = ()) -> str:
    data = {
        "source": report.source,
        "has_truth": report.has_truth,
        "faults": report.faults,
        "results": [
            {"detector": e.detector, "sensor_type": e.sensor_type, **e.metrics.to_dict()}
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
    }
    return json.dumps(data, indent=2, allow_nan=False) + "\n"


def to_markdown(report: Report, gate_results: Sequence[GateResult] = ()) -> str:
    header = ["Detector", "Sensor"] + [h for _, h, _, _ in TABLE_COLUMNS]
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
            "| Fault | Detector | Sensor | Detected | Delay s | Recovery s | Isolated to it % |",
            "|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {f.fault_id} | {e.detector} | {e.sensor_type} | {'yes' if f.detected else 'no'} | "
            f"{format_value(f.detection_delay_s, 1.0, '{:.3f}')} | "
            f"{format_value(f.recovery_delay_s, 1.0, '{:.3f}')} | "
            f"{format_value(f.isolated_correctly, 100.0, '{:.1f}')} |"
            for e, f in per_fault
        ]
    if gate_results:
        lines += ["", "## Gates", ""]
        lines += [f"- {'❌' if r.failed else '✅'} {r.message}" for r in gate_results]
    if report.notes:
        lines += [""] + [f"> {note}" for note in report.notes]
    return "\n".join(lines) + "\n"


CSV_FIELDS = [
    "detector",
    "sensor_type",
    "samples",
    "fault_free_samples",
    "faulty_samples",
    "far",
    "mar",
    "accuracy",
    "fir",
    "isolation_accuracy",
    "detection_delay_s",
    "recovery_delay_s",
    "alarm_rate",
    "alarm_events",
    "false_alarm_events_per_hour",
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
                f"{h}={format_value(e.metrics.value(m), s, f)}" for m, h, s, f in TABLE_COLUMNS
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


def plot_report(report: Report, path: str) -> None:
    """Detection statistic vs threshold and isolation scores over time, faults shaded
    (like Li et al. Figure 15). Needs the ``plot`` extra (matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:
        from imufdi_cli.errors import UsageError

        raise UsageError("--plot needs matplotlib: pip install 'imufdi-cli[plot]'") from err
    entries = report.entries
    fig, axes = plt.subplots(
        len(entries), 2, figsize=(12, 3.2 * len(entries)), squeeze=False, constrained_layout=True
    )
    for row, e in enumerate(entries):
        t = (e.t_ns - report.t0_ns) / 1e9
        shade = e.faulty.any(axis=1)
        for ax in axes[row]:
            if shade.any():
                ax.fill_between(
                    t,
                    0,
                    1,
                    where=shade,
                    transform=ax.get_xaxis_transform(),
                    color="tab:red",
                    alpha=0.12,
                    label="fault active",
                    step="post",
                )
        ax = axes[row][0]
        ax.plot(t, e.statistic, lw=0.7, label="statistic")
        ax.plot(t, e.threshold, "k--", lw=1.0, label="threshold")
        finite = e.statistic[np.isfinite(e.statistic) & (e.statistic > 0)]
        if finite.size and finite.max() / max(finite.min(), 1e-12) > 100:
            ax.set_yscale("log")
        ax.set_title(f"{e.detector} · {e.sensor_type}: detection statistic")
        ax.set_xlabel("time, s")
        ax.legend(loc="upper left", fontsize=8)
        ax = axes[row][1]
        scores = e.scores
        if scores.size and np.isfinite(scores).any():
            peak = np.nanmax(np.where(np.isfinite(scores), scores, -np.inf), axis=0)
            top = np.argsort(peak)[::-1][: min(6, scores.shape[1])]
            for j in top:
                ax.plot(t, scores[:, j], lw=0.7, label=e.sensor_ids[j])
            ax.legend(loc="upper left", fontsize=7, ncol=2)
        else:
            ax.text(0.5, 0.5, "no isolation scores", ha="center", transform=ax.transAxes)
        ax.set_title(f"{e.detector} · {e.sensor_type}: isolation scores (top sensors)")
        ax.set_xlabel("time, s")
    fig.savefig(path, dpi=110)
    plt.close(fig)
